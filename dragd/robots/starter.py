"""A starting configuration for any robot from its URDF (``dragd config init --robot PATH``).

Joint names, order and ranges come from the URDF; node ids are 1..N on one CAN FD bus; the drives are sized by
:mod:`dragd.robots.sizing` (torque constant, rated current and current limit from the URDF's effort limits and
the gravity load); friction beliefs are zero until ``dragd identify fit`` measures them. The text is validated
as a :class:`dragd.config.Config` before it is returned.
"""

from __future__ import annotations

from pathlib import Path

import yaml

from dragd.model import RobotModel
from dragd.robots import urdf_reference
from dragd.robots.sizing import ENCODER_COUNTS_PER_REV, GEAR_RATIO, JointSizing, size_joints


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
                    gravity_m_s2: tuple[float, float, float] = (0.0, 0.0, -9.81)) -> str:
    """The YAML text of a starting configuration for ``robot`` (a bundled name or a URDF path)."""
    from dragd.config import Config

    ref = urdf_reference(robot, base_dir)
    model = RobotModel.from_urdf(ref, base_dir, gravity_m_s2)
    sizes = size_joints(model)
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
    lines += [
        "",
        "# teach and replay: the daemon's position loop per joint, scaled with each joint's peak torque",
        "replay:",
        f"  position_kp_Nm_per_rad: {_flow([round(12.0 * p) for p in peaks])}",
        f"  position_kd_Nm_s_per_rad: {_flow([round(0.2 * p, 1) for p in peaks])}",
        f"  position_ki_Nm_per_rad_s: {_flow([round(24.0 * p) for p in peaks])}",
        "",
    ]
    text = "\n".join(lines)
    Config.model_validate(yaml.safe_load(text))  # a generated file that does not load is a bug here, not the user's
    return text
