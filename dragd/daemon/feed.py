"""The events a client that follows the arm polls (the ``events`` command: every event the daemon records, numbered,
from any point on; ``state`` and ``robot`` are in daemon/commands.py).

`EventLog` is the one path of events to clients: whatever the daemon records as a telemetry event (mode changes,
faults, protective stops of the guard and the monitors, motions' ends, streams, teach marks, and the kinds later
issues add) is numbered here too, so a client (the ROS 2 bridge) passes new kinds on without knowing them.
"""

from __future__ import annotations

from collections import deque
from typing import Any

EVENTS_KEPT = 512  # the newest events kept for clients (older ones count as lost to a client that asks for them)


class EventLog:
    """The newest ``EVENTS_KEPT`` events, numbered from 1: ``{"seq", "t_s", "name", **fields}``."""

    def __init__(self, keep: int = EVENTS_KEPT) -> None:
        self.seq = 0  # the newest event's number (0: none yet)
        self._events: deque[dict[str, Any]] = deque(maxlen=keep)

    def add(self, t_s: float, name: str, fields: dict[str, Any]) -> None:
        self.seq += 1
        self._events.append({"seq": self.seq, "t_s": round(float(t_s), 4), "name": name, **fields})

    def since(self, since: int) -> tuple[list[dict[str, Any]], int]:
        """Events numbered above ``since`` still kept, oldest first; and how many of those were dropped."""
        kept = [e for e in self._events if e["seq"] > since]
        first = kept[0]["seq"] if kept else self.seq + 1
        return kept, max(0, first - since - 1)
