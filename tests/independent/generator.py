"""Independent log generator for ``dragd gap``: motor-current logs written from the equations, not by dragd or ``sim``.

This module is a test fixture. It shares nothing with dragd's code (no import of ``dragd`` or ``sim``); the only
contracts are the two file formats dragd reads:

* the CSV log ``t,q1..qN,i1..iN[,dq1..dqN]`` (s, rad, A, rad/s; docs/IDENTIFICATION.md, dragd/identify/data.py);
* the params file (YAML, ``version: 1``, ``joints.jointK.{torque_constant_Nm_per_A, friction, effects}``,
  ``payload``; dragd/config.py ``ParamsFile``) and a minimal configuration file (dragd/config.py ``Config``).

Physics (per joint j; SI units, currents in amperes)
-----------------------------------------------------
The arm follows a *prescribed* trajectory q(t) exactly (no control loop is simulated — inverse dynamics), except
the joint of a ``Backlash`` effect, whose output is simulated (see there).

    τ_rb(q, q̇, q̈)  = M(q)·q̈ + C(q, q̇)·q̇ + G(q)           [N·m]  Pinocchio RNEA on the truth URDF (+ payload)
    τ_J            = J_a,j · q̈_j                           [N·m]  rotor inertia reflected to the joint (armature)
    τ_x            = hidden torque effects                  [N·m]  ripple, load-dependent friction
    i_delivered    = (τ_rb + τ_J + τ_x) / K_t,j + I_f,j(q̇_j, t)                                      [A]
    I_f(v)         = s·[F_c,s + (F_s,s − F_c,s)·exp(−(|v|/v_s)^δ)] + F_v,s·v,   s = sign v  (per direction) [A]
    i_reported     = i_delivered + back-EMF shortfall + Hall offset                                    [A]
    i_log          = Δ_i · round((i_reported + n) / Δ_i),   n ~ N(0, σ²) Hall noise, Δ_i = rated current/1000
    q_log          = Δ_q · round(q / Δ_q),                   Δ_q = 2π / encoder counts per revolution

Friction is written in amperes (joint-side friction torque / K_t), as dragd's configuration holds it; the sign is
exact (no smoothing): at rest (|q̇| < 1e-6 rad/s) the friction current is 0.

Hidden effects (what the truth has and the belief lacks) are the classes below, each naming its dragd catalogue
effect in ``name``; ``BeliefError`` subclasses leave the truth alone and change what the user believes instead.
``generate(spec, out_dir)`` writes ``log.csv``, ``belief.yaml`` (params file), ``config.yaml`` and ``truth.json``
(the truth, and per effect and joint the RMS of the current the belief misses: the expected answer).
Deterministic by ``CaseSpec.seed``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin
import yaml
from scipy.optimize import brentq
from scipy.signal import butter, sosfiltfilt

REPO = Path(__file__).resolve().parents[2]
SEED_COBOT_URDF = REPO / "dragd" / "robots" / "seed_cobot.urdf"
GRID_HZ = 1000  # internal time grid of the truth; log rates must divide it
# expected names dragd's catalogue lacks (none since torque_constant, coulomb_friction)
NAMES_NOT_IN_CATALOGUE: tuple[str, ...] = ()

# ------------------------------------------------------------------------------------------ robots and truth


@dataclass(frozen=True)
class JointTruth:
    """One joint's true drive and friction parameters (joint side; currents in A)."""

    kt_Nm_per_A: float  # joint-side torque constant K_t: joint torque per ampere of motor current
    coulomb_pos_A: float  # F_c,+ ≥ 0: sliding friction level, positive direction
    coulomb_neg_A: float  # F_c,− ≤ 0
    static_pos_A: float  # F_s,+ ≥ F_c,+: level at breakaway (Stribeck hump top)
    static_neg_A: float  # F_s,− ≤ F_c,−
    stribeck_velocity_rad_s: float  # v_s: the hump decays over this speed
    stribeck_exponent: float  # δ
    viscous_pos_A_s_per_rad: float  # F_v,+ ≥ 0
    viscous_neg_A_s_per_rad: float  # F_v,− ≥ 0
    armature_kgm2: float  # J_a: rotor (+ gear input) inertia reflected to the joint, n²·J_m
    rated_current_A: float  # 6075h: the per-mille current quantum is rated/1000
    current_limit_A: float
    velocity_limit_rad_s: float
    gear_ratio: float = 101.0
    encoder_counts_per_rev: int = 524288  # output encoder, per joint revolution


@dataclass(frozen=True)
class RobotSpec:
    """A robot: URDF, joint names (joint1..jointN, as dragd's configuration requires), joint truths, excitation
    envelope (home pose, per-joint excursion, speed and acceleration caps used by the trajectory builders)."""

    name: str
    urdf: Path
    joints: tuple[JointTruth, ...]
    home_rad: tuple[float, ...]
    excursion_rad: tuple[float, ...]  # trajectories stay within home ± excursion
    speed_rad_s: tuple[float, ...]  # cruise speed cap per joint (≤ 0.8 × the velocity limit)
    accel_rad_s2: float = 1.5  # peak acceleration of the trajectory builders
    pass_robot_flag: bool = False  # give --robot to dragd (a URDF that is not the config's)
    joint_names: tuple[str, ...] | None = None  # the URDF's joint names when not joint1..jointN

    @property
    def n(self) -> int:
        return len(self.joints)


def _seed_joints() -> tuple[JointTruth, ...]:
    """The seed cobot's drives as config/default.yaml describes them (values copied, not read: the fixture must not
    change when the configuration does), plus rotor inertias n²·J_m (J_m 5.4e-5 / 2.9e-5 / 1.0e-5 kg·m², n = 101)."""
    F = [  # cp, cn, sp, sn, v_s, δ, viscous
        (0.55, -0.52, 0.72, -0.68, 0.02, 2, 0.60), (0.86, -0.86, 1.14, -1.10, 0.02, 2, 0.75),
        (0.46, -0.44, 0.61, -0.58, 0.02, 2, 0.45), (0.35, -0.33, 0.48, -0.45, 0.03, 2, 0.25),
        (0.31, -0.29, 0.42, -0.40, 0.03, 2, 0.22), (0.24, -0.23, 0.33, -0.31, 0.03, 2, 0.17)]
    kt = [9.09, 9.09, 9.09, 4.545, 4.545, 4.545]
    rated = [4.0, 4.0, 3.0, 2.0, 2.0, 2.0]
    limit = [12.0, 12.0, 9.0, 6.0, 6.0, 6.0]
    vlim = [1.0, 1.0, 1.0, 1.5, 1.5, 1.5]
    ja = [0.55, 0.55, 0.30, 0.10, 0.10, 0.10]
    return tuple(JointTruth(kt[j], F[j][0], F[j][1], F[j][2], F[j][3], F[j][4], F[j][5], F[j][6], F[j][6], ja[j],
                            rated[j], limit[j], vlim[j]) for j in range(6))


def seed_cobot() -> RobotSpec:
    """The bundled ``seed_cobot`` (dragd/robots/seed_cobot.urdf; dragd's default configuration's robot)."""
    return RobotSpec("seed_cobot", SEED_COBOT_URDF, _seed_joints(), home_rad=(0.0, -0.6, 1.2, -0.6, 1.5708, 0.0),
                     excursion_rad=(0.8, 0.5, 0.6, 0.8, 0.8, 1.0), speed_rad_s=(0.8, 0.8, 0.8, 1.2, 1.2, 1.2))


def ur5_urdf_path() -> Path:
    """The UR5 URDF of example-robot-data (``example_robot_data.load('ur5')``'s file) in this environment."""
    try:
        import example_robot_data  # type: ignore[import-not-found]

        return Path(example_robot_data.getModelPath("ur_description/urdf/ur5_robot.urdf")) / \
            "ur_description/urdf/ur5_robot.urdf"
    except Exception:  # the python module is optional: look for the cmeel data directory
        import site
        for base in site.getsitepackages():
            p = Path(base) / "cmeel.prefix/share/example-robot-data/robots/ur_description/urdf/ur5_robot.urdf"
            if p.is_file():
                return p
    raise FileNotFoundError("ur5_robot.urdf of example-robot-data not found")


def ur5(out_dir: Path, rename_joints: bool = True) -> RobotSpec:
    """example-robot-data's UR5 (a different URDF than the seed cobot: other masses, inertias, K_t).

    dragd's configuration requires joints named joint1..jointN and ``dragd gap`` requires the URDF's joint names to
    match, so by default a copy with ``shoulder_pan_joint`` → ``joint1`` … is written to ``out_dir`` (the file
    otherwise unchanged); ``rename_joints=False`` keeps the original file (what a user would try first).
    """
    src = ur5_urdf_path()
    path = src
    if rename_joints:
        text = src.read_text()
        for k, nm in enumerate(UR_JOINT_NAMES, start=1):
            text = re.sub(rf'"{nm}"', f'"joint{k}"', text)
        out_dir.mkdir(parents=True, exist_ok=True)
        path = out_dir / "ur5_joint_names.urdf"
        path.write_text(text)
    base = _seed_joints()
    kt = [13.0, 13.0, 9.4, 4.6, 4.6, 4.6]  # UR5-like gear 101 × K_m 0.13/0.093/0.046 N·m/A
    ja = [0.62, 0.62, 0.35, 0.09, 0.09, 0.09]
    joints = tuple(dataclasses.replace(b, kt_Nm_per_A=kt[j], armature_kgm2=ja[j],
                                       coulomb_pos_A=b.coulomb_pos_A * 0.9, coulomb_neg_A=b.coulomb_neg_A * 0.9,
                                       static_pos_A=b.static_pos_A * 0.9, static_neg_A=b.static_neg_A * 0.9)
                   for j, b in enumerate(base))
    names = None if rename_joints else UR_JOINT_NAMES
    return RobotSpec("ur5" if rename_joints else "ur5_original_names", path, joints,
                     home_rad=(0.0, -1.0, 1.3, -1.5, -1.5708, 0.0), excursion_rad=(0.8, 0.5, 0.6, 0.8, 0.8, 1.0),
                     speed_rad_s=(0.8, 0.8, 0.8, 1.2, 1.2, 1.2), pass_robot_flag=True, joint_names=names)


UR_JOINT_NAMES = ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint",
                  "wrist_3_joint")


def rename_joints(x: Any, names: tuple[str, ...]) -> Any:
    """``x`` (nested dicts/lists) with every ``jointK`` key or string replaced by the URDF's K-th joint name."""
    table = {f"joint{k + 1}": nm for k, nm in enumerate(names)}
    if isinstance(x, dict):
        return {table.get(k, k): rename_joints(v, names) for k, v in x.items()}
    if isinstance(x, list):
        return [rename_joints(v, names) for v in x]
    return table.get(x, x) if isinstance(x, str) else x


def load_pin_model(urdf: Path) -> pin.Model:
    return pin.buildModelFromUrdf(str(urdf))


def with_payload(model: pin.Model, mass_kg: float, com_joint_m: np.ndarray, radius_m: float) -> pin.Model:
    """A copy of ``model`` with a payload on the last body: a solid sphere (mass m, radius r, inertia 2/5·m·r²
    about its centre) at ``com_joint_m`` in the last joint's frame."""
    m = model.copy()
    body = m.njoints - 1
    I_c = np.eye(3) * 0.4 * mass_kg * radius_m ** 2
    m.inertias[body] = m.inertias[body] + pin.Inertia(float(mass_kg), np.asarray(com_joint_m, float), I_c)
    return m


def flange_to_last_joint(model: pin.Model, p_flange_m: np.ndarray) -> np.ndarray:
    """A point given in the flange frame (``flange`` or ``tool0`` when the URDF has one) in the last joint's frame."""
    for name in ("flange", "tool0", "ee_link"):
        if model.existFrame(name):
            f = model.frames[model.getFrameId(name)]
            if f.parentJoint == model.njoints - 1:
                return f.placement.act(np.asarray(p_flange_m, float))
    return np.asarray(p_flange_m, float)


# ------------------------------------------------------------------------------------------ trajectories


@dataclass
class Motion:
    """A trajectory on the truth grid (GRID_HZ): t [s], q [rad], dq [rad/s], ddq [rad/s²], each (T, n)."""

    t: np.ndarray
    q: np.ndarray
    dq: np.ndarray
    ddq: np.ndarray

    def copy(self) -> Motion:
        return Motion(self.t.copy(), self.q.copy(), self.dq.copy(), self.ddq.copy())


class Profile:
    """One joint's motion as a chain of acceleration pieces with closed-form integrals.

    A piece of duration T changes the speed by Δv with a raised-cosine acceleration (finite jerk, as a drive's
    profile generator): with τ = (t − t₀)/T ∈ [0, 1],
        q̈ = Δv/T·(1 − cos 2πτ),  q̇ = v₀ + Δv·(τ − sin(2πτ)/2π),  q = q₀ + v₀·T·τ + Δv·T·(τ²/2 + (cos 2πτ − 1)/4π²)
    (peak acceleration 2Δv/T; a hold is a piece with Δv = 0).
    """

    def __init__(self, q0: float) -> None:
        self.t0: list[float] = []
        self.T: list[float] = []
        self.v0: list[float] = []
        self.dv: list[float] = []
        self.q0: list[float] = []
        self.t = 0.0
        self.v = 0.0
        self.q = q0

    def add(self, T: float, dv: float = 0.0) -> None:
        if T <= 0:
            return
        self.t0.append(self.t)
        self.T.append(T)
        self.v0.append(self.v)
        self.dv.append(dv)
        self.q0.append(self.q)
        self.q += self.v * T + 0.5 * dv * T
        self.v += dv
        self.t += T

    def ramp(self, v_to: float, accel: float) -> None:
        """Change speed to ``v_to`` at peak acceleration ``accel`` (duration 2|Δv|/accel)."""
        dv = v_to - self.v
        if dv:
            self.add(2.0 * abs(dv) / accel, dv)

    def evaluate(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        q = np.full(t.shape, self.q)
        dq = np.full(t.shape, self.v)
        ddq = np.zeros(t.shape)
        if not self.t0:
            return q, dq, ddq
        t0 = np.asarray(self.t0)
        k = np.clip(np.searchsorted(t0, t, side="right") - 1, 0, len(t0) - 1)
        T, v0, dv, qs = (np.asarray(a)[k] for a in (self.T, self.v0, self.dv, self.q0))
        inside = t < self.t
        tau = np.clip((t - t0[k]) / T, 0.0, 1.0)
        c2 = 2.0 * math.pi
        qq = qs + v0 * T * tau + dv * T * (tau ** 2 / 2 + (np.cos(c2 * tau) - 1.0) / (c2 ** 2))
        vv = v0 + dv * (tau - np.sin(c2 * tau) / c2)
        aa = dv / T * (1.0 - np.cos(c2 * tau))
        q = np.where(inside, qq, q)
        dq = np.where(inside, vv, dq)
        ddq = np.where(inside, aa, 0.0)
        return q, dq, ddq

    def turn_distance(self, v_to: float, accel: float) -> float:
        """Distance from the start of a ramp v → v_to (opposite signs) to where the speed crosses zero."""
        v0, dv = self.v, v_to - self.v
        T = 2.0 * abs(dv) / accel
        c2 = 2.0 * math.pi
        tau0 = brentq(lambda x: v0 + dv * (x - math.sin(c2 * x) / c2), 0.0, 1.0)
        return v0 * T * tau0 + dv * T * (tau0 ** 2 / 2 + (math.cos(c2 * tau0) - 1.0) / c2 ** 2)


def _grid(duration_s: float) -> np.ndarray:
    return np.arange(int(round(duration_s * GRID_HZ)) + 1) / GRID_HZ


def _stack(profiles: list[Profile], t: np.ndarray) -> Motion:
    cols = [p.evaluate(t) for p in profiles]
    return Motion(t, *(np.column_stack([c[k] for c in cols]) for k in range(3)))


def trapezoid_passes(robot: RobotSpec, duration_s: float, rng: np.random.Generator) -> Motion:
    """Every joint reciprocates between home ± excursion in trapezoid passes **back to back, without rests**: each
    reversal is one ramp from +v_k to −v_{k+1} (the speed crosses zero under acceleration; peak 2 × the robot's
    acceleration cap). Speeds per pass are drawn from {0.2 … 1.0} × the joint's speed cap (itself capped so that a
    pass fits the stroke); joints run unsynchronised, so the arm never rests."""
    profiles = []
    for j in range(robot.n):
        home, amp, a = robot.home_rad[j], robot.excursion_rad[j], 2.0 * robot.accel_rad_s2
        # a reversal v → −v' at peak acceleration a covers (v² + v'²)/a: cap v so that a pass fits the stroke
        vmax = min(robot.speed_rad_s[j], math.sqrt(0.9 * a * amp))
        lo, hi = home - amp, home + amp
        p = Profile(home)
        direction = 1.0 if rng.random() < 0.5 else -1.0
        v = direction * min(vmax * rng.choice([0.2, 0.35, 0.5, 0.7, 0.85, 1.0]), math.sqrt(0.45 * a * amp))
        p.ramp(v, a)  # the first pass starts at home: half a stroke
        while p.t < duration_s + 5.0:
            target = hi if v > 0 else lo
            v_next = -math.copysign(vmax * rng.choice([0.2, 0.35, 0.5, 0.7, 0.85, 1.0]), v)
            cruise = (target - p.q - p.turn_distance(v_next, a)) / v
            p.add(max(cruise, 0.0))
            p.ramp(v_next, a)
            v = v_next
        profiles.append(p)
    return _stack(profiles, _grid(duration_s))


def point_to_point(robot: RobotSpec, duration_s: float, rng: np.random.Generator) -> Motion:
    """Synchronised point-to-point moves of all joints to random targets in home ± excursion (trapezoid speed
    profiles, 0.8 s raised-cosine ramps, common cruise time), each followed by a rest of 0.6–1.5 s."""
    n = robot.n
    profiles = [Profile(h) for h in robot.home_rad]
    pos = np.array(robot.home_rad, float)
    Ta = 0.8
    rest = 0.5
    for p in profiles:
        p.add(rest)
    while profiles[0].t < duration_s:
        target = np.array(robot.home_rad) + np.array(robot.excursion_rad) * rng.uniform(-1, 1, n)
        D = target - pos
        Tc = max(0.3, float(np.max(np.abs(D) / np.array(robot.speed_rad_s) - Ta)))
        v = D / (Ta + Tc)
        v = np.where(np.abs(2 * v / Ta) > robot.accel_rad_s2 * 1.5, np.sign(v) * robot.accel_rad_s2 * Ta * 0.75, v)
        hold = float(rng.uniform(0.6, 1.5))
        for j, p in enumerate(profiles):
            p.add(Ta, v[j])
            p.add(Tc)
            p.add(Ta, -v[j])
            p.add(hold)
        pos = np.array([p.q for p in profiles])
    return _stack(profiles, _grid(duration_s))


def constant_speed(robot: RobotSpec, duration_s: float, rng: np.random.Generator,
                   joints: tuple[int, ...] = (1, 2)) -> Motion:
    """Seed 000's experiment: **one joint at a time** (the others hold still), reciprocating at constant speeds
    (0.08, 0.2, 0.4 rad/s; short 2.5 rad/s² ramps) with 0.5 s rests at each end; the joints in ``joints`` in turn,
    each getting an equal share of the duration (its stroke sized to fit)."""
    profiles = [Profile(h) for h in robot.home_rad]
    share = duration_s / len(joints)
    speeds = (0.08, 0.2, 0.4)
    a = 2.5
    rest = 0.5
    for jj in joints:
        # time per stroke at v: D/v + (ramps ≈ v/a) + rest; solve D for the share
        fixed = sum(2 * (2 * v / a + rest) for v in speeds) + 1.0
        D = min(2 * robot.excursion_rad[jj], (share - fixed) / sum(2.0 / v for v in speeds))
        sign = 1.0 if rng.random() < 0.5 else -1.0
        start_t = profiles[jj].t
        for p in profiles:  # everyone waits until this joint's turn
            p.add(start_t - p.t)
        p = profiles[jj]
        # start from home − D/2 (sign): move there slowly first
        pre = -sign * D / 2
        if abs(pre) > 1e-9:
            vv = math.copysign(0.2, pre)
            p.add(2 * 0.2 / a, vv)
            p.add(max(abs(pre) / 0.2 - 2 * 0.2 / a, 0.0))
            p.add(2 * 0.2 / a, -vv)
            p.add(rest)
        for v in speeds:
            for s in (sign, -sign):
                Tr = 2 * v / a
                p.add(Tr, s * v)
                p.add(max(D / v - Tr, 0.0))
                p.add(Tr, -s * v)
                p.add(rest)
        for q in profiles:
            q.add(p.t - q.t)
    return _stack(profiles, _grid(duration_s))


def fourier_series(robot: RobotSpec, duration_s: float, rng: np.random.Generator, harmonics: int = 5,
                   period_s: float = 10.0) -> Motion:
    """Swevers' finite Fourier series per joint, Δq_j(t) = Σ_k a_jk/(kω)·sin(kωt) − b_jk/(kω)·cos(kωt) (ω = 2π/10 s,
    5 harmonics, random coefficients) scaled into the excursion, speed and acceleration caps, faded in and out over
    2 s by a quintic window w(t) (q = home + w·Δq, derivatives by the product rule), so the log starts and ends at
    rest."""
    t = _grid(duration_s)
    w0 = 2 * math.pi / period_s
    n = robot.n
    q = np.empty((t.size, n))
    dq = np.empty_like(q)
    ddq = np.empty_like(q)
    # window: quintic smoothstep up over [0, Tw] and down over [D − Tw, D]
    Tw = 2.0

    def smooth(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        x = np.clip(x, 0, 1)
        return (10 * x ** 3 - 15 * x ** 4 + 6 * x ** 5, (30 * x ** 2 - 60 * x ** 3 + 30 * x ** 4),
                (60 * x - 180 * x ** 2 + 120 * x ** 3))

    u1, du1, ddu1 = smooth(t / Tw)
    u2, du2, ddu2 = smooth((duration_s - t) / Tw)
    w = u1 * u2
    dw = du1 / Tw * u2 - u1 * du2 / Tw
    ddw = ddu1 / Tw ** 2 * u2 - 2 * du1 * du2 / Tw ** 2 + u1 * ddu2 / Tw ** 2
    for j in range(n):
        k = np.arange(1, harmonics + 1)
        a = rng.normal(0, 1, harmonics) / k
        b = rng.normal(0, 1, harmonics) / k
        ph = np.outer(t, k * w0)
        x = (np.sin(ph) * (a / (k * w0)) - np.cos(ph) * (b / (k * w0))).sum(1)
        dx = (np.cos(ph) * a + np.sin(ph) * b).sum(1)
        ddx = (-np.sin(ph) * (a * k * w0) + np.cos(ph) * (b * k * w0)).sum(1)
        x -= x.mean()
        s = min(robot.excursion_rad[j] / np.abs(x).max(), robot.speed_rad_s[j] / np.abs(dx).max(),
                robot.accel_rad_s2 / np.abs(ddx).max())
        x, dx, ddx = s * x, s * dx, s * ddx
        q[:, j] = robot.home_rad[j] + w * x
        dq[:, j] = dw * x + w * dx
        ddq[:, j] = ddw * x + 2 * dw * dx + w * ddx
    return Motion(t, q, dq, ddq)


EXCITATIONS = ("trapezoid", "fourier", "ptp", "constant_speed")


def build_motion(kind: str, robot: RobotSpec, duration_s: float, rng: np.random.Generator,
                 joints: tuple[int, ...] | None = None) -> Motion:
    if kind == "trapezoid":
        return trapezoid_passes(robot, duration_s, rng)
    if kind == "fourier":
        return fourier_series(robot, duration_s, rng)
    if kind == "ptp":
        return point_to_point(robot, duration_s, rng)
    if kind == "constant_speed":
        return constant_speed(robot, duration_s, rng, joints or (1, 2))
    raise ValueError(f"excitation: expected one of {', '.join(EXCITATIONS)}, got {kind!r}")


# ------------------------------------------------------------------------------------------ effects


@dataclass
class Context:
    """What effect terms are computed from (truth grid): the motion, the truth's rigid-body torques, the joints."""

    motion: Motion
    joints: tuple[JointTruth, ...]
    G_Nm: np.ndarray  # (T, n) gravity torque of the truth model (payload included)
    tau_rb_Nm: np.ndarray  # (T, n) M q̈ + C q̇ + G of the truth model


class Effect:
    """A physical effect the truth has and the belief lacks. ``name``: the dragd catalogue effect that should be
    named for it; ``joints``: 0-based joint indices it acts on (empty: all joints / shared)."""

    name = ""
    joints: tuple[int, ...] = ()
    reported_only = False  # the effect is in the sensor/drive reading only, not in the delivered torque

    def torque_Nm(self, ctx: Context) -> np.ndarray | None:
        """(T, n) extra joint torque that the motor must deliver (divided by the true K_t into current)."""
        return None

    def current_A(self, ctx: Context, friction_A: np.ndarray) -> np.ndarray | None:
        """(T, n) extra current in the reported current (``friction_A``: the truth's friction current)."""
        return None

    def describe(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)  # type: ignore[call-overload]
        d["joints"] = [f"joint{j + 1}" for j in self.joints]
        return {"effect": self.name, "class": type(self).__name__, **d}


def _sign(v: np.ndarray) -> np.ndarray:
    """Exact sign of a velocity, 0 at rest (|v| < 1e-6 rad/s)."""
    return np.where(np.abs(v) < 1e-6, 0.0, np.sign(v))


@dataclass
class ViscousFriction(Effect):
    """Extra viscous friction the belief lacks: I = F_v,s·q̇ [A], F_v per direction [A·s/rad]."""

    joints: tuple[int, ...] = (1,)
    pos_A_s_per_rad: float = 0.6
    neg_A_s_per_rad: float = 0.6
    name = "viscous_friction"

    def current_A(self, ctx, friction_A):
        out = np.zeros_like(ctx.motion.dq)
        for j in self.joints:
            v = ctx.motion.dq[:, j]
            out[:, j] = np.where(v > 0, self.pos_A_s_per_rad, self.neg_A_s_per_rad) * v
        return out


@dataclass
class StribeckHump(Effect):
    """A Stribeck hump the belief lacks (boundary lubrication): I = s·ΔF_s·exp(−(|q̇|/v_s)^δ) [A], ΔF_s = static −
    Coulomb level [A], v_s [rad/s], δ. (The truth's own narrow hump of the joint, v_s 0.02–0.03, stays in both.)"""

    joints: tuple[int, ...] = (1,)
    hump_A: float = 0.35
    velocity_rad_s: float = 0.1
    exponent: float = 1.0
    name = "stribeck"

    def current_A(self, ctx, friction_A):
        out = np.zeros_like(ctx.motion.dq)
        for j in self.joints:
            v = ctx.motion.dq[:, j]
            out[:, j] = _sign(v) * self.hump_A * np.exp(-(np.abs(v) / self.velocity_rad_s) ** self.exponent)
        return out


@dataclass
class PositionRipple(Effect):
    """Position-periodic torque ripple (gear meshing, cogging): τ = A·sin(c·q + φ) [N·m], c cycles per joint
    revolution, φ [rad]."""

    joints: tuple[int, ...] = (2,)
    amplitude_Nm: float = 0.5
    cycles_per_rev: float = 24.0
    phase_rad: float = 0.7
    name = "position_periodic"

    def torque_Nm(self, ctx):
        out = np.zeros_like(ctx.motion.q)
        for j in self.joints:
            out[:, j] = self.amplitude_Nm * np.sin(self.cycles_per_rev * ctx.motion.q[:, j] + self.phase_rad)
        return out


@dataclass
class LoadFriction(Effect):
    """Load-dependent (gear mesh) friction: τ = μ·|G_j(q)|·sign(q̇) [N·m], μ [N·m per N·m of gravity load]."""

    joints: tuple[int, ...] = (1,)
    coefficient: float = 0.04
    name = "load_dependent_friction"

    def torque_Nm(self, ctx):
        out = np.zeros_like(ctx.motion.q)
        for j in self.joints:
            out[:, j] = self.coefficient * np.abs(ctx.G_Nm[:, j]) * _sign(ctx.motion.dq[:, j])
        return out


@dataclass
class MissingDynamics(Effect):
    """The belief has no dynamics at all (no ``armature_kgm2``: dragd then models G/K_t + friction only), while the
    truth has M(q)q̈ + C q̇ and the rotor inertia J_a q̈: the whole (τ_rb − G + J_a q̈)/K_t is missing. Nothing to
    add to the truth; ``edit_belief`` drops the armature."""

    name = "inertia"

    def edit_belief(self, belief: dict[str, Any]) -> None:
        for jp in belief["joints"].values():
            jp["effects"]["armature_kgm2"] = None


@dataclass
class TemperatureDrift(Effect):
    """Warm-up of the gear lubricant: the joint temperature rises as ΔT(t) = ΔT∞·(1 − e^(−t/τ_th)) [K]; viscous
    friction falls as e^(−β·ΔT) (β [1/K], grease viscosity), the Coulomb/Stribeck levels by (1 − γ·ΔT) (γ [1/K]).
    The extra current is I_f,warm(q̇, t) − I_f,cold(q̇)."""

    joints: tuple[int, ...] = (1,)
    delta_T_K: float = 25.0
    time_constant_s: float = 20.0
    viscous_per_K: float = 0.015
    coulomb_per_K: float = 0.006
    name = "temperature_drift"

    def current_A(self, ctx, friction_A):
        out = np.zeros_like(ctx.motion.dq)
        t = ctx.motion.t
        dT = self.delta_T_K * (1.0 - np.exp(-t / self.time_constant_s))
        for j in self.joints:
            jt = ctx.joints[j]
            v = ctx.motion.dq[:, j]
            visc = np.where(v > 0, jt.viscous_pos_A_s_per_rad, jt.viscous_neg_A_s_per_rad) * v
            levels = friction_A[:, j] - visc
            out[:, j] = visc * (np.exp(-self.viscous_per_K * dT) - 1.0) + levels * (-self.coulomb_per_K * dT)
        return out


@dataclass
class BackEmf(Effect):
    """Voltage headroom of the current loop: above the knee speed the PWM saturates (supply − R·i − k_e·n·|q̇| < 0)
    and the winding current falls short of the loop's reference — which the drive reports — by
    k_e·n/R·(|q̇| − knee)·sign q̇. Prescribed motion: the delivered current is what the motion needs, so the
    *reported* current exceeds it by that amount. k_e [V·s/rad, motor side], n the gear ratio, R [Ω]."""

    joints: tuple[int, ...] = (1,)
    ke_V_s_per_rad: float = 0.005
    winding_ohm: float = 1.0
    knee_rad_s: float = 0.3
    name = "back_emf"
    reported_only = True

    def slope_A_s_per_rad(self, jt: JointTruth) -> float:
        return self.ke_V_s_per_rad * jt.gear_ratio / self.winding_ohm

    def current_A(self, ctx, friction_A):
        out = np.zeros_like(ctx.motion.dq)
        for j in self.joints:
            v = ctx.motion.dq[:, j]
            out[:, j] = self.slope_A_s_per_rad(ctx.joints[j]) * np.maximum(np.abs(v) - self.knee_rad_s, 0.0) * _sign(v)
        return out


@dataclass
class CurrentOffset(Effect):
    """Hall-sensor offset: the reported current = delivered + I₀ [A], at rest and in both directions."""

    joints: tuple[int, ...] = (3,)
    offset_A: float = 0.08
    name = "current_offset"
    reported_only = True

    def current_A(self, ctx, friction_A):
        out = np.zeros_like(ctx.motion.dq)
        for j in self.joints:
            out[:, j] = self.offset_A
        return out


@dataclass
class Payload(Effect):
    """A payload on the flange the URDF lacks: a solid sphere of ``mass_kg`` and ``radius_m`` centred at
    ``com_flange_m`` in the flange frame, added to the truth's Pinocchio model (its gravity and dynamics enter
    τ_rb on every joint)."""

    mass_kg: float = 1.5
    com_flange_m: tuple[float, float, float] = (0.0, 0.0, 0.06)
    radius_m: float = 0.04
    name = "payload_mass"


@dataclass
class Backlash(Effect):
    """A play of width b [rad] between rotor and output on one joint; the output of that joint is **simulated**
    (the only exception to prescribed motion): the drive's CSP loop on the output encoder
        i = i_ff(r) + k_p·(r − q_o) + k_d·(ṙ − q̇_o)                                              [A]
    (i_ff: the rigid model's current along the reference r — the truth's, so without the play q_o = r),
        rotor:   J_a·q̈_r = K_t·i − (1 − φ)·K_t·I_f(q̇_r) − τ_c
        output:  M_jj(r)·q̈_o = τ_c − φ·K_t·I_f(q̇_o) − h_j(r, ṙ, r̈)                              [N·m]
    with τ_c = k_c·(δ ∓ b/2) + c_c·(q̇_r − q̇_o) when the dead zone δ = q_r − q_o is outside ±b/2 (compressive only),
    else 0 (tooth stiffness k_c [N·m/rad], damping c_c [N·m·s/rad]); φ the output's share of the friction; h_j the
    rest of the rigid-body torque (gravity, Coriolis, the other joints' accelerations) along the reference.
    Semi-implicit Euler at 10 kHz; the reported current is i. The other joints follow the reference (the play's
    joint deviates by mrad: its effect on their torques is neglected)."""

    joints: tuple[int, ...] = (0,)
    play_rad: float = 0.008
    output_friction_fraction: float = 0.3
    kp_A_per_rad: float = 100.0
    kd_A_s_per_rad: float = 3.0
    tooth_stiffness_Nm_per_rad: float = 3.0e4
    tooth_damping_ratio: float = 0.3
    name = "backlash"


@dataclass
class BeliefError(Effect):
    """A wrong belief (the truth is unchanged): the params file carries value × (1 + ``relative``)."""

    joints: tuple[int, ...] = (1,)
    relative: float = 0.2

    def edit_belief(self, belief: dict[str, Any]) -> None:
        raise NotImplementedError


@dataclass
class TorqueConstantError(BeliefError):
    """The believed K_t is off: the model predicts the joint's whole torque (gravity, dynamics, rotor inertia,
    ripple) divided by K_t·(1 + relative). dragd has no such catalogue effect yet (to be named ``torque_constant``)."""

    name = "torque_constant"

    def edit_belief(self, belief):
        for j in self.joints:
            jp = belief["joints"][f"joint{j + 1}"]
            jp["torque_constant_Nm_per_A"] *= 1.0 + self.relative


@dataclass
class ViscousBeliefError(BeliefError):
    """The believed viscous slopes are off by ``relative`` (the missing current (F_v − F_v,belief)·q̇)."""

    name = "viscous_friction"

    def edit_belief(self, belief):
        for j in self.joints:
            f = belief["joints"][f"joint{j + 1}"]["friction"]
            for k in ("viscous_pos_A_s_per_rad", "viscous_neg_A_s_per_rad"):
                f[k] *= 1.0 + self.relative


@dataclass
class CoulombBeliefError(BeliefError):
    """The believed Coulomb and static levels are off by ``relative`` (a constant per direction: no catalogue effect
    represents it; expected name ``coulomb_friction``, outside dragd's catalogue)."""

    name = "coulomb_friction"

    def edit_belief(self, belief):
        for j in self.joints:
            f = belief["joints"][f"joint{j + 1}"]["friction"]
            for k in ("coulomb_pos_A", "coulomb_neg_A", "static_pos_A", "static_neg_A"):
                f[k] *= 1.0 + self.relative


EFFECT_CLASSES = {c.__name__: c for c in (ViscousFriction, StribeckHump, PositionRipple, LoadFriction, MissingDynamics,
                                          TemperatureDrift, BackEmf, CurrentOffset, Payload, Backlash,
                                          TorqueConstantError, ViscousBeliefError, CoulombBeliefError)}


# ------------------------------------------------------------------------------------------ the truth's current


def friction_current(jt: JointTruth, v: np.ndarray) -> np.ndarray:
    """I_f(v) = s·[F_c,s + (F_s,s − F_c,s)·exp(−(|v|/v_s)^δ)] + F_v,s·v  [A], exact sign (0 at rest)."""
    pos = v > 0
    fc = np.where(pos, jt.coulomb_pos_A, jt.coulomb_neg_A)
    fs = np.where(pos, jt.static_pos_A, jt.static_neg_A)
    fv = np.where(pos, jt.viscous_pos_A_s_per_rad, jt.viscous_neg_A_s_per_rad)
    hump = np.exp(-(np.abs(v) / jt.stribeck_velocity_rad_s) ** jt.stribeck_exponent)
    level = fc + (fs - fc) * hump  # signed already (negative-direction levels are negative)
    return np.where(np.abs(v) < 1e-6, 0.0, level) + fv * v


def rnea_all(model: pin.Model, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> np.ndarray:
    data = model.createData()
    out = np.empty_like(q)
    for k in range(q.shape[0]):
        out[k] = pin.rnea(model, data, q[k], dq[k], ddq[k])
    return out


def gravity_all(model: pin.Model, q: np.ndarray) -> np.ndarray:
    data = model.createData()
    out = np.empty_like(q)
    for k in range(q.shape[0]):
        out[k] = pin.computeGeneralizedGravity(model, data, q[k])
    return out


@dataclass
class Truth:
    """The truth of one case: robot, joint parameters (the stribeck-hump joints' own narrow hump removed), hidden
    effects and belief errors."""

    robot: RobotSpec
    joints: tuple[JointTruth, ...]
    effects: tuple[Effect, ...]

    def hidden(self) -> list[Effect]:
        return [e for e in self.effects if not isinstance(e, BeliefError)]

    def model(self, with_payload_effect: bool = True) -> pin.Model:
        m = load_pin_model(self.robot.urdf)
        for e in self.effects:
            if isinstance(e, Payload) and with_payload_effect:
                m = with_payload(m, e.mass_kg, flange_to_last_joint(m, np.array(e.com_flange_m)), e.radius_m)
        return m


def ideal_current(truth: Truth, motion: Motion, joints: tuple[JointTruth, ...] | None = None,
                  skip: Effect | None = None, dynamics: bool = True) -> np.ndarray:
    """The noise-free reported current (T, n) [A] of the truth along ``motion`` (prescribed), optionally with one
    effect left out (``skip``), other joint parameters (``joints``: a belief's, for the belief errors' signal) or
    without dynamics (τ = G: what a belief without dynamics predicts). The backlash joint is handled by the caller."""
    joints = joints or truth.joints
    model = truth.model(with_payload_effect=not isinstance(skip, Payload))
    G = gravity_all(model, motion.q)
    tau = rnea_all(model, motion.q, motion.dq, motion.ddq) if dynamics else G.copy()
    ctx = Context(motion, joints, G, tau)
    n = motion.q.shape[1]
    fr = np.column_stack([friction_current(joints[j], motion.dq[:, j]) for j in range(n)])
    torque = tau.copy()
    if dynamics:
        torque += motion.ddq * np.array([jt.armature_kgm2 for jt in joints])
    extra_A = np.zeros_like(fr)
    for e in truth.hidden():
        if e is skip:
            continue
        x = e.torque_Nm(ctx)
        if x is not None:
            torque += x
        y = e.current_A(ctx, fr)
        if y is not None:
            extra_A += y
    kt = np.array([jt.kt_Nm_per_A for jt in joints])
    return torque / kt + fr + extra_A


def simulate_backlash(truth: Truth, e: Backlash, ref: Motion) -> tuple[Motion, np.ndarray]:
    """The play's joint simulated along the reference (see ``Backlash``): returns the actual motion (that joint's
    column replaced by the output's) and the drive's current of that joint on the truth grid [A]."""
    j = e.joints[0]
    jt = truth.joints[j]
    model = truth.model()
    data = model.createData()
    T = ref.t.size
    M = np.empty(T)
    h = np.empty(T)
    for k in range(T):
        a = ref.ddq[k].copy()
        a[j] = 0.0
        h[k] = pin.rnea(model, data, ref.q[k], ref.dq[k], a)[j]
        M[k] = pin.crba(model, data, ref.q[k])[j, j]
    # feed-forward: the rigid current this joint delivers along the reference (the play's own effect and what only
    # the sensor adds left out)
    delivered = Truth(truth.robot, truth.joints, tuple(x for x in truth.effects if x is not e and not x.reported_only))
    i_ff = ideal_current(delivered, ref)[:, j]
    Kt, Ja, phi, b = jt.kt_Nm_per_A, jt.armature_kgm2, e.output_friction_fraction, e.play_rad / 2
    kc = e.tooth_stiffness_Nm_per_rad
    kp, kd = e.kp_A_per_rad, e.kd_A_s_per_rad
    sub = 10
    dt = 1.0 / (GRID_HZ * sub)
    r, rd = ref.q[:, j], ref.dq[:, j]
    fc_p, fc_n = jt.coulomb_pos_A, jt.coulomb_neg_A
    fv_p, fv_n = jt.viscous_pos_A_s_per_rad, jt.viscous_neg_A_s_per_rad
    eps = 1e-3  # rad/s: a smoothed sign inside the integrator (friction of a free rotor at near-zero speed)

    def fr(v: float) -> float:
        w = math.tanh(v / eps)
        return (fc_p * w + fv_p * v) if v >= 0 else (-fc_n * w + fv_n * v)

    qo, vo = float(r[0]), float(rd[0])
    qr, vr = qo, vo
    out_q = np.empty(T)
    out_v = np.empty(T)
    out_a = np.empty(T)
    out_i = np.empty(T)
    for k in range(T):
        k1 = min(k + 1, T - 1)
        out_q[k], out_v[k] = qo, vo  # the state at the grid instant (before its sub-steps)
        for s in range(sub):
            x = s / sub
            rr = r[k] + (r[k1] - r[k]) * x
            rrd = rd[k] + (rd[k1] - rd[k]) * x
            Mk = M[k] + (M[k1] - M[k]) * x
            hk = h[k] + (h[k1] - h[k]) * x
            i = i_ff[k] + (i_ff[k1] - i_ff[k]) * x + kp * (rr - qo) + kd * (rrd - vo)
            dz = qr - qo
            pen = dz - b if dz > b else (dz + b if dz < -b else 0.0)
            tc = 0.0
            if pen != 0.0:
                Jeff = Ja * Mk / (Ja + Mk)
                tc = kc * pen + 2.0 * e.tooth_damping_ratio * math.sqrt(kc * Jeff) * (vr - vo)
                if tc * pen < 0:  # teeth only push
                    tc = 0.0
            ar = (Kt * i - (1 - phi) * Kt * fr(vr) - tc) / Ja
            ao = (tc - phi * Kt * fr(vo) - hk) / Mk
            if s == 0:
                out_i[k], out_a[k] = i, ao
            vr += ar * dt
            vo += ao * dt
            qr += vr * dt
            qo += vo * dt
    actual = ref.copy()
    actual.q[:, j], actual.dq[:, j], actual.ddq[:, j] = out_q, out_v, out_a
    return actual, out_i


# ------------------------------------------------------------------------------------------ the case


@dataclass
class CaseSpec:
    """One generated case. Units in the field names; ``effects``: hidden effects and belief errors."""

    case_id: str
    robot: str = "seed_cobot"  # seed_cobot | ur5 | ur5_original_names
    excitation: str = "trapezoid"  # trapezoid | fourier | ptp | constant_speed
    rate_Hz: int = 500  # log rate (divides 1000)
    with_dq: bool = True  # the CSV has dq1..dqN (the drive's velocity)
    noise_A: float = 0.02  # Hall noise σ
    duration_s: float = 45.0
    effects: tuple[Effect, ...] = ()
    seed: int = 0
    moving_joints: tuple[int, ...] | None = None  # constant_speed: the joints moved in turn (0-based)
    description: str = ""


def robot_for(spec: CaseSpec, out_dir: Path) -> RobotSpec:
    if spec.robot == "seed_cobot":
        return seed_cobot()
    if spec.robot == "ur5":
        return ur5(out_dir, rename_joints=True)
    if spec.robot == "ur5_original_names":
        return ur5(out_dir, rename_joints=False)
    raise ValueError(f"robot: expected seed_cobot, ur5 or ur5_original_names, got {spec.robot!r}")


def truth_joints(robot: RobotSpec, effects: tuple[Effect, ...]) -> tuple[JointTruth, ...]:
    """The robot's joints; a joint with a hidden wide Stribeck hump gets static = Coulomb (one hump only)."""
    joints = list(robot.joints)
    for e in effects:
        if isinstance(e, StribeckHump):
            for j in e.joints:
                joints[j] = dataclasses.replace(joints[j], static_pos_A=joints[j].coulomb_pos_A,
                                                static_neg_A=joints[j].coulomb_neg_A)
    return tuple(joints)


def belief_params(truth: Truth, robot: RobotSpec, spec: CaseSpec) -> dict[str, Any]:
    """What the user believes, as a dragd params file (mapping): the truth's K_t, friction and rotor inertia, with
    every hidden effect absent, then the belief errors (and ``MissingDynamics``) applied."""
    joints = {}
    for j, jt in enumerate(truth.joints):
        joints[f"joint{j + 1}"] = {
            "torque_constant_Nm_per_A": jt.kt_Nm_per_A,
            "friction": {"coulomb_pos_A": jt.coulomb_pos_A, "coulomb_neg_A": jt.coulomb_neg_A,
                         "static_pos_A": jt.static_pos_A, "static_neg_A": jt.static_neg_A,
                         "stribeck_velocity_rad_s": jt.stribeck_velocity_rad_s,
                         "stribeck_exponent": jt.stribeck_exponent,
                         "viscous_pos_A_s_per_rad": jt.viscous_pos_A_s_per_rad,
                         "viscous_neg_A_s_per_rad": jt.viscous_neg_A_s_per_rad},
            "effects": {"armature_kgm2": jt.armature_kgm2},
        }
    pf = {"version": 1, "method": "belief (tests/independent/generator.py)", "robot": str(robot.urdf),
          "joints": joints, "payload": None,
          "notes": {"case": spec.case_id, "what": "the user's belief: truth minus the hidden effects, with belief "
                                                  "errors"}}
    for e in truth.effects:
        if hasattr(e, "edit_belief"):
            e.edit_belief(pf)
    return pf


def joints_from_params(pf: dict[str, Any], base: tuple[JointTruth, ...]) -> tuple[JointTruth, ...]:
    """JointTruth values as a params mapping states them (for the belief's predicted current)."""
    out = []
    for j, jt in enumerate(base):
        jp = pf["joints"][f"joint{j + 1}"]
        f = jp["friction"]
        out.append(dataclasses.replace(jt, kt_Nm_per_A=jp["torque_constant_Nm_per_A"], **{k: f[k] for k in f}))
    return tuple(out)


def config_yaml(robot: RobotSpec, pf: dict[str, Any]) -> dict[str, Any]:
    """A minimal dragd configuration for the robot whose K_t and friction are the belief's."""
    joints = []
    for j, jt in enumerate(robot.joints):
        jp = pf["joints"][f"joint{j + 1}"]
        joints.append({"name": f"joint{j + 1}", "node_id": j + 1, "gear_ratio": jt.gear_ratio,
                       "torque_constant_Nm_per_A": jp["torque_constant_Nm_per_A"],
                       "current_limit_A": jt.current_limit_A, "rated_current_A": jt.rated_current_A,
                       "encoder_counts_per_rev": jt.encoder_counts_per_rev,
                       "velocity_limit_rad_s": jt.velocity_limit_rad_s, "friction": dict(jp["friction"])})
    return {"robot": {"urdf": str(robot.urdf), "gravity_m_s2": [0.0, 0.0, -9.81]}, "joints": joints}


def lowpass(x: np.ndarray, cutoff_Hz: float, fs_Hz: float) -> np.ndarray:
    sos = butter(4, cutoff_Hz, fs=fs_Hz, output="sos")
    return sosfiltfilt(sos, x, axis=0)


def sliding_mask(dq: np.ndarray, fs_Hz: float, v: float = 0.01, guard_s: float = 0.1) -> np.ndarray:
    """(T, n): the joint above ``v`` rad/s for ± ``guard_s`` (where a residual is evaluated)."""
    from scipy.ndimage import minimum_filter1d

    g = int(round(guard_s * fs_Hz))
    return minimum_filter1d((np.abs(dq) > v).astype(np.uint8), size=2 * g + 1, axis=0, mode="constant").astype(bool)


REQUIRED_RATIO = 0.5  # a joint must be named where the missing current's 5 Hz RMS ≥ this × the Hall noise σ
# (dragd's own threshold: the held-out RMS an effect explains ≥ 0.3 σ, on 5 Hz-filtered rows)


def expected_answer(truth: Truth, spec: CaseSpec, motion: Motion, rigid: np.ndarray, reported: np.ndarray,
                    backlash_joint: int | None) -> dict[str, Any]:
    """Per effect name: the RMS per joint of the current the belief misses because of that effect (5 Hz low-pass,
    over the sliding samples: where dragd evaluates and fits; ``signal_raw_A`` unfiltered, for information) →
    ``required`` joints (≥ REQUIRED_RATIO × σ) and
    ``allowed`` joints (the effect acts there at all, RMS > 0.1 mA). ``rigid``: the truth's current along the actual
    motion with every joint rigid; ``reported``: the same with the play's joint simulated."""
    n = motion.q.shape[1]
    slide = sliding_mask(motion.dq, GRID_HZ)
    out: dict[str, Any] = {}
    for e in truth.effects:
        if isinstance(e, BeliefError):
            one = belief_params(Truth(truth.robot, truth.joints, (e,)), truth.robot, spec)
            missing = rigid - ideal_current(truth, motion, joints=joints_from_params(one, truth.joints))
        elif isinstance(e, MissingDynamics):
            missing = rigid - ideal_current(truth, motion, dynamics=False)
        elif isinstance(e, Backlash):
            missing = reported - rigid
        else:
            missing = rigid - ideal_current(truth, motion, skip=e)
        f = lowpass(missing, 5.0, GRID_HZ)
        rms = np.array([math.sqrt(float(np.mean(f[slide[:, j], j] ** 2))) if slide[:, j].any() else 0.0
                        for j in range(n)])
        acts = np.zeros(n, bool)
        if e.joints:
            acts[list(e.joints)] = True
        else:
            acts[:] = True
        acts &= slide.any(axis=0)  # a joint that never slides cannot be named
        raw = np.array([math.sqrt(float(np.mean(missing[slide[:, j], j] ** 2))) if slide[:, j].any() else 0.0
                        for j in range(n)])
        ent = out.setdefault(e.name, {"required": [], "allowed": [], "signal_A": {}, "signal_raw_A": {}})
        for j in range(n):
            nm = f"joint{j + 1}"
            ent["signal_A"][nm] = max(ent["signal_A"].get(nm, 0.0), round(float(rms[j]), 5))
            ent["signal_raw_A"][nm] = max(ent["signal_raw_A"].get(nm, 0.0), round(float(raw[j]), 5))
            if acts[j] and rms[j] >= REQUIRED_RATIO * spec.noise_A and nm not in ent["required"]:
                ent["required"].append(nm)
            if acts[j] and rms[j] > 1e-4 and nm not in ent["allowed"]:
                ent["allowed"].append(nm)
    for ent in out.values():
        ent["required"].sort()
        ent["allowed"].sort()
    return out


def _quantise(x: np.ndarray, q: float | np.ndarray) -> np.ndarray:
    return np.round(x / q) * q


def generate(spec: CaseSpec, out_dir: str | Path) -> dict[str, Any]:
    """Write the case's ``log.csv``, ``belief.yaml``, ``config.yaml`` and ``truth.json`` into ``out_dir``; return
    the truth.json mapping (with ``expected``)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if GRID_HZ % spec.rate_Hz:
        raise ValueError(f"rate_Hz: expected a divisor of {GRID_HZ}, got {spec.rate_Hz}")
    ss = np.random.SeedSequence(spec.seed)
    rng_traj, rng_noise = (np.random.default_rng(s) for s in ss.spawn(2))
    robot = robot_for(spec, out)
    truth = Truth(robot, truth_joints(robot, spec.effects), tuple(spec.effects))
    ref = build_motion(spec.excitation, robot, spec.duration_s, rng_traj, spec.moving_joints)
    motion = ref
    bl = [e for e in spec.effects if isinstance(e, Backlash)]
    backlash_joint = None
    if bl:
        backlash_joint = bl[0].joints[0]
        for e in spec.effects:
            if e is not bl[0] and backlash_joint in e.joints and not e.reported_only:
                raise ValueError(f"{spec.case_id}: the play's joint may carry only reported-current effects "
                                 f"(offset, back-EMF), not {e.name}")
        motion, i_drive = simulate_backlash(truth, bl[0], ref)
    rigid = ideal_current(truth, motion)  # every joint rigid, along the actual motion
    reported = rigid.copy()
    if bl:
        j = backlash_joint
        ctx = Context(motion, truth.joints, np.zeros_like(motion.q), np.zeros_like(motion.q))
        on_top = sum((e.current_A(ctx, np.zeros_like(motion.q))[:, j] for e in spec.effects
                      if e.reported_only), np.zeros(motion.t.size))
        reported[:, j] = i_drive + on_top  # the drive's current, and what the sensor adds to it
    pf = belief_params(truth, robot, spec)
    expected = expected_answer(truth, spec, motion, rigid, reported, backlash_joint)

    # --- the log at its rate: encoder counts, Hall noise, per-mille quantisation
    step = GRID_HZ // spec.rate_Hz
    idx = np.arange(0, motion.t.size, step)
    n = robot.n
    counts = np.array([2 * math.pi / jt.encoder_counts_per_rev for jt in robot.joints])
    quantum = np.array([jt.rated_current_A / 1000.0 for jt in robot.joints])
    q_log = _quantise(motion.q[idx], counts)
    i_log = _quantise(reported[idx] + rng_noise.normal(0.0, spec.noise_A, (idx.size, n)), quantum)
    cols = [motion.t[idx][:, None], q_log, i_log]
    header = ["t"] + [f"q{k + 1}" for k in range(n)] + [f"i{k + 1}" for k in range(n)]
    if spec.with_dq:  # the drive's velocity: the encoder's, 1 mrad/s white noise
        dq_log = motion.dq[idx] + rng_noise.normal(0.0, 1e-3, (idx.size, n))
        cols.append(dq_log)
        header += [f"dq{k + 1}" for k in range(n)]
    data = np.hstack(cols)
    fmt = ["%.4f"] + ["%.7f"] * n + ["%.4f"] * n + (["%.5f"] * n if spec.with_dq else [])
    np.savetxt(out / "log.csv", data, delimiter=",", header=",".join(header), comments="", fmt=fmt)

    cfg = config_yaml(robot, pf)
    if robot.joint_names:  # the files name the joints as the URDF does (the CSV's columns stay q1..qN)
        pf, cfg, expected = (rename_joints(x, robot.joint_names) for x in (pf, cfg, expected))
    (out / "belief.yaml").write_text(yaml.safe_dump(pf, sort_keys=False))
    (out / "config.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    peak = np.abs(reported).max(axis=0)
    info = {
        "case_id": spec.case_id, "description": spec.description, "robot": robot.name, "urdf": str(robot.urdf),
        "pass_robot_flag": robot.pass_robot_flag, "excitation": spec.excitation, "rate_Hz": spec.rate_Hz,
        "with_dq": spec.with_dq, "noise_A": spec.noise_A, "duration_s": spec.duration_s, "seed": spec.seed,
        "effects": [e.describe() for e in spec.effects],
        "truth_joints": {f"joint{j + 1}": dataclasses.asdict(jt) for j, jt in enumerate(truth.joints)},
        "expected": expected,
        "peak_current_A": {f"joint{j + 1}": round(float(peak[j]), 3) for j in range(n)},
        "over_current_limit": [f"joint{j + 1}" for j in range(n) if peak[j] > robot.joints[j].current_limit_A],
        "max_speed_rad_s": {f"joint{j + 1}": round(float(np.abs(motion.dq[:, j]).max()), 3) for j in range(n)},
        "range_rad": {f"joint{j + 1}": [round(float(motion.q[:, j].min()), 3), round(float(motion.q[:, j].max()), 3)]
                      for j in range(n)},
    }
    (out / "truth.json").write_text(json.dumps(info, indent=1))
    return info


def spec_to_json(spec: CaseSpec) -> dict[str, Any]:
    d = {k: getattr(spec, k) for k in ("case_id", "robot", "excitation", "rate_Hz", "with_dq", "noise_A",
                                        "duration_s", "seed", "moving_joints", "description")}
    d["effects"] = [e.describe() for e in spec.effects]
    return d


__all__ = ["CaseSpec", "generate", "EFFECT_CLASSES", "EXCITATIONS", "NAMES_NOT_IN_CATALOGUE", "seed_cobot", "ur5"]
