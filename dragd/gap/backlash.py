"""Backlash: a physical predictor of the motor current of a joint with play between its rotor and its output.

The model (joint side; currents in amperes, torques divided by K_t):

* the drive closes its position loop on the output encoder (CSP): i = s(t) − k_p·q − k_d·q̇, where the loop input
  s = k_p·r + k_d·ṙ + feed-forward is smooth (r is the reference);
* the rotor (inertia J, the share 1 − φ of the joint's friction) drives the output through a dead zone of width b
  (hard contact, plastic impacts); the output carries its URDF inertia M_jj, its loads and the friction share φ
  (bearings, seals);
* in contact the rotor moves with the output and the rigid model î holds; the contact ends when the tooth force of
  the rigid pair, [M·(i − f_r) + J·(f_o + load)]/(M + J), changes sign; in flight the rotor moves under
  J·q̈_r = i − f_r(q̇_r) (sticking when it stops) until it reaches a flank.

Along the measured output path the rotor is simulated (the output is not: it is measured). Where the rotor is in
flight, and ±50 ms around its impacts (the rigid model turns the output's velocity jump into a current impulse through
the zero-phase q̈ filter, which the drive never produced), the current is the loop's: ŝ − k_p·q − k_d·q̇. The loop input
ŝ is estimated from the contact phases, where ŝ = î + k_p·q + k_d·q̇, by a weighted smoother (Whittaker, second
differences) that bridges the flights; the slow part of q (the reference's shape) is taken out before smoothing, so a
flight that ends in a rest does not extrapolate the ramp k_p·r. The contact windows depend on ŝ and the gains, so
simulation and estimate are iterated (a fixed number of times, from the same start: a params file reproduces the
prediction exactly). Fitting: a grid over b and φ, the gains by least squares on the flight windows inside each
point, Nelder–Mead on (b, φ) from the best; J is the model's rotor inertia when it has one.

Where the current follows the drive's reference (which the output does not show while the rotor flies) the prediction
is an interpolation: what it leaves there is not for rigid-body effects to explain (``exclude`` in the selection).

Nothing here depends on the proof's plan: the inputs are t, q, i of any log and the model's current.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy.linalg import solve_banded
from scipy.optimize import minimize

LOOP_CUTOFF_HZ = 5.0  # bandwidth of the loop-input estimate ŝ (Whittaker smoother, half power)
REFERENCE_CUTOFF_HZ = 3.0  # bandwidth of the output's slow part (the reference's shape), taken out before smoothing
V_CONTACT_RAD_S = 0.01  # contact samples used for ŝ: the joint moves (the rigid model is meaningful)
SUBSTEPS = 4  # rotor integration steps per work-rate sample
ITERATIONS = 4  # simulation ↔ estimate fixed-point iterations
PLAYS_RAD = (0.002, 0.004, 0.008, 0.016, 0.032)  # grid of the play (geometric)
SHARES = (0.0, 0.15, 0.3, 0.5)  # grid of the output's friction share
SCREEN_PLAYS_RAD = (0.004, 0.016)  # the grid's first points: nothing gained there, no search
SCREEN_SHARES = (0.15, 0.3)


@dataclass(frozen=True)
class BacklashParams:
    """The physical parameters of the predictor (what ``effects.backlash_*`` in a params file holds)."""

    play_rad: float  # b: the dead zone's full width
    rotor_inertia_A_s2_per_rad: float  # J / K_t
    kp_A_per_rad: float  # the drive's position-loop gain
    kd_A_s_per_rad: float  # ... and its velocity (damping) gain
    output_friction_fraction: float  # φ: share of the joint's friction on the output side of the play
    cutoff_Hz: float = LOOP_CUTOFF_HZ  # bandwidth of the loop-input estimate


@dataclass
class JointPath:
    """One joint's measured output path at the work rate and the model's current along it (the predictor's inputs)."""

    q: np.ndarray  # (T,) rad, output position (zero-phase filtered)
    v: np.ndarray  # (T,) rad/s
    a: np.ndarray  # (T,) rad/s²
    model_A: np.ndarray  # (T,) the rigid model's current î (everything but the play)
    friction: tuple[float, float, float, float]  # the model's friction current: Coulomb +/−, viscous +/− (A, A·s/rad)
    output_inertia_A_s2_per_rad: np.ndarray  # (T,) M_jj(q)/K_t
    fs: float  # work rate [Hz]
    segments: list[tuple[int, int]]  # contiguous stretches (start, stop)
    fit_mask: np.ndarray  # (T,) bool: samples the fit scores (the joint slides)
    impact_window_s: float  # ± this around a simulated impact the loop's current replaces the rigid model's
    fast_q: np.ndarray = field(init=False)  # (T,) q minus its slow part (the reference's shape)
    fast_v: np.ndarray = field(init=False)
    moving: np.ndarray = field(init=False)  # (T,) bool: |q̇| above V_CONTACT_RAD_S

    def __post_init__(self) -> None:
        slow_q = _smooth_segments(self.q[:, None], np.ones(self.q.size), REFERENCE_CUTOFF_HZ, self.fs,
                                  self.segments)[:, 0]
        slow_v = np.zeros_like(slow_q)
        for a, b in self.segments:
            if b - a > 1:
                slow_v[a:b] = np.gradient(slow_q[a:b], 1.0 / self.fs)
        self.fast_q = self.q - slow_q
        self.fast_v = self.v - slow_v
        self.moving = np.abs(self.v) > V_CONTACT_RAD_S

    def friction_A(self, v: np.ndarray) -> np.ndarray:
        """The model's friction current at velocity ``v`` (Coulomb and viscous per direction)."""
        cp, cn, vp, vn = self.friction
        return np.where(v > 0, cp + vp * v, np.where(v < 0, cn + vn * v, 0.0))


@dataclass(eq=False)  # compared by identity (the selection matches a candidate's hyperparameter with ==)
class BacklashFit:
    """A fitted predictor: parameters, the current it adds to the model (T,), and the evidence."""

    params: BacklashParams
    column: np.ndarray  # (T,) A: predicted current − the model's
    sse_after: float  # Σ r² on the fit samples (work rate)
    loop: np.ndarray  # (T,) bool: where the predicted current is the drive loop's (crossings, impacts)


# ------------------------------------------------------------------------------------------ smoothing


def _lambda(cutoff_Hz: float, fs: float) -> float:
    """Whittaker (second-difference) penalty whose half-power frequency is ``cutoff_Hz``."""
    w = 2.0 * math.pi * min(cutoff_Hz, 0.4 * fs) / fs
    return 1.0 / (2.0 * math.sin(w / 2.0)) ** 4


def _whittaker(y: np.ndarray, w: np.ndarray, lam: float) -> np.ndarray:
    """argmin_s Σ w·(y − s)² + λ·Σ (Δ²s)², for each column of y (a banded solve; bridges samples of weight 0)."""
    n = y.shape[0]
    if n < 5 or w.sum() < 3:  # nothing to smooth towards
        return y.copy()
    d0 = np.full(n, 6.0)
    d0[[0, -1]] = 1.0
    d0[[1, -2]] = 5.0
    d1 = np.full(n - 1, -4.0)
    d1[[0, -1]] = -2.0
    ab = np.zeros((5, n))
    ab[0, 2:] = lam
    ab[1, 1:] = lam * d1
    ab[2] = lam * d0 + w + 1e-9
    ab[3, :-1] = lam * d1
    ab[4, :-2] = lam
    return solve_banded((2, 2), ab, w[:, None] * y + 1e-9 * y, check_finite=False)


def _smooth_segments(y: np.ndarray, w: np.ndarray, cutoff_Hz: float, fs: float,
                     segments: list[tuple[int, int]]) -> np.ndarray:
    lam = _lambda(cutoff_Hz, fs)
    out = np.empty_like(y, dtype=float)
    for a, b in segments:
        out[a:b] = _whittaker(y[a:b], w[a:b], lam)
    return out


# ------------------------------------------------------------------------------------------ the rotor


def rotor_modes(path: JointPath, loop_A: np.ndarray, prm: BacklashParams) -> np.ndarray:
    """Simulate the rotor along the measured output: per sample +1/−1 (in contact, pushing the output forward/back)
    or 0 (in flight). ``loop_A`` is the drive's current ŝ − k_p·q − k_d·q̇."""
    T = path.q.size
    modes = np.zeros(T, dtype=np.int8)
    if prm.play_rad <= 0.0:
        modes[:] = 1
        return modes
    J = max(prm.rotor_inertia_A_s2_per_rad, 1e-9)
    phi = prm.output_friction_fraction
    M = path.output_inertia_A_s2_per_rad
    f = path.friction_A(path.v)
    load = path.model_A - f - (M + J) * path.a  # the output's loads besides its own inertia and friction
    tooth = (M * (loop_A - (1.0 - phi) * f) + J * (phi * f + load)) / (M + J)
    c_pos, c_neg, v_pos, v_neg = path.friction
    fr = (c_pos * (1.0 - phi), c_neg * (1.0 - phi), v_pos * (1.0 - phi), v_neg * (1.0 - phi))  # the rotor's share
    for a, b in path.segments:
        _simulate(path.q[a:b], path.v[a:b], loop_A[a:b], tooth[a:b], modes[a:b], 0.5 * prm.play_rad, J, fr,
                  1.0 / path.fs)
    return modes


def _simulate(q: np.ndarray, v: np.ndarray, loop_A: np.ndarray, tooth: np.ndarray, modes: np.ndarray, h: float,
              J: float, fr: tuple[float, float, float, float], dt: float) -> None:
    """The event loop of :func:`rotor_modes` on one stretch (contact phases and a stuck rotor are skipped by search)."""
    T = q.size
    if T < 2:
        modes[:] = 1
        return
    cp, cn, vp, vn = fr
    neg = np.flatnonzero(tooth < 0.0)
    pos = np.flatnonzero(tooth > 0.0)
    brk = np.flatnonzero((loop_A > cp) | (loop_A < cn))  # the loop's current breaks a stuck rotor away
    md = 1 if tooth[0] >= 0.0 else -1
    qr = vr = 0.0
    hdt = dt / SUBSTEPS
    ql, vl, il = q.tolist(), v.tolist(), loop_A.tolist()
    k = 0
    events = 0
    while k < T - 1:
        events += 1
        if events > 4 * T + 16:  # every pass advances k or leaves a contact; more would be a bug, not a hang
            raise RuntimeError("backlash: rotor simulation does not advance")
        if md != 0:  # in contact until the tooth force changes sign
            idx = neg if md > 0 else pos
            p = int(np.searchsorted(idx, k))
            k2 = int(idx[p]) if p < idx.size else T
            modes[k:k2] = md
            if k2 >= T:
                return
            qr, vr = ql[k2] + md * h, vl[k2]
            md = 0
            k = k2
            modes[k] = 0
            continue
        if vr == 0.0 and cn <= il[k] <= cp:  # stuck in the gap: until the current breaks it away or a flank arrives
            p = int(np.searchsorted(brk, k))
            k_brk = int(brk[p]) if p < brk.size else T
            k_brk = max(k_brk, k + 1)
            k_hit = T
            start = k + 1
            while start < min(k_brk, T):
                stop = min(start + 512, k_brk, T)
                hit = np.flatnonzero(np.abs(q[start:stop] - qr) > h)
                if hit.size:
                    k_hit = start + int(hit[0])
                    break
                start = stop
            k2 = min(k_brk, k_hit, T)
            modes[k:k2] = 0
            if k2 >= T - 1:
                return
            k = k2
            if k2 == k_hit:  # the output reaches the resting rotor: contact (the pair's tooth force decides next)
                md = 1 if qr - ql[k2] >= h else -1
                modes[k2] = md
                continue
            # else the loop's current breaks the rotor away at k: fly from here
        # one sample of flight in sub-steps (the output's path and the loop current interpolated)
        q0, q1, v0, v1, i0, i1 = ql[k], ql[k + 1], vl[k], vl[k + 1], il[k], il[k + 1]
        for s in range(1, SUBSTEPS + 1):
            x = s / SUBSTEPS
            qo = q0 + x * (q1 - q0)
            vo = v0 + x * (v1 - v0)
            i = i0 + x * (i1 - i0)
            if vr > 0.0:
                vn_ = vr + hdt * (i - cp - vp * vr) / J
                if vn_ < 0.0:
                    vn_ = 0.0
            elif vr < 0.0:
                vn_ = vr + hdt * (i - cn - vn * vr) / J
                if vn_ > 0.0:
                    vn_ = 0.0
            elif i > cp:
                vn_ = hdt * (i - cp) / J
            elif i < cn:
                vn_ = hdt * (i - cn) / J
            else:
                vn_ = 0.0
            vr = vn_
            qr += vr * hdt
            if qr - qo >= h and vr >= vo:
                md = 1
                break
            if qr - qo <= -h and vr <= vo:
                md = -1
                break
        k += 1
        modes[k] = md


# ------------------------------------------------------------------------------------------ the predictor


def _loop_window(modes: np.ndarray, fs: float, window_s: float) -> np.ndarray:
    """Where the loop's current is used (flights, ± ``window_s`` around impacts); elsewhere the rigid model is
    trusted for ŝ (contact, away from impacts)."""
    flight = modes == 0
    imp = np.zeros(modes.size, dtype=bool)
    imp[1:] = (modes[1:] != 0) & flight[:-1]
    n = int(round(window_s * fs))
    near = np.convolve(imp.astype(float), np.ones(2 * n + 1), mode="same") > 0.5
    return flight | near


def _parts(path: JointPath, weight: np.ndarray, cutoff_Hz: float) -> np.ndarray:
    """(T, 3): S(î) − î, S(q_f) − q_f, S(q̇_f) − q̇_f with S the weighted smoother and q_f the output's fast part — the
    loop's current minus the model's is parts @ (1, k_p, k_d)."""
    y = np.column_stack([path.model_A, path.fast_q, path.fast_v])
    return _smooth_segments(y, weight.astype(float), cutoff_Hz, path.fs, path.segments) - y


def predict(path: JointPath, prm: BacklashParams) -> tuple[np.ndarray, np.ndarray]:
    """The current the play adds to the rigid model (T,) and the loop mask, for known parameters (zero where the
    joint rests: there the current is anywhere in the static band, for the rigid model as for this one)."""
    col, loop, _ = _iterate(path, prm, None)
    return np.where(path.moving, col, 0.0), loop


def _iterate(path: JointPath, prm: BacklashParams,
             resid: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, BacklashParams]:
    """Simulation ↔ loop-input estimate, ``ITERATIONS`` times from the moving samples as contact; with ``resid`` the
    gains are refitted each time (least squares on the fit samples in the loop's windows, non-negative)."""
    gains = np.array([prm.kp_A_per_rad, prm.kd_A_s_per_rad])
    weight = path.moving.copy()
    P = _parts(path, weight, prm.cutoff_Hz)
    loop = np.zeros(path.q.size, dtype=bool)
    for _ in range(ITERATIONS):
        loop_A = path.model_A + P @ np.array([1.0, gains[0], gains[1]])
        modes = rotor_modes(path, loop_A, prm)
        loop = _loop_window(modes, path.fs, path.impact_window_s)
        P = _parts(path, ~loop & path.moving, prm.cutoff_Hz)
        if resid is not None:
            m = path.fit_mask & loop
            if m.sum() >= 10:
                A = P[m, 1:]
                y = resid[m] - P[m, 0]
                g, *_ = np.linalg.lstsq(A, y, rcond=None)
                gains = np.maximum(g, 0.0)
        prm = replace(prm, kp_A_per_rad=float(gains[0]), kd_A_s_per_rad=float(gains[1]))
    col = np.where(loop, P @ np.array([1.0, gains[0], gains[1]]), 0.0)
    return col, loop, prm


def fit(path: JointPath, resid: np.ndarray, rotor_inertia_A_s2_per_rad: float,
        min_gain: float = 0.0) -> BacklashFit | None:
    """The play, the output's friction share and the loop gains that best explain ``resid`` (measured − model current,
    work rate) on the fit samples: a grid over play and share (gains by least squares inside), then Nelder–Mead on
    both. Returns None when the grid's first (screening) points lower the error by less than ``min_gain``
    (relative): nothing there to search for."""
    m = path.fit_mask
    if m.sum() < 50:
        return None
    sse0 = float(resid[m] @ resid[m])

    def run(b: float, phi: float) -> tuple[float, np.ndarray, np.ndarray, BacklashParams]:
        _, _, prm = _iterate(path, BacklashParams(b, rotor_inertia_A_s2_per_rad, 0.0, 0.0, phi), resid)
        col, loop = predict(path, prm)  # the gains found; scored as the params file will reproduce it
        e = resid[m] - col[m]
        return float(e @ e), col, loop, prm

    best: tuple[float, np.ndarray, np.ndarray, BacklashParams] | None = None
    screen = [(b, phi) for b in SCREEN_PLAYS_RAD for phi in SCREEN_SHARES]
    for b, phi in screen + [(b, phi) for b in PLAYS_RAD for phi in SHARES if (b, phi) not in screen]:
        r = run(b, phi)
        if best is None or r[0] < best[0]:
            best = r
        if (b, phi) == screen[-1] and sse0 - best[0] <= min_gain * sse0:
            return None  # the screen found nothing: no play worth a full search
    assert best is not None
    cache: dict[tuple[float, float], tuple[float, np.ndarray, np.ndarray, BacklashParams]] = {}

    def f(x: np.ndarray) -> float:
        b, phi = math.exp(x[0]), float(x[1])
        if not (0.0 <= phi <= 0.9 and 1e-4 <= b <= 0.2):
            return float("inf")
        key = (round(b, 7), round(phi, 5))
        if key not in cache:
            cache[key] = run(b, phi)
        return cache[key][0]

    x0 = np.array([math.log(best[3].play_rad), best[3].output_friction_fraction])
    simplex = np.array([x0, x0 + [math.log(1.4), 0.0], x0 + [0.0, 0.07]])
    minimize(f, x0, method="Nelder-Mead", options={"initial_simplex": simplex, "maxfev": 16, "xatol": 0.02,
                                                   "fatol": 1e-9})
    for r in cache.values():
        if r[0] < best[0]:
            best = r
    sse, col, loop, prm = best
    return BacklashFit(prm, col, sse, loop)


def params_dict(prm: BacklashParams, kt: float) -> dict[str, Any]:
    """The params file's ``effects`` entries of a fitted play (joint side, SI and A units)."""
    return {"backlash_rad": float(prm.play_rad), "backlash_inertia_kgm2": float(prm.rotor_inertia_A_s2_per_rad * kt),
            "backlash_loop_A_per_rad": [float(prm.kp_A_per_rad), float(prm.kd_A_s_per_rad)],
            "backlash_output_friction_fraction": float(prm.output_friction_fraction),
            "backlash_cutoff_Hz": float(prm.cutoff_Hz)}
