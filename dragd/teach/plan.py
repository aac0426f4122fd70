"""Replay planning: a taught program → a joint trajectory table at the loop period, within the limits.

Interpolation modes (a *cycle* starts and ends at rest at the first waypoint; the daemon repeats it):

* ``linear``: point-to-point joint-space moves p1 → p2 → … → pn → p1, each a synchronised jerk-limited
  double-S profile (every joint starts and stops together), with a settle dwell at every waypoint;
* ``circular``: the Cartesian circle of the frame (``tool0``) through p1, p2, p3 and back to p1, orientation
  interpolated smoothly through the three taught orientations; joint positions by damped-least-squares inverse
  kinematics (Pinocchio), warm-started along the path so the arm keeps its configuration;
* ``spline``: a closed cubic spline in joint space through the waypoints (passes them without stopping);
* source ``path``: the continuous recording reduced to keyframes (``keyframes.py``), replayed as splines between
  the pauses (stops), then back to the start point to point.

Paths are time-scaled by ``retime``: a velocity-limit curve (joint velocity, centripetal acceleration, TCP speed),
a forward/backward pass with the tangential acceleration budget, a moving-average (FIR) filter that bounds the
jerk, then a check of every joint's velocity, acceleration and jerk and the TCP speed on the final samples; when a
bound is exceeded the piece is stretched uniformly in time (v/k, a/k², j/k³) until all hold.

Before the cycle, a move-to-start brings the arm from where it is to p1 at ``move_to_start_speed``.
The result carries the feed-forward torque of the rigid-body dynamics M(q)q̈ + C(q,q̇)q̇ of every sample (the
daemon adds gravity and friction itself).
"""

from __future__ import annotations

import itertools
import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin
from scipy.interpolate import CubicSpline

from dragd.teach.keyframes import chord_parameter, extract_keyframes, path_spline
from dragd.teach.kinematics import Circle, Kinematics, KinematicsError
from dragd.teach.profile import SCurve
from dragd.teach.program import Program, load_program
from dragd.teach.request import INTERPS, SOURCES, Limits, ReplayRequest, limits_from_config


class PlanError(ValueError):
    """A program that cannot be replayed as asked; the message says what and what to do."""


# ------------------------------------------------------------------------------------------------ pieces


class Piece(ABC):
    """A rest-to-rest part of the motion: ``evaluate(t)`` → q, q̇, q̈, q⃛ (rows per time)."""

    duration: float
    label: str = ""

    @abstractmethod
    def evaluate(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Position, velocity, acceleration, jerk at local times ``t``."""

    @abstractmethod
    def stretched(self, k: float) -> Piece:
        """The same piece slowed down by ``k`` ≥ 1."""

    def marks(self) -> list[tuple[float, str, str]]:
        """(local time, waypoint name, kind) of the waypoints this piece stops at or passes."""
        return []


@dataclass
class Dwell(Piece):
    q: np.ndarray
    duration: float
    label: str = "settle"
    stop: str | None = None  # the waypoint the arm settles at

    def evaluate(self, t):
        t = np.atleast_1d(t)
        z = np.zeros((len(t), len(self.q)))
        return np.tile(self.q, (len(t), 1)), z, z.copy(), z.copy()

    def stretched(self, k):
        return self

    def marks(self):
        return [(self.duration, self.stop, "stop")] if self.stop else []


@dataclass
class PTP(Piece):
    """Joint-space straight line qa → qb with a synchronised double-S profile."""

    qa: np.ndarray
    qb: np.ndarray
    profile: SCurve
    label: str = "ptp"

    @classmethod
    def plan(cls, qa: np.ndarray, qb: np.ndarray, lim: Limits, label: str = "ptp") -> PTP:
        d = np.abs(qb - qa)
        moving = d > 1e-12
        if not moving.any():
            return cls(qa.copy(), qb.copy(), SCurve.plan(0.0, 1.0, 1.0, 1.0), label)
        V = float(np.min(lim.velocity[moving] / d[moving]))
        A = float(np.min(lim.acceleration[moving] / d[moving]))
        J = float(np.min(lim.jerk[moving] / d[moving]))
        return cls(qa.copy(), qb.copy(), SCurve.plan(1.0, V, A, J), label)

    @property
    def duration(self) -> float:  # type: ignore[override]  # computed here; Piece declares the attribute Dwell sets
        return self.profile.duration

    def evaluate(self, t):
        s, v, a, j = self.profile.evaluate(np.atleast_1d(t))
        d = self.qb - self.qa
        return self.qa + np.outer(s, d), np.outer(v, d), np.outer(a, d), np.outer(j, d)

    def stretched(self, k):
        p = self.profile
        return PTP(self.qa, self.qb, SCurve.plan(p.length, p.v_max / k, p.a_max / k ** 2, p.j_max / k ** 3), self.label)


@dataclass
class PathPiece(Piece):
    """A geometric path q(u) (cubic spline, u ∈ [0, length]) with a timing u(t) sampled at ``dt``."""

    spline: CubicSpline
    length: float
    dt: float
    u: np.ndarray  # u at k·dt
    ud: np.ndarray
    udd: np.ndarray
    uddd: np.ndarray
    label: str = "path"
    passes: list[tuple[float, str]] = field(default_factory=list)  # (u, waypoint name) passed on the way

    @property
    def duration(self) -> float:  # type: ignore[override]  # computed here; Piece declares the attribute Dwell sets
        return (len(self.u) - 1) * self.dt

    def _at(self, t: np.ndarray) -> tuple[np.ndarray, ...]:
        x = np.clip(np.atleast_1d(t) / self.dt, 0.0, len(self.u) - 1)
        grid = np.arange(len(self.u))
        return tuple(np.interp(x, grid, a) for a in (self.u, self.ud, self.udd, self.uddd))

    def evaluate(self, t):
        u, ud, udd, uddd = self._at(t)
        u = np.clip(u, 0.0, self.length)
        q1 = self.spline(u, 1)
        q2 = self.spline(u, 2)
        q3 = self.spline(u, 3)
        q = self.spline(u)
        dq = q1 * ud[:, None]
        ddq = q2 * (ud ** 2)[:, None] + q1 * udd[:, None]
        dddq = q3 * (ud ** 3)[:, None] + 3.0 * q2 * (ud * udd)[:, None] + q1 * uddd[:, None]
        return q, dq, ddq, dddq

    def stretched(self, k):
        n = int(math.ceil(self.duration * k / self.dt - 1e-9)) + 1
        t = np.arange(n) * self.dt / k
        u, ud, udd, uddd = self._at(t)
        u[-1] = self.length
        return PathPiece(self.spline, self.length, self.dt, u, ud / k, udd / k ** 2, uddd / k ** 3, self.label,
                         self.passes)

    def marks(self):
        out = []
        for up, name in self.passes:
            i = int(np.searchsorted(self.u, up - 1e-12))
            i = min(max(i, 0), len(self.u) - 1)
            # linear interpolation of the crossing time
            if 0 < i < len(self.u) and self.u[i] != self.u[i - 1]:
                f = (up - self.u[i - 1]) / (self.u[i] - self.u[i - 1])
                tp = (i - 1 + f) * self.dt
            else:
                tp = i * self.dt
            out.append((float(tp), name, "pass"))
        return out


def retime(spline: CubicSpline, length: float, lim: Limits, dt: float, *, speed_cap: np.ndarray | None = None,
           grid_points: int = 4000, label: str = "path", passes: list[tuple[float, str]] | None = None) -> PathPiece:
    """Rest-to-rest timing u(t) of the path q(u), u ∈ [0, length], under the joint limits (see module doc).

    ``speed_cap`` optionally caps u̇ at the grid points (e.g. the TCP speed). The result is not yet checked
    against the limits; ``fit`` does that and stretches.
    """
    K = max(50, int(grid_points))
    u = np.linspace(0.0, length, K)
    h = np.diff(u)
    q1 = np.abs(spline(u, 1)) + 1e-12
    q2 = np.abs(spline(u, 2)) + 1e-12
    cap = np.min(lim.velocity / q1, axis=1)
    cap = np.minimum(cap, np.min(np.sqrt(0.5 * lim.acceleration / q2), axis=1))
    if speed_cap is not None:
        cap = np.minimum(cap, np.interp(u, np.linspace(0.0, length, len(speed_cap)), speed_cap))
    acc = np.min(0.5 * lim.acceleration / q1, axis=1)
    w = cap ** 2
    w[0] = w[-1] = 0.0
    for k in range(K - 1):  # forward: accelerate at most at the tangential budget
        w[k + 1] = min(w[k + 1], w[k] + 2.0 * acc[k] * h[k])
    for k in range(K - 2, -1, -1):  # backward: brake in time
        w[k] = min(w[k], w[k + 1] + 2.0 * acc[k + 1] * h[k])
    s = np.sqrt(np.maximum(w, 0.0))
    dtk = 2.0 * h / np.maximum(s[:-1] + s[1:], 1e-12)
    tk = np.concatenate([[0.0], np.cumsum(dtk)])
    n = int(math.ceil(tk[-1] / dt)) + 1
    vel = np.interp(np.arange(n) * dt, tk, s)
    # FIR (moving average) over a_max/j_max·2: the acceleration becomes continuous, the jerk bounded
    tf = float(np.max(2.0 * lim.acceleration / lim.jerk))
    m = max(1, int(round(tf / dt)))
    if m > 1:
        vel = np.convolve(vel, np.ones(m) / m)
    vel[0] = 0.0
    vel[-1] = 0.0
    pos = np.concatenate([[0.0], np.cumsum((vel[:-1] + vel[1:]) * 0.5 * dt)])
    scale = length / pos[-1]
    pos *= scale
    vel *= scale
    pos[-1] = length
    acc_t = np.gradient(vel, dt)
    jerk_t = np.gradient(acc_t, dt)
    return PathPiece(spline, length, dt, pos, vel, acc_t, jerk_t, label, list(passes or []))


def _tcp_speed(kin: Kinematics | None, q: np.ndarray, dt: float, step: int = 4) -> np.ndarray:
    if kin is None or len(q) < 3:
        return np.zeros(1)
    idx = np.arange(0, len(q), step)
    if idx[-1] != len(q) - 1:
        idx = np.append(idx, len(q) - 1)
    p = np.array([kin.position(q[i]) for i in idx])
    return np.linalg.norm(np.diff(p, axis=0), axis=1) / (np.diff(idx) * dt)


def fit(piece: Piece, lim: Limits, dt: float, kin: Kinematics | None = None, rounds: int = 4) -> tuple[Piece, dict]:
    """Check ``piece`` against the limits on its samples; stretch it uniformly in time until every one holds."""
    report: dict[str, Any] = {}
    for _ in range(rounds):
        if piece.duration <= 0:
            return piece, {"stretch": 1.0}
        t = np.arange(0.0, piece.duration + dt / 2, dt)
        q, dq, ddq, dddq = piece.evaluate(t)
        rv = float(np.max(np.abs(dq) / lim.velocity))
        ra = float(np.max(np.abs(ddq) / lim.acceleration))
        rj = float(np.max(np.abs(dddq) / lim.jerk))
        rt = float(np.max(_tcp_speed(kin, q, dt))) / lim.cartesian_speed_m_s if kin is not None else 0.0
        k = max(rv, math.sqrt(ra), rj ** (1.0 / 3.0), rt)
        report = {"velocity_ratio": rv, "acceleration_ratio": ra, "jerk_ratio": rj, "tcp_speed_ratio": rt}
        if k <= 1.0 + 1e-6:
            return piece, report
        piece = piece.stretched(k * 1.002)
    return piece, report


# ------------------------------------------------------------------------------------------------ builders


def circle_piece(q1: np.ndarray, q2: np.ndarray, q3: np.ndarray, names: tuple[str, str, str], kin: Kinematics,
                 lim: Limits, dt: float, samples_per_rev: int = 1440, tolerance_rad: float = 0.01) -> PathPiece:
    """The full circle of the frame through the taught poses of q1, q2, q3, back to q1, in joint space."""
    M = [kin.pose(q) for q in (q1, q2, q3)]
    try:
        circ = Circle.through(*(m.translation for m in M))
    except KinematicsError as exc:
        raise PlanError(f"circular: {exc}") from None
    _, a2, a3 = circ.angles
    two_pi = 2.0 * math.pi
    # orientation: a periodic cubic spline of the rotation vector relative to p1's orientation
    R1 = M[0].rotation
    rv = [np.zeros(3), pin.log3(R1.T @ M[1].rotation), pin.log3(R1.T @ M[2].rotation), np.zeros(3)]
    if max(np.linalg.norm(rv[1]), np.linalg.norm(rv[2])) > 0.9 * math.pi:
        raise PlanError("circular: the taught orientations differ by almost half a turn; teach them closer")
    rot = CubicSpline([0.0, a2, a3, two_pi], np.array(rv), bc_type="periodic")
    # grid with the waypoints on it
    parts = []
    for lo, hi in ((0.0, a2), (a2, a3), (a3, two_pi)):
        m = max(8, int(math.ceil(samples_per_rev * (hi - lo) / two_pi)))
        parts.append(np.linspace(lo, hi, m + 1)[:-1])
    theta = np.concatenate(parts + [[two_pi]])
    Q = np.zeros((len(theta), len(q1)))
    Q[0] = q1
    q = q1.copy()
    for i in range(1, len(theta)):
        th = theta[i]
        target = pin.SE3(R1 @ pin.exp3(rot(th)), circ.point(th))
        try:
            q = kin.ik(target, q)
        except KinematicsError as exc:
            raise PlanError(f"circular: at {math.degrees(th):.1f}° along the circle: {exc}") from None
        Q[i] = q
    for name, qt, ang in ((names[1], q2, a2), (names[2], q3, a3), (names[0], q1, two_pi)):
        i = int(np.argmin(np.abs(theta - ang)))
        dev = np.abs(Q[i] - qt)
        if dev.max() > tolerance_rad:
            j = int(np.argmax(dev))
            raise PlanError(f"circular: the circle reaches {name} in another arm configuration "
                            f"({kin.model.names[j + 1]} differs by {math.degrees(dev[j]):.1f}°); teach points the arm "
                            "can join without reconfiguring, or use linear")
        Q[i] = qt  # the taught encoder positions exactly (the IK agrees to ~1e-10)
    Q[-1] = Q[0]
    spline = CubicSpline(theta, Q, bc_type="periodic")
    r = circ.radius
    cap = np.full(64, min(lim.cartesian_speed_m_s / r, math.sqrt(0.5 * lim.cartesian_acceleration_m_s2 / r)))
    piece = retime(spline, two_pi, lim, dt, speed_cap=cap, label="circle",
                   passes=[(a2, names[1]), (a3, names[2])])
    piece.circle = circ  # type: ignore[attr-defined]
    return piece


def spline_piece(points: np.ndarray, names: list[str | None], lim: Limits, dt: float, closed: bool,
                 kin: Kinematics | None, label: str = "spline") -> PathPiece:
    """A cubic spline in joint space through ``points`` (closed: back to the first), chord-length parameter."""
    pts = np.vstack([points, points[:1]]) if closed else np.asarray(points)
    u = chord_parameter(pts)
    if np.any(np.diff(u) < 1e-6):
        k = int(np.argmin(np.diff(u)))
        raise PlanError(f"spline: points {k + 1} and {k + 2} coincide; remove one")
    spline = path_spline(u, pts, closed=closed and len(points) >= 3)
    cap = None
    if kin is not None:  # TCP speed per unit of path parameter
        uu = np.linspace(0.0, u[-1], 400)
        p = np.array([kin.position(q) for q in spline(uu)])
        dp = np.linalg.norm(np.gradient(p, uu, axis=0), axis=1)
        cap = lim.cartesian_speed_m_s / np.maximum(dp, 1e-9)
    passes = [(float(u[i]), nm) for i, nm in enumerate(names) if nm and 0 < i < len(points)]
    return retime(spline, float(u[-1]), lim, dt, speed_cap=cap, label=label, passes=passes)


# ------------------------------------------------------------------------------------------------ assembly


@dataclass
class Plan:
    dt: float
    q: np.ndarray
    dq: np.ndarray
    ddq: np.ndarray
    body_row: int  # the repeated cycle runs from this row to the last
    marks: list[dict[str, Any]]  # waypoints: {name, t_s (table time), kind stop|pass, q_rad}
    segments: list[dict[str, Any]]  # {label, t0_s, t1_s, report}
    info: dict[str, Any]
    ff_Nm: np.ndarray | None = None

    @property
    def duration_s(self) -> float:
        return (len(self.q) - 1) * self.dt

    def summary(self) -> dict[str, Any]:
        return {"duration_s": round(self.duration_s, 4), "cycle_s": round(self.duration_s - self.body_row * self.dt, 4),
                "move_to_start_s": round(self.body_row * self.dt, 4), "samples": len(self.q),
                "segments": self.segments, "marks": [{k: v for k, v in m.items() if k != "q_rad"} for m in self.marks],
                **self.info}


def assemble(pieces: list[Piece], dt: float, body_index: int, waypoint_q: dict[str, np.ndarray]) -> Plan:
    qs, dqs, ddqs, segs, marks = [], [], [], [], []
    row = 0
    body_row = 0
    for i, p in enumerate(pieces):
        if i == body_index:
            body_row = row
        m = int(math.ceil(p.duration / dt - 1e-9))
        if m == 0:
            continue
        t = np.arange(m) * dt
        q, dq, ddq, _ = p.evaluate(t)
        qs.append(q)
        dqs.append(dq)
        ddqs.append(ddq)
        segs.append({"label": p.label, "t0_s": round(row * dt, 4), "t1_s": round((row + m) * dt, 4),
                     **getattr(p, "report", {})})
        for tl, name, kind in p.marks():
            if name is not None:
                tg = row * dt + min(tl, m * dt)
                marks.append({"name": name, "t_s": round(tg, 4), "kind": kind,
                              "q_rad": waypoint_q[name].tolist() if name in waypoint_q else None})
        row += m
    last = pieces[-1].evaluate(np.array([pieces[-1].duration]))
    qs.append(last[0])
    dqs.append(np.zeros_like(last[1]))
    ddqs.append(np.zeros_like(last[2]))
    return Plan(dt, np.vstack(qs), np.vstack(dqs), np.vstack(ddqs), body_row, marks, segs, {})


def _check_soft_limits(plan: Plan, lim: Limits, names: list[str]) -> None:
    lo = plan.q < lim.lower
    hi = plan.q > lim.upper
    if lo.any() or hi.any():
        bad = lo | hi
        r, j = np.argwhere(bad)[0]
        t = r * plan.dt
        seg = next((s["label"] for s in plan.segments if s["t0_s"] <= t < s["t1_s"]), "?")
        raise PlanError(f"the motion leaves the soft limits of {names[j]} at t = {t:.2f} s ({seg}): "
                        f"{plan.q[r, j]:.3f} rad outside [{lim.lower[j]:.3f}, {lim.upper[j]:.3f}]")


def feedforward(model: pin.Model, plan: Plan) -> np.ndarray:
    """M(q)q̈ + C(q,q̇)q̇ of every sample [N·m] (RNEA minus gravity)."""
    data = model.createData()
    out = np.zeros_like(plan.q)
    for i in range(len(plan.q)):
        out[i] = pin.rnea(model, data, plan.q[i], plan.dq[i], plan.ddq[i])
        out[i] -= pin.computeGeneralizedGravity(model, data, plan.q[i])
    return out


_MODELS: dict[tuple[str, tuple[float, ...]], pin.Model] = {}


def _model(urdf: str, gravity: tuple[float, float, float]) -> pin.Model:
    key = (urdf, tuple(gravity))
    if key not in _MODELS:
        m = pin.buildModelFromUrdf(urdf)
        m.gravity.linear = np.asarray(gravity, dtype=float)
        _MODELS[key] = m
    return _MODELS[key]


def plan_program(program: Program, req: ReplayRequest, model: pin.Model) -> Plan:
    lim = Limits.from_dict(req.limits)
    n = program.n
    if model.nq != n:
        raise PlanError(f"program '{program.name}': {n} joints, the robot has {model.nq}")
    if req.interp not in INTERPS:
        raise PlanError(f"--interp: expected one of {', '.join(INTERPS)}, got '{req.interp}'")
    dt = req.dt
    kin = Kinematics(model, req.frame)
    wps = program.waypoint_array()
    names = [w.name for w in program.waypoints]
    source = req.source or ("waypoints" if len(wps) >= 2 else "path")
    if source not in SOURCES:
        raise PlanError(f"--source: expected one of {', '.join(SOURCES)}, got '{source}'")
    q_now = np.asarray(req.q_start, dtype=float)
    body: list[Piece] = []
    wq = {nm: wps[i] for i, nm in enumerate(names)}
    info: dict[str, Any] = {"interp": req.interp, "source": source, "program": program.name}
    if source == "waypoints":
        if len(wps) < 2:
            raise PlanError(f"program '{program.name}' has {len(wps)} waypoint(s); "
                            "replaying waypoints needs at least 2 "
                            "(mark them with 'dragd teach mark'), or use --source path")
        start = wps[0]
        if req.interp == "linear":
            for i in range(len(wps)):
                a, b = wps[i], wps[(i + 1) % len(wps)]
                body.append(PTP.plan(a, b, lim, f"ptp {names[i]}→{names[(i + 1) % len(wps)]}"))
                body.append(Dwell(b.copy(), req.settle_s, stop=names[(i + 1) % len(wps)]))
        elif req.interp == "circular":
            if len(wps) != 3:
                raise PlanError(f"circular interpolation goes through exactly 3 waypoints (p1, p2, p3); program "
                                f"'{program.name}' has {len(wps)}")
            body.append(circle_piece(wps[0], wps[1], wps[2], tuple(names), kin, lim, dt))  # type: ignore[arg-type]
            body.append(Dwell(wps[0].copy(), req.settle_s, stop=names[0]))
            c = body[0].circle  # type: ignore[attr-defined]
            info["circle"] = {"center_m": c.center.round(5).tolist(), "radius_m": round(c.radius, 5),
                              "normal": c.normal.round(5).tolist()}
        else:  # spline
            if len(wps) == 2:
                body.append(PTP.plan(wps[0], wps[1], lim, f"ptp {names[0]}→{names[1]}"))
                body.append(Dwell(wps[1].copy(), req.settle_s, stop=names[1]))
                body.append(PTP.plan(wps[1], wps[0], lim, f"ptp {names[1]}→{names[0]}"))
            else:
                body.append(spline_piece(wps, list(names), lim, dt, closed=True, kin=kin))
            body.append(Dwell(wps[0].copy(), req.settle_s, stop=names[0]))
    else:
        if req.interp == "circular":
            raise PlanError("circular interpolation replays waypoints (p1, p2, p3), not the continuous path")
        t, q = program.path_arrays()
        if len(t) < 2:
            raise PlanError(f"program '{program.name}' has no continuous recording to replay")
        if program.keyframes:
            kq = np.array([k.q_rad for k in program.keyframes])
            kinds = [k.kind for k in program.keyframes]
        else:
            kf = extract_keyframes(t, q, req.keyframe_tolerance_rad, marks_t=[w.t_s for w in program.waypoints])
            kq, kinds = q[kf.index], kf.kind
            info["keyframes"] = len(kf.index)
            info["keyframe_deviation_deg"] = round(math.degrees(kf.max_deviation_rad), 4)
        if len(kq) < 2:
            raise PlanError(f"program '{program.name}': the recording holds no motion (the arm never moved)")
        start = kq[0]
        stops = [0] + [i for i, k in enumerate(kinds) if k == "pause" and 0 < i < len(kq) - 1] + [len(kq) - 1]
        for a, b in itertools.pairwise(stops):
            sec = kq[a:b + 1]
            if np.abs(sec[-1] - sec[0]).max() < 1e-6 and len(sec) <= 2:
                continue
            if len(sec) == 2:
                body.append(PTP.plan(sec[0], sec[1], lim, "path"))
            else:
                body.append(spline_piece(sec, [None] * len(sec), lim, dt, closed=False, kin=kin, label="path"))
            body.append(Dwell(sec[-1].copy(), req.settle_s))
        body.append(PTP.plan(kq[-1], kq[0], lim, "ptp back to start"))
        body.append(Dwell(kq[0].copy(), req.settle_s))
    # move to start at low speed, then settle there
    slow = lim.scaled(req.move_to_start_speed)
    intro: list[Piece] = [PTP.plan(q_now, start, slow, "move to start"), Dwell(start.copy(), req.settle_s)]
    fitted: list[Piece] = []
    for i, p in enumerate(intro + body):
        f, rep = fit(p, slow if i == 0 else lim, dt, kin)
        f.report = {k: round(v, 4) for k, v in rep.items()}  # type: ignore[attr-defined]
        fitted.append(f)
    total = sum(p.duration for p in fitted) / dt
    if total > req.max_samples:
        raise PlanError(f"the replay would take {total * dt:.0f} s ({total:.0f} samples, max {req.max_samples}); "
                        "split the program")
    plan = assemble(fitted, dt, len(intro), wq)
    plan.info = info
    _check_soft_limits(plan, lim, list(model.names[1:]))
    if req.feedforward:
        plan.ff_Nm = feedforward(model, plan)
    return plan


def rigid_body_effort(urdf: str, gravity: tuple[float, float, float], q: np.ndarray,
                      dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Along a joint table sampled every ``dt``: M(q)q̈ + C(q,q̇)q̇ [N·m] (float32; the residual monitor's), and per
    joint the peak of the whole rigid-body effort |M q̈ + C q̇ + G| [N·m] and its row (the motion's current check)."""
    model = _model(urdf, gravity)
    data = model.createData()
    q = np.asarray(q, dtype=float)
    dq = np.gradient(q, dt, axis=0)
    ddq = np.gradient(dq, dt, axis=0)
    step = 1 if len(q) <= 20000 else 4  # long runs: every 4 ms, linear in between (the monitor filters at 10 Hz)
    idx = np.arange(0, len(q), step)
    if idx[-1] != len(q) - 1:
        idx = np.append(idx, len(q) - 1)
    coarse = np.empty((len(idx), q.shape[1]))
    peak = np.zeros(q.shape[1])
    peak_row = np.zeros(q.shape[1], dtype=int)
    for k, i in enumerate(idx):
        full = pin.rnea(model, data, q[i], dq[i], ddq[i])
        a = np.abs(full)
        more = a > peak
        peak[more], peak_row[more] = a[more], i
        coarse[k] = full - pin.computeGeneralizedGravity(model, data, q[i])
    if step == 1:
        return coarse.astype(np.float32), peak, peak_row
    rows = np.arange(len(q))
    dyn = np.column_stack([np.interp(rows, idx, coarse[:, j]) for j in range(q.shape[1])]).astype(np.float32)
    return dyn, peak, peak_row


def plan_replay(req: ReplayRequest) -> dict[str, Any]:
    """Entry point of the planner (worker process): the plan as plain arrays + a summary."""
    program = load_program(req.program)
    model = _model(req.urdf, req.gravity_m_s2)
    if list(model.names[1:]) != list(program.joints):
        raise PlanError(f"program '{program.name}' was taught on joints {', '.join(program.joints)}; the robot has "
                        f"{', '.join(model.names[1:])}")
    plan = plan_program(program, req, model)
    return {"q": plan.q, "dq": plan.dq, "ff_Nm": plan.ff_Nm, "body_row": plan.body_row, "marks": plan.marks,
            "summary": plan.summary(), "dt": plan.dt}


def warm_up() -> bool:
    """Import everything the planner needs (called once in a fresh worker process)."""
    return True


def request_from_config(cfg: Any, program: str | Path, q_start: Any, *, interp: str = "linear",
                        source: str | None = None) -> ReplayRequest:
    from dragd.robots import resolve_urdf

    urdf = str(resolve_urdf(cfg.robot.urdf, cfg.base_dir))
    model = _model(urdf, tuple(cfg.robot.gravity_m_s2))
    rc = cfg.replay
    return ReplayRequest(program=str(program), q_start=[float(x) for x in q_start], dt=1.0 / cfg.loop.rate_Hz,
                         urdf=urdf, gravity_m_s2=tuple(cfg.robot.gravity_m_s2),
                         limits=limits_from_config(cfg, model).as_dict(), interp=interp, source=source, frame=rc.frame,
                         move_to_start_speed=rc.move_to_start_speed, settle_s=rc.settle_s,
                         keyframe_tolerance_rad=rc.keyframe_tolerance_rad, feedforward=rc.inertia_feedforward)
