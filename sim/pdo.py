"""PDOs of the simulated drives (CiA 301): mapping validation, compiled channels and the node's PDO service.

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

import can

from dragd.hardware.busload import fd_length
from dragd.hardware.cia301 import (
    COB_ID_EXTENDED,
    COB_ID_INVALID,
    COB_ID_MASK,
    COB_ID_NO_RTR,
    DUMMY_TYPES,
    OD_RPDO_COMM,
    OD_RPDO_MAP,
    OD_TPDO_COMM,
    OD_TPDO_MAP,
    PDO_TRANSMISSION_EVENT,
    NmtState,
)
from dragd.hardware.cia402 import EMCY_PDO_LENGTH, EMCY_RPDO_TIMEOUT, ERR_REG_COMMUNICATION
from sim.od import (
    ABORT_CANNOT_MAP,
    ABORT_DEVICE_STATE,
    ABORT_NO_OBJECT,
    ABORT_PDO_LENGTH,
    ABORT_VALUE_RANGE,
    STRUCT_CODES,
    ObjectStore,
    SdoAbort,
    fixed_size_bits,
)

COB_INVALID, COB_NO_RTR, COB_EXTENDED = COB_ID_INVALID, COB_ID_NO_RTR, COB_ID_EXTENDED
CLASSIC_MAX_BYTES = 8
FD_MAX_BYTES = 64


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
    if index in DUMMY_TYPES:
        if not receive or index not in store.dummy_indices:
            raise SdoAbort(ABORT_CANNOT_MAP, map_index, 0,
                           f"dummy 0x{index:04X} is only mappable in RPDOs declared in [DummyUsage]")
        if bits != DUMMY_TYPES[index]:
            raise SdoAbort(ABORT_CANNOT_MAP, map_index, 0,
                           f"dummy 0x{index:04X} is {DUMMY_TYPES[index]} bits, entry says {bits}")
        return MapEntry(index, subindex, bits, None, f"{bits // 8}x")
    slot = store.slots.get((index, subindex))
    if slot is None:
        raise SdoAbort(ABORT_NO_OBJECT, map_index, 0, f"mapped object 0x{index:04X}:{subindex:02X} does not exist")
    var = store.vars[slot]
    assert var is not None  # (slots of the dictionary's objects)
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


MAX_CHANNELS = 512


def find_channels(store: ObjectStore, comm_base: int, map_base: int, receive: bool) -> list[PdoChannel]:
    """The PDOs the dictionary has: a communication record with its COB-ID (sub 1) and a mapping record."""
    return [PdoChannel(n + 1, receive, comm_base + n, map_base + n) for n in range(MAX_CHANNELS)
            if store.has(comm_base + n, 1) and store.has(map_base + n, 0)]


class PdoService:
    """The node's PDOs: the channels its EDS has, checks on their parameters, reception, SYNC and event transmission.

    RPDO deadlines (event timer, 140xh sub 5) and inhibit / event times of TPDOs (180xh sub 3 / sub 5) exist where the
    EDS has those sub-indices. A TPDO whose COB-ID the EDS gives with bit 30 set ("no RTR") keeps the bit whatever a
    master writes: this drive does not answer remote frames.
    """

    def __init__(self, store: ObjectStore, *, fd: bool, counters: Any, nmt_state: Callable[[], NmtState],
                 sample: Callable[[], None], tx: Callable[[Any], None],
                 send_data: Callable[[int, bytes, bool], None] | None,
                 raise_error: Callable[[int, int, bytes], None], clear_error: Callable[[int], None],
                 refresh: Callable[[], None], routing_changed: Callable[[], None]) -> None:
        self.store = store
        self.fd = fd
        self.max_bytes = FD_MAX_BYTES if fd else CLASSIC_MAX_BYTES
        self.counters = counters
        self._nmt_state = nmt_state
        self._sample = sample
        self._tx = tx
        self._send_data = send_data
        self._raise_error = raise_error
        self._clear_error = clear_error
        self._refresh = refresh
        self._routing_changed = routing_changed
        self.rpdos = find_channels(store, OD_RPDO_COMM, OD_RPDO_MAP, receive=True)
        self.tpdos = find_channels(store, OD_TPDO_COMM, OD_TPDO_MAP, receive=False)
        self.no_rtr = frozenset(ch.comm_index for ch in self.tpdos
                                if store.defaults[store.slot(ch.comm_index, 1)] & COB_NO_RTR)
        self.rpdo_hooks: dict[int, Callable[[int], None]] = {}  # slot -> side effect of an RPDO write (the drive's)
        self.rpdo_by_cob: dict[int, list[PdoChannel]] = {}
        self.sync_rpdos: list[PdoChannel] = []
        self.sync_tpdos: list[PdoChannel] = []
        self.event_tpdos: list[PdoChannel] = []
        self.deadline_rpdos: list[PdoChannel] = []
        self.last_rx_s: float | None = None  # the last RPDO of any channel (a vendor's reception watchdog)
        self.watchdog_expired = False
        before, after = store.before_write, store.after_write
        for ch in self.rpdos + self.tpdos:
            before[ch.comm_index] = self._make_comm_check(ch)
            after[ch.comm_index] = self._make_comm_apply(ch)
            before[ch.map_index] = self._make_map_check(ch)

    # --- configuration -----------------------------------------------------------------------------------
    def load_all(self) -> None:
        """Every channel from the store (after a reset)."""
        for ch in self.rpdos + self.tpdos:
            self.load(ch)

    def _sub(self, index: int, sub: int, default: int) -> int:
        slot = self.store.slots.get((index, sub))
        return default if slot is None else self.store.cells[slot]

    def mapping_raws(self, ch: PdoChannel) -> list[int]:
        st = self.store
        count = st.get(ch.map_index, 0)
        return [self._sub(ch.map_index, sub, 0) for sub in range(1, count + 1)]

    def load(self, ch: PdoChannel) -> None:
        """(Re)compile one PDO from the store (called when its parameters change or on reset)."""
        cob = self.store.get(ch.comm_index, 1)
        ch.valid = not cob & COB_INVALID
        ch.cob_id = cob & COB_ID_MASK
        ch.trans_type = self._sub(ch.comm_index, 2, PDO_TRANSMISSION_EVENT)
        ch.inhibit_s = 0.0 if ch.receive else self._sub(ch.comm_index, 3, 0) * 1e-4
        ch.event_s = self._sub(ch.comm_index, 5, 0) * 1e-3
        entries = validate_mapping(self.store, ch.map_index, self.mapping_raws(ch), ch.receive, self.max_bytes) \
            if ch.valid else []
        ch.compile(entries, self.fd)
        ch.hooked_slots = tuple(slot for slot in self.rpdo_hooks if ch.receive and slot in ch.slots)
        self._index()

    def _index(self) -> None:
        valid_rpdos = [ch for ch in self.rpdos if ch.valid]
        by_cob: dict[int, list[PdoChannel]] = {}
        for ch in valid_rpdos:
            by_cob.setdefault(ch.cob_id, []).append(ch)
        self.rpdo_by_cob = by_cob
        self.sync_rpdos = [ch for ch in valid_rpdos if ch.synchronous]
        valid_tpdos = [ch for ch in self.tpdos if ch.valid and ch.layout.size > 0]
        self.sync_tpdos = [ch for ch in valid_tpdos if ch.synchronous]
        self.event_tpdos = [ch for ch in valid_tpdos if not ch.synchronous]
        self.deadline_rpdos = [ch for ch in valid_rpdos if ch.event_s > 0.0]

    def _make_comm_check(self, ch: PdoChannel) -> Callable[[int, Any], None]:
        def check(sub: int, value: int) -> None:
            if sub == 1:
                self._check_cob(ch, value)
            elif sub == 2:
                check_transmission_type(ch.comm_index, value, ch.receive)
            elif sub == 3 and ch.valid:
                raise SdoAbort(ABORT_DEVICE_STATE, ch.comm_index, sub,
                               "inhibit time cannot change while the PDO is valid (set COB-ID bit 31 first)")
        return check

    def _make_comm_apply(self, ch: PdoChannel) -> Callable[[int, Any], None]:
        def apply(sub: int, value: int) -> None:
            if sub == 1 and ch.comm_index in self.no_rtr:
                self.store.set(ch.comm_index, 1, value | COB_NO_RTR)
            self.load(ch)
            if sub == 1:
                self._routing_changed()
        return apply

    def _check_cob(self, ch: PdoChannel, value: int) -> None:
        index = ch.comm_index
        if value & COB_EXTENDED:
            raise SdoAbort(ABORT_VALUE_RANGE, index, 1, "29-bit COB-IDs are not supported; expected bit 29 = 0")
        can_id = value & 0x1FFFFFFF
        if not 0 < can_id <= COB_ID_MASK:
            raise SdoAbort(ABORT_VALUE_RANGE, index, 1, f"COB-ID 0x{can_id:X} outside 0x001..0x7FF")
        new_valid = not value & COB_INVALID
        if ch.valid and new_valid and can_id != ch.cob_id:
            raise SdoAbort(ABORT_VALUE_RANGE, index, 1,
                           "COB-ID cannot change while the PDO is valid (set bit 31 first)")
        if new_valid and not ch.valid:
            validate_mapping(self.store, ch.map_index, self.mapping_raws(ch), ch.receive, self.max_bytes)

    def _make_map_check(self, ch: PdoChannel) -> Callable[[int, Any], None]:
        def check(sub: int, value: int) -> None:
            index = ch.map_index
            nmt = self._nmt_state()
            if nmt is not NmtState.PRE_OPERATIONAL:
                raise SdoAbort(ABORT_DEVICE_STATE, index, sub,
                               f"PDO mapping can only change in NMT pre-operational (now {nmt.name})")
            if ch.valid:
                raise SdoAbort(ABORT_DEVICE_STATE, index, sub,
                               f"PDO is valid; set bit 31 of 0x{ch.comm_index:04X}:01 first")
            if sub == 0:
                present = max((s for s in self.store.subindices(index) if s > 0), default=0)
                if value > present:
                    raise SdoAbort(ABORT_PDO_LENGTH, index, sub,
                                   f"{value} mapping entries; this PDO has room for {present}")
                raws = [self._sub(index, s, 0) for s in range(1, value + 1)]
                validate_mapping(self.store, index, raws, ch.receive, self.max_bytes)
                return
            if self.store.get(index, 0) != 0:
                raise SdoAbort(ABORT_DEVICE_STATE, index, sub,
                               "mapping entries can only be written while sub-index 0 is 0")
            if value != 0:
                validate_entry(self.store, index, value, ch.receive)
        return check

    def on_nmt(self, previous: NmtState, state: NmtState) -> None:
        """NMT state change: RPDOs forget what they latched when leaving operational; TPDOs start afresh."""
        if previous is NmtState.OPERATIONAL:
            for ch in self.rpdos:
                ch.latched = None
                ch.last_rx_s = None
                ch.timed_out = False
            self.last_rx_s = None
            self.watchdog_expired = False
        if state is NmtState.OPERATIONAL:
            for ch in self.tpdos:
                ch.sync_count = 0
                ch.last_data = None
                ch.pending = ch.valid and not ch.synchronous  # event TPDOs report once on start

    # --- process data ------------------------------------------------------------------------------------
    def receive(self, ch: PdoChannel, data: bytes | bytearray, now: float) -> None:
        counters = self.counters
        counters.rpdos_received += 1
        if len(data) < ch.layout.size:
            counters.rpdo_length_errors += 1
            if not ch.length_error:
                ch.length_error = True
                self._raise_error(EMCY_PDO_LENGTH, ERR_REG_COMMUNICATION, bytes((ch.number,)))
                self._refresh()
            return
        if ch.length_error:
            ch.length_error = False
            self._clear_error(EMCY_PDO_LENGTH)
        ch.last_rx_s = self.last_rx_s = now
        if ch.timed_out:
            ch.timed_out = False
            self._clear_error(EMCY_RPDO_TIMEOUT)
        if self.watchdog_expired:
            self.watchdog_expired = False
            self._clear_error(EMCY_RPDO_TIMEOUT)
        if ch.synchronous:
            ch.latched = bytes(data)
        else:
            self.apply(ch, data)
            if self.event_tpdos:
                self.poll_event_tpdos(now)

    def apply(self, ch: PdoChannel, data: bytes | bytearray) -> None:
        cells = self.store.cells
        for slot, value in zip(ch.slots, ch.layout.unpack_from(data), strict=True):  # (dummies unpack to nothing)
            cells[slot] = value
        hooks = self.rpdo_hooks
        for slot in ch.hooked_slots:  # mode before controlword
            hooks[slot](cells[slot])
        self.counters.rpdos_applied += 1

    def on_sync(self, now: float) -> None:
        """SYNC (actual values sampled by the caller): synchronous TPDOs, then the latched RPDOs take effect."""
        cells = self.store.cells
        for ch in self.sync_tpdos:
            ch.sync_count += 1
            if ch.trans_type == 0:
                data = ch.sample(cells)
                if data != ch.last_data:
                    self.send(ch, data)
            elif ch.sync_count >= ch.trans_type:
                ch.sync_count = 0
                self.send(ch, ch.sample(cells))
        applied = False
        for ch in self.sync_rpdos:
            latched = ch.latched
            if latched is not None:
                ch.latched = None
                self.apply(ch, latched)
                applied = True
        if applied and self.event_tpdos:
            self.poll_event_tpdos(now, sampled=True)

    def send(self, ch: PdoChannel, data: bytes) -> None:
        ch.last_data = data
        self.counters.tpdos_sent += 1
        if self._send_data is None:
            self._tx(can.Message(arbitration_id=ch.cob_id, data=data, is_extended_id=False, is_fd=ch.is_fd,
                                 bitrate_switch=ch.is_fd, check=False))
            return
        try:
            self._send_data(ch.cob_id, data, ch.is_fd)
        except can.CanError:
            self.counters.send_errors += 1

    def poll_event_tpdos(self, now: float, sampled: bool = False) -> None:
        """Send the event-driven TPDOs whose data changed (inhibit time kept); ``sampled``: actual values are
        current."""
        if not sampled:
            self._sample()
        cells = self.store.cells
        for ch in self.event_tpdos:
            data = ch.sample(cells)
            if data != ch.last_data or ch.pending:
                if now - ch.last_tx_s >= ch.inhibit_s:
                    ch.pending = False
                    ch.last_tx_s = now
                    self.send(ch, data)
                else:
                    ch.pending = True
            elif ch.event_s > 0.0 and now - ch.last_tx_s >= ch.event_s:
                ch.last_tx_s = now
                self.send(ch, data)
