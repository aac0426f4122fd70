"""PDO mapping validation and compilation for the simulated drives (CiA 301).

A PDO channel is compiled when it is (re)configured: one `struct.Struct` for the frame layout and the
store slots it reads (TPDO) or writes (RPDO), so that the SYNC path does no object-dictionary lookups.
Mapping entries must be byte-aligned and cover the whole object; dummy entries (0002h-0007h) are
accepted in RPDOs only when the EDS declares them in [DummyUsage].
"""

from __future__ import annotations

import operator
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from dragd.hardware.busload import fd_length
from sim.od import (
    ABORT_CANNOT_MAP,
    ABORT_NO_OBJECT,
    ABORT_PDO_LENGTH,
    ABORT_VALUE_RANGE,
    STRUCT_CODES,
    ObjectStore,
    SdoAbort,
    fixed_size_bits,
)

COB_INVALID = 0x80000000
COB_NO_RTR = 0x40000000
COB_EXTENDED = 0x20000000
CLASSIC_MAX_BYTES = 8
FD_MAX_BYTES = 64
_DUMMY_BITS = {0x0002: 8, 0x0003: 16, 0x0004: 32, 0x0005: 8, 0x0006: 16, 0x0007: 32}


@dataclass(frozen=True)
class MapEntry:
    """One decoded mapping entry; slot is None for a dummy entry."""

    index: int
    subindex: int
    bits: int
    slot: int | None
    code: str  # struct code, or "Nx" padding for a dummy


def split_entry(raw: int) -> tuple[int, int, int]:
    """(index, subindex, length in bits) of a mapping entry value."""
    return raw >> 16, (raw >> 8) & 0xFF, raw & 0xFF


def validate_entry(store: ObjectStore, map_index: int, raw: int, receive: bool) -> MapEntry:
    """Check one mapping entry against the dictionary; SdoAbort 0x06020000 / 0x06040041 on failure."""
    index, subindex, bits = split_entry(raw)
    if index in _DUMMY_BITS:
        if not receive or index not in store.dummy_indices:
            raise SdoAbort(ABORT_CANNOT_MAP, map_index, 0,
                           f"dummy 0x{index:04X} is only mappable in RPDOs declared in [DummyUsage]")
        if bits != _DUMMY_BITS[index]:
            raise SdoAbort(ABORT_CANNOT_MAP, map_index, 0,
                           f"dummy 0x{index:04X} is {_DUMMY_BITS[index]} bits, entry says {bits}")
        return MapEntry(index, subindex, bits, None, f"{bits // 8}x")
    slot = store.slots.get((index, subindex))
    if slot is None:
        raise SdoAbort(ABORT_NO_OBJECT, map_index, 0, f"mapped object 0x{index:04X}:{subindex:02X} does not exist")
    var = store.vars[slot]
    direction_ok = var.writable if receive else var.readable
    if not var.pdo_mappable or not direction_ok:
        kind = "RPDO" if receive else "TPDO"
        raise SdoAbort(ABORT_CANNOT_MAP, map_index, 0,
                       f"0x{index:04X}:{subindex:02X} ({var.access_type}) cannot be mapped into a {kind}")
    size_bits = fixed_size_bits(var)
    if size_bits is None or size_bits != bits or var.data_type not in STRUCT_CODES:
        raise SdoAbort(ABORT_CANNOT_MAP, map_index, 0,
                       f"0x{index:04X}:{subindex:02X} is {size_bits} bits, entry says {bits}")
    return MapEntry(index, subindex, bits, slot, STRUCT_CODES[var.data_type])


def validate_mapping(store: ObjectStore, map_index: int, raws: list[int], receive: bool,
                     max_bytes: int) -> list[MapEntry]:
    """Validate all entries of a mapping and its total length (SdoAbort 0x06040042 if too long)."""
    entries = [validate_entry(store, map_index, raw, receive) for raw in raws]
    total_bits = sum(e.bits for e in entries)
    if total_bits > max_bytes * 8:
        raise SdoAbort(ABORT_PDO_LENGTH, map_index, 0,
                       f"mapping is {total_bits // 8} bytes, the PDO holds at most {max_bytes}")
    return entries


def check_transmission_type(comm_index: int, value: int, receive: bool) -> None:
    """Accept 0..240, 254, 255 (RTR-only types 252/253 are not supported)."""
    if value <= 240 or value in (254, 255):
        return
    kind = "RPDO" if receive else "TPDO"
    raise SdoAbort(ABORT_VALUE_RANGE, comm_index, 2,
                   f"{kind} transmission type {value} not supported; expected 0..240, 254 or 255")


def _tuple_getter(slots: tuple[int, ...]) -> Callable[[list[Any]], tuple[Any, ...]]:
    if not slots:
        return lambda cells: ()
    if len(slots) == 1:
        only = slots[0]
        return lambda cells: (cells[only],)
    return operator.itemgetter(*slots)


@dataclass
class PdoChannel:
    """The live, compiled state of one RPDO or TPDO."""

    number: int  # 1-based
    receive: bool
    comm_index: int
    map_index: int
    valid: bool = False
    cob_id: int = 0
    trans_type: int = 255
    inhibit_s: float = 0.0
    event_s: float = 0.0
    entries: list[MapEntry] = field(default_factory=list)
    layout: struct.Struct = field(default_factory=lambda: struct.Struct("<"))
    slots: tuple[int, ...] = ()
    getter: Callable[[list[Any]], tuple[Any, ...]] = field(default=lambda cells: ())
    frame_len: int = 0
    is_fd: bool = False
    hooked_slots: tuple[int, ...] = ()  # RPDO slots whose writes have side effects (set by the drive)
    # runtime
    sync_count: int = 0
    last_data: bytes | None = None
    last_tx_s: float = -1e9
    pending: bool = False
    latched: bytes | None = None
    last_rx_s: float | None = None
    timed_out: bool = False
    length_error: bool = False

    @property
    def synchronous(self) -> bool:
        return self.trans_type <= 240

    def compile(self, entries: list[MapEntry], fd: bool) -> None:
        """Build the frame layout from validated entries and reset the runtime counters."""
        self.entries = entries
        self.layout = struct.Struct("<" + "".join(e.code for e in entries))
        self.slots = tuple(e.slot for e in entries if e.slot is not None)
        self.getter = _tuple_getter(self.slots)
        size = self.layout.size
        self.is_fd = fd and size > CLASSIC_MAX_BYTES
        self.frame_len = fd_length(size) if self.is_fd else size
        self.sync_count = 0
        self.last_data = None
        self.last_tx_s = -1e9
        self.pending = False
        self.latched = None
        self.last_rx_s = None
        self.timed_out = False
        self.length_error = False

    def sample(self, cells: list[Any]) -> bytes:
        """Pack the mapped values (TPDO), padded to the frame length on CAN FD."""
        data = self.layout.pack(*self.getter(cells))
        if self.frame_len != len(data):
            data += bytes(self.frame_len - len(data))
        return data

    def unpack(self, data: bytes) -> tuple[Any, ...]:
        """Values of the mapped (non-dummy) entries of a received frame (RPDO)."""
        return self.layout.unpack_from(data)
