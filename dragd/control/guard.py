"""The runaway guard in DRAG: motion that nobody's hand explains falls back to HOLD (docs/PAYLOAD.md).

A generalised-momentum observer (De Luca's residual, Coriolis term neglected at hand-guiding speeds; the arithmetic of
dragd/control/observer.py, which the contact detector shares) estimates the joint torque the model does not account
for:

    r = K_o·(p − p₀ − ∫(τ_in + r) dt),   p = M(q)·q̇,
    τ_in = K_t·(I_cmd − I_gravity − I_offset − I_friction − I_startup − I_effects)   (damping, walls, speed cap)

so r ≈ τ_hand + (G_true − G_model) + (friction error). A hung-on tool, a removed one, a wrong K_t or sign all
make r a torque that *drives* the motion (r·q̇ > 0) and keeps it accelerating; so does a hand. The guard tells
them apart by where the torque acts and how it changes:

* a joint is a candidate while it moves (|q̇| > ``speed_rad_s``), the residual drives it (r·q̇ > 0, |r|/K_t >
  ``residual_A``) and it does not slow down (|q̇| ≥ ``keep_speed``·the run's peak: an operator's hand brings the
  arm to a stop at its target; a released arm under a gravity error does not);
* a run that goes on for ``run_max_s`` without slowing (a released arm at its terminal speed, where the residual
  is only the virtual damping's torque) is tested again every ``run_max_s`` with a residual above residual_A/3;
* after ``confirm_s`` of candidacy the residual vector is tested against what a load on the flange can produce at
  q (``explain``: the fraction of r outside span Y(q), the payload regressor): a hand pulling several joints (or
  the vertical first axis, which gravity never loads) is not payload-like → that run is the hand's and is not
  tripped again until it ends; a payload-like residual trips: HOLD where the arm is, the event names the joint,
  the missing torque and the flange mass that would explain it;
* but a joint at rest that a load can reach may be holding its share of it by static friction (its residual reads
  ~0 until it breaks away): while one is, a "not payload-like" verdict is deferred — tested again every
  ``stuck_retest_s`` — until ``stuck_wait_s`` after the first verdict of the motion (the window opens again once the
  arm has come to rest); only then is the run the hand's. A "brakes the arm" verdict (``drive_share``) is final.

Decisions use the residual and the joint speeds low-passed at ``decide_Hz`` (first order): on a real controller the
velocity estimate is noisy (encoder quantisation; on a loaded host late or repeated position samples), and K_o passes
that noise straight into r — unfiltered, a runaway's speed "drops" below ``keep_speed`` of its peak every few cycles
and no run ever lasts ``confirm_s``. The observer integrates the true elapsed time (a late cycle counts the periods
it missed). Time to trip after the arm starts moving ≈ observer lag (1/K_o) + decision filter lag (1/(2π·decide_Hz))
+ ``confirm_s``. Allocation-free per cycle; the test against Y(q) (Pinocchio, least squares) runs once per candidate
run, or up to ``stuck_wait_s``/``stuck_retest_s`` + 1 times in a motion while a loaded joint rests.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from dragd.control.observer import observer_step, observer_step_np
from dragd.jit import compile_kernels


@dataclass(frozen=True)
class GuardSettings:
    observer_Hz: float = 10.0  # residual bandwidth K_o/2π (K_o passes q̇ noise into r: not higher)
    speed_rad_s: float = 0.03  # a joint slower than this is not running away
    residual_A: float = 0.3  # a missing torque smaller than this (as current) is friction's business
    confirm_s: float = 0.03  # candidacy this long before the payload-likeness test
    keep_speed: float = 0.85  # a run whose speed falls below this fraction of its peak is decelerating: not a runaway
    unexplained_max: float = 0.1  # a residual with more than this fraction outside span Y(q) is a hand's
    settle_s: float = 0.05  # after (re)arming: observer transient, no decision
    run_max_s: float = 0.5  # a run that goes on this long without slowing is tested again (with any residual)
    stuck_wait_s: float = 0.06  # a verdict "not a load" with a joint at rest is final only this long after the first
    stuck_retest_s: float = 0.01  # ... and tested again this often meanwhile (static friction may hide the load)
    decide_Hz: float = 8.0  # low-pass of the residual and speeds the decisions use (velocity noise)
    drive_share: float = 0.5  # a runaway's residual drives the arm: r·q̇ at least this share of Σ|r_j·q̇_j|


@dataclass(frozen=True)
class Trip:
    joint: int
    residual_Nm: float
    residual_A: float
    speed_rad_s: float
    payload_kg: float
    unexplained: float
    text: str


Explain = Callable[[np.ndarray, np.ndarray], tuple[float, float]]  # (q, r) → (unexplained fraction, flange kg)


def _guard_kernel(dt: float, alpha: float, settled: bool, tau: np.ndarray, p: np.ndarray, dq: np.ndarray,
                  p0: np.ndarray, integ: np.ndarray, r: np.ndarray, r_f: np.ndarray, v_f: np.ndarray,
                  run_s: np.ndarray, peak: np.ndarray, sign: np.ndarray, hand: np.ndarray, kt: np.ndarray,
                  due: np.ndarray, k_o: float, dt_nominal: float, speed: float, keep: float, residual: float,
                  confirm_s: float, run_max_s: float, retest: bool, running: bool) -> tuple[int, bool]:
    """``RunawayGuard.update``'s arithmetic (the numpy below is its reference): (0 nothing | 1 the fast path's
    test is due | 2 the slow path's, with ``due`` marking the joints; the new ``running``)."""
    n = tau.shape[0]
    observer_step(dt, k_o, tau, p, p0, integ, r)
    for j in range(n):
        a = r[j] - r_f[j]
        a *= alpha
        r_f[j] += a
        a = dq[j] - v_f[j]
        a *= alpha
        v_f[j] += a
    if not settled:
        return 0, running
    top = abs(v_f[0])
    for j in range(1, n):
        a = abs(v_f[j])
        top = a if (a >= top or a != a) else top  # (np.max: NaN wins)
    if top <= speed:
        if running:
            for j in range(n):
                run_s[j] = 0.0
                peak[j] = 0.0
                hand[j] = False
        return 0, False
    for j in range(n):
        a = abs(v_f[j])
        m = a > speed and r_f[j] * v_f[j] > 0.0
        sg = 1.0 if v_f[j] > 0.0 else (-1.0 if v_f[j] < 0.0 else v_f[j])  # np.sign
        b = peak[j] if (peak[j] >= a or peak[j] != peak[j]) else a  # np.maximum
        if sg != sign[j]:  # direction changed: the peak restarts
            b = a
        peak[j] = b
        m = m and a >= peak[j] * keep
        sign[j] = sg
        run_s[j] += dt_nominal
        run_s[j] *= 1.0 if m else 0.0
        if not m:
            hand[j] = False
            peak[j] = 0.0
    count = 0
    for j in range(n):
        b = abs(r_f[j] / kt[j])
        x = b > residual and not hand[j] and run_s[j] >= confirm_s
        due[j] = x
        count += 1 if x else 0
    if count:
        return 1, True
    for j in range(n):
        b = abs(r_f[j] / kt[j])
        x = run_s[j] >= run_max_s and b > residual / 3.0
        due[j] = x
        count += 1 if x else 0
    if count and retest:
        return 2, True
    return 0, True


def _guard_command_kernel(cmd: np.ndarray, gravity_A: np.ndarray, offset_A: np.ndarray, friction_A: np.ndarray,
                          startup_A: np.ndarray, effects_A: np.ndarray, with_effects: bool, kt_tau: np.ndarray,
                          dt: float, alpha: float, settled: bool, tau: np.ndarray, p: np.ndarray, dq: np.ndarray,
                          p0: np.ndarray, integ: np.ndarray, r: np.ndarray, r_f: np.ndarray, v_f: np.ndarray,
                          run_s: np.ndarray, peak: np.ndarray, sign: np.ndarray, hand: np.ndarray, kt: np.ndarray,
                          due: np.ndarray, k_o: float, dt_nominal: float, speed: float, keep: float, residual: float,
                          confirm_s: float, run_max_s: float, retest: bool, running: bool) -> tuple[int, bool]:
    """``tau`` ← τ_in = K_t·(I − gravity − offset − friction − start-up [− effects]) (``update_from_command``'s
    numpy, in its order), then ``_guard_kernel``."""
    for j in range(tau.shape[0]):
        a = cmd[j] - gravity_A[j]
        a -= offset_A[j]
        a -= friction_A[j]
        a -= startup_A[j]
        if with_effects:
            a -= effects_A[j]
        a *= kt_tau[j]
        tau[j] = a
    return _guard_kernel(dt, alpha, settled, tau, p, dq, p0, integ, r, r_f, v_f, run_s, peak, sign, hand, kt, due,
                         k_o, dt_nominal, speed, keep, residual, confirm_s, run_max_s, retest, running)


def _kernels() -> dict[str, Any] | None:
    """Both compiled guard kernels (once per process), or None where numba cannot be imported."""
    f1, b1 = np.zeros(1), np.zeros(1, dtype=bool)
    state = (f1, f1, f1.copy(), f1.copy(), f1.copy(), f1.copy(), f1.copy(), f1.copy(), f1.copy(), f1.copy(), b1,
             np.ones(1), b1.copy(), 60.0, 1e-3, 0.03, 0.85, 0.3, 0.03, 0.5, True, True)  # (p, dq, ... running)
    return compile_kernels(globals(), ("observer_step", "_guard_kernel"), {
        "guard": (_guard_kernel, (1e-3, 0.05, True, f1.copy(), *state)),
        "guard_command": (_guard_command_kernel, (f1, f1, f1, f1, f1, f1, False, np.ones(1), 1e-3, 0.05, True,
                                                  f1.copy(), *state))})


def guard_kernel() -> Any:
    """The compiled ``_guard_kernel`` (once per process), or None where numba cannot be imported."""
    k = _kernels()
    return None if k is None else k["guard"]


def guard_command_kernel() -> Any:
    """The compiled ``_guard_command_kernel`` (``update_from_command``), or None where numba cannot be imported."""
    k = _kernels()
    return None if k is None else k["guard_command"]


class RunawayGuard:
    """Momentum-observer residual and the per-joint runaway decision for n joints."""

    def __init__(self, n: int, kt_Nm_per_A: np.ndarray, dt_s: float, settings: GuardSettings,
                 explain: Explain | None, joint_names: list[str]) -> None:
        self.n, self.kt, self.dt, self.s = n, kt_Nm_per_A, dt_s, settings
        self.explain = explain
        self.names = joint_names
        self.k_o = 2.0 * math.pi * settings.observer_Hz
        self.p0 = np.zeros(n)
        self.integ = np.zeros(n)
        self.r = np.zeros(n)  # residual [N·m]
        self.r_f = np.zeros(n)  # the residual low-passed at decide_Hz: what the decisions see [N·m]
        self.v_f = np.zeros(n)  # joint speeds low-passed at decide_Hz [rad/s]
        self._t_last = 0.0
        self.run_s = np.zeros(n)  # candidacy time of each joint's present run
        self.peak = np.zeros(n)  # the run's peak speed
        self.sign = np.zeros(n)  # the run's direction
        self.hand = np.zeros(n, dtype=bool)  # the run was judged a hand's
        self.armed_at = math.inf
        self.checks = 0  # payload-likeness tests run (hand runs + deferred verdicts + trips)
        self.hand_runs = 0
        self._a = np.zeros(n)
        self._b = np.zeros(n)
        self._m = np.zeros(n, dtype=bool)
        self._m2 = np.zeros(n, dtype=bool)
        self._m3 = np.zeros(n, dtype=bool)
        self.retest_at = 0.0
        self.running = False
        self._stuck_open = False  # a "not a load" verdict in this motion (the first at _stuck_since)
        self._stuck_since = 0.0
        self._retest_stuck_at = -math.inf
        self.stuck_deferrals = 0  # "not a load" verdicts deferred: a loaded joint at rest (friction may hide the load)
        # joints no flange load reaches at any pose (a vertical first axis): at rest they hide nothing (the daemon sets
        # it from the model's payload regressor)
        self.load_free = np.zeros(n, dtype=bool)
        self._kernel: Any = None
        self._command_kernel: Any = None

    def use_kernel(self, kernel: Any, command_kernel: Any = None) -> None:
        """``update`` by the compiled kernel (``guard_kernel()``; the numpy in ``update`` is its reference), and
        ``update_from_command`` by ``guard_command_kernel()`` (τ_in fused into the same call)."""
        self._kernel = kernel
        self._command_kernel = command_kernel

    def arm(self, p_Nms: np.ndarray, t_s: float) -> None:
        """Start watching (the drag law is fully in): the observer starts from the present momentum."""
        self.p0[:] = p_Nms
        self.integ.fill(0.0)
        self.r.fill(0.0)
        self.r_f.fill(0.0)
        self.v_f.fill(0.0)
        self._t_last = t_s
        self.run_s.fill(0.0)
        self.peak.fill(0.0)
        self.sign.fill(0.0)
        self.hand.fill(False)
        self._end_stuck()
        self.armed_at = t_s

    def disarm(self) -> None:
        self.armed_at = math.inf

    @property
    def armed(self) -> bool:
        return self.armed_at != math.inf

    def update_from_command(self, t_s: float, q: np.ndarray, dq: np.ndarray, p_Nms: np.ndarray, cmd_A: np.ndarray,
                            gravity_A: np.ndarray, offset_A: np.ndarray, friction_A: np.ndarray,
                            startup_A: np.ndarray, effects_A: np.ndarray | None, kt_Nm_per_A: np.ndarray,
                            tau_out: np.ndarray) -> Trip | None:
        """``update`` with τ_in = K_t·(I_cmd − gravity − offset − friction − start-up [− effects]) computed into
        ``tau_out`` first (by the command kernel in the same call, when it is in use)."""
        if self._command_kernel is None or not self.armed:
            np.subtract(cmd_A, gravity_A, out=tau_out)
            tau_out -= offset_A
            tau_out -= friction_A
            tau_out -= startup_A
            if effects_A is not None:
                tau_out -= effects_A
            tau_out *= kt_Nm_per_A
            return self.update(t_s, q, dq, p_Nms, tau_out)
        s = self.s
        dt = self._elapsed(t_s)
        code, self.running = self._command_kernel(
            cmd_A, gravity_A, offset_A, friction_A, startup_A, cmd_A if effects_A is None else effects_A,
            effects_A is not None, kt_Nm_per_A, dt, 1.0 - math.exp(-2.0 * math.pi * s.decide_Hz * dt),
            t_s - self.armed_at >= s.settle_s, tau_out, p_Nms, dq, self.p0, self.integ, self.r, self.r_f, self.v_f,
            self.run_s, self.peak, self.sign, self.hand, self.kt, self._m2, self.k_o, self.dt, s.speed_rad_s,
            s.keep_speed, s.residual_A, s.confirm_s, s.run_max_s, t_s >= self.retest_at, self.running)
        return self._decided(code, t_s, q)

    def update(self, t_s: float, q: np.ndarray, dq: np.ndarray, p_Nms: np.ndarray,
               tau_in_Nm: np.ndarray) -> Trip | None:
        """One cycle: advance the observer; a :class:`Trip` when a joint runs away."""
        if not self.armed:
            return None
        s, a, b, m, m2 = self.s, self._a, self._b, self._m, self._m2
        dt = self._elapsed(t_s)
        if self._kernel is not None:
            code, self.running = self._kernel(
                dt, 1.0 - math.exp(-2.0 * math.pi * s.decide_Hz * dt), t_s - self.armed_at >= s.settle_s, tau_in_Nm,
                p_Nms, dq, self.p0, self.integ, self.r, self.r_f, self.v_f, self.run_s, self.peak, self.sign,
                self.hand, self.kt, m2, self.k_o, self.dt, s.speed_rad_s, s.keep_speed, s.residual_A, s.confirm_s,
                s.run_max_s, t_s >= self.retest_at, self.running)
            return self._decided(code, t_s, q)
        # observer (dragd/control/observer.py): integ += (τ_in + r)·dt;  r = K_o·(p − p₀ − integ)
        observer_step_np(dt, self.k_o, tau_in_Nm, p_Nms, self.p0, self.integ, self.r, a)
        # the decision signals: residual and speeds low-passed (first order, exact for the step dt)
        alpha = 1.0 - math.exp(-2.0 * math.pi * s.decide_Hz * dt)
        np.subtract(self.r, self.r_f, out=a)
        a *= alpha
        self.r_f += a
        np.subtract(dq, self.v_f, out=a)
        a *= alpha
        self.v_f += a
        if t_s - self.armed_at < s.settle_s:
            return None
        dq = self.v_f  # (below: the filtered speeds)
        # runs: moving, driven by the residual (r·q̇ > 0), not slowing down (|q̇| ≥ keep_speed·the run's peak)
        np.abs(dq, out=a)  # a = speed
        if float(a.max()) <= s.speed_rad_s:  # the usual cycle at rest: no run can go on
            if self.running:
                self.run_s.fill(0.0)
                self.peak.fill(0.0)
                self.hand.fill(False)
                self.running = False
                if self._stuck_open:
                    self._end_stuck()
            return None
        self.running = True
        np.greater(a, s.speed_rad_s, out=m)
        np.multiply(self.r_f, dq, out=b)
        np.greater(b, 0.0, out=m2)
        m &= m2
        np.sign(dq, out=b)
        np.equal(b, self.sign, out=m2)  # same direction as the run so far (a new run starts below)
        np.maximum(self.peak, a, out=b)
        np.copyto(b, a, where=~m2)  # (direction changed: the peak restarts)
        np.copyto(self.peak, b)
        np.multiply(self.peak, s.keep_speed, out=b)
        np.greater_equal(a, b, out=m2)
        m &= m2
        np.sign(dq, out=self.sign)
        self.run_s += self.dt
        self.run_s *= m
        np.copyto(self.hand, False, where=~m)
        np.copyto(self.peak, 0.0, where=~m)
        # fast path: a missing torque above residual_A for confirm_s → the payload-likeness test, once per run
        np.divide(self.r_f, self.kt, out=b)
        np.abs(b, out=b)
        np.greater(b, s.residual_A, out=m2)
        m2 &= ~self.hand
        np.greater_equal(self.run_s, s.confirm_s, out=self._m3)
        m2 &= self._m3
        if np.count_nonzero(m2):
            return self._fast_test(t_s, q, dq, m2)
        # slow path: a run that keeps going for run_max_s (at a terminal speed the residual is only the virtual
        # damping's torque) is tested again every run_max_s, with any residual
        np.greater_equal(self.run_s, s.run_max_s, out=m2)
        np.greater(b, s.residual_A / 3.0, out=self._m3)  # (b = |r|/K_t) a residual above friction noise
        m2 &= self._m3
        if np.count_nonzero(m2) and t_s >= self.retest_at:
            self.retest_at = t_s + s.run_max_s
            self.hand &= ~m2
            return self._decide(t_s, q, dq, m2)
        return None

    def _elapsed(self, t_s: float) -> float:
        """The true elapsed time since the last update (a late cycle missed periods); bounded against clock steps."""
        dt = min(max(t_s - self._t_last, 0.0), 0.05) if t_s > self._t_last else self.dt
        self._t_last = t_s
        return dt

    def _end_stuck(self) -> None:
        self._stuck_open = False
        self._retest_stuck_at = -math.inf

    def _decided(self, code: int, t_s: float, q: np.ndarray) -> Trip | None:
        """After a kernel: the test it found due (1: the fast path's, 2: the slow path's; ``_m2`` marks the joints)."""
        if code == 0:
            if self._stuck_open and not self.running:  # the arm came to rest: a new episode tests afresh
                self._end_stuck()
            return None
        if code == 1:
            return self._fast_test(t_s, q, self.v_f, self._m2)
        if code == 2:
            self.retest_at = t_s + self.s.run_max_s
            self.hand &= ~self._m2
            return self._decide(t_s, q, self.v_f, self._m2)
        return None

    def _fast_test(self, t_s: float, q: np.ndarray, dq: np.ndarray, due: np.ndarray) -> Trip | None:
        """The fast path's test, unless a deferred verdict's retest is not due yet (a joint at rest may hide the
        load)."""
        return None if t_s < self._retest_stuck_at else self._decide(t_s, q, dq, due)

    def _decide(self, t_s: float, q: np.ndarray, dq: np.ndarray, due: np.ndarray) -> Trip | None:
        """Rare path (once per candidate run; repeated while a joint at rest may hide the load): is the residual what a
        flange load would produce?"""
        self.checks += 1
        # a runaway is driven by what is missing: the residual does positive work on the arm as a whole. A hand that
        # brakes a moving arm (an upward pull on an arm moving down) can drive one joint while it brakes the others,
        # and its force can look like a lighter load: it is the hand's while it takes more energy than it gives
        p = self.r_f * dq  # (rare path: allocates)
        if float(p.sum()) < self.s.drive_share * float(np.abs(p).sum()):
            self.hand |= due
            self.hand_runs += 1
            return None
        unexplained, kg = self.explain(q, self.r_f) if self.explain is not None else (0.0, float("nan"))
        if unexplained > self.s.unexplained_max:
            # a joint at rest that a load reaches may be holding its share by static friction (its residual then reads
            # ~0 until it breaks away): not the hand's yet; tested again while that can last
            if not self._stuck_open:
                self._stuck_open, self._stuck_since = True, t_s
            resting = np.abs(dq) <= self.s.speed_rad_s  # (rare path: allocates)
            resting &= ~self.load_free
            if t_s - self._stuck_since < self.s.stuck_wait_s and bool(resting.any()):
                self._retest_stuck_at = t_s + self.s.stuck_retest_s
                self.stuck_deferrals += 1
                return None
            self.hand |= due
            self.hand_runs += 1
            return None
        return self._trip(q, dq, due, kg, unexplained)

    def _trip(self, q: np.ndarray, dq: np.ndarray, due: np.ndarray, kg: float, unexplained: float) -> Trip:
        ratio = np.abs(self.r_f) / self.kt
        j = int(np.argmax(np.where(due, ratio, -1.0)))
        r, v = float(self.r_f[j]), float(dq[j])
        kg_text = f"; a load of about {kg:.2f} kg at the flange would explain it" if math.isfinite(kg) else ""
        text = (f"runaway in drag: {self.names[j]} moving {v:+.3f} rad/s, driven by {r:+.1f} N·m "
                f"({r / self.kt[j]:+.2f} A) that the model and no hand explain{kg_text}; holding. "
                "Check the payload (dragd payload estimate) and the joint's sign and torque constant "
                "(dragd check model)")
        self.disarm()
        return Trip(j, r, r / float(self.kt[j]), v, kg, unexplained, text)
