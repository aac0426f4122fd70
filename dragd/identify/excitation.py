"""Excitation trajectories ("plans") for identification, within joint position/velocity/acceleration limits.

A :class:`Plan` is a sampled joint trajectory (``t_s`` from 0, ``q_rad`` N×n) plus labelled segments; it is
saved as ``.npz`` (arrays ``t_s``, ``q_rad``, ``segments`` JSON) — the file the daemon's ``track`` command and
``python -m sim log`` read. Every plan starts and ends at rest.

Kinds (each after its seed paper):

* ``lowspeed`` (seed 000 §4.1): one joint at a time reciprocates at ≤ 2°/s with spline (cosine) velocity blends
  at start and reversal, ~100 s per joint, the other joints held; the method samples it at 10 ms.
* ``symmetric`` (seed 001 §4.1): all joints start and stop together on linear segments with parabolic blends,
  each pass A→B followed by B→A at the same speeds — every position is crossed in both directions at the same
  constant speed, what the half-sum/half-difference extraction needs.
* ``friction`` (seed 001 §4.2, Table VI): one joint at a time, forward/backward passes at a ladder of constant
  speeds with fine steps at low speed.
* ``synchronous`` (seed 002 §3.2–3.3): one joint at a time reciprocates ±45° with uniform acceleration and
  deceleration at several speeds, in two poses (the next joint straight / bent 90°).
* ``fourier`` (Swevers et al.): a periodic band-limited trajectory q(t) = q₀ + Σₗ aₗ/(lω) sin(lωt) − bₗ/(lω) cos(lωt)
  whose coefficients are optimised for the condition number of the per-joint base regressors (rigid body +
  armature + friction), starting and ending each period at rest; for the full-dynamics method.
* ``gap`` (``dragd gap``, docs/GAP.md): all joints together over the same span, A→B→A at several speeds in several
  gravity poses — every joint slides at each speed through the same positions in both directions.
* ``standard``: synchronous + symmetric + friction (what ``auto`` identification wants), ``all``: every kind.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dragd.identify import PLAN_KINDS

DEG = math.pi / 180.0


class PlanError(ValueError):
    """A plan that cannot be built or loaded; the message names what is wrong."""


@dataclass
class Segment:
    kind: str
    t0_s: float
    t1_s: float
    joint: int | None = None  # 0-based joint index for single-joint segments
    speed_rad_s: float | None = None
    note: str = ""


@dataclass
class Limits:
    """Per-joint bounds the plan stays within (position with margin, speed, acceleration)."""

    lower_rad: np.ndarray
    upper_rad: np.ndarray
    velocity_rad_s: np.ndarray
    acceleration_rad_s2: np.ndarray
    names: tuple[str, ...] = ()  # the robot's joint names (URDF order), for messages

    @classmethod
    def from_model(cls, model: Any, cfg: Any | None = None, margin_rad: float = 0.15,
                   acceleration_rad_s2: float = 1.5, velocity_scale: float = 0.9) -> Limits:
        """URDF limits, narrowed by a configuration's soft limits and speed caps, minus ``margin_rad``."""
        lo, hi = model.position_limits_rad
        vel = np.array(model.model.velocityLimit, dtype=float)
        vel[~np.isfinite(vel) | (vel <= 0)] = 1.0
        if cfg is not None:
            for i, j in enumerate(cfg.joints):
                if j.position_limits_rad is not None:
                    lo[i], hi[i] = max(lo[i], j.position_limits_rad[0]), min(hi[i], j.position_limits_rad[1])
                vel[i] = min(vel[i], j.velocity_limit_rad_s)
            margin_rad = margin_rad + cfg.safety.soft_limit_margin_rad
        n = lo.shape[0]
        return cls(lo + margin_rad, hi - margin_rad, vel * velocity_scale, np.full(n, float(acceleration_rad_s2)),
                   tuple(getattr(model, "joint_names", ())))

    def label(self, i: int) -> str:
        """Joint ``i``'s name (the URDF's), or its number when the limits carry no names."""
        return self.names[i] if i < len(self.names) else f"joint #{i + 1}"

    @property
    def n(self) -> int:
        return int(self.lower_rad.shape[0])

    def clip(self, q: np.ndarray) -> np.ndarray:
        return np.minimum(np.maximum(q, self.lower_rad), self.upper_rad)


@dataclass
class Plan:
    t_s: np.ndarray
    q_rad: np.ndarray
    segments: list[Segment] = field(default_factory=list)
    name: str = "plan"
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1])

    @property
    def n(self) -> int:
        return int(self.q_rad.shape[1])

    def derivatives(self) -> tuple[np.ndarray, np.ndarray]:
        """Velocity and acceleration of the sampled plan (central differences)."""
        dq = np.gradient(self.q_rad, self.t_s, axis=0)
        return dq, np.gradient(dq, self.t_s, axis=0)

    def check(self, limits: Limits, tol: float = 1.02) -> list[str]:
        """Violations of ``limits`` (empty when the plan is within them)."""
        out = []
        dq, ddq = self.derivatives()
        for i in range(self.n):
            name = limits.label(i)
            lo, hi = self.q_rad[:, i].min(), self.q_rad[:, i].max()
            if lo < limits.lower_rad[i] - 1e-9 or hi > limits.upper_rad[i] + 1e-9:
                out.append(f"{name}: position [{lo:.3f}, {hi:.3f}] rad outside [{limits.lower_rad[i]:.3f}, "
                           f"{limits.upper_rad[i]:.3f}]")
            v = np.abs(dq[:, i]).max()
            if v > limits.velocity_rad_s[i] * tol:
                out.append(f"{name}: speed {v:.3f} rad/s above {limits.velocity_rad_s[i]:.3f}")
            a = np.abs(ddq[:, i]).max()
            if a > limits.acceleration_rad_s2[i] * tol * 1.5:  # sampled parabolic blends: a step is smeared
                out.append(f"{name}: acceleration {a:.3f} rad/s² above {limits.acceleration_rad_s2[i]:.3f}")
        return out

    def save(self, path: str | Path) -> None:
        np.savez(path, t_s=self.t_s, q_rad=self.q_rad, name=np.array(self.name),
                 segments=np.array(json.dumps([asdict(s) for s in self.segments])),
                 info=np.array(json.dumps(self.info)))

    @classmethod
    def load(cls, path: str | Path) -> Plan:
        path = Path(path)
        if not path.is_file():
            raise PlanError(f"plan {path}: file not found")
        try:
            with np.load(path, allow_pickle=False) as z:
                t, q = np.asarray(z["t_s"], float), np.asarray(z["q_rad"], float)
                segs = json.loads(str(z["segments"])) if "segments" in z else []
                name = str(z["name"]) if "name" in z else path.stem
                info = json.loads(str(z["info"])) if "info" in z else {}
        except (KeyError, ValueError, OSError) as exc:
            raise PlanError(f"plan {path}: expected an .npz with t_s and q_rad: {exc}") from None
        if t.ndim != 1 or q.ndim != 2 or q.shape[0] != t.shape[0] or t.shape[0] < 2:
            raise PlanError(f"plan {path}: expected t_s (N,) and q_rad (N, joints), got {t.shape} and {q.shape}")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(q))):
            raise PlanError(f"plan {path}: t_s and q_rad must be finite")
        if t[0] != 0.0 or np.any(np.diff(t) <= 0):
            raise PlanError(f"plan {path}: t_s must start at 0 and increase strictly")
        return cls(t, q, [Segment(**s) for s in segs], name, info)

    def shifted(self, segments_offset_s: float) -> list[Segment]:
        return [Segment(**{**asdict(s), "t0_s": s.t0_s + segments_offset_s, "t1_s": s.t1_s + segments_offset_s})
                for s in self.segments]


# ------------------------------------------------------------------------------------------ profiles


def _profile(T: float, tb: float, dt: float, blend: str) -> tuple[np.ndarray, np.ndarray]:
    """Normalised path s(t) ∈ [0, 1] over [0, T] with blends of ``tb`` at both ends (cruise in between).

    ``parabolic``: constant acceleration in the blends (trapezoidal velocity, seed 001/002);
    ``cosine``: velocity rises as (1 − cos)/2 (a spline blend without acceleration steps, seed 000).
    """
    n = max(2, int(math.ceil(T / dt)) + 1)
    t = np.linspace(0.0, T, n)
    c = T - tb  # cruise end; peak rate 1/c
    sd = 1.0 / c
    s = np.empty(n)
    a = t < tb
    d = t > c
    m = ~(a | d)
    if blend == "parabolic":
        s[a] = sd * t[a] ** 2 / (2 * tb)
        s[d] = 1.0 - sd * (T - t[d]) ** 2 / (2 * tb)
    else:
        s[a] = sd * (t[a] / 2 - tb / (2 * math.pi) * np.sin(math.pi * t[a] / tb))
        u = T - t[d]
        s[d] = 1.0 - sd * (u / 2 - tb / (2 * math.pi) * np.sin(math.pi * u / tb))
    s[m] = sd * (t[m] - tb / 2)
    return t, s


def _timing(D: np.ndarray, vmax: np.ndarray, amax: np.ndarray, speed: float | None, blend: str) -> tuple[float, float]:
    """(T, tb) of a synchronised move by D: the lead joint at ``speed`` (default: its limit), all within limits."""
    ad = np.abs(D)
    if ad.max() < 1e-12:
        return 0.0, 0.0
    v = vmax.copy() if speed is None else np.minimum(vmax, speed)
    k = 2.0 if blend == "cosine" else 1.0  # a cosine blend peaks at twice the mean acceleration
    c = float(np.max(ad / v))
    tb = float(np.max(k * ad / (amax * c)))
    if tb > c:
        c = tb = float(np.sqrt(np.max(k * ad / amax)))
    return c + tb, tb


class PlanBuilder:
    """Appends moves to a sampled trajectory; each move starts where the last ended, at rest."""

    def __init__(self, q_start: np.ndarray, limits: Limits, dt_s: float = 0.005) -> None:
        self.limits = limits
        self.dt = dt_s
        self.q = np.asarray(q_start, dtype=float).copy()
        if self.q.shape[0] != limits.n:
            raise PlanError(f"plan: start pose has {self.q.shape[0]} joints, the robot {limits.n}")
        bad = np.nonzero((self.q < limits.lower_rad - 1e-9) | (self.q > limits.upper_rad + 1e-9))[0]
        if bad.size:
            raise PlanError("plan: start pose outside the identification limits (soft limits minus margin) at "
                            + ", ".join(f"{limits.label(i)} = {self.q[i]:.3f} rad not in [{limits.lower_rad[i]:.3f}, "
                                        f"{limits.upper_rad[i]:.3f}]" for i in bad.tolist()))
        self.t_parts: list[np.ndarray] = [np.zeros(1)]
        self.q_parts: list[np.ndarray] = [self.q[None, :].copy()]
        self.t = 0.0
        self.segments: list[Segment] = []

    def _append(self, t_rel: np.ndarray, q: np.ndarray) -> None:
        self.t_parts.append(self.t + t_rel[1:])
        self.q_parts.append(q[1:])
        self.t += float(t_rel[-1])
        self.q = q[-1].copy()

    def hold(self, seconds: float) -> None:
        if seconds <= 0:
            return
        t = np.linspace(0.0, seconds, max(2, int(math.ceil(seconds / self.dt)) + 1))
        self._append(t, np.tile(self.q, (t.shape[0], 1)))

    def move(self, target: np.ndarray, speed: float | None = None, blend: str = "parabolic",
             acceleration: float | None = None, kind: str | None = None, joint: int | None = None,
             note: str = "") -> None:
        """Synchronised move to ``target``: all joints start and stop together, the lead at ``speed``."""
        target = self.limits.clip(np.asarray(target, dtype=float))
        D = target - self.q
        amax = self.limits.acceleration_rad_s2 if acceleration is None else np.minimum(
            self.limits.acceleration_rad_s2, acceleration)
        T, tb = _timing(D, self.limits.velocity_rad_s, amax, speed, blend)
        if T <= 0:
            return
        t, s = _profile(T, tb, self.dt, blend)
        t0 = self.t
        self._append(t, self.q + s[:, None] * D[None, :])
        if kind is not None:
            lead = float(np.max(np.abs(D)) / (T - tb))
            self.segments.append(Segment(kind, t0, self.t, joint, lead if joint is None else abs(D[joint]) / (T - tb),
                                         note))

    def transition(self, target: np.ndarray) -> None:
        """A moderate-speed move between segments (labelled ``transition``: estimators may ignore it)."""
        self.move(target, speed=0.5, blend="cosine", kind="transition")
        self.hold(0.3)

    def build(self, name: str, info: dict[str, Any] | None = None) -> Plan:
        self.hold(0.5)
        t = np.concatenate(self.t_parts)
        q = np.concatenate(self.q_parts)
        # resample on the plan grid (segments were sampled each with its own step)
        grid = np.arange(0.0, t[-1] + self.dt / 2, self.dt)
        grid[-1] = min(grid[-1], t[-1])
        qg = np.column_stack([np.interp(grid, t, q[:, i]) for i in range(q.shape[1])])
        return Plan(grid, qg, self.segments, name, dict(info or {}))


# ------------------------------------------------------------------------------------------ kinds


def _range(limits: Limits, j: int, center: float, half: float) -> tuple[float, float]:
    """[lo, hi] of width up to 2·half around ``center`` within the joint's limits (shifted, then clipped)."""
    lo, hi = center - half, center + half
    if lo < limits.lower_rad[j]:
        hi += limits.lower_rad[j] - lo
        lo = limits.lower_rad[j]
    if hi > limits.upper_rad[j]:
        lo -= hi - limits.upper_rad[j]
        hi = limits.upper_rad[j]
    return max(lo, limits.lower_rad[j]), min(hi, limits.upper_rad[j])


def _joints(n: int, joints: list[int] | None) -> list[int]:
    js = list(range(n)) if not joints else [j - 1 for j in joints]
    bad = [j + 1 for j in js if not 0 <= j < n]
    if bad:
        raise PlanError(f"plan: --joints: expected joint numbers 1..{n}, got {bad}")
    return js


def add_lowspeed(b: PlanBuilder, joints: list[int], speed_deg_s: float = 2.0, seconds_per_joint: float = 100.0,
                 blend_s: float = 2.0, cycles: int = 2) -> None:
    """Seed 000: reciprocating single-joint motion at ≤ ``speed_deg_s`` with cosine (spline) blends."""
    home = b.q.copy()
    v = speed_deg_s * DEG
    for j in joints:
        pass_s = seconds_per_joint / (2 * cycles)
        half = max(0.5 * v * (pass_s - blend_s), 2 * DEG)
        lo, hi = _range(b.limits, j, home[j], half)
        start = home.copy()
        start[j] = lo
        b.transition(start)
        for _ in range(cycles):
            for end in (hi, lo):
                tgt = b.q.copy()
                tgt[j] = end
                b.move(tgt, speed=v, blend="cosine", acceleration=v / blend_s * 2, kind="lowspeed", joint=j)
        b.hold(0.5)
    b.transition(home)


def add_symmetric(b: PlanBuilder, passes: int = 8, speed: float = 0.2, amplitude: float = 0.8,
                  rng: np.random.Generator | None = None, repeats: int = 1) -> None:
    """Seed 001 gravity: A→B→A passes of all joints together (linear + parabolic blends), same speeds both ways."""
    rng = rng or np.random.default_rng(5)
    home = b.q.copy()
    L = b.limits
    for k in range(passes):
        a = np.empty(L.n)
        z = np.empty(L.n)
        for j in range(L.n):
            lo, hi = _range(L, j, home[j], amplitude)
            span = hi - lo
            # both ends inside [lo, hi], at least 60 % of the span apart: every joint moves fast enough to slide
            d = rng.uniform(0.6, 1.0) * span
            s0 = rng.uniform(lo, hi - d)
            a[j], z[j] = (s0, s0 + d) if rng.random() < 0.5 else (s0 + d, s0)
        b.transition(a)
        for _ in range(repeats):
            b.move(z, speed=speed, kind="symmetric", note=f"pass {k} forward")
            b.hold(0.3)
            b.move(a, speed=speed, kind="symmetric", note=f"pass {k} backward")
            b.hold(0.3)
    b.transition(home)


FRICTION_SPEEDS = (0.004, 0.008, 0.012, 0.016, 0.02, 0.025, 0.03, 0.04, 0.05, 0.06, 0.08, 0.1, 0.13, 0.17, 0.22,
                   0.3, 0.4, 0.55, 0.75)


def add_friction(b: PlanBuilder, joints: list[int], speeds: tuple[float, ...] = FRICTION_SPEEDS,
                 cruise_s: float = 3.0, max_half_range: float = 0.7) -> None:
    """Seed 001 friction: single-joint forward/backward passes at a speed ladder (fine steps at low speed)."""
    home = b.q.copy()
    L = b.limits
    for j in joints:
        for v in speeds:
            if v > L.velocity_rad_s[j]:
                continue
            a = L.acceleration_rad_s2[j]
            half = min(max_half_range, 0.5 * (v * cruise_s + v * v / a))
            lo, hi = _range(L, j, home[j], half)
            start = home.copy()
            start[j] = lo
            if abs(b.q[j] - lo) > 1e-9 or np.any(np.abs(b.q - start) > 1e-9):
                b.move(start, speed=0.4, blend="cosine", kind="transition")
                b.hold(0.3)
            end = start.copy()
            end[j] = hi
            b.move(end, speed=v, kind="friction", joint=j, note=f"{v:g} rad/s forward")
            b.hold(0.3)
            b.move(start, speed=v, kind="friction", joint=j, note=f"{v:g} rad/s backward")
            b.hold(0.3)
        b.transition(home)


def add_synchronous(b: PlanBuilder, joints: list[int], speeds: tuple[float, ...] = (0.1, 0.2, 0.3, 0.5),
                    half_range_deg: float = 45.0, cycles: int = 2, acceleration: float = 0.5) -> None:
    """Seed 002: ±45° reciprocation with uniform acceleration/deceleration at several speeds, in two poses."""
    home = b.q.copy()
    L = b.limits
    for j in joints:
        poses = [home.copy()]
        if j + 1 < L.n:  # second pose: the next joint bent by 90° (seed 002's right-angle posture)
            p = home.copy()
            p[j + 1] = L.clip(home + (math.pi / 2 if home[j + 1] <= 0 else -math.pi / 2) * np.eye(L.n)[j + 1])[j + 1]
            poses.append(p)
        for pose_k, pose in enumerate(poses):
            lo, hi = _range(L, j, pose[j], half_range_deg * DEG)
            start = pose.copy()
            start[j] = lo
            b.transition(start)
            for v in speeds:
                vv = min(v, L.velocity_rad_s[j])
                for _ in range(cycles):
                    for end in (hi, lo):
                        tgt = b.q.copy()
                        tgt[j] = end
                        b.move(tgt, speed=vv, acceleration=acceleration, kind="synchronous", joint=j,
                               note=f"pose {pose_k}, {vv:g} rad/s")
                b.hold(0.3)
        b.transition(home)


def add_gap(b: PlanBuilder, speeds: tuple[float, ...] = (0.2, 0.35, 0.5), half_range: float = 0.5, poses: int = 2,
            rng: np.random.Generator | None = None) -> None:
    """Model-gap passes: every joint spans ±``half_range`` about a pose at the same speed (all start and stop together),
    A→B→A at each speed; ``poses`` centre poses (the first: the start) so that gravity loads differ between passes."""
    rng = rng or np.random.default_rng(5)
    home = b.q.copy()
    L = b.limits
    for k in range(poses):
        centre = home if k == 0 else L.clip(home + rng.uniform(-0.6, 0.6, L.n))
        a, z = np.empty(L.n), np.empty(L.n)
        for j in range(L.n):
            lo, hi = _range(L, j, centre[j], half_range)
            a[j], z[j] = (lo, hi) if rng.random() < 0.5 else (hi, lo)
        b.transition(a)
        for v in speeds:
            b.move(z, speed=v, kind="gap", note=f"pose {k}, {v:g} rad/s forward")
            b.hold(0.3)
            b.move(a, speed=v, kind="gap", note=f"pose {k}, {v:g} rad/s backward")
            b.hold(0.3)
    b.transition(home)


# ------------------------------------------------------------------------------------------ Fourier


def _fourier_eval(coef: np.ndarray, q0: np.ndarray, w: float, t: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                                                        np.ndarray]:
    """q, q̇, q̈ (T×n) of the rest-to-rest Fourier series; coef (n, 2, L−1) holds a_l, b_l for l = 2..L."""
    n, _, m = coef.shape
    L = m + 1
    a = np.empty((n, L))
    bb = np.empty((n, L))
    ls = np.arange(1, L + 1)
    a[:, 1:] = coef[:, 0]
    bb[:, 1:] = coef[:, 1]
    a[:, 0] = -a[:, 1:].sum(axis=1)  # q̇(0) = Σ a_l = 0
    bb[:, 0] = -(bb[:, 1:] * ls[1:]).sum(axis=1)  # q̈(0) = Σ b_l·l·ω = 0
    wt = np.outer(t, ls) * w  # T×L
    s, c = np.sin(wt), np.cos(wt)
    lw = ls * w
    q = s @ (a / lw).T - c @ (bb / lw).T
    q += (bb / lw).sum(axis=1)  # q(0) = q0
    dq = c @ a.T + s @ bb.T
    ddq = -(s * lw) @ a.T + (c * lw) @ bb.T
    return q0 + q, dq, ddq


def optimise_fourier(model: Any, limits: Limits, q_center: np.ndarray, period_s: float = 10.0, harmonics: int = 5,
                     samples: int = 120, maxiter: int = 60, seed: int = 3) -> tuple[np.ndarray, np.ndarray, dict]:
    """Coefficients minimising Σ_joints log cond of the column-scaled per-joint base regressors, within limits."""
    from scipy.optimize import minimize

    from dragd.identify.regressors import RegressorModel

    rm = RegressorModel(model)
    n = limits.n
    w = 2 * math.pi / period_s
    t = np.linspace(0.0, period_s, samples, endpoint=False)
    rng = np.random.default_rng(seed)
    lo = np.maximum(limits.lower_rad, q_center - 1.2)
    hi = np.minimum(limits.upper_rad, q_center + 1.2)
    q0 = (lo + hi) / 2
    m = harmonics - 1
    shape = (n, 2, m)
    vmax, amax = limits.velocity_rad_s, limits.acceleration_rad_s2

    def unpack(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return x[: n * 2 * m].reshape(shape), x[n * 2 * m:]

    def penalty(q: np.ndarray, dq: np.ndarray, ddq: np.ndarray, qc: np.ndarray) -> float:
        p = np.sum(np.maximum(q - hi, 0) ** 2) + np.sum(np.maximum(lo - q, 0) ** 2)
        p += np.sum(np.maximum(np.abs(dq) - vmax, 0) ** 2) + np.sum(np.maximum(np.abs(ddq) - amax, 0) ** 2) * 0.1
        return 1e3 * p

    def cost(x: np.ndarray) -> float:
        coef, qc = unpack(x)
        q, dq, ddq = _fourier_eval(coef, qc, w, t)
        return rm.excitation_cost(q, dq, ddq) + penalty(q, dq, ddq, qc)

    # start: the best of a few random coefficient sets scaled into the limits
    best = None
    for _ in range(8):
        x0 = np.concatenate([rng.normal(0.0, 0.15, n * 2 * m), q0])
        coef, qc = unpack(x0)
        q, dq, ddq = _fourier_eval(coef, qc, w, t)
        per_joint = np.minimum(vmax / (np.abs(dq).max(axis=0) + 1e-9), amax / (np.abs(ddq).max(axis=0) + 1e-9))
        x0[: n * 2 * m] = (coef * np.minimum(1.0, 0.8 * per_joint)[:, None, None]).ravel()
        c = cost(x0)
        if best is None or c < best[0]:
            best = (c, x0)
    assert best is not None  # (the loop above ran)
    x0 = best[1]
    res = minimize(cost, x0, method="L-BFGS-B", options={"maxiter": maxiter, "maxfun": maxiter * (len(x0) + 1)})
    coef, qc = unpack(res.x)
    # enforce the limits exactly: shrink the excursion about the centre until everything is inside
    tt = np.linspace(0.0, period_s, 2000, endpoint=False)
    for _ in range(60):
        q, dq, ddq = _fourier_eval(coef, qc, w, tt)
        if (np.all(q <= limits.upper_rad) and np.all(q >= limits.lower_rad) and np.all(np.abs(dq) <= vmax)
                and np.all(np.abs(ddq) <= amax)):
            break
        coef = coef * 0.95
        qc = np.clip(qc, limits.lower_rad + 0.05, limits.upper_rad - 0.05)
    q, dq, ddq = _fourier_eval(coef, qc, w, t)
    info = {"period_s": period_s, "harmonics": harmonics, "cost": float(rm.excitation_cost(q, dq, ddq)),
            "iterations": int(res.nit), "condition_numbers": rm.condition_numbers(q, dq, ddq)}
    return coef, qc, info


def add_fourier(b: PlanBuilder, model: Any, periods: int = 6, period_s: float = 10.0, harmonics: int = 5,
                maxiter: int = 60, seed: int = 3) -> dict:
    home = b.q.copy()
    coef, qc, info = optimise_fourier(model, b.limits, home, period_s, harmonics, maxiter=maxiter, seed=seed)
    w = 2 * math.pi / period_s
    b.transition(qc)
    t = np.arange(0.0, periods * period_s + b.dt / 2, b.dt)
    q, _, _ = _fourier_eval(coef, qc, w, t)
    t0 = b.t
    b._append(t, q)
    b.segments.append(Segment("fourier", t0, b.t, None, None, f"{periods} periods of {period_s:g} s"))
    b.hold(0.3)
    b.transition(home)
    return info


def build_plan(kind: str, model: Any, q_start: np.ndarray, limits: Limits, joints: list[int] | None = None,
               scale: float = 1.0, seed: int = 5, fourier_iterations: int = 60) -> Plan:
    """Build a plan of ``kind`` from ``q_start``; ``scale`` < 1 shortens it (fewer passes/speeds) for quick runs."""
    if kind not in PLAN_KINDS:
        raise PlanError(f"plan: kind: expected one of {', '.join(PLAN_KINDS)}, got '{kind}'")
    b = PlanBuilder(q_start, limits)
    n = limits.n
    js = _joints(n, joints)
    rng = np.random.default_rng(seed)
    info: dict[str, Any] = {"kind": kind, "joints": [j + 1 for j in js], "scale": scale}
    kinds = {"standard": ["synchronous", "symmetric", "friction"],
             "all": ["lowspeed", "synchronous", "symmetric", "friction", "fourier"]}.get(kind, [kind])
    for k in kinds:
        if k == "lowspeed":
            add_lowspeed(b, js, seconds_per_joint=max(20.0, 100.0 * scale))
        elif k == "symmetric":
            add_symmetric(b, passes=max(2, int(round(8 * scale))), rng=rng)
        elif k == "friction":
            speeds = FRICTION_SPEEDS if scale >= 1 else FRICTION_SPEEDS[:: max(1, int(round(1 / scale)))]
            add_friction(b, js, speeds=speeds, cruise_s=3.0 if scale >= 1 else 2.0)
        elif k == "gap":
            add_gap(b, poses=max(1, int(round(3 * scale))), rng=rng)
        elif k == "synchronous":
            sp = (0.1, 0.2, 0.3, 0.5) if scale >= 1 else (0.15, 0.4)
            add_synchronous(b, js, speeds=sp, cycles=2 if scale >= 1 else 1)
        elif k == "fourier":
            info["fourier"] = add_fourier(b, model, periods=max(2, int(round(12 * scale))), maxiter=fourier_iterations,
                                          seed=seed)
    plan = b.build(kind, info)
    bad = plan.check(limits)
    if bad:
        raise PlanError("plan: the built trajectory leaves the limits: " + "; ".join(bad))
    return plan
