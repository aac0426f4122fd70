"""MCAP telemetry written off the loop: `TelemetryWriter` (the daemon) and `write_file` (logs computed offline).

The cycle side is a single-producer ring of preallocated float64 rows::

    writer = TelemetryWriter(path, cycle_layout(6))
    Q = writer.slices["q_rad"]                 # once, outside the cycle
    row = writer.begin()                       # in the cycle: a preallocated row view
    if row is not None:                        # None: ring full, the row is counted as dropped
        row[0] = t_s; row[Q] = q               # fill *every* field (slots are reused)
        writer.commit()

A writer thread drains the ring every ``flush_interval_s`` into an `McapFile`: each row a JSON message (channel
``topic``, encoding ``json``, JSON Schema registered so Foxglove shows arrays as arrays, numbers as numbers, enum
fields as their label), chunked and compressed. I/O errors, a full disk or a slow disk never reach the cycle: rows
are dropped and counted, the first error is kept and `stats()` reports it. After an I/O error the writer retries
on a fresh file (``retry_after_s``); ``max_bytes`` rolls over to a new file, keeping ``keep_rotated`` old ones. A
retry never deletes an older log: a failed file with rows is kept aside, one without is removed; on a disk that
stays full the rows are dropped and counted (``failing``, ``last_error``) and every earlier log is kept.
`close()` finishes the file (summary, indexes, statistics); a file whose writer was killed lacks them and is
read up to its last complete chunk (dragd/telemetry/reader.py).

``process=True`` (the daemon's telemetry file and record windows) moves the encoding out of the daemon's process:
the writer thread only forwards the drained rows (one array) and the events, every ``forward_interval_s`` (default
``flush_interval_s``), through a pipe to a writer *process* (started by that thread, so it runs SCHED_OTHER off the
real-time CPUs), which runs this same writer in thread mode and sends its counters back; `stats()` merges both
sides. The cycle thread then never shares the GIL with the formatting (measured: the demo's missed ticks with the
file written went from ~3× to ~1× those without it, docs/DECISIONS.md); each hand-over still takes the GIL for a
moment, so the daemon hands over a few times a second (dragd/daemon/recording.py). The file's checks and rotation
happen here, before the process starts, so a bad path still fails at once. If the process dies, its error is
reported and the rows from then on are dropped and counted.
A file object as ``path``, or sinks (the live view), keep the thread mode.

MCAP ``sequence`` of a cycle message is the producer's row counter (``begin`` calls), so a gap in sequence
numbers shows exactly where rows were dropped.

GIL: the writer thread competes with the cycle thread for the GIL. Float formatting dominates its work, so rows
are formatted through a precompiled template with ``float_digits`` significant digits (~9 us/row here instead of
~30 us with ``json.dumps``), chunks are small (64 KiB: short bursts when a chunk is indexed and compressed; zstd
itself releases the GIL), and the thread sleeps briefly every ``yield_every_rows`` rows so a waiting cycle thread
gets the GIL at once.
"""

from __future__ import annotations

import collections
import dataclasses
import errno
import importlib.util
import io
import os
import re
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, BinaryIO, Literal

import numpy as np
from mcap.writer import CompressionType, Writer

from dragd.realtime import demote_current_thread
from dragd.telemetry.foxglove import FoxgloveChannels, FoxgloveSpec
from dragd.telemetry.layout import RowLayout, dumps, normalize_labels
from dragd.telemetry.schema import (
    CYCLE_SCHEMA,
    CYCLE_TOPIC,
    EVENT_SCHEMA,
    EVENTS_TOPIC,
    HAND_EVENT,
    HAND_SCHEMA,
    HAND_TOPIC,
    RUN_METADATA,
    WRITER_METADATA,
    Field,
    event_json_schema,
    hand_json_schema,
)
from dragd.telemetry.sinks import RerunSink, RowSink

__all__ = ["TelemetryWriter", "TelemetryError", "McapFile", "write_file"]

_YIELD_S = 50e-6  # writer pause between row slices (releases the GIL)

Compression = Literal["zstd", "lz4", "none"]


class TelemetryError(RuntimeError):
    """The telemetry file cannot be set up (bad path, directory missing, ...)."""


class _CountingStream:
    """Binary sink for mcap.Writer that counts bytes that really reached ``raw``."""

    def __init__(self, raw: Any, start: int = 0) -> None:
        self._raw = raw
        self.position = start

    def write(self, data: bytes | bytearray | memoryview) -> int:
        mv = memoryview(data).cast("B")
        total = len(mv)
        while mv:
            n = self._raw.write(mv)
            if n is None:
                raise BlockingIOError(errno.EAGAIN, "telemetry output would block")
            if n <= 0:
                raise OSError(errno.EIO, "telemetry output accepted no bytes")
            self.position += n
            mv = mv[n:]
        return total

    def tell(self) -> int:
        return self.position

    def flush(self) -> None:
        flush = getattr(self._raw, "flush", None)
        if callable(flush):
            flush()


def _pick_compression(requested: str) -> tuple[CompressionType, str, str | None]:
    order = {"zstd": ["zstd", "lz4"], "lz4": ["lz4", "zstd"], "none": []}
    if requested not in order:
        raise ValueError(f"compression must be 'zstd', 'lz4' or 'none'; got {requested!r}")
    modules = {"zstd": "zstandard", "lz4": "lz4"}
    for name in order[requested]:
        try:
            found = importlib.util.find_spec(modules[name]) is not None
        except ValueError:
            found = False
        if found:
            note = None if name == requested else f"{requested} unavailable, using {name}"
            kind = CompressionType.ZSTD if name == "zstd" else CompressionType.LZ4
            return kind, name, note
    if requested == "none":
        return CompressionType.NONE, "none", None
    return (
        CompressionType.NONE,
        "none",
        "neither zstandard nor lz4 is installed; writing uncompressed chunks",
    )


def _rotated_name(path: Path, when: float) -> Path:
    stamp = datetime.fromtimestamp(when, UTC).strftime("%Y%m%dT%H%M%SZ")
    candidate = path.with_name(f"{path.stem}.{stamp}{path.suffix}")
    k = 1
    while candidate.exists():
        candidate = path.with_name(f"{path.stem}.{stamp}-{k}{path.suffix}")
        k += 1
    return candidate


def _rotated_files(path: Path) -> list[Path]:
    """Rotated copies of ``path``, oldest first (by modification time)."""
    pat = re.compile(re.escape(path.stem) + r"\.\d{8}T\d{6}Z(-\d+)?" + re.escape(path.suffix) + "$")
    found = []
    for p in path.parent.glob(f"{path.stem}.*{path.suffix}"):
        if pat.match(p.name):
            try:
                found.append((p.stat().st_mtime_ns, p.name, p))
            except OSError:
                continue
    return [p for _m, _n, p in sorted(found)]


def channels(spec: FoxgloveSpec) -> type[FoxgloveChannels]:
    """The well-known channels' class for ``spec.encoding``: Foxglove's JSON, or ROS 2's CDR."""
    if spec.encoding == "ros2":
        from dragd.telemetry.ros2 import Ros2Channels

        return Ros2Channels
    return FoxgloveChannels


class McapFile:
    """One telemetry MCAP in ``stream``: header, the cycle and event schemas and channels, the run metadata.

    The one encoding path of dragd telemetry files (`TelemetryWriter`'s thread, `write_file`). Rows are
    encoded by ``layout`` (`encode_row`), events as ``{"name": ..., **fields}`` (`encode_event`).
    """

    def __init__(
        self,
        stream: Any,
        layout: RowLayout,
        *,
        topic: str = CYCLE_TOPIC,
        events_topic: str = EVENTS_TOPIC,
        compression: CompressionType = CompressionType.ZSTD,
        chunk_size: int = 64 * 1024,
        schema_name: str = CYCLE_SCHEMA,
        metadata: Mapping[str, str] | None = None,
        library: str = "dragd",
        foxglove: FoxgloveSpec | None = None,
        cycle_decimation: int = 1,
    ) -> None:
        self.layout = layout
        self._mcap = Writer(stream, chunk_size=chunk_size, compression=compression)
        self._mcap.start(profile="", library=library)
        schema_id = self._mcap.register_schema(
            name=schema_name, encoding="jsonschema", data=dumps(layout.json_schema(schema_name))
        )
        self._cycle = self._mcap.register_channel(
            topic=topic, message_encoding="json", schema_id=schema_id,
            metadata={"decimation": str(int(cycle_decimation))} if cycle_decimation > 1 else {},
        )
        event_id = self._mcap.register_schema(
            name=EVENT_SCHEMA, encoding="jsonschema", data=dumps(event_json_schema())
        )
        self._events = self._mcap.register_channel(
            topic=events_topic, message_encoding="json", schema_id=event_id
        )
        self.foxglove = None if foxglove is None else channels(foxglove)(self._mcap, foxglove)
        self._hand: int | None = None  # /dragd/hand, registered with its first message
        if metadata:
            self._mcap.add_metadata(RUN_METADATA, {str(k): str(v) for k, v in metadata.items()})

    def encode_row(self, values: list[float], finite: bool) -> bytes:
        """JSON of one row (flat values, modified in place); ``finite``: no NaN/inf (the fast template)."""
        return self.layout.encode_json(values) if finite else dumps(self.layout.encode(values))

    @staticmethod
    def encode_event(name: str, fields: Mapping[str, Any]) -> bytes:
        return dumps({"name": name, **fields})

    def add_row(self, data: bytes, log_time_ns: int, seq: int) -> None:
        self._mcap.add_message(
            channel_id=self._cycle, log_time=log_time_ns, data=data, publish_time=log_time_ns, sequence=seq
        )

    def add_event(self, data: bytes, log_time_ns: int, name: str | None = None) -> None:
        """An event on ``/dragd/events``; one named ``hand`` (the hand guiding state) on ``/dragd/hand``."""
        channel = self._events
        if name == HAND_EVENT:
            if self._hand is None:
                schema = self._mcap.register_schema(name=HAND_SCHEMA, encoding="jsonschema",
                                                    data=dumps(hand_json_schema()))
                self._hand = self._mcap.register_channel(topic=HAND_TOPIC, message_encoding="json", schema_id=schema)
            channel = self._hand
        self._mcap.add_message(
            channel_id=channel, log_time=log_time_ns, data=data, publish_time=log_time_ns, sequence=0
        )

    def add_foxglove_event(self, log_time_ns: int, name: str, fields: Mapping[str, Any]) -> int:
        """The event as a foxglove.Log message (bytes added; 0 without the Foxglove channels)."""
        return 0 if self.foxglove is None else self.foxglove.add_event(log_time_ns, name, fields)

    def add_foxglove_rows(self, rows: np.ndarray, log_time_ns: Sequence[int]) -> int:
        """Joint states and link transforms of ``rows`` at the Foxglove rate (bytes added)."""
        return 0 if self.foxglove is None else self.foxglove.add_rows(self.layout, rows, log_time_ns)

    def finish(self, counters: Mapping[str, Any] | None = None) -> None:
        """The writer's counters (metadata ``dragd.telemetry.writer``), the last chunk and the summary."""
        if counters is not None:
            self._mcap.add_metadata(WRITER_METADATA, {str(k): str(v) for k, v in counters.items()})
        self._mcap.finish()


def write_file(
    path: str | os.PathLike[str],
    layout: Mapping[str, int | Field] | RowLayout,
    rows: np.ndarray,
    log_time_ns: Sequence[int] | np.ndarray,
    *,
    events: Iterable[tuple[int, str, Mapping[str, Any]]] = (),
    metadata: Mapping[str, str] | None = None,
    compression: Compression = "zstd",
    chunk_size: int = 1 << 20,
    library: str = "dragd",
    foxglove: FoxgloveSpec | None = None,
) -> int:
    """Write ``rows`` ((N, width) in ``layout``'s order) and ``events`` ((time_ns, name, fields)) to a finished
    MCAP at once, as `TelemetryWriter` would (sequence 1..N); for logs computed offline. Returns N.
    ``foxglove``: add Foxglove's well-known channels (joint states, transforms, logs; see `FoxgloveSpec`)."""
    lay = layout if isinstance(layout, RowLayout) else RowLayout(layout)
    rows = np.asarray(rows, dtype=np.float64)
    if rows.ndim != 2 or rows.shape[1] != lay.width:
        raise ValueError(f"write_file: rows must be (N, {lay.width}) for this layout; got {rows.shape}")
    stamps = np.asarray(log_time_ns, dtype=np.int64).tolist()
    if len(stamps) != rows.shape[0]:
        raise ValueError(f"write_file: {rows.shape[0]} rows but {len(stamps)} log times")
    kind = _pick_compression(compression)[0]
    pending = sorted(events, key=lambda e: e[0])
    with open(path, "wb") as fh:
        f = McapFile(fh, lay, compression=kind, chunk_size=chunk_size, metadata=metadata, library=library,
                     foxglove=foxglove)
        finite = np.isfinite(rows).all(axis=1).tolist()
        k = 0
        for seq, (values, ok, t) in enumerate(zip(rows.tolist(), finite, stamps, strict=True), start=1):
            while k < len(pending) and pending[k][0] <= t:
                f.add_event(f.encode_event(pending[k][1], pending[k][2]), pending[k][0], pending[k][1])
                if pending[k][1] != HAND_EVENT:
                    f.add_foxglove_event(*pending[k])
                k += 1
            f.add_row(f.encode_row(values, ok), t, seq)
        f.add_foxglove_rows(rows, stamps)
        for t_ev, name, fields in pending[k:]:
            f.add_event(f.encode_event(name, fields), t_ev, name)
            if name != HAND_EVENT:
                f.add_foxglove_event(t_ev, name, fields)
        f.finish({"written": len(stamps), "dropped": 0, "events_written": len(pending), "events_dropped": 0})
    return len(stamps)


class TelemetryWriter:
    """Off-loop MCAP writer fed by a preallocated ring of rows (see module docstring).

    ``path`` is a file path (created; an existing file is handled per ``on_exists``)
    or an open binary file object (not closed by us; no rotation/retry).
    ``foxglove`` adds Foxglove's well-known channels (joint states, link transforms, logs, the URDF; see
    dragd/telemetry/foxglove.py), written by the writer thread at ``foxglove.rate_Hz``. ``cycle_decimation``
    N > 1 writes only every N-th cycle row (producer sequence divisible by N) to ``topic``: the file's size
    option (sinks still get every row).
    ``rerun=True`` (or a viewer URL) adds a `RerunSink`; raises RerunUnavailable
    with the install hint when rerun-sdk is missing (check `rerun_unavailable()`
    before booting the drives to fail early).
    """

    def __init__(
        self,
        path: str | os.PathLike[str] | BinaryIO,
        layout: Mapping[str, int | Field],
        topic: str = CYCLE_TOPIC,
        capacity: int = 4096,
        *,
        events_topic: str = EVENTS_TOPIC,
        compression: Compression = "zstd",
        chunk_size: int = 64 * 1024,
        flush_interval_s: float = 0.02,
        forward_interval_s: float | None = None,
        float_digits: int = 12,
        yield_every_rows: int = 8,
        on_exists: Literal["rotate", "overwrite", "error"] = "rotate",
        keep_rotated: int | None = 20,
        max_bytes: int | None = None,
        retry_after_s: float | None = 30.0,
        metadata: Mapping[str, str] | None = None,
        sinks: Sequence[RowSink] = (),
        rerun: bool | str = False,
        max_pending_events: int = 10_000,
        avoid_cpus: set[int] | None = None,
        schema_name: str = CYCLE_SCHEMA,
        foxglove: FoxgloveSpec | None = None,
        cycle_decimation: int = 1,
        process: bool = False,
    ) -> None:
        if capacity < 2:
            raise ValueError(f"telemetry capacity must be >= 2 rows; got {capacity}")
        if on_exists not in ("rotate", "overwrite", "error"):
            raise ValueError(f"on_exists must be 'rotate', 'overwrite' or 'error'; got {on_exists!r}")
        if isinstance(cycle_decimation, bool) or not isinstance(cycle_decimation, int) or cycle_decimation < 1:
            raise ValueError(f"cycle_decimation must be an int >= 1; got {cycle_decimation!r}")
        self._foxglove = foxglove
        self._decimation = cycle_decimation
        self.layout = RowLayout(layout, float_digits)
        self._yield_every = max(1, int(yield_every_rows))
        self.slices = self.layout.slices
        self.topic = topic
        self.events_topic = events_topic
        self.capacity = int(capacity)
        self._rows = np.zeros((self.capacity, self.layout.width), dtype=np.float64)
        self._views = [self._rows[i] for i in range(self.capacity)]
        self._stamps = np.zeros(self.capacity, dtype=np.int64)
        self._seqs = np.zeros(self.capacity, dtype=np.int64)
        # producer state (cycle thread only)
        self._head = 0
        self._seq = 0
        self._open_row = False
        self._dropped_full = 0
        self._closed = False
        # consumer state (writer thread only)
        self._tail = 0
        self._compression, self.compression, self._compression_note = _pick_compression(compression)
        self._chunk_size = int(chunk_size)
        self._flush_interval_s = float(flush_interval_s)
        self._forward_interval_s = float(flush_interval_s if forward_interval_s is None else forward_interval_s)
        if not self._forward_interval_s > 0:
            raise ValueError(f"forward_interval_s must be > 0; got {forward_interval_s!r}")
        self._keep_rotated = keep_rotated
        self._max_bytes = max_bytes
        self._retry_after_s = retry_after_s
        self._metadata = dict(metadata or {})
        self._sinks = list(sinks)
        if rerun:  # True: spawn a viewer; a string: gRPC URL of a running viewer
            self._sinks.append(RerunSink(url=rerun if isinstance(rerun, str) else None))
        self._avoid_cpus = avoid_cpus
        self._schema_name = schema_name
        self._events: collections.deque[tuple[int, str, dict[str, Any]]] = collections.deque()
        self._max_pending_events = max_pending_events
        self._lock = threading.Lock()  # guards the counters read by stats()
        self._written = 0
        self._dropped_io = 0
        self._dropped_bytes = 0
        self._bytes_done = 0  # bytes of finished/failed segments
        self._errors = 0
        self._first_error: str | None = None
        self._events_written = 0
        self._decimated = 0
        self._events_dropped = 0
        self._sink_errors: list[str] = []
        self._segments = 0
        self._unflushed_rows = 0
        self._unflushed_events = 0
        self._unflushed_bytes = 0
        self._failed_at: float | None = None
        self._last_error: str | None = None
        self._segment_rows = 0  # rows of the open segment that reached its file
        self._failed_rows = 0  # ... of the segment that failed last (a retry keeps it only if it holds some)
        self._failed_kept = 0  # failed segments kept aside on a retry (never at the cost of older logs)
        self._failed_removed = 0  # failed segments removed on a retry (they held no row)
        self._mcap: McapFile | None = None
        self._stream: _CountingStream | None = None
        self._raw: Any = None

        if isinstance(path, (str, os.PathLike)):
            self.path: Path | None = Path(path)
            self._file_obj: BinaryIO | None = None
            self._prepare_path(on_exists)
        else:
            if not callable(getattr(path, "write", None)):
                raise TypeError(f"path must be a file path or a binary file object; got {path!r}")
            if process:
                raise ValueError("telemetry process=True needs a file path, not a file object")
            self.path = None
            self._file_obj = path
        self.process = process
        self._child: Any = None  # process mode: the writer process and its pipe
        self._conn: Any = None
        self._child_stats: dict[str, Any] = {}
        self._child_error: str | None = None
        self._forwarded = 0  # rows handed to the writer process
        self._close_timeout_s = 10.0
        if process:
            if self._sinks:
                raise ValueError("telemetry process=True: sinks (the live view) run in the writer thread; "
                                 "use process=False with them")
            assert self.path is not None and self._raw is not None
            self._raw.close()  # checked, rotated and created here; the process writes it
            self._raw = None
            self._child_kwargs: dict[str, Any] = dict(
                path=os.fspath(self.path), layout=_portable_layout(layout), topic=topic, capacity=4 * self.capacity,
                events_topic=events_topic, compression=compression, chunk_size=chunk_size,
                flush_interval_s=flush_interval_s, float_digits=float_digits, yield_every_rows=yield_every_rows,
                on_exists="overwrite", keep_rotated=keep_rotated, max_bytes=max_bytes, retry_after_s=retry_after_s,
                metadata=metadata, max_pending_events=max_pending_events, schema_name=schema_name,
                cycle_decimation=cycle_decimation,
                foxglove=None if foxglove is None else dict(joint_names=list(foxglove.joint_names),
                                                            urdf=None if foxglove.urdf is None
                                                            else os.fspath(foxglove.urdf),
                                                            rate_Hz=foxglove.rate_Hz, transforms=foxglove.transforms,
                                                            encoding=foxglove.encoding,
                                                            kt_Nm_per_A=None if foxglove.kt_Nm_per_A is None
                                                            else [float(k) for k in foxglove.kt_Nm_per_A]))
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run_process if process else self._run, name="dragd-telemetry",
                                        daemon=True)
        self._thread.start()

    # -- cycle side (allocation-free, never blocks) -----------------------------------------
    def begin(self) -> np.ndarray | None:
        """Preallocated row to fill, or None when the ring is full (row counted as dropped)."""
        if self._open_row:
            return self._views[self._head % self.capacity]
        self._seq += 1
        if self._closed or self._head - self._tail >= self.capacity:
            self._dropped_full += 1
            return None
        self._open_row = True
        return self._views[self._head % self.capacity]

    def commit(self, log_time_ns: int | None = None) -> None:
        """Publish the row from `begin` (log time: now, CLOCK_REALTIME ns, unless given)."""
        if not self._open_row:
            raise RuntimeError("TelemetryWriter.commit() without a row from begin()")
        i = self._head % self.capacity
        self._stamps[i] = time.time_ns() if log_time_ns is None else log_time_ns
        self._seqs[i] = self._seq
        self._open_row = False
        self._head += 1

    # -- rare events (may allocate; not for the cycle) --------------------------------------
    def event(self, name: str, stamp_ns: int | None = None, **fields: Any) -> None:
        """Queue an event (mode change, fault, ...) for ``events_topic`` (log time: now, CLOCK_REALTIME ns, unless
        ``stamp_ns`` is given: the lockstep clock's)."""
        if self._closed or len(self._events) >= self._max_pending_events:
            with self._lock:
                self._events_dropped += 1
            return
        self._events.append((time.time_ns() if stamp_ns is None else stamp_ns, str(name), fields))

    def pending_rows(self) -> int:
        """Rows committed and not yet taken by the writer thread."""
        return self._head - self._tail

    # -- status -----------------------------------------------------------------------------
    def stats(self) -> dict[str, Any]:
        """Counters: written/dropped rows, errors, first error, bytes on disk, ..."""
        if self.process:
            return self._process_stats()
        with self._lock:
            current = self._stream.position if self._stream is not None else 0
            return {
                "written": self._written,
                "dropped": self._dropped_full + self._dropped_io,
                "dropped_ring_full": self._dropped_full,
                "dropped_io": self._dropped_io,
                "dropped_bytes": self._dropped_bytes,
                "decimated": self._decimated,
                "errors": self._errors,
                "first_error": self._first_error,
                "last_error": self._last_error,
                # failing now (no file open after an error): rows are dropped and counted, older logs are kept
                "failing": self._failed_at is not None and self._mcap is None,
                "failed_segments_kept": self._failed_kept,
                "failed_segments_removed": self._failed_removed,
                "bytes": self._bytes_done + current,
                "pending": self._head - self._tail,
                "capacity": self.capacity,
                "events_written": self._events_written,
                "events_dropped": self._events_dropped,
                "compression": self.compression,
                "compression_note": self._compression_note,
                "path": os.fspath(self.path) if self.path is not None else None,
                "segments": self._segments,
                "sink_errors": list(self._sink_errors),
            }

    def close(self, timeout_s: float = 10.0) -> dict[str, Any]:
        """Flush everything, finish the MCAP (summary + indexes) and stop the thread (and the writer process)."""
        if not self._closed:
            self._closed = True
            self._close_timeout_s = timeout_s
            self._stop.set()
            self._thread.join(timeout_s)
            if self._thread.is_alive() and self._child is not None:
                # a wedged writer process (stopped, stuck on a disk) holds the thread in a send: it goes, and what it
                # held is counted as lost
                self._child_down(f"close: the telemetry writer process did not finish within {timeout_s:g} s; "
                                 "killed")
                self._child.kill()
                self._thread.join(2.0)
            if self._thread.is_alive():
                self._record_error(f"close: writer thread did not finish within {timeout_s:g} s")
        return self.stats()

    async def aclose(self, timeout_s: float = 10.0) -> dict[str, Any]:
        """`close` without blocking the event loop (joins the thread in an executor)."""
        import asyncio

        return await asyncio.to_thread(self.close, timeout_s)

    def __enter__(self) -> TelemetryWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- process mode: this side ------------------------------------------------------------
    def _process_stats(self) -> dict[str, Any]:
        """The writer process's latest counters with this side's (ring, forwarding) folded in."""
        with self._lock:
            st = dict(self._child_stats) or {
                "written": 0, "dropped_ring_full": 0, "dropped_io": 0, "dropped_bytes": 0, "decimated": 0,
                "errors": 0, "first_error": None, "last_error": None, "failing": False, "failed_segments_kept": 0,
                "failed_segments_removed": 0, "bytes": 0, "pending": 0, "events_written": 0, "events_dropped": 0,
                "segments": 0, "sink_errors": []}
            lost = 0
            if self._child_error is not None:  # forwarded rows the process neither wrote nor counted: lost with it
                accounted = st["written"] + st["decimated"] + st["dropped_ring_full"] + st["dropped_io"]
                lost = max(0, self._forwarded - accounted)
            st["dropped_ring_full"] += self._dropped_full
            st["dropped_io"] += self._dropped_io + lost
            st["dropped"] = st["dropped_ring_full"] + st["dropped_io"]
            st["events_dropped"] += self._events_dropped
            st["pending"] += self._head - self._tail
            if self._errors:
                st["errors"] += self._errors
                st["first_error"] = st["first_error"] or self._first_error
                st["last_error"] = self._last_error
            st["failing"] = bool(st["failing"] or self._child_error is not None)
            st.update(capacity=self.capacity, compression=self.compression, compression_note=self._compression_note,
                      path=os.fspath(self.path) if self.path is not None else None,
                      writer_pid=self._child.pid if self._child is not None else None)
            return st

    def _run_process(self) -> None:
        demote_current_thread(self._avoid_cpus)  # the process inherits this thread's policy and CPUs
        try:
            self._start_child()
        except Exception as e:  # noqa: BLE001 - counted: the rows are dropped
            self._child_down(f"cannot start the telemetry writer process: {type(e).__name__}: {e}")
        self._every_flush(self._forward, self._forward_interval_s)
        self._finish_process()

    def _start_child(self) -> None:
        """A fresh interpreter (not multiprocessing's spawn, which would re-import the caller's main module) talking
        over a socket pair: the options first, then row batches and events; counters come back."""
        import socket
        import subprocess
        import sys
        from multiprocessing.connection import Connection

        ours, theirs = socket.socketpair()
        try:
            # a session of its own: a terminal's ^C or a signal to the daemon's process group does not cut the file
            # short; the process finishes when its input ends (the daemon closed it, or died)
            self._child = subprocess.Popen(
                [sys.executable, "-c", "from dragd.telemetry.writer import _writer_main; _writer_main()",
                 str(theirs.fileno())], pass_fds=[theirs.fileno()], stdin=subprocess.DEVNULL, close_fds=True,
                start_new_session=True)
        except BaseException:
            ours.close()
            raise
        finally:
            theirs.close()
        self._conn = Connection(ours.detach())
        self._conn.send(("start", self._child_kwargs))

    def _forward(self) -> None:
        """Hand the ring's rows and the queued events to the writer process; take its counters."""
        taken = self._take_rows()
        events: list[tuple[int, str, dict[str, Any]]] = []
        while self._events:
            events.append(self._events.popleft())
        if self._child_error is None and events:
            try:
                self._conn.send(("events", events))
                events = []
            except (OSError, EOFError) as e:
                self._child_down(f"the telemetry writer process is gone ({type(e).__name__}: {e})")
            except Exception as e:  # noqa: BLE001 - an event field pickle refuses: those events are counted lost
                self._record_error(f"telemetry events not forwarded: {type(e).__name__}: {e}")
        if self._child_error is None and taken is not None:
            try:
                self._conn.send(("rows", taken[0], taken[1], taken[2]))
                with self._lock:
                    self._forwarded += len(taken[1])
                taken = None
            except (OSError, EOFError, ValueError) as e:
                self._child_down(f"the telemetry writer process is gone ({type(e).__name__}: {e})")
        if taken is not None or events:
            with self._lock:
                self._dropped_io += 0 if taken is None else len(taken[1])
                self._events_dropped += len(events)
        self._receive_stats()

    def _receive_stats(self, timeout_s: float = 0.0) -> bool:
        """Take every message the process sent; True once its final counters came."""
        try:
            while self._conn is not None and self._child_error is None and self._conn.poll(timeout_s):
                kind, st = self._conn.recv()
                if kind == "failed":
                    self._child_down(f"the telemetry writer process failed: {st}")
                    break
                with self._lock:
                    self._child_stats = st
                if kind == "final":
                    return True  # the process closes its end after this
                timeout_s = 0.0
        except (OSError, EOFError) as e:
            self._child_down(f"the telemetry writer process is gone ({type(e).__name__}: {e})")
        return False

    def _finish_process(self) -> None:
        """Ask the process to finish its file within ``close``'s budget; past it, kill it (its rows counted lost)."""
        import subprocess

        if self._child is None:
            return
        budget = max(1.0, self._close_timeout_s - 1.0)  # within close()'s join
        if self._child_error is None:
            try:
                self._conn.send(("close", max(0.5, budget - 1.0)))
            except (OSError, EOFError, ValueError) as e:
                self._child_down(f"the telemetry writer process is gone ({type(e).__name__}: {e})")
        end = time.monotonic() + budget
        while self._child_error is None and time.monotonic() < end:
            if self._receive_stats(0.1):
                break
        else:
            if self._child_error is None:
                self._child_down(f"close: the telemetry writer process did not finish within {budget:g} s; killed")
        if self._conn is not None:
            self._conn.close()  # a live process sees the end of its input
        try:
            self._child.wait(max(0.2, end - time.monotonic()))
        except subprocess.TimeoutExpired:
            self._child.kill()
            try:
                self._child.wait(5.0)
            except subprocess.TimeoutExpired:
                self._record_error(f"close: the telemetry writer process {self._child.pid} did not exit after SIGKILL")

    def _child_down(self, message: str) -> None:
        """The writer process is gone (or given up): say so; from now on its unwritten rows count as dropped."""
        import subprocess

        if self._child_error is not None:
            return
        code = None
        if self._child is not None:
            try:
                code = self._child.wait(0.5)  # its socket closes a moment before it can be reaped
            except subprocess.TimeoutExpired:
                code = None
        self._child_error = message + ("" if code is None else f", exit code {code}")
        self._record_error(self._child_error)

    def _put_events(self, events: Iterable[tuple[int, str, dict[str, Any]]]) -> None:
        """Writer process: events another producer stamped, into this writer's queue (its pending cap applies)."""
        for ev in events:
            if len(self._events) >= self._max_pending_events:
                with self._lock:
                    self._events_dropped += 1
            else:
                self._events.append(ev)

    def _put_rows(self, rows: np.ndarray, stamps: Sequence[int], seqs: Sequence[int]) -> None:
        """Writer process: rows that another producer numbered (``seqs``) into this ring; those that do not fit
        are counted as dropped (ring full)."""
        n = len(stamps)
        free = self.capacity - (self._head - self._tail)
        take = max(0, min(n, free))
        if take:
            idx = (self._head + np.arange(take)) % self.capacity
            self._rows[idx] = rows[:take]
            self._stamps[idx] = stamps[:take]
            self._seqs[idx] = seqs[:take]
            self._head += take
        self._dropped_full += n - take

    # -- writer thread ----------------------------------------------------------------------
    def _prepare_path(self, on_exists: str) -> None:
        assert self.path is not None
        p = self.path
        if not p.parent.is_dir():
            raise TelemetryError(f"telemetry directory {p.parent} does not exist (for {p})")
        if p.is_dir():
            raise TelemetryError(f"telemetry path {p} is a directory; expected a file name like telemetry.mcap")
        if p.exists():
            if on_exists == "error":
                raise TelemetryError(f"telemetry file {p} already exists (on_exists='error')")
            if on_exists == "rotate" and p.is_file():  # never rename devices/FIFOs
                try:
                    p.rename(_rotated_name(p, p.stat().st_mtime))
                except OSError as e:
                    raise TelemetryError(f"cannot rotate existing telemetry file {p}: {e.strerror}") from e
                self._prune_rotated()
        try:
            self._raw = open(p, "wb", buffering=0)
        except OSError as e:
            raise TelemetryError(f"cannot open telemetry file {p} for writing: {e.strerror}") from e

    def _prune_rotated(self) -> None:
        if self.path is None or self._keep_rotated is None:
            return
        old = _rotated_files(self.path)
        for p in old[: max(0, len(old) - self._keep_rotated)]:
            try:
                p.unlink()
            except OSError:
                pass

    def _record_error(self, message: str) -> None:
        with self._lock:
            self._errors += 1
            self._last_error = message
            if self._first_error is None:
                self._first_error = message

    def _describe(self, exc: BaseException, doing: str) -> str:
        where = os.fspath(self.path) if self.path is not None else "the telemetry file object"
        if isinstance(exc, OSError) and exc.errno is not None:
            return f"{doing} {where}: [{errno.errorcode.get(exc.errno, exc.errno)}] {exc.strerror or exc}"
        return f"{doing} {where}: {type(exc).__name__}: {exc}"

    def _start_segment(self) -> None:
        """Open (if needed) and start an MCAP in ``self._raw`` / the file object."""
        if self._raw is None and self._file_obj is None:
            assert self.path is not None
            if self.path.is_file():
                if self._failed_at is None:  # a roll-over: the finished file goes aside, the oldest beyond N go
                    self.path.rename(_rotated_name(self.path, self.path.stat().st_mtime))
                    self._prune_rotated()
                elif self._failed_rows > 0:  # a retry: the failed file holds rows (readable up to its last
                    # chunk): kept aside, and no older log is deleted for it (a full disk must not eat them)
                    self.path.rename(_rotated_name(self.path, self.path.stat().st_mtime))
                    self._failed_kept += 1
                else:  # a retry over a failed file without a single row: nothing to keep
                    self.path.unlink()
                    self._failed_removed += 1
                self._failed_rows = 0
            self._raw = open(self.path, "wb", buffering=0)
        self._segment_rows = 0
        target = self._raw if self._file_obj is None else self._file_obj
        start = 0
        if self._file_obj is not None:
            try:
                start = self._file_obj.tell()
            except (OSError, AttributeError, io.UnsupportedOperation):
                start = 0
        stream = _CountingStream(target, start)
        with self._lock:
            self._stream = stream
            self._segments += 1
        self._mcap = McapFile(
            stream,
            self.layout,
            topic=self.topic,
            events_topic=self.events_topic,
            compression=self._compression,
            chunk_size=self._chunk_size,
            schema_name=self._schema_name,
            metadata=self._metadata,
            foxglove=self._foxglove,
            cycle_decimation=self._decimation,
        )
        self._failed_at = None

    def _fail(self, exc: BaseException, doing: str) -> None:
        """Abandon the current segment after an error; count what was lost."""
        self._record_error(self._describe(exc, doing))
        if self._mcap is not None:
            self._failed_rows = self._segment_rows
        with self._lock:
            self._dropped_io += self._unflushed_rows
            self._dropped_bytes += self._unflushed_bytes
            self._events_dropped += self._unflushed_events
            if self._stream is not None:
                self._bytes_done += self._stream.position
            self._stream = None
        self._unflushed_rows = self._unflushed_events = self._unflushed_bytes = 0
        self._mcap = None
        self._failed_at = time.monotonic()
        if self._file_obj is None and self._raw is not None:
            try:
                self._raw.close()
            except OSError:
                pass
            self._raw = None

    def _note_flush(self) -> None:
        """Rows/events added so far reached the file when the stream position moved."""
        assert self._stream is not None
        with self._lock:
            self._written += self._unflushed_rows
            self._events_written += self._unflushed_events
        self._segment_rows += self._unflushed_rows
        self._unflushed_rows = self._unflushed_events = self._unflushed_bytes = 0

    def _add(self, log_time: int, data: bytes, seq: int, is_row: bool, name: str | None = None) -> None:
        assert self._mcap is not None and self._stream is not None
        before = self._stream.position
        self._unflushed_bytes += len(data)
        if is_row:
            self._unflushed_rows += 1
            self._mcap.add_row(data, log_time, seq)
        else:
            self._unflushed_events += 1
            self._mcap.add_event(data, log_time, name)
        if self._stream.position != before:
            self._note_flush()

    def _finish_segment(self) -> None:
        """Write statistics metadata + summary and close the current segment."""
        if self._mcap is None:
            return
        mcap = self._mcap
        try:
            st = self.stats()
            st["written"] += self._unflushed_rows  # finish() below writes them
            st["events_written"] += self._unflushed_events
            mcap.finish(
                {
                    k: st[k]
                    for k in ("written", "dropped", "dropped_ring_full", "dropped_io", "decimated", "errors",
                              "first_error", "events_written", "events_dropped", "segments")
                }
            )
            self._stream.flush()  # type: ignore[union-attr]
            if self._file_obj is None and self._raw is not None:
                try:
                    os.fsync(self._raw.fileno())  # a finished file survives a power cut
                except OSError:
                    pass  # not a regular file (FIFO, device): nothing to sync
            self._note_flush()
        except Exception as e:  # noqa: BLE001 - any failure: count and move on
            self._fail(e, "finishing")
            return
        with self._lock:
            assert self._stream is not None
            self._bytes_done += self._stream.position
            self._stream = None
        self._mcap = None
        if self._file_obj is None and self._raw is not None:
            try:
                self._raw.close()
            except OSError as e:
                self._record_error(self._describe(e, "closing"))
            self._raw = None

    def _ensure_segment(self) -> bool:
        if self._mcap is not None:
            return True
        if self._failed_at is not None:
            if self._file_obj is not None or self._retry_after_s is None:
                return False
            if time.monotonic() - self._failed_at < self._retry_after_s:
                return False
        try:
            self._start_segment()
            return True
        except Exception as e:  # noqa: BLE001
            self._fail(e, "starting")
            return False

    def _take_rows(self) -> tuple[np.ndarray, list[int], list[int]] | None:
        head = self._head
        n = head - self._tail
        if n <= 0:
            return None
        idx = np.arange(self._tail, head) % self.capacity
        rows = self._rows[idx]  # copies
        stamps = self._stamps[idx].tolist()
        seqs = self._seqs[idx].tolist()
        self._tail = head  # slots free for the producer again
        return rows, stamps, seqs

    def _drain(self) -> None:
        taken = self._take_rows()
        events: list[tuple[int, str, dict[str, Any]]] = []
        while self._events:
            events.append(self._events.popleft())
        if taken is None and not events:
            return
        if taken is not None:
            self._feed_sinks(taken[0], taken[1])
        for ev in events:
            self._feed_sinks_event(ev)
        if not self._ensure_segment():
            with self._lock:
                self._dropped_io += 0 if taken is None else len(taken[1])
                self._events_dropped += len(events)
            return
        events_done = rows_done = 0
        batch_rows = 0 if taken is None else len(taken[1])
        try:
            for t, name, fields in events:
                data = McapFile.encode_event(name, fields)
                events_done += 1  # from here on a failure is counted by _fail()
                self._add(t, data, 0, False, name)
                assert self._mcap is not None
                if name != HAND_EVENT:  # (the state snapshots have their own channel, not the log's lines)
                    self._unflushed_bytes += self._mcap.add_foxglove_event(t, name, fields)
            if taken is not None:
                rows, stamps, seqs = taken
                assert self._mcap is not None
                if self._mcap.foxglove is not None:
                    self._unflushed_bytes += self._mcap.add_foxglove_rows(rows, stamps)
                    time.sleep(_YIELD_S)
                d = self._decimation
                if d > 1:  # thinned out by choice: counted apart (not lost, not written)
                    keep = np.flatnonzero(np.asarray(seqs, dtype=np.int64) % d == 0)
                    with self._lock:
                        self._decimated += len(seqs) - keep.size
                    batch_rows = keep.size
                    rows = rows[keep]
                    stamps = [stamps[i] for i in keep.tolist()]
                    seqs = [seqs[i] for i in keep.tolist()]
                finite = np.isfinite(rows).all(axis=1).tolist()
                encode_row = self._mcap.encode_row
                for values, ok, t, seq in zip(rows.tolist(), finite, stamps, seqs, strict=True):
                    data = encode_row(values, ok)
                    rows_done += 1  # from here on a failure is counted by _fail()
                    self._add(t, data, seq, True)
                    if rows_done % self._yield_every == 0:
                        time.sleep(_YIELD_S)  # hand the GIL to the cycle thread
        except Exception as e:  # noqa: BLE001 - never let the writer thread die
            # rows/events of this batch not handed to the MCAP writer are lost too
            with self._lock:
                self._dropped_io += batch_rows - rows_done
                self._events_dropped += len(events) - events_done
            self._fail(e, "writing")
            return
        if self._max_bytes is not None and self._stream is not None and self.path is not None:
            if self._stream.position + self._unflushed_bytes >= self._max_bytes:
                self._finish_segment()  # next drain starts a fresh file (old one rotated)

    def _feed_sinks(self, rows: np.ndarray, stamps: list[int]) -> None:
        if not self._sinks:
            return
        t = np.asarray(stamps, dtype=np.int64)
        for sink in list(self._sinks):
            try:
                sink.write_rows(self.layout, rows, t)
            except Exception as e:  # noqa: BLE001
                self._drop_sink(sink, e)

    def _feed_sinks_event(self, ev: tuple[int, str, dict[str, Any]]) -> None:
        for sink in list(self._sinks):
            try:
                sink.write_event(*ev)
            except Exception as e:  # noqa: BLE001
                self._drop_sink(sink, e)

    def _drop_sink(self, sink: RowSink, exc: BaseException) -> None:
        self._sinks.remove(sink)
        with self._lock:
            self._sink_errors.append(f"{type(sink).__name__} disabled: {type(exc).__name__}: {exc}")

    def _every_flush(self, step: Callable[[], None], interval_s: float | None = None) -> None:
        """Run ``step`` every ``interval_s`` (``flush_interval_s``) until close(), and once more after it (the
        last rows)."""
        while not self._stop.wait(self._flush_interval_s if interval_s is None else interval_s):
            step()
        step()

    def _run(self) -> None:
        demote_current_thread(self._avoid_cpus)
        self._ensure_segment()
        self._every_flush(self._drain)
        self._finish_segment()
        for sink in self._sinks:
            try:
                sink.close()
            except Exception as e:  # noqa: BLE001
                with self._lock:
                    self._sink_errors.append(f"{type(sink).__name__} close: {e}")


def _portable_layout(layout: Mapping[str, int | Field]) -> dict[str, int | Field]:
    """The layout with enum labels as plain mappings (the writer process need not import the caller's enums)."""
    out: dict[str, int | Field] = {}
    for name, f in layout.items():
        if isinstance(f, Field) and f.labels is not None:
            f = dataclasses.replace(f, labels=normalize_labels(name, f.labels))
        out[name] = f
    return out


def _writer_main() -> None:
    """Entry of the writer process: ``python -c ... FD`` with FD one end of the daemon's socket pair."""
    import signal
    import sys
    from multiprocessing.connection import Connection

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the daemon decides when to stop (a terminal's ^C reaches both)
    conn = Connection(int(sys.argv[1]))
    try:
        kind, kwargs = conn.recv()
    except (EOFError, OSError):
        return
    if kind == "start":
        _writer_process(conn, kwargs)
    conn.close()


def _writer_process(conn: Any, kwargs: dict[str, Any]) -> None:
    """The writer process (``process=True``): this module's writer in thread mode, fed from the pipe."""
    fox = kwargs.pop("foxglove")
    writer: TelemetryWriter | None = None
    close_timeout_s = 10.0
    try:
        try:
            writer = TelemetryWriter(**kwargs, foxglove=None if fox is None else FoxgloveSpec(**fox))
        except Exception as e:  # noqa: BLE001 - reported to the daemon, which counts the rows as dropped
            conn.send(("failed", f"{type(e).__name__}: {e}"))
            return
        next_stats = 0.0
        while True:
            if conn.poll(0.1):
                msg = conn.recv()
                if msg[0] == "rows":
                    writer._put_rows(msg[1], msg[2], msg[3])
                elif msg[0] == "events":
                    writer._put_events(msg[1])
                elif msg[0] == "close":
                    close_timeout_s = float(msg[1])
                    break
            now = time.monotonic()
            if now >= next_stats:
                conn.send(("stats", writer.stats()))
                next_stats = now + 0.1
    except (EOFError, OSError):
        pass  # the daemon is gone: finish the file
    finally:
        if writer is not None:
            st = writer.close(close_timeout_s)
            try:
                conn.send(("final", st))
            except (OSError, EOFError):
                pass

