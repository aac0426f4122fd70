"""Process-data layout of a bus: which PDOs each drive sends and receives, their mappings and codecs.

The layout is data: the master writes it to the drives over SDO, the cycle encodes/decodes frames with
precompiled ``struct`` codecs from it, and the bus budget is computed from it.

Layouts (``layout_for``):
- ``shared`` (default on CAN FD): per drive one SYNC TPDO [6041h sw16, 6064h pos32, 6078h cur16] (8 bytes);
  one *shared command RPDO* carrying every joint's slot [6040h cw16, 607Ah pos32, 60B2h offset16] — each
  drive maps dummy entries (0007h, 32 bit) over the other joints' slots. FD: up to 8 slots per 64-byte frame;
  classic CAN: one slot per 8-byte frame.
- ``compact`` (classic CAN, drag only): per drive a SYNC TPDO [pos32, cur16] (6 bytes) and an event TPDO
  [sw16] with inhibit time; shared RPDO(s) of torque offsets [60B2h × up to 4 joints] each cycle; per drive
  an event RPDO [cw16] sent on change (at most every ``event_min_interval_ms``) and as a keep-alive.

In both, the cyclic torque command is 60B2h (torque offset): CiA 402 adds it to 6071h (kept 0) in CST, and uses
it as torque feed-forward in CSP, so one layout serves both modes and a CST↔CSP switch needs no remapping.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from typing import Literal

from dragd.hardware.busload import BusLoadReport, FrameSpec, bus_load
from dragd.hardware.cia402 import OD_CONTROLWORD, OD_CURRENT_ACTUAL, OD_POSITION_ACTUAL, OD_STATUSWORD, OD_TARGET_POSITION, OD_TORQUE_OFFSET

SYNC_COB_ID = 0x080
SHARED_RPDO_BASE = 0x200  # 0x200 (+0x80·k): "RPDO of node 0", unused by any node; not a restricted COB-ID
DUMMY_U32 = 0x0007
DUMMY_U16 = 0x0006
TPDO_COMM, TPDO_MAP = 0x1800, 0x1A00
RPDO_COMM, RPDO_MAP = 0x1400, 0x1600
TRANS_SYNC = 1
TRANS_EVENT = 255

Field = Literal["statusword", "position", "current", "controlword", "target_position", "torque_offset"]
_FORMAT = {"statusword": "H", "position": "i", "current": "h", "controlword": "H", "target_position": "i", "torque_offset": "h"}
_OBJECT = {"statusword": OD_STATUSWORD, "position": OD_POSITION_ACTUAL, "current": OD_CURRENT_ACTUAL,
           "controlword": OD_CONTROLWORD, "target_position": OD_TARGET_POSITION, "torque_offset": OD_TORQUE_OFFSET}
_BITS = {"H": 16, "h": 16, "i": 32}


@dataclass(frozen=True)
class MapEntry:
    """One mapping entry: an object (or a dummy 0002h–0007h) and its length in bits."""

    index: int
    subindex: int
    bits: int
    field: Field | None = None  # None for a dummy

    @property
    def word(self) -> int:
        """The 32-bit mapping value written to 16xxh/1Axxh."""
        return (self.index << 16) | (self.subindex << 8) | self.bits


def _entry(f: Field) -> MapEntry:
    return MapEntry(_OBJECT[f], 0, _BITS[_FORMAT[f]], f)


@dataclass(frozen=True)
class PdoSpec:
    """One PDO of one drive: communication and mapping parameters."""

    direction: Literal["tpdo", "rpdo"]
    number: int  # 1..4
    cob_id: int
    transmission_type: int
    entries: tuple[MapEntry, ...]
    inhibit_100us: int = 0
    event_timer_ms: int = 0

    @property
    def comm_index(self) -> int:
        return (TPDO_COMM if self.direction == "tpdo" else RPDO_COMM) + self.number - 1

    @property
    def map_index(self) -> int:
        return (TPDO_MAP if self.direction == "tpdo" else RPDO_MAP) + self.number - 1

    @property
    def data_bytes(self) -> int:
        return sum(e.bits for e in self.entries) // 8


@dataclass(frozen=True)
class Slot:
    """Where one joint's fields sit in a frame: byte offset and struct format (little endian)."""

    joint: int
    offset: int
    fields: tuple[Field, ...]

    @property
    def fmt(self) -> str:
        return "<" + "".join(_FORMAT[f] for f in self.fields)


@dataclass(frozen=True)
class FrameLayout:
    """A frame on the bus as the master sees it: COB-ID, length, the joints' slots, when it is sent."""

    name: str
    cob_id: int
    data_bytes: int
    slots: tuple[Slot, ...]
    direction: Literal["tpdo", "rpdo"]
    cyclic: bool  # every cycle (SYNC-driven) vs event
    max_rate_Hz: float  # worst case, for the bus budget


@dataclass
class BusLayout:
    """Everything the master needs to configure and run one bus."""

    bus: str
    kind: Literal["shared", "compact"]
    fd: bool
    brs: bool
    joints: tuple[int, ...]  # joint indices on this bus
    node_ids: tuple[int, ...]
    pdos: dict[int, list[PdoSpec]]  # node id -> PDOs to configure (others disabled)
    frames: list[FrameLayout] = field(default_factory=list)

    def frame_specs(self, rate_Hz: float, heartbeat_Hz: float) -> list[FrameSpec]:
        """Worst-case periodic frames for the bus budget: SYNC, every PDO, master heartbeat."""
        specs = [FrameSpec("SYNC", 0, rate_Hz)]
        for fr in self.frames:  # on a CAN FD bus every PDO travels as an FD frame with bit-rate switch
            hz = rate_Hz if fr.cyclic else fr.max_rate_Hz
            specs.append(FrameSpec(fr.name, fr.data_bytes, hz, fd=self.fd, brs=self.brs))
        specs.append(FrameSpec("master heartbeat", 1, heartbeat_Hz))
        return specs

    def budget(self, rate_Hz: float, bitrate: int, data_bitrate: int | None, heartbeat_Hz: float) -> BusLoadReport:
        return bus_load(self.frame_specs(rate_Hz, heartbeat_Hz), bitrate, data_bitrate if self.fd else None)


def layout_for(bus: str, joints: list[int], node_ids: list[int], *, fd: bool, kind: str | None = None,
               rate_Hz: float = 1000.0, event_min_interval_ms: int = 10) -> BusLayout:
    """Build the PDO layout of one bus carrying ``joints`` (indices) on drives ``node_ids``."""
    kind = kind or "shared"
    if kind not in ("shared", "compact"):
        raise ValueError(f"bus '{bus}': layout: expected 'shared' or 'compact', got '{kind}'")
    if kind == "compact" and fd:
        raise ValueError(f"bus '{bus}': layout 'compact' is for classic CAN; use 'shared' on CAN FD")
    pdos: dict[int, list[PdoSpec]] = {n: [] for n in node_ids}
    frames: list[FrameLayout] = []
    if kind == "shared":
        tp_fields: tuple[Field, ...] = ("statusword", "position", "current")
        for j, n in zip(joints, node_ids):
            pdos[n].append(PdoSpec("tpdo", 1, 0x180 + n, TRANS_SYNC, tuple(_entry(f) for f in tp_fields)))
            frames.append(FrameLayout(f"TPDO1 node {n}", 0x180 + n, 8, (Slot(j, 0, tp_fields),), "tpdo", True, rate_Hz))
        slot_fields: tuple[Field, ...] = ("controlword", "target_position", "torque_offset")
        per_frame = 8 if fd else 1
        groups = [list(range(i, min(i + per_frame, len(joints)))) for i in range(0, len(joints), per_frame)]
        for k, group in enumerate(groups):
            cob = SHARED_RPDO_BASE + 0x80 * k
            for pos_in_frame, gi in enumerate(group):
                entries: list[MapEntry] = []
                for other in range(len(group)):
                    if other == pos_in_frame:
                        entries.extend(_entry(f) for f in slot_fields)
                    else:
                        entries.extend([MapEntry(DUMMY_U32, 0, 32), MapEntry(DUMMY_U32, 0, 32)])
                pdos[node_ids[gi]].append(PdoSpec("rpdo", 4, cob, TRANS_SYNC, tuple(entries)))
            slots = tuple(Slot(joints[gi], 8 * p, slot_fields) for p, gi in enumerate(group))
            frames.append(FrameLayout(f"command RPDO 0x{cob:03X}", cob, 8 * len(group), slots, "rpdo", True, rate_Hz))
    else:
        ev_hz = 1000.0 / event_min_interval_ms
        for j, n in zip(joints, node_ids):
            pdos[n].append(PdoSpec("tpdo", 1, 0x180 + n, TRANS_SYNC, (_entry("position"), _entry("current"))))
            pdos[n].append(PdoSpec("tpdo", 2, 0x280 + n, TRANS_EVENT, (_entry("statusword"),),
                                   inhibit_100us=event_min_interval_ms * 10, event_timer_ms=100))
            pdos[n].append(PdoSpec("rpdo", 1, 0x200 + n, TRANS_EVENT, (_entry("controlword"),)))
            frames.append(FrameLayout(f"TPDO1 node {n}", 0x180 + n, 6, (Slot(j, 0, ("position", "current")),), "tpdo", True, rate_Hz))
            frames.append(FrameLayout(f"TPDO2 node {n}", 0x280 + n, 2, (Slot(j, 0, ("statusword",)),), "tpdo", False, ev_hz))
            frames.append(FrameLayout(f"RPDO1 node {n}", 0x200 + n, 2, (Slot(j, 0, ("controlword",)),), "rpdo", False, ev_hz))
        groups = [list(range(i, min(i + 4, len(joints)))) for i in range(0, len(joints), 4)]
        for k, group in enumerate(groups):
            cob = SHARED_RPDO_BASE + 0x100 + 0x80 * k  # 0x300, 0x380: PDO COB-IDs of node 0, unused
            for pos_in_frame, gi in enumerate(group):
                entries = [(_entry("torque_offset") if other == pos_in_frame else MapEntry(DUMMY_U16, 0, 16))
                           for other in range(len(group))]
                pdos[node_ids[gi]].append(PdoSpec("rpdo", 4, cob, TRANS_SYNC, tuple(entries)))
            slots = tuple(Slot(joints[gi], 2 * p, ("torque_offset",)) for p, gi in enumerate(group))
            frames.append(FrameLayout(f"torque RPDO 0x{cob:03X}", cob, 2 * len(group), slots, "rpdo", True, rate_Hz))
    return BusLayout(bus, kind, fd, fd, tuple(joints), tuple(node_ids), pdos, frames)  # type: ignore[arg-type]


class RpdoEncoder:
    """One outgoing frame: a preallocated buffer and per-slot precompiled structs."""

    def __init__(self, frame: FrameLayout, fd: bool, min_interval_s: float = 0.0, keepalive_s: float = 0.1) -> None:
        self.frame = frame
        self.buffer = bytearray(frame.data_bytes)
        self.slots = [(s.joint, s.offset, struct.Struct(s.fmt), s.fields) for s in frame.slots]
        self.fd = fd and frame.direction == "rpdo"
        self.cyclic = frame.cyclic
        # event frames: sent when the payload changes (at most every min_interval_s) and as a keep-alive
        self.min_interval_s = min_interval_s if not frame.cyclic else 0.0
        self.keepalive_s = keepalive_s
        self.last_sent_s = -1e9
        self.last_payload = bytearray(frame.data_bytes)

    def due(self, t_s: float) -> bool:
        """Whether an event frame should go out now (cyclic frames always do)."""
        if self.cyclic:
            return True
        since = t_s - self.last_sent_s
        if since < self.min_interval_s:
            return False
        return since >= self.keepalive_s or self.buffer != self.last_payload

    def sent(self, t_s: float) -> None:
        self.last_sent_s = t_s
        self.last_payload[:] = self.buffer
