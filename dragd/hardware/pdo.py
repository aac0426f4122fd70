"""Process-data layout of a bus: which PDOs each drive sends and receives, their mappings and codecs.

The layout is data planned from each joint's drive profile (hardware/profile.py): the master writes it to the drives
over SDO, the cycle encodes/decodes frames with precompiled ``struct`` codecs from it (the field types from the EDS),
and the bus budget is computed from it. Every mapping is checked against the drive's EDS before anything is written
(``plan_bus``): PDOs the drive has, their mapping-entry counts, the frame's length limit (8 bytes on classic CAN,
64 on CAN FD), PDO-mappable objects, dummy entries ([DummyUsage]).

Layouts (``buses[].layout``):
- ``shared`` (CAN FD): per drive one SYNC TPDO [6041h sw, 6064h pos, current]; one *shared command RPDO* carrying
  every joint's slot [6040h cw, 607Ah pos, torque command] — each drive maps dummy entries (0007h, 32 bit) over the
  other joints' slots: up to 8 slots per 64-byte frame. On classic CAN one slot per 8-byte frame (no dummies).
- ``compact`` (classic CAN, drag only, drives with dummy mapping): per drive a SYNC TPDO [pos, current] and an
  event TPDO [sw] with inhibit time; shared RPDO(s) of torque commands [× up to 4 joints] each cycle (dummies over
  the others); per drive an event RPDO [cw] sent on change and as a keep-alive.
- ``per_node`` (any drive, no dummy entries): per drive one SYNC RPDO [(607Ah,) torque command] and one SYNC TPDO
  [pos, current]; on classic CAN the statusword and the controlword travel in event PDOs where the drive has a
  second TPDO with an inhibit time and a second RPDO (the bus budget), else in the SYNC PDOs when they fit.

The torque command is 60B2h (torque offset: CiA 402 adds it to 6071h, kept 0, in CST and uses it as torque
feed-forward in CSP, so a CST↔CSP switch needs no remapping) or, where a drive does not map 60B2h, 6071h.
"""

from __future__ import annotations

import struct
from collections import Counter
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Literal

from dragd.hardware.busload import BusLoadReport, FrameSpec, bus_load
from dragd.hardware.cia301 import (
    COB_ID_MASK,
    DT_INTEGER8,
    DT_INTEGER16,
    DT_INTEGER32,
    DT_UNSIGNED8,
    DT_UNSIGNED16,
    DT_UNSIGNED32,
    DUMMY_TYPES,
    OD_RPDO_COMM,
    OD_RPDO_MAP,
    OD_TPDO_COMM,
    OD_TPDO_MAP,
    PDO_COB_STEP,
    PDO_TRANSMISSION_EVENT,
    PDO_TRANSMISSION_SYNC,
    RPDO1_BASE,
    TPDO1_BASE,
)
from dragd.hardware.profile import Finding, PdoChannel, ProcessObject

if TYPE_CHECKING:
    from dragd.hardware.profile import DriveProfile

SHARED_RPDO_BASE = RPDO1_BASE  # 200h (+80h·k): "RPDO of node 0", unused by any node; not a restricted COB-ID
STATUS_EVENT_TIMER_MS = 100  # an event TPDO's keep-alive (where the drive has an event timer)

Field = Literal["statusword", "position", "current", "controlword", "target_position", "torque", "inputs"]
Kind = Literal["shared", "compact", "per_node"]
_FORMAT = {"statusword": "H", "position": "i", "current": "h", "controlword": "H", "target_position": "i",
           "torque": "h", "inputs": "I"}


@dataclass(frozen=True)
class MapEntry:
    """One mapping entry: an object (or a dummy 0002h–0007h) and its length in bits."""

    index: int
    subindex: int
    bits: int
    field: Field | None = None  # None for a dummy
    code: str = ""  # struct code of the object's EDS data type ("" for a dummy)

    @property
    def word(self) -> int:
        """The 32-bit mapping value written to 16xxh/1Axxh."""
        return (self.index << 16) | (self.subindex << 8) | self.bits


def _entry(obj: ProcessObject) -> MapEntry:
    return MapEntry(obj.index, obj.sub, obj.bits, obj.field, obj.code)  # type: ignore[arg-type]


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
    fixed_mapping: bool = False  # the drive's read-only mapping, used as it is (never written)
    comm_subs: frozenset[int] = frozenset({1, 2, 3, 5})  # the communication parameter's sub-indices (EDS)
    cob_writable: bool = True

    @property
    def comm_index(self) -> int:
        return (OD_TPDO_COMM if self.direction == "tpdo" else OD_RPDO_COMM) + self.number - 1

    @property
    def map_index(self) -> int:
        return (OD_TPDO_MAP if self.direction == "tpdo" else OD_RPDO_MAP) + self.number - 1

    @property
    def data_bytes(self) -> int:
        return sum(e.bits for e in self.entries) // 8

    @property
    def name(self) -> str:
        return f"{self.direction.upper()}{self.number}"


@dataclass(frozen=True)
class Slot:
    """Where one joint's fields sit in a frame: byte offset, fields and their struct codes (little endian)."""

    joint: int
    offset: int
    fields: tuple[Field, ...]
    codes: tuple[str, ...] = ()  # () : the bundled drive's types (_FORMAT)

    @property
    def fmt(self) -> str:
        return "<" + "".join(self.codes or tuple(_FORMAT[f] for f in self.fields))


def _slot(joint: int, offset: int, entries: tuple[MapEntry, ...] | list[MapEntry]) -> Slot:
    own = [e for e in entries if e.field is not None]
    return Slot(joint, offset, tuple(e.field for e in own), tuple(e.code for e in own))  # type: ignore[misc]


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
    kind: Kind
    fd: bool
    brs: bool
    joints: tuple[int, ...]  # joint indices on this bus
    node_ids: tuple[int, ...]
    pdos: dict[int, list[PdoSpec]]  # node id -> PDOs to configure (others disabled)
    frames: list[FrameLayout] = field(default_factory=list)
    position_targets: bool = True  # the command frames carry 607Ah (CSP motions possible)

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


class LayoutError(ValueError):
    """A layout the drives cannot carry: every finding of the bus, each naming the key to change."""

    def __init__(self, findings: list[Finding]) -> None:
        super().__init__("\n".join(f.text for f in findings))
        self.findings = findings


# ------------------------------------------------------------------------------------------------ planning


@dataclass(frozen=True)
class _Role:
    """A PDO a node needs: direction, entries, SYNC or event, the preferred PDO number and COB-ID."""

    direction: Literal["tpdo", "rpdo"]
    entries: tuple[MapEntry, ...]
    cyclic: bool
    number: int
    cob_id: int | None  # None: the pre-defined connection set's COB-ID of the PDO chosen
    what: str
    needs_inhibit: bool = False
    needs_timer: bool = False  # an event PDO whose loss must show (the enabling switch, a stop): an event timer (sub 5)
    inhibit_ms: int | None = None  # an event TPDO's inhibit time and keep-alive (default: the statusword's)
    event_timer_ms: int | None = None


def _predefined_cob(direction: str, number: int, node_id: int) -> int:
    return (TPDO1_BASE if direction == "tpdo" else RPDO1_BASE) + PDO_COB_STEP * (number - 1) + node_id


def _dummies(bits: int, have: frozenset[int]) -> list[MapEntry] | None:
    """Dummy entries covering ``bits`` with the largest dummy types the drive supports (None: impossible)."""
    out: list[MapEntry] = []
    for index in (DT_UNSIGNED32, DT_INTEGER32, DT_UNSIGNED16, DT_INTEGER16, DT_UNSIGNED8, DT_INTEGER8):
        size = DUMMY_TYPES[index]
        while index in have and bits >= size:
            out.append(MapEntry(index, 0, size))
            bits -= size
    return out if bits == 0 else None


class _Planner:
    """Assigns one bus's roles to the PDOs each drive has; collects every finding instead of stopping at one."""

    def __init__(self, bus_key: str, fd: bool, kind: Kind, event_min_interval_ms: int) -> None:
        self.bus_key, self.fd, self.kind = bus_key, fd, kind
        self.inputs_timer_ms, self.inputs_inhibit_ms = 10, 2  # (plan_bus sets the configuration's)
        self.event_min_interval_ms = event_min_interval_ms
        self.findings: list[Finding] = []
        self.max_bits = 512 if fd else 64

    def error(self, p: DriveProfile, what: str, fix: str) -> None:
        self.findings.append(Finding("error", f"{p.where}: {what}; {fix}", where=p.where))

    def entries(self, p: DriveProfile, fields: tuple[Field, ...]) -> tuple[MapEntry, ...] | None:
        """The drive's mapping entries for ``fields`` (None where the profile lacks one: its own finding says why)."""
        objs = {"statusword": p.statusword, "position": p.position, "current": p.current,
                "controlword": p.controlword, "target_position": p.target_position, "torque": p.command,
                "inputs": p.inputs}
        got = [objs[f] for f in fields]
        if any(o is None for o in got):
            if "target_position" in fields and p.target_position is None:
                self.error(p, f"layout '{self.kind}' carries 607Ah position targets (CSP), but "
                              f"{p.csp_reason() or '607Ah is not mappable'}",
                           f"set {self.bus_key}.position_targets: false (drag only; identify run, replay and track "
                           "refused)" if self.kind == "per_node" else f"set {self.bus_key}.layout: per_node with "
                           "position_targets: false (drag only)")
            return None
        return tuple(_entry(o) for o in got)  # type: ignore[arg-type]

    def _place(self, p: DriveProfile, role: _Role, used: set[tuple[str, int]],
               why: list[str]) -> tuple[PdoChannel, tuple[MapEntry, ...] | None] | None:
        """The drive's PDO for a role (the preferred number first) and, for a fixed mapping, its entry order."""
        chans = p.tpdos if role.direction == "tpdo" else p.rpdos
        words = Counter(e.word for e in role.entries)
        for ch in sorted(chans, key=lambda c: (c.number != role.number, c.number)):
            if (ch.direction, ch.number) in used:
                continue
            if not {1, 2} <= ch.comm_subs or not ch.ttype_writable:
                why.append(f"{ch.name}: no writable transmission type ({ch.comm_index:04X}h sub 2)")
                continue
            if role.needs_inhibit and 3 not in ch.comm_subs:
                why.append(f"{ch.name}: no inhibit time ({ch.comm_index:04X}h sub 3) for an event PDO")
                continue
            if role.needs_timer and 5 not in ch.comm_subs:
                why.append(f"{ch.name}: no event timer ({ch.comm_index:04X}h sub 5): a lost event TPDO would not show")
                continue
            cob = role.cob_id if role.cob_id is not None else _predefined_cob(ch.direction, ch.number, p.node_id)
            if not ch.cob_writable and (ch.cob_default or 0) & COB_ID_MASK != cob:
                why.append(f"{ch.name}: COB-ID read-only at 0x{(ch.cob_default or 0) & COB_ID_MASK:03X}, "
                           f"0x{cob:03X} needed")
                continue
            if ch.map_writable:
                if len(role.entries) > ch.max_entries:
                    why.append(f"{ch.name}: {len(role.entries)} mapping entries needed, {ch.map_index:04X}h has "
                               f"{ch.max_entries}")
                    continue
                return ch, None
            if Counter(ch.default_words) == words:  # a fixed mapping with exactly these objects: used as it is
                by_word = {e.word: e for e in role.entries}
                return ch, tuple(by_word[w] for w in ch.default_words)
            why.append(f"{ch.name}: mapping {ch.map_index:04X}h read-only "
                       f"[{', '.join(f'{w:08X}h' for w in ch.default_words)}]")
        return None

    def assign(self, p: DriveProfile, roles: list[_Role], used: set[tuple[str, int]] | None = None,  # noqa: C901
               dry: bool = False) -> list[PdoSpec] | None:
        """Every role on a PDO of the drive, or (``dry``) None when one cannot be placed; without ``dry`` each role
        that cannot be placed is a finding and the others are returned."""
        used = set() if used is None else used
        trial = set(used)
        out = []
        for role in roles:
            bits = sum(e.bits for e in role.entries)
            why: list[str] = []
            placed = self._place(p, role, trial, why) if bits <= self.max_bits else None
            if placed is None:
                if dry:
                    return None
                if bits > self.max_bits:
                    parts = " + ".join(f"{e.index:04X}h ({e.bits})" for e in role.entries)
                    self.error(p, f"{role.what} needs {bits} bits ({parts}), more than a "
                                  f"{'CAN FD' if self.fd else 'classic CAN'} frame's {self.max_bits}",
                               f"set {self.bus_key}.layout: per_node, or {p.key}.current to a 16-bit object")
                else:
                    chans = p.tpdos if role.direction == "tpdo" else p.rpdos
                    detail = "; ".join(dict.fromkeys(why)) or f"the drive has {len(chans)} {role.direction.upper()}"
                    self.error(p, f"no {role.direction.upper()} left for {role.what} ({detail})",
                               f"set {self.bus_key}.layout to another layout (shared, compact, per_node)")
                continue
            ch, fixed = placed
            trial.add((ch.direction, ch.number))
            cob = role.cob_id if role.cob_id is not None else _predefined_cob(ch.direction, ch.number, p.node_id)
            event = not role.cyclic
            inhibit_ms = role.inhibit_ms if role.inhibit_ms is not None else self.event_min_interval_ms
            timer_ms = role.event_timer_ms if role.event_timer_ms is not None else STATUS_EVENT_TIMER_MS
            transmission = PDO_TRANSMISSION_SYNC if role.cyclic else PDO_TRANSMISSION_EVENT
            out.append(PdoSpec(role.direction, ch.number, cob, transmission,
                               fixed if fixed is not None else role.entries,
                               inhibit_100us=inhibit_ms * 10 if event and role.direction == "tpdo" else 0,
                               event_timer_ms=(timer_ms if event and role.direction == "tpdo"
                                               and 5 in ch.comm_subs else 0),
                               fixed_mapping=fixed is not None, comm_subs=ch.comm_subs, cob_writable=ch.cob_writable))
        used |= trial
        return out

    def first_fit(self, p: DriveProfile, options: list[list[_Role]], used: set[tuple[str, int]]) -> list[PdoSpec]:
        """The first option whose roles all fit the drive's PDOs; else the last one's findings."""
        for roles in options[:-1]:
            got = self.assign(p, roles, used, dry=True)
            if got is not None:
                return got
        return self.assign(p, options[-1], used) or []


def _with_inputs(pl: _Planner, p: DriveProfile, options: list[list[_Role]]) -> list[list[_Role]]:
    """A drive whose digital inputs are wired to the hand (docs/HAND.md): its feedback options, the inputs object
    added — in the cyclic feedback TPDO where it fits, else beside the statusword in its event TPDO, else in an event
    TPDO of its own (inhibit time; an event timer where the enabling switch or a stop rides in it, so that a lost
    frame shows), else in a SYNC TPDO of its own. The first option every role of fits is the plan."""
    if p.inputs is None:
        return options
    di = (_entry(p.inputs),)
    safety = bool({"enable", "stop"} & set(p.input_functions))
    what = (f"the digital inputs {p.inputs.index:04X}h (hand.inputs: {', '.join(p.input_functions)}; bit"
            f"{'s' if len(p.input_bits) > 1 else ''} {', '.join(map(str, p.input_bits))})")
    inhibit_ms, timer_ms = pl.inputs_inhibit_ms, pl.inputs_timer_ms
    fits: list[list[_Role]] = []
    for opt in options:  # in the cyclic feedback
        new, done = [], False
        for r in opt:
            if not done and r.direction == "tpdo" and r.cyclic and any(e.field == "position" for e in r.entries):
                r, done = replace(r, entries=r.entries + di, what=f"{r.what} with {what}"), True
            new.append(r)
        if done and all(sum(e.bits for e in r.entries) <= pl.max_bits for r in new):
            fits.append(new)
    for opt in options:  # beside the statusword's event TPDO
        new, done = [], False
        for r in opt:
            if not done and r.direction == "tpdo" and not r.cyclic and any(e.field == "statusword" for e in r.entries):
                r, done = replace(r, entries=r.entries + di, what=f"{r.what} with {what}", needs_timer=safety,
                                  inhibit_ms=inhibit_ms, event_timer_ms=timer_ms), True
            new.append(r)
        if done and all(sum(e.bits for e in r.entries) <= pl.max_bits for r in new):
            fits.append(new)
    for opt in options:  # an event TPDO of their own
        fits.append(opt + [_Role("tpdo", di, False, 3, None, f"{what} (event)", needs_inhibit=True,
                                 needs_timer=safety, inhibit_ms=inhibit_ms, event_timer_ms=timer_ms)])
    for opt in options:  # a SYNC TPDO of their own
        fits.append(opt + [_Role("tpdo", di, True, 3, None, f"{what} (SYNC)")])
    return fits


def plan_bus(bus: str, joints: list[int], profiles: list[DriveProfile], *, fd: bool, kind: str | None = None,
             rate_Hz: float = 1000.0, event_min_interval_ms: int = 10, position_targets: bool = True,
             bus_key: str | None = None, inputs_timer_ms: int = 10,
             inputs_inhibit_ms: int = 2) -> tuple[BusLayout, list[Finding]]:
    """The PDO layout of one bus carrying ``joints`` (indices) on the drives of ``profiles`` (one per joint), and
    every finding against the drives' EDS (an empty list: the layout is complete). ``inputs_*``: the event TPDO
    timing of a drive's digital inputs where they cannot ride in the cyclic feedback (hand.event_timer_ms, ...)."""
    kind = kind or "shared"
    bus_key = bus_key or f"bus '{bus}'"
    if kind not in ("shared", "compact", "per_node"):
        raise ValueError(f"{bus_key}: layout: expected 'shared', 'compact' or 'per_node', got '{kind}'")
    pl = _Planner(bus_key, fd, kind, event_min_interval_ms)  # type: ignore[arg-type]
    pl.inputs_timer_ms, pl.inputs_inhibit_ms = inputs_timer_ms, inputs_inhibit_ms
    node_ids = [p.node_id for p in profiles]
    pdos: dict[int, list[PdoSpec]] = {n: [] for n in node_ids}
    frames: list[FrameLayout] = []
    ev_hz = 1000.0 / event_min_interval_ms
    if kind == "compact" and fd:
        pl.findings.append(Finding("error", f"{bus_key}: layout 'compact' is for classic CAN; set {bus_key}.layout: "
                                            "shared or per_node on CAN FD"))
        kind = pl.kind = "shared"
    targets = position_targets if kind == "per_node" else kind == "shared"

    def tpdo_frame(j: int, n: int, spec: PdoSpec, what: str) -> None:
        event_hz = 1e4 / spec.inhibit_100us if spec.inhibit_100us else ev_hz  # (the worst case: every inhibit time)
        frames.append(FrameLayout(f"{spec.name} node {n}{what}", spec.cob_id, spec.data_bytes,
                                  (_slot(j, 0, spec.entries),), "tpdo", spec.transmission_type <= 240, rate_Hz
                                  if spec.transmission_type <= 240 else max(ev_hz, event_hz)))

    if kind == "shared":
        slot_fields: tuple[Field, ...] = ("controlword", "target_position", "torque")
        slot_entries: list[tuple[MapEntry, ...] | None] = []
        for j, p in zip(joints, profiles, strict=True):
            tp = pl.entries(p, ("statusword", "position", "current"))
            slot_entries.append(pl.entries(p, slot_fields))
            if tp is not None:
                fb = _with_inputs(pl, p, [[_Role("tpdo", tp, True, 1, None, "the cyclic feedback")]])
                for spec in pl.first_fit(p, fb, set()):
                    pdos[p.node_id].append(spec)
                    tpdo_frame(j, p.node_id, spec, "")
        slot_bits = [sum(e.bits for e in s) if s is not None else 64 for s in slot_entries]
        groups: list[list[int]] = []
        for i in range(len(joints)):  # up to 8 slots per frame on CAN FD (64 bytes), one on classic CAN
            if groups and fd and len(groups[-1]) < 8 and sum(slot_bits[g] for g in groups[-1]) + slot_bits[i] <= 512:
                groups[-1].append(i)
            else:
                groups.append([i])
        _shared_frames(pl, "shared", "command", joints, profiles, slot_entries, groups, SHARED_RPDO_BASE, rate_Hz,
                       pdos, frames)
    elif kind == "compact":
        for j, p in zip(joints, profiles, strict=True):
            pc, sw, cw = (pl.entries(p, ("position", "current")), pl.entries(p, ("statusword",)),
                          pl.entries(p, ("controlword",)))
            if pc is None or sw is None or cw is None:
                continue
            used: set[tuple[str, int]] = set()
            specs = pl.first_fit(p, _with_inputs(pl, p, [[
                _Role("tpdo", pc, True, 1, None, "position and current"),
                _Role("tpdo", sw, False, 2, None, "the statusword (event)", needs_inhibit=True),
                _Role("rpdo", cw, False, 1, None, "the controlword (event)")]]), used)
            for spec in specs:
                pdos[p.node_id].append(spec)
                if spec.direction == "tpdo":
                    tpdo_frame(j, p.node_id, spec, "")
                else:
                    frames.append(FrameLayout(f"{spec.name} node {p.node_id}", spec.cob_id, spec.data_bytes,
                                              (_slot(j, 0, spec.entries),), "rpdo", False, ev_hz))
        groups = [list(range(i, min(i + 4, len(joints)))) for i in range(0, len(joints), 4)]
        # 300h, 380h: PDO COB-IDs of node 0, unused
        _shared_frames(pl, "compact", "torque", joints, profiles, [pl.entries(p, ("torque",)) for p in profiles],
                       groups, SHARED_RPDO_BASE + PDO_COB_STEP, rate_Hz, pdos, frames)
    else:  # per_node
        for j, p in zip(joints, profiles, strict=True):
            cmd_fields: tuple[Field, ...] = ("target_position", "torque") if targets else ("torque",)
            pc, sw = pl.entries(p, ("position", "current")), pl.entries(p, ("statusword",))
            cw, cmd = pl.entries(p, ("controlword",)), pl.entries(p, cmd_fields)
            if pc is None or sw is None or cw is None or cmd is None:
                continue
            sync_fb = _Role("tpdo", sw + pc, True, 1, None, "the cyclic feedback")
            split_fb = [_Role("tpdo", pc, True, 1, None, "position and current"),
                        _Role("tpdo", sw, False, 2, None, "the statusword (event)", needs_inhibit=True)]
            two_sync_fb = [_Role("tpdo", pc, True, 1, None, "position and current"),
                           _Role("tpdo", sw, True, 2, None, "the statusword")]
            sync_cmd = _Role("rpdo", cw + cmd, True, 1, None, "the cyclic command")
            split_cmd = [_Role("rpdo", cmd, True, 1, None, "the cyclic command"),
                         _Role("rpdo", cw, False, 2, None, "the controlword (event)")]
            # classic CAN: the statusword and controlword by event where the drive can (bus load); CAN FD: all cyclic
            fb_options = [split_fb, [sync_fb], two_sync_fb] if not fd else [[sync_fb], two_sync_fb]
            cmd_options = [split_cmd, [sync_cmd]] if not fd else [[sync_cmd], split_cmd]
            placed: set[tuple[str, int]] = set()
            specs = pl.first_fit(p, _with_inputs(pl, p, fb_options), placed) + pl.first_fit(p, cmd_options, placed)
            for spec in specs:
                pdos[p.node_id].append(spec)
                if spec.direction == "tpdo":
                    tpdo_frame(j, p.node_id, spec, "")
                else:
                    cyclic = spec.transmission_type <= 240
                    frames.append(FrameLayout(f"{spec.name} node {p.node_id}", spec.cob_id, spec.data_bytes,
                                              (_slot(j, 0, spec.entries),), "rpdo", cyclic,
                                              rate_Hz if cyclic else ev_hz))
    layout = BusLayout(bus, kind, fd, fd, tuple(joints), tuple(node_ids), pdos, frames,  # type: ignore[arg-type]
                       position_targets=targets)
    return layout, pl.findings


def _shared_frames(pl: _Planner, kind: str, what: str, joints: list[int], profiles: list[DriveProfile],
                   own: list[tuple[MapEntry, ...] | None], groups: list[list[int]], cob_base: int, rate_Hz: float,
                   pdos: dict[int, list[PdoSpec]], frames: list[FrameLayout]) -> None:
    """Frames that several joints share (RPDO 4 of each drive, COB-ID ``cob_base`` + 0x80·k): each drive maps its own
    slot and dummy entries over the others' (the drive's [DummyUsage] must allow them)."""
    bits = [sum(e.bits for e in s) if s is not None else 0 for s in own]
    for k, group in enumerate(groups):
        cob = cob_base + 0x80 * k
        slots, offset, complete = [], 0, True
        for gi in group:
            mine, p = own[gi], profiles[gi]
            if mine is None:
                complete = False
                continue
            entries: list[MapEntry] = []
            for other in group:
                cover = list(mine) if other == gi else _dummies(bits[other], p.dummies)
                if cover is None:
                    pl.error(p, f"layout '{kind}' puts {len(group)} joints in {what} frame "
                                f"0x{cob:03X}: this drive must "
                                f"map dummy entries over the others' {bits[other]} bits, and its EDS [DummyUsage] "
                                f"allows {', '.join(f'{d:04X}h' for d in sorted(p.dummies)) or 'none'}",
                             f"set {pl.bus_key}.layout: per_node")
                    complete = False
                    break
                entries.extend(cover)
            else:
                placed: set[tuple[str, int]] = {(s.direction, s.number) for s in pdos[p.node_id]}
                pdos[p.node_id].extend(pl.assign(p, [_Role("rpdo", tuple(entries), True, 4, cob,
                                                           f"{what} frame 0x{cob:03X}")], placed) or [])
            slots.append(_slot(joints[gi], offset, mine))
            offset += bits[gi] // 8
        if complete:
            frames.append(FrameLayout(f"{what} RPDO 0x{cob:03X}", cob, offset, tuple(slots), "rpdo", True, rate_Hz))


def layout_for(bus: str, joints: list[int], node_ids: list[int], *, fd: bool, kind: str | None = None,
               rate_Hz: float = 1000.0, event_min_interval_ms: int = 10,
               profiles: list[DriveProfile] | None = None, position_targets: bool = True) -> BusLayout:
    """``plan_bus`` that raises LayoutError on any finding; without ``profiles`` the drives are dragd's own joint
    drive (canopen_eds/joint_drive.eds) at ``node_ids``."""
    if profiles is None:
        profiles = bundled_profiles(node_ids)
    layout, findings = plan_bus(bus, joints, profiles, fd=fd, kind=kind, rate_Hz=rate_Hz,
                                event_min_interval_ms=event_min_interval_ms, position_targets=position_targets)
    if findings:
        raise LayoutError(findings)
    return layout


def bundled_profiles(node_ids: list[int]) -> list[DriveProfile]:
    """Profiles of dragd's own joint drive at ``node_ids`` (one joint each, sized like config/default.yaml)."""
    from dragd.config import Config
    from dragd.hardware.profile import DriveProfile

    joints = [{"name": f"j{n}", "node_id": n, "gear_ratio": 100, "torque_constant_Nm_per_A": 1.0,
               "current_limit_A": 3.0, "rated_current_A": 1.0, "encoder_counts_per_rev": 4096} for n in node_ids]
    cfg = Config.model_validate({"joints": joints})
    return [DriveProfile(cfg, j) for j in range(len(node_ids))]


class RpdoEncoder:
    """One outgoing frame: a preallocated buffer and per-slot precompiled structs."""

    # what a slot packs, in its order: one of these (fields in frame order); anything else packs field by field
    KINDS: dict[tuple[str, ...], int] = {("controlword", "target_position", "torque"): 0, ("torque",): 1,
                                         ("controlword",): 2, ("target_position", "torque"): 3,
                                         ("controlword", "torque"): 4}

    def __init__(self, frame: FrameLayout, fd: bool, min_interval_s: float = 0.0, keepalive_s: float = 0.1) -> None:
        self.frame = frame
        self.buffer = bytearray(frame.data_bytes)
        self.slots = [(s.joint, s.offset, struct.Struct(s.fmt), self.KINDS.get(s.fields, -1)) for s in frame.slots]
        # slots in an order no kind names: (joint, offset, struct, field) per field
        self.loose = []
        for s in frame.slots:
            if s.fields not in self.KINDS:
                off = s.offset
                for f, code in zip(s.fields, s.codes or tuple(_FORMAT[f] for f in s.fields), strict=True):
                    c = struct.Struct("<" + code)
                    self.loose.append((s.joint, off, c, f))
                    off += c.size
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
