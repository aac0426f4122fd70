"""The one reader of dragd telemetry MCAP files: rows as arrays per field, events, metadata, the summary.

A file whose writer was killed (SIGKILL, power cut) or is still writing has no summary and no footer and may end
inside a chunk. It is read up to its last complete record: every message in a complete chunk is recovered, and
`TelemetryLog.truncated` / the summary's ``"truncated"`` say so (`read_rows` warns with
`TruncatedTelemetryWarning`). A file that is not MCAP, or holds a corrupt record (bad CRC, undecodable chunk),
raises `TelemetryFileError` naming the file.

Records are walked sequentially (no index needed); chunks are decompressed and split here, and the cycle rows'
JSON is decoded in batches, cut first to the requested fields (parsing ~100 numbers per row dominates reading).
"""

from __future__ import annotations

import collections
import json
import math
import os
import struct
import warnings
import zlib
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from io import BytesIO
from pathlib import Path
from typing import Any

import numpy as np
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import Channel, Header, Metadata, Schema, Statistics

from dragd.telemetry.schema import CYCLE_TOPIC, EVENTS_TOPIC

__all__ = [
    "Event",
    "TelemetryLog",
    "TelemetryFileError",
    "TruncatedTelemetryWarning",
    "read_log",
    "read_rows",
    "read_events",
    "read_metadata",
    "summarize",
]

MCAP_MAGIC = b"\x89MCAP0\r\n"
_BATCH_ROWS = 50_000  # rows decoded at once: a 10 min log is 600 k rows of ~1 kB
_RECORD = struct.Struct("<BQ")  # opcode, length
_MESSAGE = struct.Struct("<HIQ")  # channel id, sequence, log time (publish time follows)
_MESSAGE_HEAD = 2 + 4 + 8 + 8
_CHUNK = struct.Struct("<QQQII")  # start, end, uncompressed size, uncompressed crc, compression length
_OPCODES = {int(v): k.lower() for k, v in vars(Opcode).items() if k.isupper()}


class TelemetryFileError(ValueError):
    """A telemetry file cannot be read: missing, not MCAP, corrupt, or without the requested fields."""


class TruncatedTelemetryWarning(UserWarning):
    """A telemetry file ends without its footer (writer killed or still writing); its complete part was read."""


@dataclass(frozen=True)
class Event:
    """A message of ``/dragd/events``."""

    time_ns: int  # log time, CLOCK_REALTIME
    name: str
    fields: dict[str, Any]


@dataclass
class TelemetryLog:
    """What `read_log` found in a file."""

    path: str
    rows: dict[str, np.ndarray]  # field -> (N,) or (N, width); enum fields as label strings
    events: list[Event]
    metadata: dict[str, dict[str, str]]
    complete: bool  # the footer was read
    truncated: bool  # the file ends without a footer; everything up to its last complete record was read
    problem: str | None = None  # where reading stopped (truncated files)
    cycle_schema: dict[str, Any] | None = None  # the rows' JSON Schema as written (field types, descriptions)

    @property
    def n_rows(self) -> int:
        return len(next(iter(self.rows.values()))) if self.rows else 0

    @property
    def warning(self) -> str | None:
        """One line naming the file when it was truncated, else None."""
        if not self.truncated:
            return None
        return (f"{self.path}: truncated telemetry (no footer: the writer was killed or is still writing); "
                f"recovered {self.n_rows} rows, reading stopped at: {self.problem}")


# ------------------------------------------------------------------------------------------ the record walk


@dataclass
class _Message:
    channel_id: int
    sequence: int
    log_time: int
    data: bytes


class _Corrupt(Exception):
    pass


@dataclass
class _Walk:
    """One sequential pass over an MCAP file's records, tolerant of a missing tail."""

    path: Path
    size: int = 0
    header: Header | None = None
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    statistics: Statistics | None = None
    compressions: collections.Counter[str] = field(default_factory=collections.Counter)
    counts: collections.Counter[int] = field(default_factory=collections.Counter)
    complete: bool = False
    truncated: bool = False
    problem: str | None = None

    @classmethod
    def open(cls, path: str | os.PathLike[str]) -> _Walk:
        p = Path(path)
        if not p.exists():
            raise TelemetryFileError(f"{p}: no such file")
        if p.is_dir():
            raise TelemetryFileError(f"{p}: is a directory, expected an .mcap file")
        return cls(p, p.stat().st_size)

    def messages(self) -> Iterator[tuple[Channel, _Message]]:
        """Every message in file order with its channel; afterwards the walk's fields describe the file."""
        p = self.path
        with open(p, "rb") as f:
            head = f.read(len(MCAP_MAGIC))
            if self.size == 0:
                raise TelemetryFileError(f"{p}: empty file (0 bytes), expected an MCAP file")
            if head != MCAP_MAGIC:
                if MCAP_MAGIC.startswith(head):
                    raise TelemetryFileError(f"{p}: truncated MCAP: {self.size} bytes, no record to read")
                raise TelemetryFileError(
                    f"{p}: not a readable MCAP file (it starts with {head.hex(' ')}, not the MCAP magic "
                    f"{MCAP_MAGIC.hex(' ')})")
            offset = len(MCAP_MAGIC)
            while True:
                rec = f.read(_RECORD.size)
                if len(rec) < _RECORD.size:
                    self._stop(offset, "the file ends after its last complete record, without a footer" if not rec
                               else "the file ends inside a record header")
                    return
                opcode, length = _RECORD.unpack(rec)
                left = self.size - offset - _RECORD.size
                what = _OPCODES.get(opcode, f"opcode 0x{opcode:02x}")
                if length > left:
                    self._stop(offset, f"the file ends inside a {what} record ({length} bytes, {left} left)")
                    return
                if self.header is None and opcode != Opcode.HEADER:
                    self._corrupt(offset, what, "the first record is not a header")
                body = f.read(length)
                try:
                    yield from self._record(opcode, body)
                except _Corrupt as exc:
                    self._corrupt(offset, what, str(exc))
                except (struct.error, ValueError, UnicodeDecodeError, KeyError) as exc:
                    self._corrupt(offset, what, f"{type(exc).__name__}: {exc}")
                offset += _RECORD.size + length
                if opcode == Opcode.FOOTER:
                    self.complete = True
                    return

    def _stop(self, offset: int, why: str) -> None:
        if self.header is None:
            raise TelemetryFileError(f"{self.path}: truncated MCAP before its header ({why}): nothing to read")
        self.truncated = True
        self.problem = f"{why} at byte {offset} of {self.size}"

    def _corrupt(self, offset: int, what: str, why: str) -> None:
        n = sum(self.counts.values())
        raise TelemetryFileError(f"{self.path}: corrupt MCAP: {what} record at byte {offset}: {why} "
                                 f"({n} messages before it are readable)")

    def _record(self, opcode: int, body: bytes) -> Iterator[tuple[Channel, _Message]]:
        if opcode == Opcode.CHUNK:
            yield from self._chunk(body)
        elif opcode == Opcode.MESSAGE:
            m = self._message(body, 0, len(body))
            if m is not None:
                yield m
        elif opcode == Opcode.SCHEMA:
            s = Schema.read(_stream(body))
            self.schemas[s.id] = s
        elif opcode == Opcode.CHANNEL:
            c = Channel.read(_stream(body))
            self.channels[c.id] = c
        elif opcode == Opcode.METADATA:
            md = Metadata.read(_stream(body))
            self.metadata[md.name] = dict(md.metadata)
        elif opcode == Opcode.HEADER:
            self.header = Header.read(_stream(body))
        elif opcode == Opcode.STATISTICS:
            self.statistics = Statistics.read(_stream(body))
        # indexes, data end, summary offsets, attachments: not needed

    def _message(self, buf: bytes, start: int, end: int) -> tuple[Channel, _Message] | None:
        if end - start < _MESSAGE_HEAD:
            raise _Corrupt("message record too short")
        cid, seq, log_time = _MESSAGE.unpack_from(buf, start)
        self.counts[cid] += 1
        ch = self.channels.get(cid)
        if ch is None:
            return None
        return ch, _Message(cid, seq, log_time, buf[start + _MESSAGE_HEAD : end])

    def _chunk(self, body: bytes) -> Iterator[tuple[Channel, _Message]]:
        _t0, _t1, size, crc, n = _CHUNK.unpack_from(body, 0)
        compression = body[_CHUNK.size : _CHUNK.size + n].decode()
        (n_records,) = struct.unpack_from("<Q", body, _CHUNK.size + n)
        start = _CHUNK.size + n + 8
        records = body[start : start + n_records]
        self.compressions[compression or "none"] += 1
        data = _decompress(compression, records, size)
        if crc and zlib.crc32(data) != crc:
            raise _Corrupt("chunk CRC mismatch")
        pos, end = 0, len(data)
        while pos < end:
            if end - pos < _RECORD.size:
                raise _Corrupt("chunk ends inside a record header")
            opcode, length = _RECORD.unpack_from(data, pos)
            pos += _RECORD.size
            if pos + length > end:
                raise _Corrupt("chunk record longer than the chunk")
            if opcode == Opcode.MESSAGE:
                m = self._message(data, pos, pos + length)
                if m is not None:
                    yield m
            elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL):
                yield from self._record(opcode, data[pos : pos + length])
            pos += length


def _stream(body: bytes) -> ReadDataStream:
    return ReadDataStream(BytesIO(body))


def _decompress(compression: str, data: bytes, size: int) -> bytes:
    try:
        if compression == "zstd":
            import zstandard

            return bytes(zstandard.decompress(data, size))
        if compression == "lz4":
            import lz4.frame

            return bytes(lz4.frame.decompress(data))
    except ImportError:
        raise _Corrupt(f"{compression} chunks need the Python package "
                       f"{'zstandard' if compression == 'zstd' else 'lz4'}") from None
    except Exception as exc:  # noqa: BLE001 - decompressors raise their own error types
        raise _Corrupt(f"{compression} chunk does not decompress: {exc}") from None
    if compression:
        raise _Corrupt(f"unknown chunk compression {compression!r}")
    return data


# ------------------------------------------------------------------------------------------ rows as arrays


@dataclass(frozen=True)
class _Spec:
    kind: str | None  # JSON Schema item type: number, integer, boolean, string; None: unknown
    width: int | None  # None: a scalar field


def _specs(schema: Schema | None, first: bytes) -> dict[str, _Spec]:
    """Field specs in row order from the channel's JSON Schema (else the first message's keys)."""
    props = (_json_schema(schema) or {}).get("properties") or {}
    if isinstance(props, dict) and props:
        out = {}
        for name, p in props.items():
            if p.get("type") == "array":
                out[name] = _Spec(p.get("items", {}).get("type"), p.get("maxItems"))
            else:
                out[name] = _Spec(p.get("type"), None)
        return out
    try:
        sample = json.loads(first)
    except ValueError:
        sample = {}
    return {k: _Spec(None, None) for k in (sample if isinstance(sample, dict) else {})}


def _json_schema(schema: Schema | None) -> dict[str, Any] | None:
    if schema is None or schema.encoding != "jsonschema":
        return None
    try:
        d = json.loads(schema.data)
    except ValueError:
        return None
    return d if isinstance(d, dict) else None


def _trimmer(names: Sequence[str], wanted: set[str]) -> Callable[[bytes], bytes] | None:
    """Cut a compact row JSON (fields in ``names`` order) to the ``wanted`` fields; None when all are wanted.

    A row that does not match (another order, a marker not found) is left whole.
    """
    if wanted >= set(names):
        return None
    runs: list[tuple[bytes, bytes | None]] = []
    i = 0
    while i < len(names):
        if names[i] not in wanted:
            i += 1
            continue
        j = i
        while j + 1 < len(names) and names[j + 1] in wanted:
            j += 1
        start = (b'{"' if i == 0 else b',"') + names[i].encode() + b'":'
        stop = b',"' + names[j + 1].encode() + b'":' if j + 1 < len(names) else None
        runs.append((start, stop))
        i = j + 1

    def trim(m: bytes) -> bytes:
        parts = []
        pos = 0
        for start, stop in runs:
            a = m.find(start, pos)
            if a < 0:
                return m
            b = len(m) - 1 if stop is None else m.find(stop, a + 1)
            if b < 0:
                return m
            parts.append(m[a + 1 : b])
            pos = b
        return b"{" + b",".join(parts) + b"}"

    return trim


class _Columns:
    """Cycle messages -> column arrays, decoded in batches; ``sink`` receives each batch."""

    def __init__(self, path: Path, topic: str, schema: Schema | None, first: bytes, fields: Sequence[str] | None,
                 sink: Callable[[dict[str, np.ndarray]], None]) -> None:
        self.path, self.topic = path, topic
        specs = _specs(schema, first)
        if fields is not None:
            missing = [f for f in fields if f not in specs]
            if missing:
                raise TelemetryFileError(f"{path}: {topic}: no field {', '.join(missing)} (the rows have "
                                         f"{', '.join(specs) or 'no fields'})")
        self.names = list(specs) if fields is None else list(fields)
        self.specs = specs
        self._trim = _trimmer(list(specs), set(self.names))
        self._parts: list[bytes] = []
        self._sink = sink

    def add(self, data: bytes) -> None:
        self._parts.append(data)
        if len(self._parts) >= _BATCH_ROWS:
            self.flush()

    def flush(self) -> None:
        if not self._parts:
            return
        parts = self._parts if self._trim is None else [self._trim(m) for m in self._parts]
        self._parts = []
        try:
            rows = json.loads(b"[" + b",".join(parts) + b"]")
        except ValueError as exc:
            raise TelemetryFileError(f"{self.path}: {self.topic}: messages are not JSON rows ({exc})") from None
        if not all(isinstance(r, dict) for r in rows):
            raise TelemetryFileError(f"{self.path}: {self.topic}: messages are not JSON objects")
        self._sink({name: self._array(name, [r.get(name) for r in rows]) for name in self.names})

    def _array(self, name: str, vals: list[Any]) -> np.ndarray:
        spec = self.specs[name]
        try:
            if spec.kind in ("number", "integer") and spec.width:
                blank = [None] * spec.width
                vals = [blank if v is None else v for v in vals]
            if spec.kind == "number":
                return np.array(vals, dtype=np.float64)
            if spec.kind == "integer":
                try:
                    return np.array(vals, dtype=np.int64)
                except TypeError:  # a null among them (a non-finite value was written)
                    return np.array(vals, dtype=np.float64)
            if spec.kind == "boolean":
                return np.array(vals, dtype=bool)
            if spec.kind == "string":
                return np.array(vals, dtype=object).astype(str)
            return np.array(vals)
        except (ValueError, TypeError) as exc:
            raise TelemetryFileError(f"{self.path}: {self.topic}: field {name}: rows of unequal shape or "
                                     f"unexpected values ({exc})") from None


# ------------------------------------------------------------------------------------------ reading


def _event(m: _Message) -> Event:
    try:
        d = json.loads(m.data)
    except ValueError:
        d = {"name": "<undecodable event>"}
    if not isinstance(d, dict):
        d = {"name": "<undecodable event>"}
    name = d.pop("name", "?")
    return Event(m.log_time, str(name), d)


def read_log(path: str | os.PathLike[str], fields: Sequence[str] | None = None, *, topic: str = CYCLE_TOPIC,
             events_topic: str = EVENTS_TOPIC) -> TelemetryLog:
    """Rows of ``topic`` (``fields``, default all; a field the rows lack is an error), events and metadata."""
    walk = _Walk.open(path)
    batches: dict[str, list[np.ndarray]] = {}
    cols: _Columns | None = None
    events: list[Event] = []
    schema: Schema | None = None

    def collect(batch: dict[str, np.ndarray]) -> None:
        for k, v in batch.items():
            batches.setdefault(k, []).append(v)

    for ch, m in walk.messages():
        if ch.topic == topic:
            if cols is None:
                schema = walk.schemas.get(ch.schema_id)
                cols = _Columns(walk.path, topic, schema, m.data, fields, collect)
            cols.add(m.data)
        elif ch.topic == events_topic:
            events.append(_event(m))
    if cols is not None:
        cols.flush()
    if schema is None:  # no rows: the channel's schema as registered
        schema = next((walk.schemas.get(c.schema_id) for c in walk.channels.values() if c.topic == topic), None)
    rows = {k: np.concatenate(v) for k, v in batches.items()}
    if cols is None and fields is not None:
        rows = {f: np.empty(0) for f in fields}
    return TelemetryLog(os.fspath(walk.path), rows, events, walk.metadata, walk.complete, walk.truncated,
                        walk.problem, _json_schema(schema))


def read_rows(path: str | os.PathLike[str], fields: Sequence[str] | None = None, *,
              topic: str = CYCLE_TOPIC) -> dict[str, np.ndarray]:
    """The rows of ``topic`` as arrays per field; a truncated file warns (`TruncatedTelemetryWarning`)."""
    log = read_log(path, fields, topic=topic)
    if log.warning:
        warnings.warn(log.warning, TruncatedTelemetryWarning, stacklevel=2)
    return log.rows


def read_log_times(path: str | os.PathLike[str], topic: str = CYCLE_TOPIC) -> np.ndarray:
    """The log times (CLOCK_REALTIME ns) of ``topic``'s messages in file order: one per row of `read_rows`."""
    walk = _Walk.open(path)
    return np.array([m.log_time for ch, m in walk.messages() if ch.topic == topic], dtype=np.int64)


def read_events(path: str | os.PathLike[str], name: str | None = None, *,
                topic: str = EVENTS_TOPIC) -> list[Event]:
    """The events of a file (only those called ``name`` when given), in file order."""
    walk = _Walk.open(path)
    out = []
    for ch, m in walk.messages():
        if ch.topic == topic:
            ev = _event(m)
            if name is None or ev.name == name:
                out.append(ev)
    return out


def read_metadata(path: str | os.PathLike[str]) -> dict[str, dict[str, str]]:
    """The metadata records of a file: name -> key/value strings."""
    walk = _Walk.open(path)
    for _ in walk.messages():
        pass
    return walk.metadata


# ------------------------------------------------------------------------------------------ summary


class _Stats:
    """Min/max/mean per element of a numeric field (non-finite values ignored), or label counts."""

    def __init__(self, spec: _Spec) -> None:
        self.is_array = spec.width is not None
        self.enum = spec.kind == "string"
        self.counts: collections.Counter[str] = collections.Counter()
        self.nulls = 0
        self.total: np.ndarray | None = None
        self.valid: np.ndarray | None = None
        self.lo: np.ndarray | None = None
        self.hi: np.ndarray | None = None

    def add(self, a: np.ndarray) -> None:
        if self.enum or a.dtype.kind in "US":
            self.enum = True
            self.counts.update(a.reshape(-1).tolist())
            return
        x = a.astype(np.float64).reshape(len(a), -1)
        ok = np.isfinite(x)
        self.nulls += int((~ok).any(axis=1).sum())
        parts = (ok.sum(axis=0), np.where(ok, x, 0.0).sum(axis=0), np.where(ok, x, np.inf).min(axis=0),
                 np.where(ok, x, -np.inf).max(axis=0))
        if self.total is None:
            self.valid, self.total, self.lo, self.hi = parts
        else:
            assert self.valid is not None and self.lo is not None and self.hi is not None
            self.valid = self.valid + parts[0]
            self.total = self.total + parts[1]
            self.lo = np.minimum(self.lo, parts[2])
            self.hi = np.maximum(self.hi, parts[3])

    def result(self) -> dict[str, Any]:
        if self.enum:
            return {"type": "enum", "counts": dict(sorted(self.counts.items()))}
        if self.total is None or self.valid is None or self.lo is None or self.hi is None:
            return {"type": "array" if self.is_array else "number", "min": None, "max": None, "mean": None,
                    "rows_with_null": self.nulls}

        def pack(arr: np.ndarray) -> Any:
            vals = [float(v) if math.isfinite(v) else None for v in arr]
            return vals if self.is_array else vals[0]

        mean = np.where(self.valid > 0, self.total / np.maximum(self.valid, 1), np.nan)
        return {"type": "array" if self.is_array else "number", "min": pack(self.lo), "max": pack(self.hi),
                "mean": pack(mean), "rows_with_null": self.nulls}


def _decimation(ch: Channel) -> int:
    try:
        return max(1, int((ch.metadata or {}).get("decimation", 1)))
    except (TypeError, ValueError):
        return 1


def _iso(ns: int) -> str:
    return datetime.fromtimestamp(ns / 1e9, UTC).isoformat()


def summarize(path: str | os.PathLike[str], *, cycle_topic: str = CYCLE_TOPIC,
              events_topic: str = EVENTS_TOPIC) -> dict[str, Any]:
    """Summary of a telemetry MCAP for ``dragd log summary FILE.mcap``.

    Channels (topic, encodings, schema, message count), time range, per-field min/max/mean of the cycle topic
    (per joint for arrays; label counts for enum fields), sequence gaps (dropped rows), the events and the
    metadata records. A file without its footer is summarized up to its last complete record with
    ``"truncated": true`` and ``"recovered_rows"``; a missing, non-MCAP or corrupt file raises TelemetryFileError.
    """
    walk = _Walk.open(path)
    stats: dict[str, _Stats] = {}
    cols: _Columns | None = None
    events: list[dict[str, Any]] = []
    start_ns: int | None = None
    end_ns: int | None = None
    rows = gaps = 0
    last_seq: int | None = None

    def accumulate(batch: dict[str, np.ndarray]) -> None:
        assert cols is not None
        for name, a in batch.items():
            stats.setdefault(name, _Stats(cols.specs[name])).add(a)

    for ch, m in walk.messages():
        start_ns = m.log_time if start_ns is None else min(start_ns, m.log_time)
        end_ns = m.log_time if end_ns is None else max(end_ns, m.log_time)
        if ch.topic == events_topic:
            ev = _event(m)
            events.append({"time_ns": ev.time_ns, "name": ev.name, "fields": ev.fields})
        elif ch.topic == cycle_topic and ch.message_encoding == "json":
            if cols is None:
                cols = _Columns(walk.path, cycle_topic, walk.schemas.get(ch.schema_id), m.data, None, accumulate)
            cols.add(m.data)
            rows += 1
            step = _decimation(ch)  # a decimated file keeps every step-th producer row
            if m.sequence and last_seq is not None and m.sequence > last_seq + step:
                gaps += (m.sequence - last_seq) // step - 1
            if m.sequence:
                last_seq = m.sequence
    if cols is not None:
        cols.flush()

    channels = []
    for cid, ch in sorted(walk.channels.items()):
        sch = walk.schemas.get(ch.schema_id)
        channels.append({"topic": ch.topic, "message_encoding": ch.message_encoding,
                         "schema": sch.name if sch else None, "schema_encoding": sch.encoding if sch else None,
                         "messages": walk.counts.get(cid, 0)})
    if start_ns is not None:
        for e in events:
            e["t_s"] = (e["time_ns"] - start_ns) / 1e9
    cycle = None
    if cols is not None:
        cycle = {"topic": cycle_topic, "rows": rows, "sequence_gaps": gaps,
                 "decimation": max((_decimation(c) for c in walk.channels.values() if c.topic == cycle_topic),
                                   default=1),
                 "fields": {name: stats[name].result() if name in stats else _Stats(cols.specs[name]).result()
                            for name in cols.names}}
    header = walk.header
    return {
        "file": os.fspath(walk.path),
        "size_bytes": walk.size,
        "complete": walk.complete,
        "truncated": walk.truncated,
        "recovered_rows": rows if walk.truncated else None,
        "problem": walk.problem,
        "library": header.library if header else None,
        "profile": header.profile if header else None,
        "chunks": dict(walk.compressions),
        "schemas": sorted({s.name for s in walk.schemas.values()}),
        "channels": channels,
        "message_count": sum(walk.counts.values()),
        "start_ns": start_ns,
        "end_ns": end_ns,
        "start_utc": _iso(start_ns) if start_ns is not None else None,
        "duration_s": (end_ns - start_ns) / 1e9 if start_ns is not None and end_ns is not None else 0.0,
        "statistics_message_count": walk.statistics.message_count if walk.statistics else None,
        "cycle": cycle,
        "events": events,
        "metadata": walk.metadata,
    }
