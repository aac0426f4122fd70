"""Object dictionary values of one simulated CANopen node: slots, SDO-level access checks, defaults.

Definitions (type, access, limits, defaults, mappability) come from an EDS loaded with
`canopen.objectdictionary.import_od`; the values live in one flat list (`cells`) so that the hot paths
(PDOs on SYNC, the 4 kHz drive update) read and write them by precomputed slot numbers.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from pathlib import Path
from typing import Any

import canopen
from canopen.objectdictionary import ODArray, ODRecord, ODVariable, datatypes

from dragd.hardware.cia301 import DT_UNSIGNED32

# --- SDO abort codes (CiA 301) ---------------------------------------------------------------------------
ABORT_TOGGLE = 0x05030000
ABORT_TIMEOUT = 0x05040000
ABORT_UNKNOWN_COMMAND = 0x05040001
ABORT_UNSUPPORTED_ACCESS = 0x06010000
ABORT_READ_WRITE_ONLY = 0x06010001
ABORT_WRITE_READ_ONLY = 0x06010002
ABORT_NO_OBJECT = 0x06020000
ABORT_CANNOT_MAP = 0x06040041
ABORT_PDO_LENGTH = 0x06040042
ABORT_PARAMETER_INCOMPATIBLE = 0x06040043
ABORT_LENGTH_MISMATCH = 0x06070010
ABORT_NO_SUBINDEX = 0x06090011
ABORT_VALUE_RANGE = 0x06090030
ABORT_GENERAL = 0x08000000
ABORT_DEVICE_STATE = 0x08000022

MAX_STRING_BYTES = 255

# struct codes of the fixed-size types this device stores (and may map into PDOs)
STRUCT_CODES: dict[int, str] = {
    datatypes.BOOLEAN: "?",
    datatypes.INTEGER8: "b",
    datatypes.UNSIGNED8: "B",
    datatypes.INTEGER16: "h",
    datatypes.UNSIGNED16: "H",
    datatypes.INTEGER32: "i",
    datatypes.UNSIGNED32: "I",
    datatypes.REAL32: "f",
    datatypes.INTEGER64: "q",
    datatypes.UNSIGNED64: "Q",
    datatypes.REAL64: "d",
}
_STRUCTS: dict[int | None, struct.Struct] = {dt: struct.Struct("<" + code) for dt, code in STRUCT_CODES.items()}
_STRING_TYPES = (datatypes.VISIBLE_STRING, datatypes.OCTET_STRING, datatypes.DOMAIN)


class SdoAbort(Exception):
    """An SDO access that the server answers with an abort code."""

    def __init__(self, code: int, index: int, subindex: int, detail: str) -> None:
        super().__init__(f"0x{index:04X}:{subindex:02X}: {detail} (SDO abort 0x{code:08X})")
        self.code = code
        self.index = index
        self.subindex = subindex
        self.detail = detail


# a hook sees (subindex, decoded value) before the value is stored; it raises SdoAbort to refuse it
WriteHook = Callable[[int, Any], None]


def fixed_size_bits(var: ODVariable) -> int | None:
    """Bit size of a fixed-size data type, None for strings/domains and unsupported types."""
    st = _STRUCTS.get(var.data_type)
    return None if st is None else st.size * 8


class ObjectStore:
    """The values of one node's object dictionary, addressed by (index, subindex) or by slot."""

    def __init__(self, od: canopen.ObjectDictionary) -> None:
        self.od = od
        self.slots: dict[tuple[int, int], int] = {}
        self.vars: list[ODVariable | None] = []  # None: an internal cell (see ``internal``)
        self.defaults: list[Any] = []
        self.internal_names: dict[str, int] = {}
        self.dummy_indices: frozenset[int] = frozenset()
        self._build()
        self.cells: list[Any] = list(self.defaults)
        self.before_write: dict[int, WriteHook] = {}
        self.after_write: dict[int, WriteHook] = {}
        self.written: Callable[[], None] | None = None  # called after every checked write (an SDO download)

    @classmethod
    def from_eds(cls, eds_path: str | Path, node_id: int) -> ObjectStore:
        """Load an EDS for a node (resolving $NODEID) and build its store."""
        return cls(canopen.objectdictionary.import_od(str(eds_path), node_id))

    def _build(self) -> None:
        dummies = []
        for index in sorted(self.od.indices):
            obj = self.od.indices[index]
            if isinstance(obj, (ODRecord, ODArray)):
                for sub in sorted(obj.subindices):
                    self._add(obj.subindices[sub])
            elif index <= DT_UNSIGNED32:  # the basic data types 0001h-0007h: dummy mapping entries
                dummies.append(index)
            else:
                self._add(obj)
        self.dummy_indices = frozenset(dummies)

    def _add(self, var: ODVariable) -> None:
        if var.data_type not in STRUCT_CODES and var.data_type not in _STRING_TYPES:
            raise ValueError(f"0x{var.index:04X}:{var.subindex:02X} {var.name!r}: data type 0x{var.data_type:X} "
                             f"is not supported by the simulated drive; expected a fixed-size number or a string")
        self.slots[(var.index, var.subindex)] = len(self.vars)
        self.vars.append(var)
        self.defaults.append(_initial_value(var))

    def internal(self, name: str, value: Any) -> int:
        """A cell for a value the device holds but its dictionary does not show (a quantity the EDS lacks, e.g. the
        rated current of a drive without 6075h): no SDO access, not mappable, back to ``value`` on reset node."""
        slot = self.internal_names.get(name)
        if slot is None:
            slot = self.internal_names[name] = len(self.vars)
            self.vars.append(None)
            self.defaults.append(value)
            self.cells.append(value)
        else:
            self.defaults[slot] = self.cells[slot] = value
        return slot

    def hook_after(self, index: int, hook: WriteHook) -> None:
        """Add a hook after writes to ``index`` (run after the hooks added before it)."""
        first = self.after_write.get(index)
        if first is None:
            self.after_write[index] = hook
            return

        def both(sub: int, value: Any) -> None:
            first(sub, value)
            hook(sub, value)
        self.after_write[index] = both

    def slot_or_internal(self, index: int, subindex: int, name: str, value: Any) -> int:
        """The object's slot, or an internal cell holding ``value`` where the dictionary lacks it."""
        slot = self.slots.get((index, subindex))
        return self.internal(name, value) if slot is None else slot

    def has(self, index: int, subindex: int = 0) -> bool:
        """Whether the dictionary holds the object."""
        return (index, subindex) in self.slots

    def subindices(self, index: int) -> list[int]:
        """The sub-indices of an object that the dictionary holds (ascending), [] if it has none."""
        return sorted(sub for (i, sub) in self.slots if i == index)

    # --- plain access (no SDO checks) -------------------------------------------------------------------
    def slot(self, index: int, subindex: int = 0) -> int:
        """Slot number of an object; KeyError naming the object if it is not in the dictionary."""
        try:
            return self.slots[(index, subindex)]
        except KeyError:
            raise KeyError(f"object 0x{index:04X}:{subindex:02X} is not in the object dictionary") from None

    def get(self, index: int, subindex: int = 0) -> Any:
        return self.cells[self.slot(index, subindex)]

    def set(self, index: int, subindex: int, value: Any) -> None:
        """Store a value without hooks or access checks (the device's own writes)."""
        self.cells[self.slot(index, subindex)] = value

    def set_default(self, index: int, subindex: int, value: Any) -> None:
        """Change a default (device-specific factory value) and the current value."""
        slot = self.slot(index, subindex)
        self.defaults[slot] = value
        self.cells[slot] = value

    def reset(self, indices: range | None = None) -> None:
        """Restore defaults, for all objects or for those whose index is in ``indices`` (an area of cia301)."""
        for slot, var in enumerate(self.vars):
            if indices is None or (var is not None and var.index in indices):
                self.cells[slot] = self.defaults[slot]

    def var(self, index: int, subindex: int) -> ODVariable:
        """The definition of an object, raising SdoAbort 0x06020000 / 0x06090011 if absent."""
        slot = self.slots.get((index, subindex))
        if slot is not None:
            return self.vars[slot]  # type: ignore[return-value]  # (slots hold dictionary objects only)
        if index in self.od.indices and index > DT_UNSIGNED32:
            raise SdoAbort(ABORT_NO_SUBINDEX, index, subindex, "sub-index does not exist")
        raise SdoAbort(ABORT_NO_OBJECT, index, subindex, "object does not exist")

    # --- SDO-level access -----------------------------------------------------------------------------
    def sdo_read(self, index: int, subindex: int) -> bytes:
        """Encoded value for an SDO upload (checks existence and read access)."""
        var = self.var(index, subindex)
        if not var.readable:
            raise SdoAbort(ABORT_READ_WRITE_ONLY, index, subindex, "object is write-only")
        return encode(var, self.cells[self.slots[(index, subindex)]])

    def check_writable(self, index: int, subindex: int) -> ODVariable:
        """Definition of a writable object, raising the matching SdoAbort otherwise."""
        var = self.var(index, subindex)
        if not var.writable:
            raise SdoAbort(ABORT_WRITE_READ_ONLY, index, subindex, f"object is {var.access_type}")
        return var

    def sdo_write(self, index: int, subindex: int, data: bytes, size_known: bool = True) -> None:
        """Decode, check (access, length, limits, hooks) and store an SDO download."""
        var = self.check_writable(index, subindex)
        value = decode(var, data, size_known)
        self.write_checked(var, value)

    def write_checked(self, var: ODVariable, value: Any) -> None:
        """Range-check a decoded value, run the hooks and store it."""
        if var.data_type in STRUCT_CODES and not isinstance(value, bool):
            if var.min is not None and value < var.min:
                raise SdoAbort(ABORT_VALUE_RANGE, var.index, var.subindex,
                               f"value {value} below the minimum {var.min}")
            if var.max is not None and value > var.max:
                raise SdoAbort(ABORT_VALUE_RANGE, var.index, var.subindex,
                               f"value {value} above the maximum {var.max}")
        hook = self.before_write.get(var.index)
        if hook is not None:
            hook(var.subindex, value)
        self.cells[self.slots[(var.index, var.subindex)]] = value
        after = self.after_write.get(var.index)
        if after is not None:
            after(var.subindex, value)
        if self.written is not None:
            self.written()


def _initial_value(var: ODVariable) -> Any:
    """The EDS default of an object (ParameterValue wins), typed for the store."""
    value = var.value if var.value is not None else var.default
    if var.data_type == datatypes.VISIBLE_STRING:
        return "" if value is None else str(value)
    if var.data_type in (datatypes.OCTET_STRING, datatypes.DOMAIN):
        return b"" if value is None else bytes(value)
    if value is None:
        return 0.0 if var.data_type in (datatypes.REAL32, datatypes.REAL64) else 0
    st = _STRUCTS.get(var.data_type)
    if st is not None and isinstance(value, int) and not isinstance(value, bool) and st.format[-1] in "bhiqBHIQ":
        bits = st.size * 8  # a default given as a bit pattern (0xFFFF for an INTEGER16: -1) or out of the type's range
        value &= (1 << bits) - 1
        if st.format[-1] in "bhiq" and value >= 1 << (bits - 1):
            value -= 1 << bits
    return value


def encode(var: ODVariable, value: Any) -> bytes:
    """Little-endian bytes of a stored value."""
    st = _STRUCTS.get(var.data_type)
    if st is not None:
        return st.pack(value)
    if var.data_type == datatypes.VISIBLE_STRING:
        return str(value).encode("ascii")
    return bytes(value)


def decode(var: ODVariable, data: bytes, size_known: bool = True) -> Any:
    """Decode downloaded bytes; SdoAbort 0x06070010 on a length mismatch, 0x06090030 on bad text.

    `size_known=False` (expedited download without size indication) takes the object's size from the
    four data bytes.
    """
    st = _STRUCTS.get(var.data_type)
    if st is not None:
        if not size_known and len(data) >= st.size:
            data = data[: st.size]
        if len(data) != st.size:
            raise SdoAbort(ABORT_LENGTH_MISMATCH, var.index, var.subindex,
                           f"{len(data)} data bytes for a {st.size}-byte object")
        return st.unpack(data)[0]
    if len(data) > MAX_STRING_BYTES:
        raise SdoAbort(ABORT_LENGTH_MISMATCH, var.index, var.subindex,
                       f"{len(data)} bytes exceed the {MAX_STRING_BYTES}-byte limit")
    if var.data_type == datatypes.VISIBLE_STRING:
        try:
            return bytes(data).decode("ascii").rstrip("\x00")
        except UnicodeDecodeError:
            raise SdoAbort(ABORT_VALUE_RANGE, var.index, var.subindex, "VISIBLE_STRING must be ASCII") from None
    return bytes(data)
