"""What one simulated joint drive is beyond CiA 402's defaults: its EDS, where its firmware keeps each process quantity,
the values it was commissioned with, and what the simulator assumes where the EDS says nothing.

A profile is part of the sim's truth — the joint's ``drive`` entry in the truth file, and for vendors' drives an entry
of ``sim/config/drives/`` written from the vendor's manual — never dragd's configuration: the simulated drive must not
share dragd's assumptions. ``build_profile`` loads the EDS (python-canopen ``import_od``) and checks everything at once;
a ``ProfileError`` lists every problem with the file and key to change. docs/SIM_DRIVES.md describes the assumptions.

Object addresses are written ``30D1h:2`` (index hex, sub-index decimal; ``0x30D1:0x02`` and ``30D1h:02h`` also work).
"""

from __future__ import annotations

import configparser
import functools
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import canopen
from canopen.objectdictionary import ODArray, ODRecord, ODVariable, datatypes

from dragd.hardware.cia301 import (
    OD_DEVICE_TYPE,
    OD_ERROR_BEHAVIOUR,
    OD_IDENTITY,
    OD_PRODUCER_HEARTBEAT,
    OD_RPDO_COMM,
    OD_RPDO_MAP,
    OD_TPDO_COMM,
    OD_TPDO_MAP,
)
from dragd.hardware.cia402 import (
    DEVICE_TYPE_402,
    DEVICE_TYPE_SERVO,
    OD_ABORT_CONNECTION_OPTION,
    OD_CONTROLWORD,
    OD_CURRENT_ACTUAL,
    OD_DIGITAL_INPUTS,
    OD_DISABLE_OPERATION_OPTION,
    OD_FAULT_REACTION_OPTION,
    OD_MAX_CURRENT,
    OD_MAX_TORQUE,
    OD_MODES_OF_OPERATION,
    OD_MOTOR_RATED_CURRENT,
    OD_MOTOR_RATED_TORQUE,
    OD_POSITION_ACTUAL,
    OD_PROFILE_DECELERATION,
    OD_QUICK_STOP_DECELERATION,
    OD_QUICK_STOP_OPTION,
    OD_SHUTDOWN_OPTION,
    OD_STATUSWORD,
    OD_SUPPORTED_DRIVE_MODES,
    OD_TARGET_POSITION,
    OD_TARGET_TORQUE,
    OD_TARGET_VELOCITY,
    OD_TORQUE_ACTUAL,
    OD_TORQUE_DEMAND,
    OD_TORQUE_OFFSET,
    OD_TORQUE_SLOPE,
    AbortConnectionOption,
    FaultReactionOption,
    Mode,
    QuickStopOption,
    ShutdownOption,
    supported_modes_bits,
)
from dragd.hardware.eds import import_od as cached_import_od
from dragd.resources import eds_path as bundled_eds_path
from dragd.vocabulary import ConfigError, read_yaml

DRIVES_DIR = Path(__file__).resolve().parent / "config" / "drives"
DEVICE_TYPE_402_SERVO = DEVICE_TYPE_SERVO | DEVICE_TYPE_402  # 00020192h: CiA 402, additional information: servo
# a drive without a torque offset to feed forward (no RPDO-mappable 60B2h) holds the arm with an integrating position
# loop (cascaded PI velocity loop): its CSP integral gain per proportional gain where the truth names none (1/s: the
# integral catches up with a constant load in about 0.1 s)
VENDOR_CSP_KI_PER_KP = 10.0
# option codes a drive acts on when its EDS lacks the object: value, and what the drive then does
ASSUMED_OPTIONS: dict[int, tuple[int, str]] = {
    OD_ABORT_CONNECTION_OPTION: (int(AbortConnectionOption.FAULT),
                                 "a loss of communication (heartbeat, RPDO deadline, NMT stop) faults the drive"),
    OD_QUICK_STOP_OPTION: (int(QuickStopOption.QUICK_STOP_RAMP),
                           "quick stop on the quick stop ramp, then switch on disabled"),
    OD_SHUTDOWN_OPTION: (int(ShutdownOption.DISABLE_DRIVE), "shutdown disables the drive at once"),
    OD_DISABLE_OPERATION_OPTION: (int(ShutdownOption.SLOW_DOWN_THEN_DISABLE), "disable operation slows down first"),
    OD_FAULT_REACTION_OPTION: (int(FaultReactionOption.QUICK_STOP_RAMP), "the fault reaction is the quick stop ramp"),
}

_INTEGER_TYPES = frozenset({datatypes.INTEGER8, datatypes.INTEGER16, datatypes.INTEGER32, datatypes.INTEGER64,
                            datatypes.UNSIGNED8, datatypes.UNSIGNED16, datatypes.UNSIGNED32, datatypes.UNSIGNED64})
_ADDRESS = re.compile(r"^\s*(?:0x)?([0-9A-Fa-f]{4})h?\s*(?::\s*(0x[0-9A-Fa-f]{1,2}|[0-9A-Fa-f]{1,2}h|\d{1,3}))?\s*$")

# unit -> how many of it make the kind's SI unit (A, N·m, N·m/A); None: per mille of the rated value (6075h / 6076h)
UNITS: dict[str, dict[str, float | None]] = {
    "current": {"permille": None, "mA": 1000.0, "cA": 100.0, "A": 1.0},
    "torque": {"permille": None, "mNm": 1000.0, "uNm": 1e6, "Nm": 1.0},
    "torque_constant": {"mNm_per_A": 1000.0, "uNm_per_A": 1e6, "Nm_per_A": 1.0},
    "time": {"ms": 1000.0, "s": 1.0},
    "bits": {"bits": None},
}


@dataclass(frozen=True)
class Quantity:
    """A process quantity of the drive's firmware, its CiA 402 object and unit (``index`` None: no standard object)."""

    name: str
    index: int | None
    kind: str  # a key of UNITS
    unit: str
    role: str  # "actual" (the drive writes it, a master reads it), "command" (a master writes it), "parameter"
    meaning: str


QUANTITIES: dict[str, Quantity] = {q.name: q for q in (
    Quantity("current_actual", OD_CURRENT_ACTUAL, "current", "permille", "actual", "motor current measured"),
    Quantity("torque_actual", OD_TORQUE_ACTUAL, "torque", "permille", "actual",
             "motor torque (current x torque constant)"),
    Quantity("torque_demand", OD_TORQUE_DEMAND, "torque", "permille", "actual",
             "torque the current loop is asked for"),
    Quantity("target_torque", OD_TARGET_TORQUE, "torque", "permille", "command", "CST / profile torque command"),
    Quantity("torque_offset", OD_TORQUE_OFFSET, "torque", "permille", "command",
             "torque added to the mode's command"),
    Quantity("max_torque", OD_MAX_TORQUE, "torque", "permille", "parameter", "torque limit"),
    Quantity("max_current", OD_MAX_CURRENT, "current", "permille", "parameter", "current limit"),
    Quantity("rated_current", OD_MOTOR_RATED_CURRENT, "current", "mA", "parameter",
             "base of the current per-mille values"),
    Quantity("rated_torque", OD_MOTOR_RATED_TORQUE, "torque", "mNm", "parameter",
             "base of the torque per-mille values"),
    Quantity("torque_constant", None, "torque_constant", "mNm_per_A", "parameter",
             "the firmware's motor torque constant (torque command -> current)"),
    Quantity("rpdo_watchdog", None, "time", "ms", "parameter",
             "a vendor's reception watchdog: no RPDO for this long (0: off) is an RPDO timeout (EMCY 8250h, 6007h)"),
    Quantity("digital_inputs", OD_DIGITAL_INPUTS, "bits", "bits", "actual",
             "the digital inputs (60FDh: 0-3 limit switches, home, interlock; 16-31 the manufacturer's)"),
)}


class ProfileError(ConfigError):
    """A drive profile that cannot be simulated; the message lists every problem with its file and key."""


def parse_address(text: Any) -> tuple[int, int]:
    """(index, sub-index) of ``30D1h:2`` / ``0x30D1:0x02`` / ``6502h`` (sub-index 0); ValueError otherwise."""
    if isinstance(text, int) and not isinstance(text, bool) and 0 <= text <= 0xFFFF:
        return text, 0
    m = _ADDRESS.match(str(text)) if isinstance(text, str) else None
    if m is None:
        raise ValueError(f"expected an object address like 30D1h:2 (index hex, sub-index decimal), got {text!r}")
    sub_text = m.group(2)
    if sub_text is None:
        sub = 0
    elif sub_text.lower().startswith("0x"):
        sub = int(sub_text, 16)
    elif sub_text.lower().endswith("h"):
        sub = int(sub_text[:-1], 16)
    else:
        sub = int(sub_text)
    if sub > 0xFF:
        raise ValueError(f"expected a sub-index 0..255, got {text!r}")
    return int(m.group(1), 16), sub


def format_address(index: int, subindex: int) -> str:
    return f"{index:04X}h" if subindex == 0 else f"{index:04X}h:{subindex}"


@dataclass(frozen=True)
class Binding:
    """Where the firmware keeps one quantity: an object of the dictionary, or an internal value (``index`` None)."""

    quantity: str
    index: int | None
    subindex: int
    unit: str
    source: str  # "CiA 402", the catalog entry or the truth key that named it, or "internal"

    @property
    def per_si(self) -> float | None:
        """Units per SI unit (A, N·m, N·m/A); None for per mille of the rated value."""
        return UNITS[QUANTITIES[self.quantity].kind][self.unit]

    def label(self) -> str:
        where = "internal" if self.index is None else format_address(self.index, self.subindex)
        return f"{self.quantity} {where} [{self.unit}]"


@dataclass(frozen=True)
class ProfileSpec:
    """A joint drive as the sim's truth describes it (the input of ``build_profile``)."""

    eds: str | None = None  # None: the bundled canopen_eds/joint_drive.eds
    profile: str | None = None  # a catalog entry (sim/config/drives/NAME.yaml); None: matched by the EDS's identity
    objects: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)  # quantity -> {object, unit}
    values: Mapping[str, int] = field(default_factory=dict)  # "6502h" -> commissioned value
    can_fd: bool | None = None  # None: the catalog's, else True for the bundled EDS, False for any other
    where: str = "drive"  # how errors name this entry (the truth file and key)
    assumed_csp_ki: float | None = None  # the CSP integral gain the drive model assumes (the truth names none)


@dataclass(frozen=True)
class CatalogEntry:
    """A vendor's drive as its manual describes it (sim/config/drives/NAME.yaml)."""

    name: str
    path: Path
    match: Mapping[str, Any]
    objects: Mapping[str, Mapping[str, Any]]
    values: Mapping[str, int]
    can_fd: bool | None
    notes: str

    @property
    def label(self) -> str:
        return f"sim/config/drives/{self.path.name}" if self.path.parent == DRIVES_DIR else str(self.path)


@dataclass
class DriveProfile:
    """Everything the simulated drive needs to answer as one drive model does."""

    eds_path: Path
    node_id: int
    od: canopen.ObjectDictionary
    catalog: CatalogEntry | None
    bindings: dict[str, Binding]
    commissioned: dict[tuple[int, int], int]  # values that replace the EDS defaults (the drive as delivered)
    truth_raw: dict[str, int]  # what the truth's rated current / torque / torque constant read in their objects
    hardware: Hardware  # the truth's hardware as this drive holds it (rated values fitted to its limits)
    supported_modes: int  # 6502h as the drive reports it (also when the EDS gives none: see assumptions)
    can_fd: bool
    assumptions: list[str]
    identity: tuple[int, int, int]  # 1018h sub 1..3 as delivered (vendor, product, revision)

    @property
    def bundled(self) -> bool:
        return self.eds_path.resolve() == bundled_eds_path().resolve()

    def summary(self) -> dict[str, Any]:
        """The profile as JSON-able data (``python -m sim drives --json``)."""
        info = self.od.device_information
        return {
            "node_id": self.node_id, "eds": str(self.eds_path), "vendor": info.vendor_name,
            "product": info.product_name,
            "profile": self.catalog.name if self.catalog else None, "can_fd": self.can_fd,
            "supported_modes": self.supported_modes,
            "rated_current_A": self.hardware.rated_current_A, "rated_torque_Nm": self.hardware.rated_torque_Nm,
            "objects": {b.quantity: {"object": None if b.index is None else format_address(b.index, b.subindex),
                                     "unit": b.unit, "source": b.source} for b in self.bindings.values()},
            "commissioned": {format_address(i, s): v for (i, s), v in sorted(self.commissioned.items())},
            "assumptions": list(self.assumptions),
        }

    def describe(self) -> str:
        """One paragraph for ``python -m sim`` and the status report: EDS, catalog entry, bindings, assumptions."""
        lines = [f"node {self.node_id}: {self.eds_path} ({self.od.device_information.vendor_name or '?'} "
                 f"{self.od.device_information.product_name or '?'})"
                 + (f", profile {self.catalog.name}" if self.catalog else "")
                 + f", {'CAN FD' if self.can_fd else 'classic CAN'}, 6502h 0x{self.supported_modes:08X}"]
        lines += [f"  {b.label()} ({b.source})" for b in self.bindings.values()]
        lines += [f"  assumption: {a}" for a in self.assumptions]
        return "\n".join(lines)


# ======================================================================================================= catalog
@functools.cache
def load_catalog(directory: Path = DRIVES_DIR) -> tuple[CatalogEntry, ...]:
    """Every vendor drive entry of ``directory`` (sorted by name); ProfileError lists every broken file."""
    entries, problems = [], []
    for path in sorted(directory.glob("*.yaml")):
        try:
            data = read_yaml(path)
        except ConfigError as exc:
            problems.append(str(exc))
            continue
        if not isinstance(data, dict):
            problems.append(f"{path}: expected a mapping with match, objects, values")
            continue
        unknown = set(data) - {"match", "objects", "values", "can_fd", "notes"}
        if unknown:
            problems.append(f"{path}: unknown keys {sorted(unknown)}; expected match, objects, values, can_fd, notes")
        match = data.get("match") or {}
        if not isinstance(match, dict) or not match or set(match) - {"vendor_number", "product_number", "product_name"}:
            problems.append(f"{path}: match: expected a mapping of vendor_number, product_number, product_name "
                            f"(the EDS's [DeviceInfo]), got {match!r}")
        entries.append(CatalogEntry(name=path.stem, path=path, match=match if isinstance(match, dict) else {},
                                    objects=data.get("objects") or {}, values=data.get("values") or {},
                                    can_fd=None if data.get("can_fd") is None else bool(data["can_fd"]),
                                    notes=str(data.get("notes", ""))))
    if problems:
        raise ProfileError("\n".join(problems))
    return tuple(entries)


def _matches(entry: CatalogEntry, od: canopen.ObjectDictionary) -> bool:
    info = od.device_information
    have = {"vendor_number": info.vendor_number or 0, "product_number": info.product_number or 0,
            "product_name": info.product_name or ""}
    return all(have[key] == want for key, want in entry.match.items())


# ======================================================================================================= EDS
def import_eds(path: str | Path, node_id: int) -> canopen.ObjectDictionary:
    """The dictionary of an EDS for a node ($NODEID resolved): python-canopen's ``import_od``, the file parsed once
    per version (dragd/hardware/eds.py, proven equal to canopen's per-node import by tests/test_eds_cache.py)."""
    try:
        return cached_import_od(path, node_id)
    except FileNotFoundError:
        raise ProfileError(f"{path}: EDS file not found") from None
    except Exception as exc:  # (python-canopen raises what configparser and int() raise on a broken file)
        raise ProfileError(f"{path}: not a readable EDS ({type(exc).__name__}: {exc})") from None


@functools.lru_cache(maxsize=64)
def _device_info_fd(path: str, mtime_ns: int) -> bool | None:
    parser = configparser.ConfigParser(strict=False, interpolation=None)
    parser.optionxform = str  # type: ignore[assignment,method-assign]
    try:
        parser.read(path, encoding="latin-1")
        value = parser.get("DeviceInfo", "CANopenFD", fallback=None)
    except configparser.Error:
        return None
    return None if value is None else value.strip() not in ("0", "")


def eds_declares_fd(path: str | Path) -> bool | None:
    """``[DeviceInfo] CANopenFD`` (dragd's marker; EDS 4.0 has no standard key): True/False, None if absent."""
    p = Path(path)
    return _device_info_fd(str(p.resolve()), p.stat().st_mtime_ns) if p.is_file() else None


def takes_torque_offset(eds: str | Path, node_id: int) -> bool:
    """Whether the EDS's drive takes a torque offset a master can feed forward each cycle (60B2h writable and
    RPDO-mappable); False for a file that cannot be read (build_profile reports why)."""
    try:
        var = _variable(import_eds(eds, node_id), OD_TORQUE_OFFSET, 0)
    except ProfileError:
        return False
    return var is not None and var.writable and var.pdo_mappable


def _variable(od: canopen.ObjectDictionary, index: int, subindex: int) -> ODVariable | None:
    obj = od.indices.get(index)  # (``od.get`` builds a KeyError text for every absent index)
    if obj is None:
        return None
    if isinstance(obj, (ODRecord, ODArray)):
        return obj.subindices.get(subindex) if subindex in obj.subindices else None
    return obj if subindex == 0 else None


# ======================================================================================================= build
@dataclass(frozen=True)
class Hardware:
    """The truth's hardware facts the profile commissions into the dictionary (SI units, joint/motor as named)."""

    node_id: int
    rated_current_A: float
    rated_torque_Nm: float
    max_current_A: float
    max_torque_permille: int
    counts_per_rev: int
    quickstop_decel_rad_s2: float
    slowdown_decel_rad_s2: float
    identity: tuple[int, int, int] | None = None  # 1018h 1..3; None: the EDS's [DeviceInfo]

    @property
    def torque_constant_Nm_per_A(self) -> float:
        return self.rated_torque_Nm / self.rated_current_A


def build_profile(spec: ProfileSpec, hw: Hardware, base_dir: Path | None = None) -> DriveProfile:
    """Load the EDS, resolve the catalog entry and bindings, commission the truth's values; every problem at once."""
    problems: list[str] = []
    where = spec.where
    eds = bundled_eds_path() if spec.eds is None else Path(spec.eds)
    if not eds.is_absolute() and base_dir is not None:
        eds = base_dir / eds
    try:
        od = import_eds(eds, hw.node_id)
    except ProfileError as exc:
        raise ProfileError(f"{where}.eds: {exc}") from None
    catalog = _catalog_entry(spec, od, problems)
    bundled = eds.resolve() == bundled_eds_path().resolve()
    declared = eds_declares_fd(eds)
    if spec.can_fd is not None:
        can_fd = spec.can_fd
    elif catalog is not None and catalog.can_fd is not None:
        can_fd = catalog.can_fd
    else:
        can_fd = declared if declared is not None else bundled

    def var_of(index: int, sub: int) -> ODVariable | None:
        return _variable(od, index, sub)

    # --- required objects
    for index, what, need in ((OD_CONTROLWORD, "controlword", "writable"), (OD_STATUSWORD, "statusword", "readable"),
                              (OD_POSITION_ACTUAL, "position actual value", "readable")):
        var = var_of(index, 0)
        if var is None:
            problems.append(f"{where}.eds: {eds}: the simulated CiA 402 drive needs {index:04X}h ({what}); the EDS "
                            f"has no such object")
        elif not (var.writable if need == "writable" else var.readable) or var.data_type not in _INTEGER_TYPES:
            problems.append(f"{where}.eds: {eds}: {index:04X}h ({what}) must be a {need} integer object, the EDS "
                            f"says {var.access_type} of type 0x{var.data_type:X}")

    # --- bindings: CiA 402 default, then the catalog's, then the truth's
    bindings: dict[str, Binding] = {}
    for q in QUANTITIES.values():
        if q.index is not None and var_of(q.index, 0) is not None:
            bindings[q.name] = Binding(q.name, q.index, 0, q.unit, "CiA 402")
        else:
            bindings[q.name] = Binding(q.name, None, 0, q.unit, "internal")
    for source, objects in ((f"{catalog.label}: objects" if catalog else "", catalog.objects if catalog else {}),
                            (f"{where}.objects", spec.objects)):
        if not isinstance(objects, Mapping):
            problems.append(f"{source}: expected a mapping of quantity -> {{object, unit}}, got {objects!r}")
            continue
        for name, entry in objects.items():
            b = _binding(name, entry, f"{source}.{name}", od, problems)
            if b is not None:
                bindings[name] = b

    # --- commissioned values: the truth's hardware, then the catalog's values, then the truth's values
    commissioned: dict[tuple[int, int], int] = {}
    truth_raw: dict[str, int] = {}
    assumptions: list[str] = []
    hw = _fit_hardware(hw, bindings, var_of, assumptions)
    _commission_hardware(bindings, hw, var_of, commissioned, truth_raw)
    for (index, sub), value in list(commissioned.items()):
        var = var_of(index, sub)
        if var is None:
            continue
        lo, hi = var.min, var.max
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            fitted = max(lo, value) if lo is not None else value
            fitted = min(hi, fitted) if hi is not None else fitted
            commissioned[(index, sub)] = fitted
            assumptions.append(f"{format_address(index, sub)} ({var.name}): the truth's value {value} is outside the "
                               f"EDS's limits [{lo}, {hi}] (its unit may not be the one the "
                               f"simulator assumes): {fitted}")
    for source, values in ((f"{catalog.label}: values" if catalog else "", catalog.values if catalog else {}),
                           (f"{where}.values", spec.values)):
        if not isinstance(values, Mapping):
            problems.append(f"{source}: expected a mapping of object -> value, got {values!r}")
            continue
        for key, value in values.items():
            try:
                index, sub = parse_address(key)
            except ValueError as exc:
                problems.append(f"{source}.{key}: {exc}")
                continue
            var = var_of(index, sub)
            if var is None:
                problems.append(f"{source}.{key}: the EDS ({eds}) has no object {format_address(index, sub)}")
            elif isinstance(value, bool) or not isinstance(value, int) or var.data_type not in _INTEGER_TYPES:
                problems.append(f"{source}.{key}: expected an integer for an integer object, got {value!r}")
            elif not _type_range(var)[0] <= value <= _type_range(var)[1]:
                lo, hi = _type_range(var)
                problems.append(f"{source}.{key}: {value} does not fit {format_address(index, sub)} ({var.name}), "
                                f"an integer of {lo}..{hi}")
            else:
                commissioned[(index, sub)] = value
    for (index, sub), value in commissioned.items():
        var = var_of(index, sub)
        if var is not None and ((var.min is not None and value < var.min) or (var.max is not None and value > var.max)):
            problems.append(f"{where}: {format_address(index, sub)} ({var.name}) would hold {value}, outside the EDS's "
                            f"limits [{var.min}, {var.max}]: the truth asks for a drive this model is not")

    # --- identity (1018h) and the assumptions where the EDS gives no value
    info = od.device_information
    identity = hw.identity if hw.identity is not None else (info.vendor_number or 0, info.product_number or 0,
                                                             info.revision_number or 0)
    for sub, value in zip((1, 2, 3), identity, strict=True):
        if var_of(OD_IDENTITY, sub) is not None:
            commissioned.setdefault((OD_IDENTITY, sub), value)
    if var_of(OD_IDENTITY, 4) is not None:
        commissioned.setdefault((OD_IDENTITY, 4), hw.node_id)
    device_type = var_of(OD_DEVICE_TYPE, 0)
    if device_type is not None and device_type.default is None and device_type.value is None \
            and (OD_DEVICE_TYPE, 0) not in commissioned:
        commissioned[(OD_DEVICE_TYPE, 0)] = DEVICE_TYPE_402_SERVO
        assumptions.append("1000h (device type) has no value in the EDS: "
                           f"0x{DEVICE_TYPE_402_SERVO:08X} (CiA 402, servo "
                           f"drive)")
    modes = _supported_modes(var_of, commissioned, assumptions)
    for index, sub in ((OD_PRODUCER_HEARTBEAT, 0), (OD_ERROR_BEHAVIOUR, 1)):
        var = var_of(index, sub)
        if var is not None and var.default is None and var.value is None and (index, sub) not in commissioned:
            assumptions.append(f"{format_address(index, sub)} ({var.name}) has no default in the EDS: 0")
    for index, (value, what) in ASSUMED_OPTIONS.items():
        if var_of(index, 0) is None:
            assumptions.append(f"no {index:04X}h: {what} ({index:04X}h = {value}, CiA 402's default)")
    for quantity in ("rated_current", "rated_torque"):
        if bindings[quantity].index is None:
            assumptions.append(f"no object holds the {quantity.replace('_', ' ')} ({QUANTITIES[quantity].index:04X}h "
                               f"absent, no vendor object named): the truth's value, not reachable over SDO")
    if bindings["max_current"].index is None:
        assumptions.append("no object holds the current limit: the truth's max_current_A")
    if bindings["max_torque"].index is None:
        assumptions.append("no 6072h (max torque): the current limit alone bounds the torque")
    if spec.assumed_csp_ki is not None:
        assumptions.append("no torque offset to feed forward (60B2h): the position loop (CSP) "
                           "holds the arm itself and "
                           f"integrates, as a servo drive's cascaded loops do: {spec.assumed_csp_ki:g} A/(rad·s), "
                           f"{VENDOR_CSP_KI_PER_KP:g}/s x kp (the truth names no csp_ki_A_per_rad_s)")
    if var_of(OD_TORQUE_SLOPE, 0) is None:
        assumptions.append("no 6087h (torque slope): profile torque steps without a ramp")
    problems += _default_mapping_problems(od, eds, can_fd, where)
    if problems:
        raise ProfileError("\n".join(problems))
    return DriveProfile(eds_path=eds, node_id=hw.node_id, od=od, catalog=catalog, bindings=bindings,
                        commissioned=commissioned, truth_raw=truth_raw, hardware=hw, supported_modes=modes,
                        can_fd=can_fd, assumptions=assumptions,
                        identity=identity)


def _default_mapping_problems(od: canopen.ObjectDictionary, eds: Path, can_fd: bool, where: str) -> list[str]:
    """The EDS's default mappings of its valid PDOs that the drive could not hold (an absent or unmappable object,
    a frame too long): such a drive would not boot."""
    from sim.od import ObjectStore, SdoAbort
    from sim.pdo import CLASSIC_MAX_BYTES, COB_INVALID, FD_MAX_BYTES, find_channels, validate_mapping

    store = ObjectStore(od)
    out = []
    for comm_base, map_base, receive in ((OD_RPDO_COMM, OD_RPDO_MAP, True), (OD_TPDO_COMM, OD_TPDO_MAP, False)):
        for ch in find_channels(store, comm_base, map_base, receive):
            if store.get(ch.comm_index, 1) & COB_INVALID:
                continue
            count = store.get(ch.map_index, 0)
            raws = [store.get(ch.map_index, sub) if store.has(ch.map_index, sub) else 0 for sub in range(1, count + 1)]
            try:
                validate_mapping(store, ch.map_index, raws, receive, FD_MAX_BYTES if can_fd else CLASSIC_MAX_BYTES)
            except SdoAbort as exc:
                out.append(f"{where}.eds: {eds}: the default mapping of {ch.map_index:04X}h (a valid "
                           f"{'RPDO' if receive else 'TPDO'}) cannot be held: {exc.detail}")
    return out


def _catalog_entry(spec: ProfileSpec, od: canopen.ObjectDictionary, problems: list[str]) -> CatalogEntry | None:
    try:
        catalog = load_catalog()
    except ProfileError as exc:
        problems.append(str(exc))
        return None
    if spec.profile is not None:
        found = next((e for e in catalog if e.name == spec.profile), None)
        if found is None:
            problems.append(f"{spec.where}.profile: expected one of {[e.name for e in catalog]} "
                            f"(sim/config/drives/), got {spec.profile!r}")
        return found
    return next((e for e in catalog if _matches(e, od)), None)


def _type_range(var: ODVariable) -> tuple[int, int]:
    bits = {datatypes.INTEGER8: 8, datatypes.INTEGER16: 16, datatypes.INTEGER32: 32, datatypes.INTEGER64: 64,
            datatypes.UNSIGNED8: 8, datatypes.UNSIGNED16: 16, datatypes.UNSIGNED32: 32, datatypes.UNSIGNED64: 64}
    n = bits[int(var.data_type or 0)]
    signed = var.data_type in (datatypes.INTEGER8, datatypes.INTEGER16, datatypes.INTEGER32, datatypes.INTEGER64)
    return (-(1 << (n - 1)), (1 << (n - 1)) - 1) if signed else (0, (1 << n) - 1)


def _binding(name: str, entry: Any, source: str, od: canopen.ObjectDictionary, problems: list[str]) -> Binding | None:
    q = QUANTITIES.get(name)
    if q is None:
        problems.append(f"{source}: unknown quantity; expected one of {', '.join(QUANTITIES)}")
        return None
    if not isinstance(entry, Mapping) or set(entry) - {"object", "unit"} or "object" not in entry:
        problems.append(f"{source}: expected {{object: 30D1h:2, unit: ...}}, got {entry!r}")
        return None
    unit = entry.get("unit", q.unit)
    if unit not in UNITS[q.kind]:
        problems.append(f"{source}.unit: expected one of {', '.join(UNITS[q.kind])} for a {q.kind}, got {unit!r}")
        return None
    try:
        index, sub = parse_address(entry["object"])
    except ValueError as exc:
        problems.append(f"{source}.object: {exc}")
        return None
    var = _variable(od, index, sub)
    if var is None:
        problems.append(f"{source}.object: the EDS has no object {format_address(index, sub)}")
        return None
    if var.data_type not in _INTEGER_TYPES:
        problems.append(f"{source}.object: {format_address(index, sub)} ({var.name}) is of type 0x{var.data_type:X}; "
                        f"the simulated drive keeps process quantities in integer objects")
        return None
    if q.role == "command" and not var.writable:
        problems.append(f"{source}.object: {format_address(index, sub)} ({var.name}) is {var.access_type}; a "
                        f"{q.meaning} must be writable")
        return None
    if q.role != "command" and not var.readable:
        problems.append(f"{source}.object: {format_address(index, sub)} ({var.name}) is {var.access_type}; expected "
                        f"a readable object")
        return None
    return Binding(name, index, sub, unit, source)


def _fit_hardware(hw: Hardware, bindings: dict[str, Binding], var_of: Any, assumptions: list[str]) -> Hardware:
    """The truth's hardware with the drive's rated current and torque raised where its per-mille limit objects cannot
    hold the truth's peak (e.g. a 6072h limited to 1000 per mille): the same amperes and newton-metres at the limit,
    a larger per-mille base."""
    factor = 1.0
    for name, need in (("max_torque", float(hw.max_torque_permille)),
                       ("max_current", 1000.0 * hw.max_current_A / hw.rated_current_A)):
        b = bindings[name]
        var = None if b.index is None or b.per_si is not None else var_of(b.index, b.subindex)
        if var is not None and var.max is not None and 0 < var.max < need:
            factor = max(factor, need / var.max)
    if factor == 1.0:
        return hw
    fitted = Hardware(**{**vars(hw), "rated_current_A": hw.rated_current_A * factor,
                         "rated_torque_Nm": hw.rated_torque_Nm * factor,
                         "max_torque_permille": max(1, round(hw.max_torque_permille / factor))})
    assumptions.append(f"the drive's per-mille limits cannot hold the truth's peak ({hw.max_torque_permille} per mille "
                       f"of {hw.rated_torque_Nm:g} N·m): its rated current and torque are taken "
                       f"{factor:g} x the truth's "
                       f"({fitted.rated_current_A:g} A, {fitted.rated_torque_Nm:g} N·m), the same peak in amperes")
    return fitted


def _raw(bindings: dict[str, Binding], name: str, si_value: float, rated_si: float) -> int:
    """The integer a binding holds for ``si_value`` (A, N·m, N·m/A; per mille of ``rated_si``)."""
    per_si = bindings[name].per_si
    return round(1000.0 * si_value / rated_si) if per_si is None else round(si_value * per_si)


def _commission_hardware(bindings: dict[str, Binding], hw: Hardware, var_of: Any,
                         commissioned: dict[tuple[int, int], int], truth_raw: dict[str, int]) -> None:
    """The truth's motor and limits into the objects that hold them (the drive as its integrator commissioned it)."""
    rated_I, rated_T = hw.rated_current_A, hw.rated_torque_Nm
    truth_raw["rated_current"] = _raw(bindings, "rated_current", rated_I, rated_I)
    truth_raw["rated_torque"] = _raw(bindings, "rated_torque", rated_T, rated_T)
    truth_raw["torque_constant"] = _raw(bindings, "torque_constant", hw.torque_constant_Nm_per_A, 1.0)

    def put(name: str, value: int) -> None:
        b = bindings[name]
        if b.index is not None:
            commissioned[(b.index, b.subindex)] = value

    for name in ("rated_current", "rated_torque", "torque_constant"):
        put(name, truth_raw[name])
    put("max_current", _raw(bindings, "max_current", hw.max_current_A, rated_I))
    put("max_torque", hw.max_torque_permille if bindings["max_torque"].per_si is None
        else _raw(bindings, "max_torque", hw.max_torque_permille * rated_T / 1000.0, rated_T))
    counts_per_rad = hw.counts_per_rev / (2.0 * math.pi)
    for index, decel in ((OD_PROFILE_DECELERATION, hw.slowdown_decel_rad_s2),
                         (OD_QUICK_STOP_DECELERATION, hw.quickstop_decel_rad_s2)):
        if var_of(index, 0) is not None:
            commissioned[(index, 0)] = max(1, round(decel * counts_per_rad))


def _supported_modes(var_of: Any, commissioned: dict[tuple[int, int], int], assumptions: list[str]) -> int:
    """6502h: the commissioned value, the EDS's, or (none given) the cyclic modes whose command objects exist."""
    var = var_of(OD_SUPPORTED_DRIVE_MODES, 0)
    if (OD_SUPPORTED_DRIVE_MODES, 0) in commissioned:
        return commissioned[(OD_SUPPORTED_DRIVE_MODES, 0)]
    if var is not None and (var.value is not None or var.default is not None):
        return int(var.value if var.value is not None else var.default)
    modes = [mode for mode, index in ((Mode.CYCLIC_SYNC_POSITION, OD_TARGET_POSITION),
                                      (Mode.CYCLIC_SYNC_VELOCITY, OD_TARGET_VELOCITY),
                                      (Mode.CYCLIC_SYNC_TORQUE, OD_TARGET_TORQUE)) if var_of(index, 0) is not None]
    if var_of(OD_TARGET_TORQUE, 0) is not None and var_of(OD_TORQUE_SLOPE, 0) is not None:
        modes.append(Mode.PROFILE_TORQUE)
    bits = supported_modes_bits(modes)
    if var_of(OD_MODES_OF_OPERATION, 0) is None:
        bits = 0
    assumptions.append(f"6502h (supported drive modes) has no value in the EDS: 0x{bits:08X}, the modes whose command "
                       f"objects exist ({', '.join(m.name for m in modes) or 'none'})")
    if var is not None:
        commissioned[(OD_SUPPORTED_DRIVE_MODES, 0)] = bits
    return bits
