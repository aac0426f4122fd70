"""MCAP telemetry written off the loop, and `summarize` for ``dragd log summary``.

The cycle side is a single-producer ring of preallocated float64 rows::

    writer = TelemetryWriter(path, {"t_s": 1, "mode": Field(labels=Mode), "q_rad": 6, ...})
    Q = writer.slices["q_rad"]                 # once, outside the cycle
    row = writer.begin()                       # in the cycle: a preallocated row view
    if row is not None:                        # None: ring full, the row is counted as dropped
        row[0] = t_s; row[Q] = q               # fill *every* field (slots are reused)
        writer.commit()

A writer thread drains the ring every ``flush_interval_s``, encodes each row as a
JSON message (channel ``topic``, encoding ``json``, JSON Schema registered so
Foxglove shows arrays as arrays, numbers as numbers, enum fields as their label),
and writes a chunked, compressed MCAP. I/O errors, a full disk or a slow disk never
reach the cycle: rows are dropped and counted, the first error is kept and
`stats()` reports it. After an I/O error the writer retries on a fresh file
(``retry_after_s``); ``max_bytes`` rolls over to a new file, keeping ``keep_rotated``
old ones. `close()` finishes the file (summary, indexes, statistics).

MCAP ``sequence`` of a cycle message is the producer's row counter (``begin`` calls),
so a gap in sequence numbers shows exactly where rows were dropped.

GIL: the writer thread competes with the cycle thread for the GIL. Float formatting
dominates its work, so rows are formatted through a precompiled template with
``float_digits`` significant digits (~9 us/row here instead of ~30 us with
``json.dumps``), chunks are small (64 KiB: short bursts when a chunk is indexed and
compressed; zstd itself releases the GIL), and the thread sleeps briefly every
``yield_every_rows`` rows so a waiting cycle thread gets the GIL at once.
"""

from __future__ import annotations

import collections
import enum
import errno
import importlib.util
import io
import json
import math
import os
import re
import struct
import threading
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, BinaryIO, Iterable, Literal, Mapping, Protocol, Sequence, Union

import numpy as np
from mcap.exceptions import EndOfFile
from mcap.records import Channel, Chunk, Footer, Header, Message, Metadata, Schema, Statistics
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType, Writer

from dragd.realtime import demote_current_thread

__all__ = [
    "Field",
    "RowLayout",
    "TelemetryWriter",
    "TelemetryError",
    "TelemetryFileError",
    "RowSink",
    "RerunSink",
    "RerunUnavailable",
    "rerun_unavailable",
    "summarize",
    "CYCLE_TOPIC",
    "EVENTS_TOPIC",
]

_YIELD_S = 50e-6  # writer pause between row slices (releases the GIL)

CYCLE_TOPIC = "/dragd/cycle"
EVENTS_TOPIC = "/dragd/events"
MCAP_MAGIC = b"\x89MCAP0\r\n"

Labels = Union[Mapping[int, str], Sequence[str], type[enum.Enum]]


class TelemetryError(RuntimeError):
    """The telemetry file cannot be set up (bad path, directory missing, ...)."""


class TelemetryFileError(ValueError):
    """A telemetry file cannot be read: missing, not MCAP, truncated or corrupt."""


# -- layout ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class Field:
    """A layout entry: ``width`` values of ``kind``; ``labels`` make it an enum (label strings)."""

    width: int = 1
    kind: Literal["float", "int", "bool"] = "float"
    labels: Labels | None = None
    description: str | None = None
    digits: int | None = None
    """Significant digits written for floats (default: the writer's ``float_digits``)."""


def _normalize_labels(name: str, labels: Labels) -> dict[int, str]:
    if isinstance(labels, type) and issubclass(labels, enum.Enum):
        out = {}
        for member in labels:
            if not isinstance(member.value, int):
                raise ValueError(f"field {name!r}: enum {labels.__name__} needs integer values")
            out[int(member.value)] = member.name
        return out
    if isinstance(labels, Mapping):
        return {int(k): str(v) for k, v in labels.items()}
    if isinstance(labels, (list, tuple)):
        return {i: str(v) for i, v in enumerate(labels)}
    raise ValueError(
        f"field {name!r}: labels must be an int Enum, a mapping int -> str or a list of names; "
        f"got {type(labels).__name__}"
    )


@dataclass(frozen=True)
class _Column:
    name: str
    offset: int
    width: int
    kind: str  # "float" | "int" | "bool" | "enum"
    labels: dict[int, str] | None
    description: str | None
    digits: int


_NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


class RowLayout:
    """Ordered fields of a telemetry row: offsets, slices, JSON Schema and row encoders.

    Floats are written with ``float_digits`` significant digits (12 by default:
    1 us resolution for a ``t_s`` up to 10^6 s; ``Field(digits=17)`` round-trips
    float64 exactly). Formatting floats dominates the writer's CPU (and GIL) time,
    hence the precompiled %-template in `encode_json`.
    """

    def __init__(self, layout: Mapping[str, int | Field], float_digits: int = 12) -> None:
        if not layout:
            raise ValueError("telemetry layout is empty; expected e.g. {'t_s': 1, 'q_rad': 6}")
        if not 1 <= float_digits <= 17:
            raise ValueError(f"float_digits must be in 1..17; got {float_digits}")
        cols: list[_Column] = []
        offset = 0
        for name, spec in layout.items():
            if not isinstance(name, str) or not _NAME_RE.match(name):
                raise ValueError(f"telemetry field name {name!r} must be an identifier like 'q_rad'")
            f = spec if isinstance(spec, Field) else Field(width=spec)
            if isinstance(f.width, bool) or not isinstance(f.width, int) or f.width < 1:
                raise ValueError(f"telemetry field {name!r}: width must be an int >= 1; got {f.width!r}")
            if f.kind not in ("float", "int", "bool"):
                raise ValueError(
                    f"telemetry field {name!r}: kind must be 'float', 'int' or 'bool'; got {f.kind!r}"
                )
            digits = float_digits if f.digits is None else f.digits
            if not 1 <= digits <= 17:
                raise ValueError(f"telemetry field {name!r}: digits must be in 1..17; got {digits}")
            labels = _normalize_labels(name, f.labels) if f.labels is not None else None
            kind = "enum" if labels is not None else f.kind
            cols.append(_Column(name, offset, f.width, kind, labels, f.description, digits))
            offset += f.width
        self.columns: tuple[_Column, ...] = tuple(cols)
        self.width = offset
        self.names = tuple(c.name for c in cols)
        self.slices: dict[str, slice] = {c.name: slice(c.offset, c.offset + c.width) for c in cols}
        self._plan = tuple((c.name, c.offset, c.width, c.kind, c.labels, c.digits) for c in cols)
        parts = []
        special: list[tuple[int, dict[int, str] | None]] = []
        for c in cols:
            fmt = {"float": f"%.{c.digits}g", "int": "%d"}.get(c.kind, "%s")
            if c.kind in ("enum", "bool"):
                quoted = (
                    {k: json.dumps(v) for k, v in c.labels.items()} if c.labels is not None else None
                )
                special.extend((c.offset + j, quoted) for j in range(c.width))
            body = fmt if c.width == 1 else "[" + ",".join([fmt] * c.width) + "]"
            parts.append(f'"{c.name}":{body}')
        self._template = "{" + ",".join(parts) + "}"
        self._special = tuple(special)

    def encode_json(self, values: list[Any]) -> bytes:
        """Compact JSON of one row of *finite* values (flat list; modified in place)."""
        for off, quoted in self._special:
            v = int(values[off])
            if quoted is None:
                values[off] = "true" if v else "false"
            else:
                values[off] = quoted.get(v) or f'"{v}"'
        return (self._template % tuple(values)).encode()

    def json_schema(self, title: str = "dragd.Cycle") -> dict[str, Any]:
        """JSON Schema of an encoded row (what Foxglove reads to type the fields)."""
        props: dict[str, Any] = {}
        for c in self.columns:
            if c.kind == "enum":
                assert c.labels is not None
                item: dict[str, Any] = {
                    "type": "string",
                    "description": "one of " + ", ".join(c.labels[k] for k in sorted(c.labels)),
                }
            elif c.kind == "int":
                item = {"type": "integer"}
            elif c.kind == "bool":
                item = {"type": "boolean"}
            else:
                item = {"type": "number"}
            if c.description and c.kind != "enum":
                item["description"] = c.description
            if c.width == 1:
                props[c.name] = item
            else:
                props[c.name] = {
                    "type": "array",
                    "items": item,
                    "minItems": c.width,
                    "maxItems": c.width,
                }
                if c.description:
                    props[c.name]["description"] = c.description
        return {
            "title": title,
            "type": "object",
            "description": "one dragd control cycle; non-finite numbers are written as null",
            "properties": props,
            "required": list(self.names),
        }

    def encode(self, values: Sequence[float]) -> dict[str, Any]:
        """Row values (flat, e.g. ``row.tolist()``) -> JSON-ready dict (non-finite -> None)."""
        out: dict[str, Any] = {}
        for name, off, w, kind, labels, digits in self._plan:
            if w == 1:
                out[name] = _convert(values[off], kind, labels, digits)
            else:
                out[name] = [_convert(v, kind, labels, digits) for v in values[off : off + w]]
        return out

    def encode_any(self, values: list[float]) -> bytes:
        """Compact JSON of one row; rows with NaN/inf take the slower dict path (-> null)."""
        if all(map(math.isfinite, values)):
            return self.encode_json(values)
        return _dumps(self.encode(values))


def _convert(v: float, kind: str, labels: dict[int, str] | None, digits: int) -> Any:
    if v != v or v in (math.inf, -math.inf):
        return None
    if kind == "float":
        return float(f"{v:.{digits}g}")
    if kind == "int":
        return int(v)
    if kind == "bool":
        return bool(v)
    assert labels is not None
    i = int(v)
    return labels.get(i, str(i))


def _dumps(obj: Any) -> bytes:
    """Compact JSON; NaN/inf -> null (strict JSON for Foxglove)."""
    try:
        return json.dumps(obj, separators=(",", ":"), allow_nan=False, default=_default).encode()
    except ValueError:
        return json.dumps(_finite(obj), separators=(",", ":"), allow_nan=False, default=_default).encode()


def _finite(obj: Any) -> Any:
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    return obj


def _default(obj: Any) -> Any:
    tolist = getattr(obj, "tolist", None)
    if callable(tolist):
        return tolist()
    if isinstance(obj, enum.Enum):
        return obj.name
    return str(obj)


# -- sinks ----------------------------------------------------------------------------------


class RowSink(Protocol):
    """Extra consumer of drained rows (runs in the writer thread, never in the cycle)."""

    def write_rows(self, layout: RowLayout, rows: np.ndarray, log_time_ns: np.ndarray) -> None: ...

    def write_event(self, log_time_ns: int, name: str, fields: Mapping[str, Any]) -> None: ...

    def close(self) -> None: ...


class RerunUnavailable(ImportError):
    """rerun-sdk is not installed."""


RERUN_HINT = (
    "the live view needs the optional extra dragd[rerun] (rerun-sdk==0.41.0): "
    "pip install 'dragd[rerun]'"
)


def rerun_unavailable() -> str | None:
    """None when rerun-sdk can be imported, else the message telling how to install it."""
    try:
        found = importlib.util.find_spec("rerun") is not None
    except ValueError:
        found = False
    return None if found else RERUN_HINT


class RerunSink:
    """Logs the telemetry rows to a Rerun viewer (``dragd run --rerun``).

    ``url`` connects to a running viewer (gRPC), ``save_path`` writes an .rrd file,
    otherwise a viewer is spawned. Raises RerunUnavailable when rerun-sdk is missing.
    Each scalar becomes ``cycle/<field>`` (``cycle/<field>/<joint>`` for arrays) on
    the ``time`` timeline (wall-clock log time); rows are sent in columnar batches.
    """

    def __init__(
        self,
        *,
        app_id: str = "dragd",
        url: str | None = None,
        save_path: str | os.PathLike[str] | None = None,
        spawn: bool = True,
        timeline: str = "time",
    ) -> None:
        try:
            import rerun as rr
        except ImportError as e:
            raise RerunUnavailable(RERUN_HINT) from e
        self._rr = rr
        self._timeline = timeline
        rr.init(app_id)
        if url is not None:
            rr.connect_grpc(url)
        elif save_path is not None:
            rr.save(os.fspath(save_path))
        elif spawn:
            rr.spawn()

    def write_rows(self, layout: RowLayout, rows: np.ndarray, log_time_ns: np.ndarray) -> None:
        rr = self._rr
        times = [rr.TimeColumn(self._timeline, timestamp=log_time_ns.astype("datetime64[ns]"))]
        for c in layout.columns:
            for j in range(c.width):
                path = f"cycle/{c.name}" if c.width == 1 else f"cycle/{c.name}/{j}"
                rr.send_columns(
                    path, indexes=times, columns=rr.Scalars.columns(scalars=rows[:, c.offset + j])
                )

    def write_event(self, log_time_ns: int, name: str, fields: Mapping[str, Any]) -> None:
        rr = self._rr
        rr.set_time(self._timeline, timestamp=np.datetime64(log_time_ns, "ns"))
        text = name + (" " + json.dumps(fields, default=_default) if fields else "")
        rr.log("events", rr.TextLog(text))

    def close(self) -> None:
        disconnect = getattr(self._rr, "disconnect", None)
        if callable(disconnect):
            disconnect()


# -- the writer -----------------------------------------------------------------------------


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
    stamp = datetime.fromtimestamp(when, timezone.utc).strftime("%Y%m%dT%H%M%SZ")
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


class TelemetryWriter:
    """Off-loop MCAP writer fed by a preallocated ring of rows (see module docstring).

    ``path`` is a file path (created; an existing file is handled per ``on_exists``)
    or an open binary file object (not closed by us; no rotation/retry).
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
        compression: Literal["zstd", "lz4", "none"] = "zstd",
        chunk_size: int = 64 * 1024,
        flush_interval_s: float = 0.02,
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
        schema_name: str = "dragd.Cycle",
    ) -> None:
        if capacity < 2:
            raise ValueError(f"telemetry capacity must be >= 2 rows; got {capacity}")
        if on_exists not in ("rotate", "overwrite", "error"):
            raise ValueError(f"on_exists must be 'rotate', 'overwrite' or 'error'; got {on_exists!r}")
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
        self._events_dropped = 0
        self._sink_errors: list[str] = []
        self._segments = 0
        self._unflushed_rows = 0
        self._unflushed_events = 0
        self._unflushed_bytes = 0
        self._failed_at: float | None = None
        self._mcap: Writer | None = None
        self._stream: _CountingStream | None = None
        self._raw: Any = None
        self._cycle_channel = 0
        self._event_channel = 0

        if isinstance(path, (str, os.PathLike)):
            self.path: Path | None = Path(path)
            self._file_obj: BinaryIO | None = None
            self._prepare_path(on_exists)
        else:
            if not callable(getattr(path, "write", None)):
                raise TypeError(f"path must be a file path or a binary file object; got {path!r}")
            self.path = None
            self._file_obj = path
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="dragd-telemetry", daemon=True)
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
    def event(self, name: str, **fields: Any) -> None:
        """Queue an event (mode change, fault, ...) for ``events_topic``."""
        if self._closed or len(self._events) >= self._max_pending_events:
            with self._lock:
                self._events_dropped += 1
            return
        self._events.append((time.time_ns(), str(name), fields))

    # -- status -----------------------------------------------------------------------------
    def stats(self) -> dict[str, Any]:
        """Counters: written/dropped rows, errors, first error, bytes on disk, ..."""
        with self._lock:
            current = self._stream.position if self._stream is not None else 0
            return {
                "written": self._written,
                "dropped": self._dropped_full + self._dropped_io,
                "dropped_ring_full": self._dropped_full,
                "dropped_io": self._dropped_io,
                "dropped_bytes": self._dropped_bytes,
                "errors": self._errors,
                "first_error": self._first_error,
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
        """Flush everything, finish the MCAP (summary + indexes) and stop the thread."""
        if not self._closed:
            self._closed = True
            self._stop.set()
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                self._record_error(f"close: writer thread did not finish within {timeout_s} s")
        return self.stats()

    async def aclose(self, timeout_s: float = 10.0) -> dict[str, Any]:
        """`close` without blocking the event loop (joins the thread in an executor)."""
        import asyncio

        return await asyncio.to_thread(self.close, timeout_s)

    def __enter__(self) -> "TelemetryWriter":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

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
                self.path.rename(_rotated_name(self.path, self.path.stat().st_mtime))
                self._prune_rotated()
            self._raw = open(self.path, "wb", buffering=0)
        target = self._raw if self._file_obj is None else self._file_obj
        start = 0
        if self._file_obj is not None:
            try:
                start = self._file_obj.tell()
            except (OSError, AttributeError, io.UnsupportedOperation):
                start = 0
        stream = _CountingStream(target, start)
        mcap = Writer(
            stream,  # type: ignore[arg-type]  # write/tell/flush is all mcap uses
            chunk_size=self._chunk_size,
            compression=self._compression,
        )
        with self._lock:
            self._stream = stream
            self._segments += 1
        mcap.start(profile="", library="dragd")
        schema_id = mcap.register_schema(
            name=self._schema_name,
            encoding="jsonschema",
            data=_dumps(self.layout.json_schema(self._schema_name)),
        )
        self._cycle_channel = mcap.register_channel(
            topic=self.topic, message_encoding="json", schema_id=schema_id
        )
        event_schema = {
            "title": "dragd.Event",
            "type": "object",
            "description": "rare daemon event; further fields depend on the event name",
            "properties": {"name": {"type": "string"}},
            "required": ["name"],
            "additionalProperties": True,
        }
        ev_schema_id = mcap.register_schema(
            name="dragd.Event", encoding="jsonschema", data=_dumps(event_schema)
        )
        self._event_channel = mcap.register_channel(
            topic=self.events_topic, message_encoding="json", schema_id=ev_schema_id
        )
        if self._metadata:
            mcap.add_metadata("dragd.run", {str(k): str(v) for k, v in self._metadata.items()})
        self._mcap = mcap
        self._failed_at = None

    def _fail(self, exc: BaseException, doing: str) -> None:
        """Abandon the current segment after an error; count what was lost."""
        self._record_error(self._describe(exc, doing))
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
        self._unflushed_rows = self._unflushed_events = self._unflushed_bytes = 0

    def _add(self, channel: int, log_time: int, data: bytes, seq: int, is_row: bool) -> None:
        assert self._mcap is not None and self._stream is not None
        before = self._stream.position
        if is_row:
            self._unflushed_rows += 1
        else:
            self._unflushed_events += 1
        self._unflushed_bytes += len(data)
        self._mcap.add_message(
            channel_id=channel, log_time=log_time, data=data, publish_time=log_time, sequence=seq
        )
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
            mcap.add_metadata(
                "dragd.telemetry.writer",
                {
                    k: str(st[k])
                    for k in ("written", "dropped", "dropped_ring_full", "dropped_io", "errors",
                              "first_error", "events_written", "events_dropped", "segments")
                },
            )
            mcap.finish()
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
        try:
            for t, name, fields in events:
                data = _dumps({"name": name, **fields})
                events_done += 1  # from here on a failure is counted by _fail()
                self._add(self._event_channel, t, data, 0, False)
            if taken is not None:
                rows, stamps, seqs = taken
                finite = np.isfinite(rows).all(axis=1).tolist()
                encode_json = self.layout.encode_json
                encode = self.layout.encode
                channel = self._cycle_channel
                for values, ok, t, seq in zip(rows.tolist(), finite, stamps, seqs):
                    data = encode_json(values) if ok else _dumps(encode(values))
                    rows_done += 1  # from here on a failure is counted by _fail()
                    self._add(channel, t, data, seq, True)
                    if rows_done % self._yield_every == 0:
                        time.sleep(_YIELD_S)  # hand the GIL to the cycle thread
        except Exception as e:  # noqa: BLE001 - never let the writer thread die
            # rows/events of this batch not handed to the MCAP writer are lost too
            with self._lock:
                self._dropped_io += (0 if taken is None else len(taken[1])) - rows_done
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

    def _run(self) -> None:
        demote_current_thread(self._avoid_cpus)
        self._ensure_segment()
        while True:
            stopping = self._stop.wait(self._flush_interval_s)
            self._drain()
            if stopping:
                break
        self._drain()
        self._finish_segment()
        for sink in self._sinks:
            try:
                sink.close()
            except Exception as e:  # noqa: BLE001
                with self._lock:
                    self._sink_errors.append(f"{type(sink).__name__} close: {e}")


# -- summary --------------------------------------------------------------------------------


class _FieldAcc:
    """Running min/max/mean per element (numbers) or label counts (strings) of one field."""

    def __init__(self, width: int, kind: str, is_array: bool) -> None:
        self.width = width
        self.kind = kind
        self.is_array = is_array
        self.nulls = 0
        self.total = np.zeros(width)
        self.valid = np.zeros(width, dtype=np.int64)
        self.lo = np.full(width, np.inf)
        self.hi = np.full(width, -np.inf)
        self.counts: dict[str, int] = {}
        self.block: list[list[Any]] = []

    def add(self, v: Any) -> None:
        if self.kind == "string":
            key = str(v) if v is not None else "null"
            self.counts[key] = self.counts.get(key, 0) + 1
            return
        row = v if isinstance(v, list) else [v]
        if len(row) != self.width or not all(isinstance(x, (int, float)) or x is None for x in row):
            row = [x if isinstance(x, (int, float)) else None for x in row[: self.width]]
            row += [None] * (self.width - len(row))
        self.block.append(row)
        if len(self.block) >= 4096:
            self.flush()

    def flush(self) -> None:
        if not self.block:
            return
        a = np.array(self.block, dtype=np.float64)
        self.block = []
        ok = np.isfinite(a)
        self.nulls += int((~ok).any(axis=1).sum())
        self.valid += ok.sum(axis=0)
        self.total += np.where(ok, a, 0.0).sum(axis=0)
        self.lo = np.minimum(self.lo, np.where(ok, a, np.inf).min(axis=0))
        self.hi = np.maximum(self.hi, np.where(ok, a, -np.inf).max(axis=0))

    def result(self) -> dict[str, Any]:
        if self.kind == "string":
            return {"type": "enum", "counts": dict(sorted(self.counts.items()))}
        self.flush()

        def pack(arr: np.ndarray) -> Any:
            vals = [float(x) if math.isfinite(x) else None for x in arr]
            return vals if self.is_array else vals[0]

        mean = np.where(self.valid > 0, self.total / np.maximum(self.valid, 1), np.nan)
        return {
            "type": "array" if self.is_array else "number",
            "min": pack(self.lo),
            "max": pack(self.hi),
            "mean": pack(mean),
            "rows_with_null": self.nulls,
        }


def _iso(ns: int) -> str:
    return datetime.fromtimestamp(ns / 1e9, timezone.utc).isoformat()


def summarize(
    path: str | os.PathLike[str],
    *,
    cycle_topic: str = CYCLE_TOPIC,
    events_topic: str = EVENTS_TOPIC,
    allow_truncated: bool = False,
) -> dict[str, Any]:
    """Summary of a telemetry MCAP for ``dragd log summary FILE.mcap``.

    Channels (topic, encodings, schema, message count), time range, per-field
    min/max/mean of the cycle topic (per joint for arrays; label counts for enum
    fields), sequence gaps (dropped rows), the events and the metadata records.
    Raises TelemetryFileError for a missing, non-MCAP, corrupt or (unless
    ``allow_truncated``) truncated file; a truncated file's readable part is
    summarized with ``"complete": False`` when ``allow_truncated`` is set.
    """
    p = Path(path)
    if not p.exists():
        raise TelemetryFileError(f"{p}: no such file")
    if p.is_dir():
        raise TelemetryFileError(f"{p}: is a directory, expected an .mcap file")
    size = p.stat().st_size
    with open(p, "rb") as f:
        head = f.read(8)
        if size == 0:
            raise TelemetryFileError(f"{p}: empty file (0 bytes), expected an MCAP file")
        if head != MCAP_MAGIC:
            raise TelemetryFileError(
                f"{p}: not an MCAP file (starts with {head.hex(' ')}, expected the MCAP magic "
                f"{MCAP_MAGIC.hex(' ')})"
            )
        f.seek(0)
        return _scan(p, f, size, cycle_topic, events_topic, allow_truncated)


def _scan(
    p: Path, f: BinaryIO, size: int, cycle_topic: str, events_topic: str, allow_truncated: bool
) -> dict[str, Any]:
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    counts: collections.Counter[int] = collections.Counter()
    metadata: dict[str, dict[str, str]] = {}
    events: list[dict[str, Any]] = []
    header: Header | None = None
    statistics: Statistics | None = None
    compressions: collections.Counter[str] = collections.Counter()
    accs: dict[str, _FieldAcc] | None = None
    start_ns: int | None = None
    end_ns: int | None = None
    rows = 0
    gaps = 0
    last_seq: int | None = None
    complete = False
    problem: str | None = None
    truncated = False

    def on_message(m: Message) -> None:
        nonlocal start_ns, end_ns, accs, rows, gaps, last_seq
        counts[m.channel_id] += 1
        start_ns = m.log_time if start_ns is None else min(start_ns, m.log_time)
        end_ns = m.log_time if end_ns is None else max(end_ns, m.log_time)
        ch = channels.get(m.channel_id)
        if ch is None:
            return
        if ch.topic == events_topic:
            try:
                d = json.loads(m.data)
            except ValueError:
                d = {"name": "<undecodable event>"}
            name = d.pop("name", "?") if isinstance(d, dict) else "?"
            events.append({"time_ns": m.log_time, "name": name, "fields": d if isinstance(d, dict) else {}})
        elif ch.topic == cycle_topic and ch.message_encoding == "json":
            try:
                d = json.loads(m.data)
            except ValueError:
                return
            if not isinstance(d, dict):
                return
            if accs is None:
                accs = _accumulators(schemas.get(ch.schema_id), d)
            rows += 1
            if m.sequence and last_seq is not None and m.sequence > last_seq + 1:
                gaps += m.sequence - last_seq - 1
            if m.sequence:
                last_seq = m.sequence
            for name, acc in accs.items():
                acc.add(d.get(name))

    def on_record(r: Any) -> None:
        nonlocal header, statistics
        if isinstance(r, Schema):
            schemas[r.id] = r
        elif isinstance(r, Channel):
            channels[r.id] = r
        elif isinstance(r, Message):
            on_message(r)
        elif isinstance(r, Metadata):
            metadata[r.name] = dict(r.metadata)
        elif isinstance(r, Header):
            header = r
        elif isinstance(r, Statistics):
            statistics = r

    reader = StreamReader(f, emit_chunks=True)
    try:
        for record in reader.records:
            if isinstance(record, Chunk):
                compressions[record.compression or "none"] += 1
                for inner in breakup_chunk(record, validate_crc=True):
                    on_record(inner)
            else:
                on_record(record)
            if isinstance(record, Footer):
                complete = True
    except (EndOfFile, struct.error, EOFError) as e:
        truncated = True
        problem = f"unexpected end of file ({type(e).__name__}{': ' + str(e) if str(e) else ''})"
    except Exception as e:  # noqa: BLE001 - mcap and decompressors raise many types
        problem = f"{type(e).__name__}: {e}"

    if not complete:
        if header is None:
            raise TelemetryFileError(f"{p}: corrupt MCAP, no readable header ({problem})")
        n = sum(counts.values())
        if not allow_truncated:
            what = (
                "truncated MCAP: no footer/summary, the writer did not finish "
                "(daemon killed or disk full?)"
                if truncated
                else "corrupt MCAP"
            )
            raise TelemetryFileError(
                f"{p}: {what} ({size} bytes); reading stopped at: {problem}; {n} complete "
                "messages before that are readable -- summarize with allow_truncated=True to see them"
            )

    channel_list = []
    for cid, ch in sorted(channels.items()):
        sch = schemas.get(ch.schema_id)
        channel_list.append(
            {
                "topic": ch.topic,
                "message_encoding": ch.message_encoding,
                "schema": sch.name if sch else None,
                "schema_encoding": sch.encoding if sch else None,
                "messages": counts.get(cid, 0),
            }
        )
    if start_ns is not None:
        for ev in events:
            ev["t_s"] = (ev["time_ns"] - start_ns) / 1e9
    cycle: dict[str, Any] | None = None
    if accs is not None:
        cycle = {
            "topic": cycle_topic,
            "rows": rows,
            "sequence_gaps": gaps,
            "fields": {name: acc.result() for name, acc in accs.items()},
        }
    return {
        "file": os.fspath(p),
        "size_bytes": size,
        "complete": complete,
        "problem": None if complete else problem,
        "library": header.library if header else None,
        "profile": header.profile if header else None,
        "chunks": dict(compressions),
        "schemas": sorted({s.name for s in schemas.values()}),
        "channels": channel_list,
        "message_count": sum(counts.values()),
        "start_ns": start_ns,
        "end_ns": end_ns,
        "start_utc": _iso(start_ns) if start_ns is not None else None,
        "duration_s": (end_ns - start_ns) / 1e9 if start_ns is not None and end_ns is not None else 0.0,
        "statistics_message_count": statistics.message_count if statistics else None,
        "cycle": cycle,
        "events": events,
        "metadata": metadata,
    }


def _accumulators(schema: Schema | None, first: Mapping[str, Any]) -> dict[str, _FieldAcc]:
    """Field accumulators in schema order (falls back to the first message's keys)."""
    props: dict[str, Any] = {}
    if schema is not None and schema.encoding == "jsonschema":
        try:
            props = json.loads(schema.data).get("properties", {}) or {}
        except (ValueError, AttributeError):
            props = {}
    names: Iterable[str] = props.keys() if props else first.keys()
    accs: dict[str, _FieldAcc] = {}
    for name in names:
        spec = props.get(name, {})
        sample = first.get(name)
        is_array = spec.get("type") == "array" or isinstance(sample, list)
        item = spec.get("items", {}) if is_array else spec
        if item.get("type") == "string" or isinstance(sample, str):
            accs[name] = _FieldAcc(1, "string", False)
        else:
            width = int(spec.get("maxItems") or (len(sample) if isinstance(sample, list) else 1))
            accs[name] = _FieldAcc(max(width, 1), "number", is_array)
    return accs


def read_rows(path: str | os.PathLike[str], topic: str = CYCLE_TOPIC) -> dict[str, np.ndarray]:
    """Every row of ``topic`` as column arrays (label fields stay strings); for analysis, not for the cycle."""
    from mcap.reader import make_reader

    cols: dict[str, list[Any]] = {}
    try:
        with open(path, "rb") as fh:
            for _, _, message in make_reader(fh).iter_messages(topics=[topic]):
                for k, v in json.loads(message.data).items():
                    cols.setdefault(k, []).append(v)
    except FileNotFoundError:
        raise TelemetryFileError(f"{path}: no such telemetry file") from None
    except (ValueError, KeyError) as exc:
        raise TelemetryFileError(f"{path}: not a readable dragd MCAP log ({exc})") from None
    return {k: np.array(v) for k, v in cols.items()}
