"""Drives built from an EDS by python-canopen (``LocalNode``: an independent CANopen implementation) on a python-can
virtual bus, with what CiA 301/402 add that ``LocalNode`` leaves out, so dragd's boot meets a drive as its EDS
describes it:

- NMT reset node/communication: boot-up message, pre-operational, the object dictionary back to its defaults;
- PDO mapping writes checked against the EDS (CiA 301): an object that does not exist or is not PDO-mappable in that
  direction, or whose length differs, aborts 0604 0041; a mapping longer than 64 bits aborts 0604 0042; dummy
  entries only where [DummyUsage] has them;
- TPDO COB-IDs whose EDS default has bit 30 ("no RTR") keep it, whatever is written;
- 6061h shows 6060h when 6502h lists the mode (else the previous mode); 6041h follows the controlword through the
  CiA 402 states the boot uses (disable voltage, shutdown, switch on, enable operation);
- values the EDS does not give (``facts``): e.g. 6502h, 1018h, 6075h of a drive whose EDS leaves them out.

``LocalNode`` itself refuses reads/writes of missing objects (0602 0000), missing sub-indices (0609 0011) and writes of
read-only objects (0601 0002).
"""

from __future__ import annotations

import functools
import struct
import time
from pathlib import Path

import can
import canopen
from canopen.objectdictionary import ODArray, ODRecord, ODVariable
from canopen.sdo import SdoAbortedError

from dragd.hardware.eds import for_node

CANNOT_MAP = 0x06040041
TOO_LONG = 0x06040042


@functools.lru_cache(maxsize=64)
def _parsed(path: str, mtime_ns: int) -> canopen.ObjectDictionary:
    """python-canopen's own ``import_od`` of the file (for node 1), once per file version in this process."""
    return canopen.import_od(path, 1)


def _dictionary(eds: Path, node_id: int) -> canopen.ObjectDictionary:
    """The node's own dictionary: a copy of canopen's parse with the ``$NODEID`` values for ``node_id``
    (dragd/hardware/eds.py ``for_node``: equal to ``canopen.import_od(eds, node_id)`` object by object for every EDS
    these tests load, tests/test_eds_cache.py), never an object dragd's own cache hands its profiles."""
    return for_node(_parsed(str(eds), Path(eds).stat().st_mtime_ns), node_id)


class EdsNode(canopen.LocalNode):
    """One drive: a LocalNode from ``eds`` with the checks above."""

    def __init__(self, node_id: int, eds: Path, facts: dict[tuple[int, int], int] | None = None,
                 max_pdo_bits: int = 64, sticky_statusword: int | None = None) -> None:
        super().__init__(node_id, _dictionary(eds, node_id))
        self.eds = eds
        self.facts = dict(facts or {})
        self.max_pdo_bits = max_pdo_bits
        self.sticky_statusword = sticky_statusword  # a drive that stays in this state whatever the controlword
        self.writes: list[tuple[int, int, bytes]] = []  # every SDO download that was accepted
        self.aborted: list[tuple[int, int, int]] = []  # (index, sub, code) of every refused download
        self.mode = 0
        self.statusword = 0x0040  # switch on disabled
        self.add_read_callback(self._on_read)
        self._reset()

    # ------------------------------------------------------------------------------------------ the store

    def _reset(self) -> None:
        self.data_store = {}
        for (index, sub), value in self.facts.items():
            obj = self._find_object(index, sub)
            self.data_store.setdefault(index, {})[sub] = obj.encode_raw(value)
        self.mode = 0
        self.statusword = self.sticky_statusword if self.sticky_statusword is not None else 0x0040

    def value(self, index: int, sub: int = 0) -> int:
        """What the drive holds now (decoded by the EDS data type)."""
        obj = self._find_object(index, sub)
        return obj.decode_raw(self.get_data(index, sub))

    def _on_read(self, index: int, subindex: int, od: ODVariable) -> int | None:
        if index == 0x6041:
            return self.statusword
        if index == 0x6061:
            return self.mode
        return None

    # ------------------------------------------------------------------------------------------ writes

    def set_data(self, index: int, subindex: int, data: bytes, check_writable: bool = False) -> None:
        try:
            obj = self._find_object(index, subindex)
            if check_writable and not obj.writable:
                raise SdoAbortedError(0x06010002)
            if obj.data_type in canopen.objectdictionary.NUMBER_TYPES and 8 * len(data) != len(obj):
                raise SdoAbortedError(0x06070010)
            data = self._check(index, subindex, bytes(data))
            super().set_data(index, subindex, data, check_writable=False)
        except SdoAbortedError as exc:
            self.aborted.append((index, subindex, exc.code))
            raise
        self.writes.append((index, subindex, bytes(data)))
        if index == 0x6060:
            mode = struct.unpack("<b", data[:1])[0]
            modes = self._modes()
            if modes is None or (mode > 0 and modes & (1 << (mode - 1))):
                self.mode = mode
        elif index == 0x6040:
            self._controlword(int.from_bytes(data[:2], "little"))

    def _modes(self) -> int | None:
        try:
            return self.value(0x6502)
        except (SdoAbortedError, KeyError):
            return None

    def _controlword(self, cw: int) -> None:
        if self.sticky_statusword is not None:
            return
        if not cw & 0x2:  # disable voltage
            self.statusword = 0x0040
        elif cw & 0x8F == 0x06:
            self.statusword = 0x0021
        elif cw & 0x8F == 0x07:
            self.statusword = 0x0023
        elif cw & 0x8F == 0x0F:
            self.statusword = 0x0027

    def _check(self, index: int, sub: int, data: bytes) -> bytes:
        """CiA 301 checks of PDO parameters; the data to store."""
        if 0x1800 <= index <= 0x19FF and sub == 1:  # a TPDO COB-ID: bit 30 stays where the EDS has it
            default = self._find_object(index, 1).default or 0
            if default & 0x4000_0000:
                value = int.from_bytes(data, "little") | 0x4000_0000
                return value.to_bytes(4, "little")
        tpdo = 0x1A00 <= index <= 0x1BFF
        if not (tpdo or 0x1600 <= index <= 0x17FF):
            return data
        if sub == 0:
            count = data[0]
            bits = 0
            for k in range(1, count + 1):
                try:
                    word = int.from_bytes(self.get_data(index, k), "little")
                except SdoAbortedError:
                    raise SdoAbortedError(TOO_LONG) from None
                bits += word & 0xFF
            if bits > self.max_pdo_bits:
                raise SdoAbortedError(TOO_LONG)
            return data
        word = int.from_bytes(data, "little")
        if word == 0:
            return data
        m_index, m_sub, m_bits = word >> 16, (word >> 8) & 0xFF, word & 0xFF
        if 1 <= m_index <= 7:  # a dummy: only where [DummyUsage] lists it (canopen adds those as objects 1..7)
            if tpdo or m_index not in self.object_dictionary:
                raise SdoAbortedError(CANNOT_MAP)
            if m_bits != len(self.object_dictionary[m_index]):
                raise SdoAbortedError(CANNOT_MAP)
            return data
        try:
            var = self._find_object(m_index, m_sub)
        except SdoAbortedError:
            raise SdoAbortedError(CANNOT_MAP) from None
        direction_ok = var.readable if tpdo else var.writable
        if not var.pdo_mappable or not direction_ok or len(var) != m_bits:
            raise SdoAbortedError(CANNOT_MAP)
        return data


class EdsBus:
    """A virtual bus with drives built from EDS files; NMT reset answered with a boot-up."""

    def __init__(self, channel: str, nodes: list[EdsNode]) -> None:
        self.network = canopen.Network()
        # the notifier's receive timeout bounds how long ``close`` waits for its thread (canopen's 1 s per bus)
        self.network.NOTIFIER_CYCLE = 0.05
        self.network.connect(interface="virtual", channel=channel, receive_own_messages=False)
        self.nodes = {n.id: n for n in nodes}
        for n in nodes:
            self.network.add_node(n)
        self.network.subscribe(0, self._nmt)

    def _nmt(self, can_id: int, data: bytearray, timestamp: float) -> None:
        cmd, target = data[0], data[1]
        if cmd not in (0x81, 0x82):
            return
        for n in self.nodes.values():
            if target not in (0, n.id):
                continue
            if cmd == 0x81:
                n._reset()
            else:  # reset communication: 1000h-1FFFh back to the defaults
                n.data_store = {k: v for k, v in n.data_store.items() if not 0x1000 <= k <= 0x1FFF}
            n.nmt.stop_heartbeat()
            n.nmt._state = 0
            self.network.send_message(0x700 + n.id, [0])
            n.nmt._state = 127

    def close(self) -> None:
        for n in self.nodes.values():
            n.nmt.stop_heartbeat()
        self.network.disconnect()


def mapping(node: EdsNode, index: int) -> list[int]:
    """The mapping words a drive holds in 16xxh/1Axxh."""
    count = node.value(index, 0)
    return [node.value(index, k) for k in range(1, count + 1)]


def has(od: canopen.ObjectDictionary, index: int, sub: int = 0) -> bool:
    obj = od.get(index)
    if obj is None:
        return False
    return sub == 0 if isinstance(obj, ODVariable) else isinstance(obj, (ODRecord, ODArray)) and sub in obj


def wait(cond, timeout_s: float = 2.0) -> bool:  # type: ignore[no-untyped-def]
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.01)
    return bool(cond())


__all__ = ["EdsBus", "EdsNode", "mapping", "has", "wait", "can"]
