"""The drive profile: dragd's contract with one joint's drive, built from its EDS and the configuration's ``drives``.

A :class:`DriveProfile` says, for one joint, which objects carry its process data (statusword, position, current,
controlword, target position, torque command) with their EDS data types, how the current and the command convert to
amperes, which PDOs the drive has (and what their communication and mapping parameters allow), whether it supports
dummy mapping and CAN FD, and which optional objects it lacks. :meth:`DriveProfile.findings` lists, offline and all
at once, everything the configuration needs that the drive lacks or cannot map, each with the configuration key to
change. The master boots from the profile (hardware/master.py), the layout maps from it (hardware/pdo.py), the
scaling converts with it (hardware/scaling.py); docs/DRIVES.md is the user's side of it.

Units (CiA 402): 6078h per mille of the rated current (6075h, mA); 6071h, 60B2h, 6077h per mille of the rated torque
(6076h, mN·m). A torque per mille is a current through the motor torque constant K_m: I = T / K_m. With
``joints[].rated_torque_Nm`` unset the rated torque is K_m × rated current, so a torque per mille is a current per
mille of the rated current and K_m drops out (the drive's own 6076h is then only compared with K_m).
"""

from __future__ import annotations

import configparser
import functools
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import canopen
from canopen.objectdictionary import ODArray, ODRecord, ODVariable, datatypes

from dragd.hardware.cia301 import (
    DUMMY_TYPES,
    OD_CONSUMER_HEARTBEAT,
    OD_DEVICE_TYPE,
    OD_IDENTITY,
    OD_PRODUCER_HEARTBEAT,
    OD_RPDO_COMM,
    OD_RPDO_MAP,
    OD_TPDO_COMM,
    OD_TPDO_MAP,
)
from dragd.hardware.cia402 import DEVICE_TYPE_402 as DEVICE_TYPE_402  # (re-exported: master.py imports it here)
from dragd.hardware.cia402 import (
    MODE_CSP,
    MODE_CST,
    OD_ABORT_CONNECTION_OPTION,
    OD_CONTROLWORD,
    OD_CURRENT_ACTUAL,
    OD_DIGITAL_INPUTS,
    OD_MAX_TORQUE,
    OD_MODES_OF_OPERATION,
    OD_MODES_OF_OPERATION_DISPLAY,
    OD_MOTOR_RATED_CURRENT,
    OD_MOTOR_RATED_TORQUE,
    OD_POSITION_ACTUAL,
    OD_QUICK_STOP_OPTION,
    OD_STATUSWORD,
    OD_SUPPORTED_DRIVE_MODES,
    OD_TARGET_POSITION,
    OD_TARGET_TORQUE,
    OD_TORQUE_ACTUAL,
    OD_TORQUE_OFFSET,
)
from dragd.hardware.eds import import_od as cached_import_od

if TYPE_CHECKING:
    from dragd.config import Config, DriveConfig, JointConfig

MAX_PDOS = 512  # CiA 301: 1400h..15FFh, 1800h..19FFh

# struct codes of the EDS data types a PDO may carry (little endian; CiA 301)
STRUCT_CODES = {datatypes.BOOLEAN: "?", datatypes.INTEGER8: "b", datatypes.INTEGER16: "h", datatypes.INTEGER32: "i",
                datatypes.INTEGER64: "q", datatypes.UNSIGNED8: "B", datatypes.UNSIGNED16: "H",
                datatypes.UNSIGNED32: "I", datatypes.UNSIGNED64: "Q", datatypes.REAL32: "f", datatypes.REAL64: "d"}
TYPE_NAMES = {v: k for k, v in vars(datatypes).items() if k.isupper() and isinstance(v, int) and v < 0x20}


def type_name(data_type: int | None) -> str:
    """``INTEGER16`` for an EDS data type (its number in hex where CiA 301 names none)."""
    return "no type" if data_type is None else TYPE_NAMES.get(data_type, f"0x{data_type:04X}")

CURRENT_UNITS_A = {"A": 1.0, "dA": 0.1, "cA": 0.01, "mA": 1e-3, "uA": 1e-6}
TORQUE_UNITS_NM = {"Nm": 1.0, "mNm": 1e-3, "uNm": 1e-6}
CURRENT_UNITS = {"permille_rated_current": "per mille of the rated current",
                 "permille_rated_torque": "per mille of the rated torque", **{u: u for u in CURRENT_UNITS_A}}
STANDARD_CURRENT_UNIT = {OD_CURRENT_ACTUAL: "permille_rated_current", OD_TORQUE_ACTUAL: "permille_rated_torque"}

Level = Literal["error", "warning", "note"]


class ProfileError(ValueError):
    """A drive profile that cannot be used: the text lists every finding (file, joint, node, object, key)."""


def parse_address(text: str) -> tuple[int, int]:
    """``"6078h"`` → (0x6078, 0); ``"30D1h:2"`` → (0x30D1, 2); sub-indices in decimal, or hex with ``h``/``0x``."""
    m = re.fullmatch(r"\s*(?:0x)?([0-9A-Fa-f]{4})h?\s*(?::\s*((?:0x)?[0-9A-Fa-f]{1,2}h?))?\s*", text)
    if m is None:
        raise ValueError(f"expected an object address like 6078h or 30D1h:2, got '{text}'")
    sub = m.group(2)
    if sub is None:
        return int(m.group(1), 16), 0
    if sub.lower().endswith("h") or sub.lower().startswith("0x"):
        return int(m.group(1), 16), int(sub.lower().removesuffix("h"), 16)
    return int(m.group(1), 16), int(sub, 10)


def address(index: int, sub: int = 0) -> str:
    """The address as configurations write it: ``6078h``, ``30D1h:2``."""
    return f"{index:04X}h" if sub == 0 else f"{index:04X}h:{sub}"


@dataclass(frozen=True)
class Finding:
    """One thing the configuration needs that the drive lacks (error), works around (warning) or notes (note)."""

    level: Level
    text: str  # where: what; the key to set
    refusal: str | None = None  # the drive cannot do torque drag at all: why (no CST, no 6071h)
    where: str = ""  # the prefix of ``text`` naming file, joint, node and bus (joints with one drive are grouped by it)

    def __str__(self) -> str:
        return f"{self.level}: {self.text}"

    @property
    def body(self) -> str:
        return self.text[len(self.where) + 2:] if self.where and self.text.startswith(self.where) else self.text


def grouped(findings: list[Finding]) -> list[tuple[Finding, str]]:
    """Findings that say the same of several joints' drives, once, with the joints they apply to (``where``:
    ``FILE: joints[i] (NAME) node N on bus 'B'``, shortened to ``FILE: NAME (node N, bus B), ...``)."""
    groups: dict[tuple[str, str, str], tuple[Finding, list[str]]] = {}
    for f in findings:
        eds = f.where.split(":", 1)[0] if f.where else ""
        key = (f.level, eds, f.body if f.where else f.text)
        if key in groups:
            groups[key][1].append(f.where)
        else:
            groups[key] = (f, [f.where] if f.where else [])
    out = []
    for f, wheres in groups.values():
        places = []
        for w in wheres:
            m = re.match(r"^(.*?): joints\[\d+\] \((.*?)\) node (\d+) on bus '(.*)'$", w)
            places.append(f"{m.group(2)} (node {m.group(3)}, bus {m.group(4)})" if m else w)
        eds = wheres[0].split(":", 1)[0] if wheres else ""
        out.append((f, f"{eds}: {', '.join(places)}" if wheres else ""))
    return out


@dataclass(frozen=True)
class PdoChannel:
    """A PDO the drive has (both its communication and mapping objects exist in the EDS)."""

    direction: Literal["tpdo", "rpdo"]
    number: int  # 1-based
    comm_subs: frozenset[int]
    cob_default: int | None
    cob_writable: bool
    ttype_writable: bool
    map_writable: bool  # sub 0 and every entry writable
    max_entries: int  # highest mapping sub-index the EDS defines
    default_words: tuple[int, ...]  # the EDS's default mapping (sub 1 .. sub 0's default)

    @property
    def comm_index(self) -> int:
        return (OD_TPDO_COMM if self.direction == "tpdo" else OD_RPDO_COMM) + self.number - 1

    @property
    def map_index(self) -> int:
        return (OD_TPDO_MAP if self.direction == "tpdo" else OD_RPDO_MAP) + self.number - 1

    @property
    def name(self) -> str:
        return f"{self.direction.upper()}{self.number}"


@dataclass(frozen=True)
class ProcessObject:
    """An object carried in a PDO: address, EDS data type, bit length and struct code."""

    field: str
    index: int
    sub: int
    bits: int
    code: str  # struct code (little endian in the frame)
    name: str

    @property
    def word(self) -> int:
        """The 32-bit mapping entry (CiA 301: index << 16 | sub << 8 | bits)."""
        return (self.index << 16) | (self.sub << 8) | self.bits


def import_eds(path: Path, node_id: int) -> canopen.ObjectDictionary:
    """``canopen.import_od`` of an EDS for a node (hardware/eds.py: parsed once per file version, cached per node;
    treat it as read-only)."""
    try:
        path.stat()
    except OSError as exc:
        raise ProfileError(f"{path}: cannot be read: {exc.strerror}") from None
    try:
        return cached_import_od(path, node_id)
    except Exception as exc:  # canopen raises configparser, ValueError, KeyError ... for a broken file
        raise ProfileError(f"{path}: not a readable EDS (canopen.import_od: {type(exc).__name__}: {exc})") from None


@functools.lru_cache(maxsize=64)
def _device_info(path: str, mtime_ns: int) -> dict[str, str]:
    cp = configparser.RawConfigParser(strict=False)
    cp.optionxform = str  # type: ignore[assignment,method-assign]
    try:
        cp.read(path, encoding="utf-8")
    except (UnicodeDecodeError, configparser.Error):
        cp = configparser.RawConfigParser(strict=False)
        cp.optionxform = str  # type: ignore[assignment,method-assign]
        cp.read(path, encoding="latin-1")
    return dict(cp["DeviceInfo"]) if cp.has_section("DeviceInfo") else {}


def device_info(path: Path) -> dict[str, str]:
    """The EDS's [DeviceInfo] keys (VendorNumber, ProductNumber, CANopenFD, ...)."""
    return _device_info(str(path), path.stat().st_mtime_ns)


def eds_says_fd(path: Path) -> bool:
    """Whether the EDS declares a CAN FD drive: ``[DeviceInfo] CANopenFD=1`` (EDS 4.0, CiA 306-1, has no standard key
    for CAN FD: CANopen FD devices are described in XDD; dragd reads this key, its own joint drive carries it)."""
    value = device_info(path).get("CANopenFD", "0").strip()
    try:
        return int(value, 0) == 1
    except ValueError:
        return False


def od_var(od: canopen.ObjectDictionary, index: int, sub: int = 0) -> ODVariable | None:
    """An object dictionary's entry for index:sub, or None."""
    obj = od.indices.get(index)  # (``od.get`` builds a KeyError text for every absent index)
    if obj is None:
        return None
    if isinstance(obj, ODVariable):
        return obj if sub == 0 else None
    var: ODVariable | None = obj.subindices.get(sub)
    return var


def _int_default(var: ODVariable) -> int | None:
    v = var.default
    return v if isinstance(v, int) and not isinstance(v, bool) else None


def channels(od: canopen.ObjectDictionary, direction: Literal["tpdo", "rpdo"]) -> list[PdoChannel]:
    """The PDOs the EDS defines (communication and mapping object both present)."""
    comm_base, map_base = (OD_TPDO_COMM, OD_TPDO_MAP) if direction == "tpdo" else (OD_RPDO_COMM, OD_RPDO_MAP)
    out = []
    for k in range(MAX_PDOS):
        comm, mapping = od.indices.get(comm_base + k), od.indices.get(map_base + k)
        if comm is None or mapping is None:  # (most of the 512: before the slower ABC isinstance below)
            continue
        if not isinstance(comm, (ODRecord, ODArray)) or not isinstance(mapping, (ODRecord, ODArray)):
            continue
        subs = frozenset(comm.subindices)
        cob = comm.subindices.get(1)
        ttype = comm.subindices.get(2)
        entries = sorted(s for s in mapping.subindices if s >= 1)
        count0 = mapping.subindices.get(0)
        n_default = (_int_default(count0) or 0) if count0 is not None else 0
        words = tuple(_int_default(mapping.subindices[s]) or 0 for s in entries[:n_default] if s in mapping.subindices)
        map_writable = count0 is not None and count0.writable and all(mapping.subindices[s].writable for s in entries)
        out.append(PdoChannel(direction, k + 1, subs, _int_default(cob) if cob is not None else None,
                              bool(cob is not None and cob.writable), bool(ttype is not None and ttype.writable),
                              map_writable, max(entries) if entries else 0, words))
    return out


class DriveProfile:
    """One joint's drive as dragd uses it (read-only after construction)."""

    def __init__(self, cfg: Config, joint: int) -> None:
        self.cfg = cfg
        self.joint_index = joint
        self.joint: JointConfig = cfg.joints[joint]
        self.node_id = self.joint.node_id
        self.drive_name = self.joint.drive  # None: dragd's own joint drive
        self.drive: DriveConfig = cfg.drive_of(joint)
        self.eds_path = cfg.eds_of(joint)
        self.key = f"drives.{self.drive_name}" if self.drive_name else f"joints[{joint}].drive"
        self.where = (f"{self.eds_path.name}: joints[{joint}] ({self.joint.name}) node {self.node_id} on bus "
                      f"'{self.joint.bus}'")
        self._findings: list[Finding] = []
        self.od = import_eds(self.eds_path, self.node_id)
        self.fd = eds_says_fd(self.eds_path)
        self.tpdos = channels(self.od, "tpdo")
        self.rpdos = channels(self.od, "rpdo")
        self.dummies = frozenset(i for i in DUMMY_TYPES if i in self.od)
        self.supported_modes = self._default(OD_SUPPORTED_DRIVE_MODES)
        self.device_type = self._default(OD_DEVICE_TYPE)
        self.statusword = self._process("statusword", OD_STATUSWORD, 0, "tpdo", "the CiA 402 statusword")
        self.position = self._process("position", OD_POSITION_ACTUAL, 0, "tpdo", "the position actual value")
        self.controlword = self._process("controlword", OD_CONTROLWORD, 0, "rpdo", "the CiA 402 controlword")
        self.current, self.current_unit = self._current()
        self.command = self._command()
        self.target_position = self._process("target_position", OD_TARGET_POSITION, 0, "rpdo",
                                             "the CSP position target", quiet=True)
        self.rated_current_object = self._rated("rated_current")
        self.rated_torque_object = self._rated("rated_torque")
        self.watchdog_object = self._watchdog()
        self.inputs = self._inputs()
        self._check_modes()
        self._check_motion()
        self._check_required()
        self._check_optional()

    # -------------------------------------------------------------------------------------------- helpers

    def var(self, index: int, sub: int = 0) -> ODVariable | None:
        """The EDS's entry for index:sub, or None."""
        return od_var(self.od, index, sub)

    def has(self, index: int, sub: int = 0) -> bool:
        return self.var(index, sub) is not None

    def describe(self, index: int, sub: int = 0) -> str:
        """``6078h:00 'Current actual value'`` (the EDS's name where it has the object)."""
        var = self.var(index, sub)
        name = ""
        if var is not None:
            name = (f" '{var.parent.name}/{var.name}'" if isinstance(var.parent, (ODRecord, ODArray))
                    else f" '{var.name}'")
        return f"{index:04X}h:{sub:02X}{name}"

    def _default(self, index: int, sub: int = 0) -> int | None:
        var = self.var(index, sub)
        return _int_default(var) if var is not None else None

    def finding(self, level: Level, index: int | None, sub: int, what: str, fix: str = "",
                refusal: str | None = None) -> None:
        obj = f"{self.describe(index, sub)}: " if index is not None else ""
        self._findings.append(Finding(level, f"{self.where}: {obj}{what}{'; ' + fix if fix else ''}", refusal,
                                      self.where))

    def findings(self) -> list[Finding]:
        """Everything found offline, errors first."""
        order = {"error": 0, "warning": 1, "note": 2}
        return sorted(self._findings, key=lambda f: order[f.level])

    @property
    def errors(self) -> list[Finding]:
        return [f for f in self._findings if f.level == "error"]

    @property
    def refusals(self) -> list[str]:
        return [f.refusal for f in self._findings if f.refusal]

    def _process(self, fld: str, index: int, sub: int, direction: Literal["tpdo", "rpdo"], what: str, *,
                 key: str | None = None, quiet: bool = False) -> ProcessObject | None:
        """A process-data object checked for presence, access, PDO mapping and type; None (and a finding) if
        unusable."""
        fix = f"set {key}" if key else ""
        var = self.var(index, sub)
        if var is None:
            if not quiet:
                self.finding("error", index, sub, f"missing: {what} must be in the drive's {direction.upper()}", fix)
            return None
        access_ok = var.readable if direction == "tpdo" else var.writable
        problems = []
        if not var.pdo_mappable:
            problems.append("not PDO-mappable (PDOMapping=0)")
        if not access_ok:
            problems.append(f"AccessType={var.access_type}: not {'readable' if direction == 'tpdo' else 'writable'}")
        code = STRUCT_CODES.get(var.data_type) if var.data_type is not None else None
        if code is None:
            problems.append(f"data type {type_name(var.data_type)} cannot be decoded")
        if problems:
            if not quiet:
                self.finding("error", index, sub, f"{what} in a {direction.upper()}: {'; '.join(problems)}", fix)
            return None
        return ProcessObject(fld, index, sub, len(var), code or "", var.name)

    # -------------------------------------------------------------------------------------------- resolution

    def _current(self) -> tuple[ProcessObject | None, str]:
        key = f"{self.key}.current"
        try:
            index, sub = parse_address(self.drive.current.object)
        except ValueError as exc:
            self.finding("error", None, 0, str(exc), f"set {key}.object")
            return None, ""
        unit = self.drive.current.unit or STANDARD_CURRENT_UNIT.get(index if sub == 0 else -1)
        if unit is None:
            self.finding("error", index, sub, "a vendor current object needs its unit", f"set {key}.unit "
                         f"(one of {', '.join(CURRENT_UNITS)})")
        alternatives = [address(i) for i in (OD_CURRENT_ACTUAL, OD_TORQUE_ACTUAL)
                        if i != index and (v := self.var(i)) is not None and v.pdo_mappable and v.readable]
        hint = f"set {key}.object" + (f" (the drive maps {' and '.join(alternatives)})" if alternatives else
                                       " to a PDO-mappable current object of the drive (index:sub) with its unit")
        obj = self._process("current", index, sub, "tpdo", "the measured current", key=hint.removeprefix("set "))
        if obj is not None and obj.code in ("?",):
            self.finding("error", index, sub, "the measured current cannot be a BOOLEAN", hint)
            obj = None
        return obj, unit or ""

    def _command(self) -> ProcessObject | None:
        key = f"{self.key}.torque_command"
        if not self.has(OD_TARGET_TORQUE):
            self.finding("error", OD_TARGET_TORQUE, 0, "missing: the drive has no target torque, so no cyclic "
                         "synchronous torque (CST) and no torque drag",
                         "use a drive with CST (dragd drags in torque mode only)",
                         refusal="no target torque 6071h: the drive cannot be commanded in torque (CST)")
        choice = self.drive.torque_command
        if choice is None:  # 60B2h (added to 6071h in CST, torque feed-forward in CSP) where it maps, else 6071h
            v = self.var(OD_TORQUE_OFFSET)
            choice = "60B2h" if v is not None and v.pdo_mappable and v.writable else "6071h"
        index = OD_TORQUE_OFFSET if choice == "60B2h" else OD_TARGET_TORQUE
        if index == OD_TARGET_TORQUE and not self.has(OD_TARGET_TORQUE):
            return None
        obj = self._process("torque", index, 0, "rpdo", "the torque command", key=key)
        if obj is not None and obj.code != "h":
            self.finding("error", index, 0, "the torque command is "
                                            f"{type_name(getattr(self.var(index), 'data_type', None))}; "
                         "CiA 402 defines it INTEGER16 (per mille of the rated torque)", f"set {key}")
            return None
        return obj

    def _rated(self, which: Literal["rated_current", "rated_torque"]) -> tuple[int, int] | None:
        cfg = self.drive.rated_current if which == "rated_current" else self.drive.rated_torque
        key = f"{self.key}.{which}.object"
        if cfg.object is None:
            return None
        try:
            index, sub = parse_address(cfg.object)
        except ValueError as exc:
            self.finding("error", None, 0, str(exc), f"set {key}")
            return None
        var = self.var(index, sub)
        standard = OD_MOTOR_RATED_CURRENT if which == "rated_current" else OD_MOTOR_RATED_TORQUE
        what = "the motor's rated current" if which == "rated_current" else "the motor's rated torque"
        if var is None:
            fallback = ("the joint's rated_current_A is used unverified" if which == "rated_current"
                        else "the joint's rated_torque_Nm (or K_m × rated current) is used unverified")
            self.finding("error", index, sub, f"missing: {what} cannot be read",
                         f"set {key} to the drive's object, or null ({fallback})"
                         + (" — the drive has 6075h" if which == 'rated_current' and index != standard
                            and self.has(standard) else ""))
            return None
        if not var.readable or var.data_type not in datatypes.NUMBER_TYPES:
            self.finding("error", index, sub, f"{what}: AccessType={var.access_type}, "
                         f"{type_name(var.data_type)}: not a readable number", f"set {key}")
            return None
        if which == "rated_torque" and self.drive.rated_torque.write and not var.writable:
            self.finding("error", index, sub, f"{self.key}.rated_torque.write is true but the object is "
                         f"AccessType={var.access_type}", f"set {self.key}.rated_torque.write: false")
        return index, sub

    def _inputs(self) -> ProcessObject | None:
        """The digital inputs object where ``hand.inputs`` name this joint's drive (None otherwise): present, TPDO-
        mappable, an unsigned integer wide enough for every bit wired to it; 60FDh's bits 4-15 are reserved."""
        wired = [(k, inp) for k, inp in enumerate(self.cfg.hand.inputs) if inp.joint == self.joint.name]
        self.input_bits = sorted({b for _, inp in wired for b in inp.bits})
        self.input_functions = sorted({inp.function for _, inp in wired})
        if not wired:
            return None
        key = f"{self.key}.digital_inputs"
        names = "; ".join(f"hand.inputs[{k}] ({inp.label}) bit{'s' if len(inp.bits) > 1 else ''} "
                          f"{', '.join(map(str, inp.bits))}" for k, inp in wired)
        try:
            index, sub = parse_address(self.drive.digital_inputs)
        except ValueError as exc:
            self.finding("error", None, 0, str(exc), f"set {key}")
            return None
        obj = self._process("inputs", index, sub, "tpdo", f"the digital inputs ({names})", key=key)
        if obj is None:
            return None
        var = self.var(index, sub)
        if var is None or var.data_type not in (datatypes.UNSIGNED8, datatypes.UNSIGNED16, datatypes.UNSIGNED32,
                                                 datatypes.INTEGER8, datatypes.INTEGER16, datatypes.INTEGER32):
            self.finding("error", index, sub, f"{names}: the inputs object is "
                         f"{type_name(getattr(var, 'data_type', None))}; expected an integer of 8, 16 or 32 bits",
                         f"set {key}")
            return None
        for k, inp in wired:
            for b in inp.bits:
                if b >= obj.bits:
                    self.finding("error", index, sub, f"hand.inputs[{k}] ({inp.label}) bit {b}: the object has "
                                 f"{obj.bits} bits (0..{obj.bits - 1})", f"set hand.inputs[{k}] to the bit the "
                                 "contact is wired to")
                elif index == OD_DIGITAL_INPUTS and sub == 0 and 4 <= b <= 15:
                    self.finding("error", index, sub, f"hand.inputs[{k}] ({inp.label}) bit {b}: CiA 402 reserves "
                                 "bits 4-15 of 60FDh (0-3: limit switches, home, interlock; 16-31: the "
                                 "manufacturer's digital inputs)", f"set hand.inputs[{k}] to the manufacturer bit "
                                 "(16 + the drive's input number, per its manual)")
        return obj

    def _watchdog(self) -> tuple[int, int] | None:
        w = self.drive.rpdo_watchdog
        if w is None:
            return None
        key = f"{self.key}.rpdo_watchdog.object"
        try:
            index, sub = parse_address(w.object)
        except ValueError as exc:
            self.finding("error", None, 0, str(exc), f"set {key}")
            return None
        var = self.var(index, sub)
        if var is None or not var.writable or var.data_type not in datatypes.INTEGER_TYPES:
            what = "missing" if var is None else f"AccessType={var.access_type}, " \
                f"{type_name(var.data_type)}: not a writable integer"
            self.finding("error", index, sub, f"the vendor watchdog object: {what}", f"set {key}")
            return None
        return index, sub

    # -------------------------------------------------------------------------------------------- checks

    def _check_modes(self) -> None:
        if self.device_type is not None and self.device_type & 0xFFFF != DEVICE_TYPE_402:
            self.finding("error", OD_DEVICE_TYPE, 0, f"device type 0x{self.device_type:08X}: not a CiA 402 drive "
                         "(expected 0x....0192)", f"set joints[{self.joint_index}].drive to a CiA 402 drive's EDS")
        modes = self.supported_modes
        if not self.has(OD_SUPPORTED_DRIVE_MODES):
            self.finding("warning", OD_SUPPORTED_DRIVE_MODES, 0, "missing: the boot confirms CST by 6060h = 10 "
                         "shown on 6061h")
        elif modes is None:
            self.finding("note", OD_SUPPORTED_DRIVE_MODES, 0, "no default value in the EDS: CST (and CSP) checked at "
                         "boot")
        elif not modes & (1 << (MODE_CST - 1)):
            self.finding("error", OD_SUPPORTED_DRIVE_MODES, 0, f"supported modes 0x{modes:08X} lack cyclic "
                         "synchronous torque (CST, bit 9): the drive cannot do torque drag",
                         "use a drive with CST (dragd drags in torque mode only)",
                         refusal=f"no CST: 6502h supported modes 0x{modes:08X} lack cyclic synchronous torque")

    def target_position_mappable(self) -> bool:
        v = self.var(OD_TARGET_POSITION)
        return v is not None and v.pdo_mappable and v.writable

    @property
    def csp(self) -> bool | None:
        """CSP (identify run, replay, track): 607Ah mappable and (where the EDS says) CSP among the modes."""
        if self.target_position is None:
            return False
        if self.supported_modes is None:
            return None
        return bool(self.supported_modes & (1 << (MODE_CSP - 1)))

    def csp_reason(self) -> str | None:
        """Why CSP motions are impossible with this drive (None: possible, or decided at boot)."""
        var = self.var(OD_TARGET_POSITION)
        if var is None:
            return f"{self.describe(OD_TARGET_POSITION)}: missing"
        if self.target_position is None:
            return f"{self.describe(OD_TARGET_POSITION)}: not RPDO-mappable (PDOMapping={int(var.pdo_mappable)}, " \
                   f"AccessType={var.access_type})"
        if self.supported_modes is not None and not self.supported_modes & (1 << (MODE_CSP - 1)):
            return f"6502h supported modes 0x{self.supported_modes:08X} lack CSP"
        return None

    @property
    def motion_mode(self) -> Literal["csp", "cst"]:
        """How the drive follows motions (identify run, replay, track): ``csp``, its own position loop with dragd's
        feed-forward in 60B2h, or ``cst``, dragd's position loop with the feed-forward in the torque command (no mode
        switch). The configured choice; by default csp where the command is 60B2h and the drive can do CSP."""
        if self.drive.motion_mode is not None:
            return self.drive.motion_mode
        offset = self.command is not None and self.command.index == OD_TORQUE_OFFSET
        return "csp" if offset and self.csp is not False else "cst"

    def _check_motion(self) -> None:
        key = f"{self.key}.motion_mode"
        if self.command is None or self.refusals:
            return
        no_offset = self.command.index != OD_TORQUE_OFFSET
        if self.motion_mode == "cst":
            why = ("the torque command is 6071h, which CiA 402 CSP ignores (no torque feed-forward in CSP)" if no_offset
                   else f"the drive cannot follow position targets: {self.csp_reason()}" if self.csp is False
                   else f"{key} is cst")
            self.finding("note", None, 0, f"motions (identify run, replay, track) run in CST: {why}; dragd's position "
                         "loop (replay.cst_*) with the model's feed-forward")
        elif self.csp is False:
            self.finding("error", OD_TARGET_POSITION, 0, f"{key} csp: the drive cannot follow position targets "
                         f"({self.csp_reason()})", f"set {key} to cst or null")
        elif no_offset:
            self.finding("warning", OD_TORQUE_OFFSET, 0, f"missing or not RPDO-mappable, and {key} csp: the torque "
                         "command is 6071h, which CiA 402 CSP ignores; in motions no feed-forward reaches the drive: "
                         "at every switch to CSP the arm sags until the drive's own loop holds its weight",
                         f"set {key} to cst (or null)")

    def _check_required(self) -> None:
        for index, what, need in ((OD_MODES_OF_OPERATION, "modes of operation", "writable"),
                                  (OD_MODES_OF_OPERATION_DISPLAY, "modes of operation display", "readable"),
                                  (OD_PRODUCER_HEARTBEAT, "heartbeat producer time (dragd watches the drives' "
                                                       "heartbeats)", "writable"),
                                  (OD_DEVICE_TYPE, "device type", "readable")):
            var = self.var(index)
            if var is None:
                self.finding("error", index, 0, f"missing: {what}", "CiA 301/402 make it mandatory; the drive cannot "
                             "be used")
            elif not getattr(var, need):
                self.finding("error", index, 0, f"{what}: AccessType={var.access_type}, not {need}")
        if not self.has(OD_IDENTITY, 1):
            self.finding("error", OD_IDENTITY, 1, "missing: the vendor id (CiA 301 mandatory)")
        if not self.tpdos:
            self.finding("error", OD_TPDO_COMM, 0, "the EDS defines no TPDO (1800h + 1A00h)")
        if not self.rpdos:
            self.finding("error", OD_RPDO_COMM, 0, "the EDS defines no RPDO (1400h + 1600h)")

    def _check_optional(self) -> None:
        """Optional objects: each missing one with its fallback (and a status line at boot)."""
        if not self.has(OD_ABORT_CONNECTION_OPTION):
            self.finding("warning", OD_ABORT_CONNECTION_OPTION, 0, "missing: safety.abort_connection_option is not "
                         "written; the drive reacts to a lost master or command frame in its own way (check its "
                         "manual)")
        if not self.has(OD_QUICK_STOP_OPTION):
            self.finding("warning", OD_QUICK_STOP_OPTION, 0, "missing: safety.quick_stop_option is not written; "
                         "the drive's own quick stop reaction applies")
        if not self.has(OD_MAX_TORQUE):
            self.finding("warning", OD_MAX_TORQUE, 0, "missing: the drive does not limit the torque to the joint's "
                         "current_limit_A; dragd's command clamp is the only limit")
        else:
            var = self.var(OD_MAX_TORQUE)
            want = 1000.0 * self.joint.current_limit_A / self.joint.rated_current_A
            if var is not None and isinstance(var.max, int) and 0 < var.max < want:
                self.finding("warning", OD_MAX_TORQUE, 0, f"its range ends at {var.max} per mille (HighLimit), below "
                             f"the joint's current_limit_A / rated_current_A = {want:.0f} per mille: the drive "
                             f"limits the current to {var.max / 1000 * self.joint.rated_current_A:.3g} A",
                             f"check joints[{self.joint_index}].rated_current_A (the drive's rated current)")
        has_consumer = self.has(OD_CONSUMER_HEARTBEAT, 1)
        deadline = any(5 in ch.comm_subs for ch in self.rpdos)
        if not has_consumer:
            self.finding("warning", OD_CONSUMER_HEARTBEAT, 1,
                         "missing: the drive does not watch the master's heartbeat")
        if not deadline and self.watchdog_object is None:
            if has_consumer:
                self.finding("warning", OD_RPDO_COMM, 5, "missing on every RPDO: no RPDO deadline; the drive stops on "
                             "a lost master heartbeat only (1016h, master.heartbeat_consumer_ms)",
                             f"name the vendor's command watchdog in {self.key}.rpdo_watchdog if the drive has one")
            else:
                self.finding("error", OD_RPDO_COMM, 5, "missing on every RPDO, and no 1016h heartbeat consumer: "
                             "nothing stops this drive when dragd stops sending",
                             f"name the vendor's command watchdog in {self.key}.rpdo_watchdog")

    # -------------------------------------------------------------------------------------------- units

    @property
    def uses_rated_torque(self) -> bool:
        """The conversions go through the rated torque and K_m (``rated_torque_Nm`` set)."""
        return self.joint.rated_torque_Nm is not None

    def A_per_current_unit(self) -> float:
        """Amperes per unit of the current object (before the joint's direction)."""
        j, unit = self.joint, self.current_unit
        if unit == "permille_rated_current":
            return j.rated_current_A / 1000.0
        if unit == "permille_rated_torque":
            return self.A_per_torque_permille()
        return CURRENT_UNITS_A[unit]

    def A_per_torque_permille(self) -> float:
        """Amperes per mille of the rated torque: T_rated / (1000 K_m); I_rated / 1000 when T_rated = K_m I_rated."""
        j = self.joint
        if j.rated_torque_Nm is None:
            return j.rated_current_A / 1000.0
        return j.rated_torque_Nm / (1000.0 * j.km_Nm_per_A)

    def command_per_A(self) -> float:
        """Torque command units (per mille of the rated torque) per ampere (before the joint's direction)."""
        j = self.joint
        if j.rated_torque_Nm is None:
            return 1000.0 / j.rated_current_A
        return 1000.0 * j.km_Nm_per_A / j.rated_torque_Nm

    def rated_current_raw(self) -> int:
        """The joint's rated current in the rated-current object's unit (what the drive should report)."""
        scale = 1e-3 if self.drive.rated_current.unit == "mA" else 1.0
        return round(self.joint.rated_current_A / scale)

    def rated_torque_raw(self) -> int:
        """The joint's rated torque (motor side) in the rated-torque object's unit."""
        return round(self.joint.rated_torque_motor_Nm / TORQUE_UNITS_NM[self.drive.rated_torque.unit])

    def summary(self) -> str:
        """One line: the drive and what its process data use."""
        cur = f"{address(self.current.index, self.current.sub)} ({CURRENT_UNITS.get(self.current_unit, '?')})" \
            if self.current is not None else "none"
        cmd = address(self.command.index) if self.command is not None else "none"
        return (f"{self.where}: {self.eds_path} ({'CAN FD' if self.fd else 'classic CAN'}, "
                f"{len(self.tpdos)} TPDO, {len(self.rpdos)} RPDO, dummies {'yes' if self.dummies else 'no'}): "
                f"current {cur}, command {cmd}")


@dataclass
class Profiles:
    """Every joint's drive profile, and what loading them found."""

    profiles: list[DriveProfile]
    findings: list[Finding] = field(default_factory=list)

    def __getitem__(self, joint: int) -> DriveProfile:
        return self.profiles[joint]

    def __len__(self) -> int:
        return len(self.profiles)

    def __iter__(self) -> Iterator[DriveProfile]:
        return iter(self.profiles)

    def all_findings(self) -> list[Finding]:
        out = list(self.findings)
        for p in self.profiles:
            out += p.findings()
        return out


def load_profiles(cfg: Config) -> Profiles:
    """Every joint's profile; an EDS that cannot be read raises ProfileError naming the file and the joints."""
    profiles: list[DriveProfile] = []
    broken: dict[tuple[str, str], list[str]] = {}
    for j in range(len(cfg.joints)):
        try:
            profiles.append(DriveProfile(cfg, j))
        except ProfileError as exc:
            name = cfg.joints[j].drive
            key = f"set drives.{name}.eds" if name else "the bundled EDS (reinstall dragd)"
            broken.setdefault((str(exc), key), []).append(f"joints[{j}] {cfg.joints[j].name}")
    if broken:
        raise ProfileError("\n".join(f"{cfg.source}: {text} (the drive of {', '.join(js)}; {key})"
                                     for (text, key), js in broken.items()))
    return Profiles(profiles)
