"""A telemetry file's content as one hash: what the lockstep clock promises bit for bit (docs/LOCKSTEP.md).

Every message of every channel (cycle rows, events, Foxglove channels) with its log time, publish time and
sequence, and every metadata record, hashed in (topic, log time, sequence) order: the file's chunking, compression
and the order in which the writer interleaved channels (which follow the writer thread's wall-clock hand-overs) are
framing, not content, and are left out.
"""

from __future__ import annotations

import hashlib
import os
from collections import Counter
from typing import Any

__all__ = ["digest"]


def digest(path: str | os.PathLike[str]) -> dict[str, Any]:
    """``{"sha256": hex, "messages": n, "channels": {topic: n}}`` of an MCAP telemetry file."""
    from mcap.reader import make_reader

    items: list[tuple[str, int, int, int, bytes]] = []
    meta: list[tuple[str, tuple[tuple[str, str], ...]]] = []
    with open(path, "rb") as f:
        reader = make_reader(f)
        for _schema, channel, message in reader.iter_messages(log_time_order=False):
            items.append((channel.topic, message.log_time, message.publish_time, message.sequence, message.data))
        f.seek(0)
        for m in make_reader(f).iter_metadata():
            meta.append((m.name, tuple(sorted(m.metadata.items()))))
    items.sort(key=lambda it: (it[0], it[1], it[3], it[4]))
    h = hashlib.sha256()
    for topic, log_time, publish_time, seq, data in items:
        h.update(f"{topic}\0{log_time}\0{publish_time}\0{seq}\0{len(data)}\0".encode())
        h.update(data)
    for name, kv in sorted(meta):
        h.update(repr((name, kv)).encode())
    return {"sha256": h.hexdigest(), "messages": len(items), "channels": dict(Counter(it[0] for it in items))}
