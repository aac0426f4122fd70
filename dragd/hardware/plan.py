"""The drives of a configuration, planned offline: every joint's profile, every bus's PDO layout and load, and
everything found against the drives' EDS files — what ``dragd config check`` prints and what the daemon refuses
to start with (docs/DRIVES.md)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from dragd.hardware.cia301 import DT_UNSIGNED32
from dragd.hardware.pdo import BusLayout, PdoSpec, plan_bus
from dragd.hardware.profile import Finding, Profiles, load_profiles

if TYPE_CHECKING:
    from dragd.config import Config


@dataclass
class DrivePlan:
    profiles: Profiles
    layouts: dict[str, BusLayout]
    budget: dict[str, dict[str, Any]]  # bus -> load_pct, limit_pct, table
    findings: list[Finding] = field(default_factory=list)

    @property
    def errors(self) -> list[Finding]:
        return [f for f in self.findings if f.level == "error"]

    @property
    def refusals(self) -> list[str]:
        """Why drives cannot do torque drag at all (each once)."""
        return list(dict.fromkeys(f.refusal for f in self.findings if f.refusal))

    def error_text(self, source: str) -> str:
        errors = self.errors
        head = f"{source}: {len(errors)} problem(s) with the drives (dragd config check lists them with the warnings):"
        return "\n".join([head] + [f"  {f.text}" for f in errors])


def _inputs_pdo(layout: BusLayout, joint: int) -> tuple[PdoSpec, bool] | None:
    """The PDO carrying ``joint``'s digital inputs, and whether it is SYNC (cyclic)."""
    node = layout.node_ids[layout.joints.index(joint)] if joint in layout.joints else None
    for spec in layout.pdos.get(node, []) if node is not None else []:
        if spec.direction == "tpdo" and any(e.field == "inputs" for e in spec.entries):
            return spec, spec.transmission_type <= 240
    return None


def input_carrier(layout: BusLayout, joint: int) -> str:
    """Where the digital inputs of ``joint``'s drive ride (config check, boot status)."""
    found = _inputs_pdo(layout, joint)
    if found is None:
        return "digital inputs: not mapped"
    spec, cyclic = found
    objs = ", ".join(f"{e.index:04X}h" for e in spec.entries if e.field is not None)
    if cyclic:
        return f"digital inputs in {spec.name} (SYNC) [{objs}]"
    timer = (f"event timer {spec.event_timer_ms} ms" if spec.event_timer_ms
             else "no event timer: a lost frame cannot show")
    return f"digital inputs in {spec.name} (event, inhibit {spec.inhibit_100us / 10:g} ms, {timer}) [{objs}]"


def inputs_lost_after(cfg: Config, layouts: dict[str, BusLayout]) -> list[int]:
    """Per joint, after how many cycles without the TPDO carrying its digital inputs they count as lost: the cyclic
    feedback's ``loop.stale_cycles_hold``, an event TPDO's 2.5 event timers (``hand.lost_after_ms`` overrides)."""
    rate = cfg.loop.rate_Hz
    out = []
    for j, jc in enumerate(cfg.joints):
        if cfg.hand.lost_after_ms is not None:
            out.append(max(1, round(cfg.hand.lost_after_ms * rate / 1000.0)))
            continue
        found = _inputs_pdo(layouts[jc.bus], j)
        if found is None or found[1]:
            out.append(cfg.loop.stale_cycles_hold)
        elif not found[0].event_timer_ms:  # (only buttons ride without a keep-alive: their loss cannot show)
            out.append(2 ** 62)
        else:
            out.append(max(cfg.loop.stale_cycles_hold, round(2.5 * found[0].event_timer_ms * rate / 1000.0)))
    return out


def plan_drives(cfg: Config, profiles: Profiles | None = None, *, budget_findings: bool = True) -> DrivePlan:
    """Profiles, layouts and bus loads of ``cfg``; every finding at once (ProfileError for an unreadable EDS).
    ``budget_findings`` false: a bus over its load limit is not a finding (the daemon raises BusBudgetError with the
    table instead)."""
    profiles = profiles if profiles is not None else load_profiles(cfg)
    findings = profiles.all_findings()
    layouts: dict[str, BusLayout] = {}
    budget: dict[str, dict[str, Any]] = {}
    for k, b in enumerate(cfg.buses):
        key = f"buses[{k}]"
        idx = [i for i, j in enumerate(cfg.joints) if j.bus == b.name]
        bus_profiles = [profiles[i] for i in idx]
        if b.fd:
            for p in bus_profiles:
                if not p.fd:
                    findings.append(Finding("error", f"{p.where}: the drive is classic CAN (its EDS declares no "
                                                     f"CANopenFD=1) on CAN FD bus '{b.name}'; set {key}.fd: false",
                                            where=p.where))
        kind = b.layout
        if kind == "auto":  # what the drives support: a shared FD frame needs dummy entries in every drive
            kind = "shared" if b.fd and all(DT_UNSIGNED32 in p.dummies for p in bus_profiles) else "per_node"
        layout, found = plan_bus(b.name, idx, bus_profiles, fd=b.fd, kind=kind, rate_Hz=cfg.loop.rate_Hz,
                                 position_targets=b.position_targets, bus_key=key,
                                 inputs_timer_ms=cfg.hand.event_timer_ms, inputs_inhibit_ms=cfg.hand.event_inhibit_ms)
        findings += found
        for p in bus_profiles:
            if p.inputs is not None and not found:
                findings.append(Finding("note", f"{p.where}: {input_carrier(layout, p.joint_index)}", where=p.where))
        layouts[b.name] = layout
        csp_motion = [p for p in bus_profiles if p.motion_mode == "csp"]  # (CST motions need no position targets)
        if not layout.position_targets and csp_motion:
            findings.append(Finding("note", f"{key} '{b.name}': layout '{layout.kind}' carries no position targets: "
                                            "drag, hold and idle only (identify run, replay and track refused)"))
        elif layout.position_targets:
            for p in csp_motion:
                if p.csp is False:
                    findings.append(Finding("note", f"{p.where}: no CSP ({p.csp_reason()}): identify run, replay and "
                                                    "track refused", where=p.where))
        r = layout.budget(cfg.loop.rate_Hz, b.bitrate, b.data_bitrate, 1000.0 / cfg.master.heartbeat_ms)
        budget[b.name] = {"load_pct": r.percent, "load_min_pct": r.percent_min, "limit_pct": b.load_limit_pct,
                          "table": r.table()}
        if r.percent > b.load_limit_pct and budget_findings:
            findings.append(Finding("error", f"{cfg.source}: {key} '{b.name}': worst-case bus load {r.percent:.1f} % "
                                             f"(no stuff bits: {r.percent_min:.1f} %) exceeds load_limit_pct "
                                             f"{b.load_limit_pct:.0f} % at {cfg.loop.rate_Hz:.0f} Hz "
                                             f"({'CAN FD' if b.fd else 'classic CAN'} {b.bitrate / 1e6:g} Mbit/s, "
                                             f"{len(idx)} joints, layout '{kind}'); use CAN FD, fewer joints per "
                                             "bus (split buses), a lower loop.rate_Hz"
                                             + (", or position_targets: false (" + (
                                                 "drag only" if csp_motion else "motions in CST need none") + ")"
                                                if kind == "per_node" and b.position_targets else "")))
    return DrivePlan(profiles, layouts, budget, findings)
