"""A starting configuration for any robot from its URDF (``dragd config init --robot PATH``).

Joint names, order and ranges come from the URDF; node ids are 1..N on one CAN FD bus; the drives are sized by
:mod:`dragd.robots.sizing` (torque constant, rated current and current limit from the URDF's effort limits and
the gravity load); friction beliefs are zero until ``dragd identify fit`` measures them. The text is validated
as a :class:`dragd.config.Config` before it is returned.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import TYPE_CHECKING

import yaml

from dragd.hardware.cia301 import DT_UNSIGNED32, OD_MANUFACTURER_AREA
from dragd.model import RobotModel
from dragd.robots import urdf_reference
from dragd.robots.sizing import ENCODER_COUNTS_PER_REV, GEAR_RATIO, JointSizing, size_joints

if TYPE_CHECKING:
    from canopen.objectdictionary import ODVariable


def _flow(value: object) -> str:
    return yaml.safe_dump(value, default_flow_style=True, width=1000).strip()


def _joint_lines(i: int, s: JointSizing) -> list[str]:
    source = "the URDF's effort limit" if s.effort_limit_Nm is not None and s.peak_torque_Nm == s.effort_limit_Nm \
        else "sized for 1.5 × gravity"
    return [
        f"  - name: {s.name}",
        f"    # peak {s.peak_torque_Nm:.1f} N·m ({source}); gravity up to {s.gravity_peak_Nm:.1f} N·m "
        f"= {s.gravity_peak_Nm / s.kt_Nm_per_A:.2f} A",
        f"    node_id: {i + 1}",
        f"    gear_ratio: {GEAR_RATIO:g}",
        f"    torque_constant_Nm_per_A: {s.kt_Nm_per_A:.6g}",
        f"    current_limit_A: {float(s.current_limit_A)}",
        f"    rated_current_A: {float(s.rated_current_A)}",
        f"    encoder_counts_per_rev: {ENCODER_COUNTS_PER_REV}",
        f"    velocity_limit_rad_s: {round(s.velocity_limit_rad_s, 3)}",
        f"    drag_damping_Nm_s_per_rad: {1.0 if s.large else 0.3}",
        "    friction: {coulomb_pos_A: 0.0, coulomb_neg_A: 0.0}   # dragd identify fit measures it",
    ]


def starting_config(robot: str | Path, base_dir: Path | None = None,
                    gravity_m_s2: tuple[float, float, float] = (0.0, 0.0, -9.81), eds: str | Path | None = None,
                    out_dir: Path | None = None, buses: int | None = None, rate_Hz: float | None = None) -> str:
    """The YAML text of a starting configuration for ``robot`` (a bundled name or a URDF path); with ``eds`` every
    joint's drive is that EDS's (:func:`drive_section`: classic CAN or FD as the EDS says, the layout, buses and loop
    rate the drives and the bus budget allow; ``out_dir``: where the file goes, for the EDS path relative to it)."""
    from dragd.config import Config

    ref = urdf_reference(robot, base_dir)
    model = RobotModel.from_urdf(ref, base_dir, gravity_m_s2)
    sizes = size_joints(model)
    if eds is not None:
        return _eds_config(ref, model, sizes, gravity_m_s2, Path(eds), out_dir or Path.cwd(), buses, rate_Hz)
    if buses is not None or rate_Hz is not None:
        raise ValueError("--buses and --rate need --eds (dragd's own drive: one CAN FD bus at 1 kHz)")
    peaks = [s.peak_torque_Nm for s in sizes]
    lines = [
        f"# dragd configuration for {model.model.name} ({model.nq} joints), made by `dragd config init` from",
        f"# {model.urdf_path}",
        "# Joint names and order are the URDF's. The drives are a guess sized from the URDF (dragd/robots/sizing.py):",
        "# set node ids, gear ratios, torque constants, current limits and encoders to your hardware, then run",
        "# `dragd config check`; `dragd identify` measures K_t and friction (a params file).",
        "# Units are in the key names: _A amperes (motor current), _Nm joint-side N·m, _rad, _rad_s, _Hz.",
        "",
        "robot:",
        f"  urdf: {ref}",
        f"  gravity_m_s2: {_flow([float(g) for g in gravity_m_s2])}",
        "",
        "params: null                  # e.g. params.yaml (written by `dragd identify fit`)",
        "",
        "buses:",
        "  - {name: arm, interface: socketcan, channel: can0, bitrate: 1000000, fd: true, data_bitrate: 5000000,",
        "     load_limit_pct: 70}",
        "",
        "joints:",
    ]
    for i, s in enumerate(sizes):
        lines += _joint_lines(i, s)
    lines += ["", *_replay_lines(peaks)]
    text = "\n".join(lines)
    Config.model_validate(yaml.safe_load(text))  # a generated file that does not load is a bug here, not the user's
    return text


def _replay_lines(peaks: list[float], cst_limits_A: list[float] | None = None) -> list[str]:
    """The ``replay`` section: the daemon's position loop around the drives' CSP loops and, with ``cst_limits_A``
    (the joints' current limits; drives that follow motions in CST), its loop for CST, all scaled with each joint's
    peak torque. The CST loop is the joint's only one: its damping is 3 x the outer loop's."""
    lines = [
        "# teach and replay: the daemon's position loop per joint, scaled with each joint's peak torque",
        "replay:",
        f"  position_kp_Nm_per_rad: {_flow([round(12.0 * p) for p in peaks])}",
        f"  position_kd_Nm_s_per_rad: {_flow([round(0.2 * p, 1) for p in peaks])}",
        f"  position_ki_Nm_per_rad_s: {_flow([round(24.0 * p) for p in peaks])}",
    ]
    if cst_limits_A is not None:
        lines += [
            "  # motions in CST (the drives' motion_mode): the daemon's loop is the joints' only position loop",
            f"  cst_kp_Nm_per_rad: {_flow([round(12.0 * p) for p in peaks])}",
            f"  cst_kd_Nm_s_per_rad: {_flow([round(0.6 * p, 1) for p in peaks])}",
            f"  cst_ki_Nm_per_rad_s: {_flow([round(24.0 * p) for p in peaks])}",
            f"  cst_integral_limit_A: {_flow([round(0.1 * a, 2) for a in cst_limits_A])}",
        ]
    return [*lines, ""]


# ------------------------------------------------------------------------------------------------ from a vendor EDS

RATES_HZ = (1000.0, 800.0, 500.0, 400.0, 250.0, 200.0, 125.0, 100.0)
LOAD_LIMIT_PCT = 70.0


def _candidates(od: object, any_of: tuple[str, ...], all_of: tuple[str, ...] = ()) -> list[str]:
    """Vendor objects (2000h-5FFFh) whose EDS name contains one of ``any_of`` and all of ``all_of``: suggestions."""
    from canopen.objectdictionary import ODVariable

    from dragd.hardware.profile import address, type_name

    out = []
    for obj in od.values():  # type: ignore[attr-defined]
        if obj.index not in OD_MANUFACTURER_AREA:
            continue
        for var in ([obj] if isinstance(obj, ODVariable) else [v for v in obj.subindices.values() if v.subindex]):
            name = var.name if isinstance(obj, ODVariable) else f"{obj.name}/{var.name}"
            low = name.lower()
            if any(w in low for w in any_of) and all(w in low for w in all_of):
                out.append(f"{address(var.index, var.subindex)} '{name}' {type_name(var.data_type)}"
                           f"{', PDO-mappable' if var.pdo_mappable else ''}")
    return out


def drive_section(eds: Path, node_id: int = 1) -> tuple[dict[str, object], list[str]]:  # noqa: C901
    """The ``drives`` entry for an EDS (what the EDS lets dragd use) and comment lines on what it lacks."""
    from dragd.hardware.cia402 import (
        OD_CURRENT_ACTUAL,
        OD_MOTOR_RATED_CURRENT,
        OD_MOTOR_RATED_TORQUE,
        OD_TORQUE_ACTUAL,
        OD_TORQUE_OFFSET,
    )
    from dragd.hardware.profile import import_eds, od_var

    od = import_eds(eds, node_id)

    def var(index: int) -> ODVariable | None:
        return od_var(od, index)

    drive: dict[str, object] = {"eds": str(eds)}
    notes: list[str] = []
    cur, tq = var(OD_CURRENT_ACTUAL), var(OD_TORQUE_ACTUAL)
    if cur is not None and cur.pdo_mappable and cur.readable:
        drive["current"] = {"object": "6078h"}
    elif tq is not None and tq.pdo_mappable and tq.readable:
        drive["current"] = {"object": "6077h"}
        notes.append(f"6078h {'not PDO-mappable' if cur is not None else 'absent'}: the current from 6077h (per mille "
                     "of the rated torque, through K_m)")
    else:
        drive["current"] = {"object": "6078h"}
        found = "; ".join(_candidates(od, ("current",), ("actual",))) or "none found by name"
        notes.append(f"no mappable 6078h or 6077h: name the drive's current object and unit in current (vendor "
                     f"candidates: {found})")
    offset = var(OD_TORQUE_OFFSET)
    drive["torque_command"] = "60B2h" if offset is not None and offset.pdo_mappable and offset.writable else "6071h"
    if drive["torque_command"] == "6071h":
        notes.append(f"60B2h {'not RPDO-mappable' if offset is not None else 'absent'}: the command is 6071h, which "
                     "CSP ignores; motions run in CST with dragd's position loop (motion_mode, replay.cst_*)")
    if var(OD_MOTOR_RATED_CURRENT) is None:
        drive["rated_current"] = {"object": None}
        cands = _candidates(od, ("nominal current", "rated current", "continuous current"))
        notes.append("6075h absent: rated_current_A is used unverified" + (
            f"; or name the drive's object in rated_current (candidates: {'; '.join(cands)})" if cands else ""))
    rated = var(OD_MOTOR_RATED_TORQUE)
    if rated is None:
        drive["rated_torque"] = {"object": None}
        notes.append("6076h absent: the rated torque is K_m × rated_current_A (or rated_torque_Nm), unverified")
    elif rated.writable and not rated.default:
        drive["rated_torque"] = {"object": "6076h", "unit": "mNm", "write": True}
        notes.append("6076h writable with no default: dragd writes K_m × rated current at boot when it reads 0 (check "
                     "its unit in the drive's manual: rated_torque.unit)")
    return drive, notes


def _eds_config(ref: str, model: RobotModel, sizes: list[JointSizing], gravity: tuple[float, float, float],
                eds: Path, out_dir: Path, n_buses: int | None, rate_Hz: float | None) -> str:
    import os

    from dragd.config import Config
    from dragd.hardware.plan import plan_drives
    from dragd.hardware.profile import eds_says_fd

    eds_abs = eds.expanduser().resolve()
    if not eds_abs.is_file():
        raise FileNotFoundError(f"--eds {eds}: file not found")
    rel = os.path.relpath(eds_abs, out_dir.resolve())
    drive, notes = drive_section(eds_abs)
    drive["eds"] = rel
    name = re.sub(r"[^A-Za-z0-9_]+", "_", eds_abs.stem).strip("_") or "drive"
    fd = eds_says_fd(eds_abs)
    n = len(sizes)
    joints = [{"name": s.name, "node_id": i + 1, "gear_ratio": GEAR_RATIO, "torque_constant_Nm_per_A": s.kt_Nm_per_A,
               "current_limit_A": float(s.current_limit_A), "rated_current_A": float(s.rated_current_A),
               "encoder_counts_per_rev": ENCODER_COUNTS_PER_REV,
               "velocity_limit_rad_s": round(s.velocity_limit_rad_s, 3), "drive": name} for i, s in enumerate(sizes)]

    def trial(nb: int, hz: float, layout: str, targets: bool) -> tuple[Config, object]:
        bus_list = [{"name": "arm" if nb == 1 else f"can{k}", "interface": "socketcan", "channel": f"can{k}",
                     "bitrate": 1_000_000, "fd": fd, **({"data_bitrate": 5_000_000} if fd else {}),
                     "load_limit_pct": LOAD_LIMIT_PCT, "layout": layout, "position_targets": targets}
                    for k in range(nb)]
        js = [dict(j, bus=bus_list[i * nb // n]["name"]) for i, j in enumerate(joints)]
        cfg = Config.model_validate({"robot": {"urdf": ref, "gravity_m_s2": list(gravity)}, "buses": bus_list,
                                     "drives": {name: dict(drive, eds=str(eds_abs))}, "joints": js,
                                     "loop": {"rate_Hz": hz}, "source": str(out_dir / "config.yaml")})
        return cfg, plan_drives(cfg)

    probe_cfg, probe = trial(1, 1000.0, "per_node", True)
    prof = probe.profiles[0]  # type: ignore[attr-defined]
    layout = "shared" if fd and DT_UNSIGNED32 in prof.dummies else "per_node"
    # position targets (607Ah) only for drives that follow motions in CSP: in CST dragd's loop needs none
    targets = prof.target_position is not None and prof.motion_mode == "csp"
    plan = None
    if n_buses is not None and n_buses < 1:
        raise ValueError(f"--buses: expected at least 1, got {n_buses}")
    bus_counts = [n_buses] if n_buses else list(range(1, n + 1))
    rates = [rate_Hz] if rate_Hz else list(RATES_HZ)
    if n_buses:  # fixed buses: the highest rate that fits
        order = [(n_buses, hz) for hz in rates]
    else:  # fixed rate (1 kHz by default): the fewest buses that fit
        order = [(nb, rates[0]) for nb in bus_counts]
    chosen = None
    for nb, hz in order:
        cfg, plan = trial(nb, hz, layout, targets)
        if all(b["load_pct"] <= LOAD_LIMIT_PCT for b in plan.budget.values()):  # type: ignore[attr-defined]
            chosen = (nb, hz, cfg, plan)
            break
    if chosen is None:
        nb, hz = order[-1]
        cfg, plan = trial(nb, hz, layout, targets)
        chosen = (nb, hz, cfg, plan)
    nb, hz, cfg, plan = chosen
    one_bus = None
    if nb > 1:
        for r in RATES_HZ:
            _, p1 = trial(1, r, layout, targets)
            if all(b["load_pct"] <= LOAD_LIMIT_PCT for b in p1.budget.values()):  # type: ignore[attr-defined]
                one_bus = (r, max(b["load_pct"] for b in p1.budget.values()))  # type: ignore[attr-defined]
                break
    loads = {k: v["load_pct"] for k, v in plan.budget.items()}  # type: ignore[attr-defined]
    peaks = [s.peak_torque_Nm for s in sizes]
    lines = [
        f"# dragd configuration for {model.model.name} ({model.nq} joints) with {eds_abs.name} drives, made by",
        f"# `dragd config init --eds` from {model.urdf_path}",
        "# Joint names and order are the URDF's; the drives' currents, torque constants and encoders are a guess sized",
        "# from the URDF (dragd/robots/sizing.py): set them to your hardware, then run `dragd config check`.",
        "# Units are in the key names: _A amperes (motor current), _Nm joint-side N·m, _rad, _rad_s, _Hz.",
        "",
        "robot:",
        f"  urdf: {ref}",
        f"  gravity_m_s2: {_flow([float(g) for g in gravity])}",
        "",
        "params: null                  # e.g. params.yaml (written by `dragd identify fit`)",
        "",
        f"# {eds_abs.name} is {'a CAN FD' if fd else 'a classic CAN'} drive ("
        + ("[DeviceInfo] CANopenFD=1" if fd else "its EDS declares no CANopenFD=1") + f"); layout {layout}"
        + ("" if targets else " without position targets (" + (
            "motions in CST with dragd's position loop need none" if prof.motion_mode == "cst"
            else "607Ah not mappable: drag only") + ")") + ".",
        f"# Worst-case bus load at {hz:g} Hz: " + ", ".join(f"{k} {v:.1f} %" for k, v in loads.items())
        + f" (limit {LOAD_LIMIT_PCT:g} %).",
    ]
    if nb > 1:
        lines.append(f"# {n} joints do not fit one {'CAN FD' if fd else 'classic'} 1 Mbit/s bus at {hz:g} Hz: "
                     f"{nb} buses" + (f"; on one bus the loop fits at {one_bus[0]:g} Hz ({one_bus[1]:.1f} %): set "
                                      "loop.rate_Hz and one bus, or `dragd config init --buses 1`" if one_bus else ""))
    lines.append("buses:")
    for b in cfg.buses:
        extra = f", data_bitrate: {b.data_bitrate}" if b.fd else ""
        lines.append(f"  - {{name: {b.name}, interface: socketcan, channel: {b.channel}, bitrate: {b.bitrate}, "
                     f"fd: {'true' if b.fd else 'false'}{extra},")
        lines.append(f"     load_limit_pct: {b.load_limit_pct:g}, layout: {b.layout}, position_targets: "
                     f"{'true' if b.position_targets else 'false'}}}")
    lines += ["", "drives:   # what dragd uses of each drive (docs/DRIVES.md); `dragd config check` lists what it "
                  "lacks", f"  {name}:"]
    for note in notes:
        lines.append(f"    # {note}")
    for key, value in drive.items():
        lines.append(f"    {key}: {_flow(value) if isinstance(value, dict) else value}")
    lines.append(f"    motion_mode: {prof.motion_mode}   # motions: csp = the drive's position loop + 60B2h, "
                 "cst = dragd's (docs/DRIVES.md)")
    lines += ["", "joints:"]
    for i, s in enumerate(sizes):
        lines += _joint_lines(i, s)
        lines.append(f"    drive: {name}")
        if nb > 1:
            lines.append(f"    bus: {cfg.joints[i].bus}")
    cst = [float(s.current_limit_A) for s in sizes] if prof.motion_mode == "cst" else None
    lines += ["", "loop:", f"  rate_Hz: {hz:g}", "", *_replay_lines(peaks, cst)]
    text = "\n".join(lines)
    data = yaml.safe_load(text)
    data["drives"][name]["eds"] = str(eds_abs)
    Config.model_validate(data)  # a generated file that does not load is a bug here, not the user's
    return text
