"""Offline, faster-than-real-time identification logs: the sim's arm driven by a drive-like CSP loop.

``python -m sim log --plan PLAN.npz --out log.mcap|log.csv [--seconds S] [--seed N]`` follows a joint
trajectory (a plan written by ``dragd identify plan``: arrays ``t_s``, ``q_rad``) the way
``dragd identify run`` does through the daemon, without a bus or real time:

* every 1 ms cycle the "daemon" samples the drives (position in encoder counts, current in per mille of the
  rated current, as TPDO1 carries them), computes the TRACK feed-forward current
  ``G(q)/K_t + friction(q̇_ref)`` from *dragd's* configuration (its beliefs, not the truth) and sends the
  target position with it as torque offset;
* the drives apply the command at the next SYNC and run their CSP loop each physics step, exactly as
  ``sim/drive.py`` does: ``kp·(q_target − q) + kd·(v_ff − q̇) (+ ki·∫e) + offset``, clamped;
* :class:`sim.physics.ArmPhysics` integrates the arm (friction, stick–slip, Hall noise, quantisation).

The MCAP is written as the daemon writes its telemetry (dragd/telemetry: ``cycle_layout``, ``write_file``;
topic ``/dragd/cycle``, mode ``track``; fields the run does not simulate hold what the daemon would write or 0,
see `write_mcap`); the CSV has
``t,q1..qN,i1..iN,dq1..dqN`` (s, rad, A, rad/s; dq is the daemon-style filtered estimate).
This is harness code: it reads the truth; dragd/ never imports it.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from dragd.control.modes import Mode
from dragd.hardware.cia402 import STATE_STATUSWORD_BITS, SW_CYCLIC_FOLLOWING, SW_REMOTE, SW_VOLTAGE_ENABLED, State
from sim.axis import AxisIO
from sim.physics import ArmPhysics
from sim.truth import Truth, csp_ki_A_per_rad_s

# 1237h: operation enabled, voltage enabled, remote, following the cyclic command; target reached cleared
STATUSWORD_ENABLED = (STATE_STATUSWORD_BITS[State.OPERATION_ENABLED] | SW_VOLTAGE_ENABLED | SW_REMOTE
                      | SW_CYCLIC_FOLLOWING)


def load_plan(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(t_s, q_rad) of a plan file (.npz with t_s, q_rad; or CSV t,q1..qN)."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"plan {path}: file not found")
    try:
        if path.suffix == ".npz":
            with np.load(path, allow_pickle=False) as z:
                t, q = np.asarray(z["t_s"], float), np.asarray(z["q_rad"], float)
        else:
            data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
            t, q = data[:, 0], data[:, 1:]
    except (KeyError, ValueError, OSError) as exc:
        raise ValueError(f"plan {path}: expected .npz with t_s, q_rad or CSV t,q1..qN: {exc}") from None
    if t.ndim != 1 or q.ndim != 2 or q.shape[0] != t.shape[0] or t.shape[0] < 2:
        raise ValueError(f"plan {path}: expected t_s (N,) and q_rad (N, joints), got {t.shape} and {q.shape}")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(q))) or np.any(np.diff(t) <= 0) or t[0] != 0.0:
        raise ValueError(f"plan {path}: t_s must start at 0 and increase strictly, q_rad must be finite")
    return t, q


def resample(t_s: np.ndarray, q_rad: np.ndarray, dt_s: float) -> np.ndarray:
    """The daemon's TRACK table: a clamped cubic spline through the plan, sampled every ``dt_s``."""
    from scipy.interpolate import CubicSpline

    grid = np.arange(0.0, float(t_s[-1]) + dt_s / 2, dt_s)
    return np.ascontiguousarray(CubicSpline(t_s, q_rad, bc_type="clamped")(grid))


class OfflineArm:
    """The sim's arm plus drive-like CSP loops and the daemon's TRACK feed-forward, stepped as fast as possible."""

    def __init__(self, truth: Truth, config: str | Path | None = None, rate_Hz: float = 1000.0,
                 csp_interpolation: bool = False) -> None:
        from dragd.config import check_joint_names, load_config
        from dragd.control.params import LawParams

        self.truth = truth
        self.model = truth.load_model()
        self.n = n = self.model.nq
        self.cfg = load_config(config)
        check_joint_names(self.cfg, (self.model.joint_names, self.model.urdf_path or "the sim's robot"))
        self.law = LawParams.from_config(self.cfg)
        self.axes = [AxisIO() for _ in range(n)]
        self.physics = ArmPhysics(truth, self.model, self.axes)
        self.dt = 1.0 / rate_Hz
        # sim/drive.py applies each CSP target for a whole SYNC period (no interpolation): its position error is a
        # sawtooth and the current sampled at SYNC sits at its low end. A drive that interpolates the target over
        # the period (CiA 402 60C2h) has no sawtooth; off by default (the sim's drive does not).
        self.csp_interpolation = csp_interpolation
        self.sub = int(round(self.dt / truth.dt_s))
        if abs(self.sub * truth.dt_s - self.dt) > 1e-12:
            raise ValueError(f"loop period {self.dt} s is not a whole number of physics steps ({truth.dt_s} s)")
        hw = [j.drive for j in truth.joints]
        self.kp = [h.csp_kp_A_per_rad for h in hw]
        self.kd = [h.csp_kd_A_s_per_rad for h in hw]
        self.ki = [csp_ki_A_per_rad_s(j) for j in truth.joints]
        self.limit = [min(h.max_torque_permille * h.rated_current_A / 1000.0, h.max_current_A) for h in hw]
        self.rated = np.array([h.rated_current_A for h in hw])
        self.cpr = np.array([h.encoder_counts_per_rev for h in hw], dtype=float)
        self.counts_per_rad = self.cpr / (2.0 * math.pi)

    def run(self, table: np.ndarray, progress: Callable[[float], None] | None = None) -> dict[str, np.ndarray]:
        """Follow ``table`` (rows every loop period, the daemon's TRACK table); return the telemetry arrays."""
        from dragd.control.estimate import VelocityEstimator
        from dragd.control.law import Workspace, friction_current

        n, sub, dt = self.n, self.sub, self.dt
        phys, axes, law = self.physics, self.axes, self.law
        steps = table.shape[0]
        phys.set_state(table[0])
        for ax in axes:
            ax.power_stage_on = True
            ax.brake_engaged = False
            ax.current_demand_A = 0.0
        target_counts = np.rint(table * self.counts_per_rad).astype(np.int64)
        vel = VelocityEstimator(self.cpr, self.cfg.law.velocity_filter_Hz)
        ws = Workspace(n)
        out: dict[str, np.ndarray] = {k: np.empty((steps, n)) for k in (
            "q_rad", "dq_rad_s", "current_measured_A", "current_command_A", "gravity_A", "friction_A")}
        out["t_s"] = np.arange(steps) * dt
        out["q_ref_rad"] = table
        kt = law.kt_Nm_per_A
        kp, kd, ki, limit = self.kp, self.kd, self.ki, self.limit
        rad_per_count = [1.0 / c for c in self.counts_per_rad]
        a_per_permille = self.rated / 1000.0
        integral = [0.0] * n
        cmd_target = [int(c) for c in target_counts[0]]  # what the drives apply this cycle
        cmd_offset = [0.0] * n
        v_ff = [0.0] * n
        prev_target = cmd_target[:]
        q_ref_prev = table[0].copy()
        dq_ref = np.zeros(n)
        tau_g = np.zeros(n)
        fr = np.zeros(n)
        q = np.zeros(n)
        t_report = time.monotonic()
        for k in range(steps):
            # --- SYNC k: drives sample (TPDO), the daemon computes and sends (applied at SYNC k+1)
            xs = phys.q_rad
            counts = np.rint(xs * self.counts_per_rad).astype(np.int64)
            q[:] = counts / self.counts_per_rad
            meas = np.rint(phys.current_measured_A / a_per_permille) * a_per_permille
            vel.update(counts, dt)
            q_ref = table[k]
            np.subtract(q_ref, q_ref_prev, out=dq_ref)
            dq_ref /= dt
            q_ref_prev = q_ref
            self.model.gravity(q, tau_g)
            friction_current(dq_ref, law, fr, ws)
            offset = tau_g / kt + fr
            out["q_rad"][k] = q
            out["dq_rad_s"][k] = vel.velocity_rad_s
            out["current_measured_A"][k] = meas
            out["current_command_A"][k] = offset
            out["gravity_A"][k] = tau_g / kt
            out["friction_A"][k] = fr
            # --- the drives latch the new command at the next SYNC; CSP velocity feed-forward from target steps
            new_target = target_counts[k].tolist()
            for j in range(n):
                v_ff[j] = (new_target[j] - prev_target[j]) * rad_per_count[j] / dt
            prev_target = new_target
            cmd_target = new_target
            cmd_offset = np.clip(np.rint(offset / a_per_permille), -32768, 32767) * a_per_permille
            cmd_offset = cmd_offset.tolist()
            # --- physics steps until the next SYNC, the drives' CSP loop each step
            for step in range(sub):
                pos = phys.q_rad.tolist()
                v = phys.dq_rad_s.tolist()
                back = (sub - 1 - step) * phys.dt_s if self.csp_interpolation else 0.0
                for j in range(n):
                    err = cmd_target[j] * rad_per_count[j] - back * v_ff[j] - pos[j]
                    if ki[j]:
                        integral[j] = max(-limit[j], min(limit[j], integral[j] + ki[j] * err * phys.dt_s))
                    d = kp[j] * err + kd[j] * (v_ff[j] - v[j]) + integral[j] + cmd_offset[j]
                    axes[j].current_demand_A = limit[j] if d > limit[j] else (-limit[j] if d < -limit[j] else d)
                phys.step()
            if progress is not None and time.monotonic() - t_report > 0.5:
                t_report = time.monotonic()
                progress((k + 1) / steps)
        if progress is not None:
            progress(1.0)
        return out


def generate(plan_t: np.ndarray, plan_q: np.ndarray, truth: Truth, *, config: str | Path | None = None,
             seconds: float | None = None, seed: int | None = None, csp_interpolation: bool = False,
             progress: Callable[[float], None] | None = None) -> dict[str, np.ndarray]:
    """Run a plan (optionally only its first ``seconds``) on the offline arm; return telemetry arrays."""
    if seed is not None:
        truth = truth.with_updates(noise_seed=int(seed))
    arm = OfflineArm(truth, config, csp_interpolation=csp_interpolation)
    if plan_q.shape[1] != arm.n:
        raise ValueError(f"plan: expected {arm.n} joints per sample ({', '.join(arm.model.joint_names)}), "
                         f"got {plan_q.shape[1]}")
    table = resample(plan_t, plan_q, arm.dt)
    if seconds is not None:
        table = table[: int(round(seconds / arm.dt)) + 1]
    return arm.run(table, progress)


def write_csv(path: str | Path, data: dict[str, np.ndarray]) -> None:
    n = data["q_rad"].shape[1]
    header = ",".join(["t"] + [f"q{i + 1}" for i in range(n)] + [f"i{i + 1}" for i in range(n)]
                      + [f"dq{i + 1}" for i in range(n)])
    arr = np.column_stack([data["t_s"], data["q_rad"], data["current_measured_A"], data["dq_rad_s"]])
    fmt = ["%.6f"] + ["%.9f"] * n + ["%.6f"] * n + ["%.6f"] * n
    np.savetxt(path, arr, delimiter=",", header=header, comments="", fmt=fmt)


def write_mcap(path: str | Path, data: dict[str, np.ndarray], metadata: dict[str, str] | None = None,
               mode: int = Mode.TRACK) -> int:
    """The daemon's telemetry file (dragd/telemetry ``cycle_layout``, ``write_file``); returns the number of rows.

    ``data`` holds what the run simulates (t_s, q_rad, dq_rad_s, current_measured_A, current_command_A,
    gravity_A, friction_A, optionally q_ref_rad: the plan's reference, else q_rad); the other fields get what the
    daemon writes in TRACK without its drag terms: statusword enabled, every feedback received, the nominal
    period, track_t_s = t_s, zeros for the drag terms, compute time and residual.
    """
    from dragd.telemetry.layout import RowLayout
    from dragd.telemetry.schema import cycle_layout
    from dragd.telemetry.writer import write_file

    t = np.asarray(data["t_s"], dtype=float)
    n = data["q_rad"].shape[1]
    layout = cycle_layout(n)
    row = RowLayout(layout)
    sl = row.slices
    period_us = float(np.median(np.diff(t))) * 1e6 if t.size > 1 else 1000.0
    values: dict[str, Any] = {
        "mode": int(mode), "statusword": STATUSWORD_ENABLED, "rx": 1, "period_us": period_us,
        "compute_us": 0.0, "q_ref_rad": data.get("q_ref_rad", data["q_rad"]), "track_t_s": t,
        "startup_A": 0.0, "damping_A": 0.0, "residual_A": 0.0, "back_emf_A": 0.0, "effects_A": 0.0,
        "contact_residual_A": 0.0, "contact_band_A": 0.0, "hand_force_N": 0.0, "grip_m": 0.0,
    }
    values.update({k: v for k, v in data.items() if k in layout})
    missing = [k for k in layout if k not in values]
    if missing:
        raise ValueError(f"write_mcap: no values for {', '.join(missing)}")
    rows = np.zeros((t.shape[0], row.width))
    for k, v in values.items():
        v = np.asarray(v, dtype=float)
        rows[:, sl[k]] = v[:, None] if v.ndim == 1 and sl[k].stop - sl[k].start == 1 else v
    stamps = time.time_ns() + np.rint(t * 1e9).astype(np.int64)
    return write_file(path, row, rows, stamps, metadata=metadata, library="sim.offline")


def write_log(path: str | Path, data: dict[str, np.ndarray], metadata: dict[str, str] | None = None) -> None:
    path = Path(path)
    if path.suffix == ".csv":
        write_csv(path, data)
    elif path.suffix == ".mcap":
        write_mcap(path, data, metadata)
    else:
        raise ValueError(f"--out {path}: expected a .mcap or .csv file name")


def truth_summary(truth: Truth) -> dict[str, Any]:
    """The truth per joint in dragd's units: K_t, friction in amperes (N·m / K_t), noise, armature."""
    joints = {}
    for j in truth.joints:
        kt = j.torque_constant_Nm_per_A
        f = j.friction
        joints[j.name] = {
            "torque_constant_Nm_per_A": kt,
            "friction": {
                "coulomb_pos_A": f.coulomb_pos_Nm / kt,
                "coulomb_neg_A": f.coulomb_neg_Nm / kt,
                "static_pos_A": f.static_pos / kt,
                "static_neg_A": f.static_neg / kt,
                "stribeck_velocity_rad_s": f.stribeck_velocity_rad_s,
                "stribeck_exponent": f.stribeck_exponent,
                "viscous_pos_A_s_per_rad": f.viscous_pos_Nm_s_per_rad / kt,
                "viscous_neg_A_s_per_rad": f.viscous_neg_Nm_s_per_rad / kt,
            },
            "friction_Nm": f.model_dump(),
            "current_noise_std_A": j.current_noise_std_A,
            "current_quantum_A": j.current_quantum_A,
            "drive_current_quantum_A": j.drive.rated_current_A / 1000.0,
            "armature_kgm2": j.armature_kgm2,
            "gear_ratio": j.gear_ratio,
            "hidden_effects": any([j.hidden.ripple, j.hidden.load_friction_per_Nm, j.hidden.thermal is not None,
                                   j.hidden.current_offset_A, j.hidden.backlash_rad]),
        }
    return {"source": truth.source, "robot": truth.robot, "physics_rate_Hz": truth.physics_rate_Hz,
            "noise_seed": truth.noise_seed, "joints": joints}
