"""Contact detection: the momentum-observer residual against per-joint bands that depend on what each joint does.

The residual (dragd/control/observer.py) of the identified model (base parameters mapped to link inertials, rotor
inertias, friction, K_t) is the torque nobody commanded, τ_ext, low-passed at K_o, plus the model's error. In
amperes, e_j = r_j / K_t,j. What that error looks like depends on the joint's state, so each joint is judged
against the band of its state (docs/CONTACT.md):

* **moving** (|q̇_j| ≥ ``rest_speed``): friction is set by the speed; d_j = e_j against the moving band
  (``ContactBands``: a base plus terms in the low-speed indicator, the speed and the acceleration, each low-passed
  like the residual — the model is worst at reversals, break-away and hard accelerations).
* **settling** (just stopped): the joint has stuck; static friction holds whatever it held when it stopped, anywhere
  within ±F_s: d_j = e_j against ``settling_A`` (at least the identified static level).
* **held** (at rest for ``settle_s`` and its residual still — within hysteresis·``held_A`` of one value for
  ``still_s``): the stuck joint's friction is now a constant the model cannot know; its
  residual is latched as the baseline b_j (followed slowly, ``baseline_s``, while nothing is pending: a position
  loop unwinds its integrator over seconds) and a contact is a departure from it: d_j = e_j − b_j against
  ``held_A`` (+ ``held_moving_A`` while the rest of the arm moves: coupling torques' model error).

* **released** (after a contact ended on an arm at rest): the pushed arm was let go and springs back, its stuck
  joints may now hold other friction — anywhere within the static band — and a position loop unwinds its integrator
  over seconds: the baseline is latched anew at the release and d_j = e_j − b_j is judged against ``settling_A``
  (the static band) until the residual is still — within hysteresis·``held_A`` of one value for ``still_s`` (at
  least ``release_s`` after the release); then held again, the baseline latched once more.

A held (or released) joint's baseline follows its residual with the time constant ``baseline_s`` while nothing is
pending (|d_j| below ``hysteresis`` of its band): a position loop unwinding its integrator after a release drifts
the residual over seconds; a contact builds up faster than hysteresis·band/baseline_s and freezes the baseline.

A joint alarms when |d_j| exceeds its band × ``scale`` (1/sensitivity). The first alarm starts an event; the event
collects every joint that alarms and their peak |d|·K_t (the estimated contact torque). A joint leaves the event
once it has been quiet for ``clear_s``: below ``hysteresis`` of its band, or, at rest, let go — back across its
baseline or under half its peak (a held arm springs back when released); a joint at rest leaves it released. The
event ends when no joint is left in it, and then every held joint is released too.

Pure functions over preallocated arrays: ``ContactDetector.update`` is the numpy reference, ``_contact_kernel`` the
compiled form (same arithmetic, tests/test_contact_kernel.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from dragd.control.observer import observer_step, observer_step_np
from dragd.jit import compile_kernels

# update() codes
QUIET, ONSET, ONGOING, ENDED = 0, 1, 2, 3
# per-joint states
MOVING, SETTLING, HELD, RELEASED = 0, 1, 2, 3
STATE_NAMES = ("moving", "settling", "held", "released")


@dataclass(frozen=True)
class ContactBands:
    """Per-joint bands [A] of the detector (``dragd contact calibrate`` sets them from free-motion logs).

    Moving: base_A + slow_A·L + speed_A_s_per_rad·V + accel_A_s2_per_rad·A, with L = max(0, 1 − |q̇|/slow_speed),
    V = |q̇| and A = |q̈| (the velocity's difference) each passed through the observer's own first-order filter
    (K_o): the residual is the low-pass of the model's error, so the band is the low-pass of where that error lives.
    """

    base_A: np.ndarray
    slow_A: np.ndarray
    speed_A_s_per_rad: np.ndarray
    accel_A_s2_per_rad: np.ndarray
    slow_speed_rad_s: np.ndarray
    settling_A: np.ndarray
    held_A: np.ndarray
    held_moving_A: np.ndarray  # added to a held joint's band while the rest of the arm moves (filtered like L, V, A)

    @classmethod
    def uniform(cls, n: int, base_A: float = 1.0, slow_A: float = 0.5, speed_A_s_per_rad: float = 0.0,
                accel_A_s2_per_rad: float = 0.0, slow_speed_rad_s: float = 0.1, settling_A: float = 1.5,
                held_A: float = 0.5, held_moving_A: float = 0.0) -> ContactBands:
        f = np.full
        return cls(f(n, base_A), f(n, slow_A), f(n, speed_A_s_per_rad), f(n, accel_A_s2_per_rad),
                   f(n, slow_speed_rad_s), f(n, settling_A), f(n, held_A), f(n, held_moving_A))


@dataclass(frozen=True)
class ContactSettings:
    observer_gain_per_s: float = 25.0  # K_o: the residual's time constant is 1/K_o
    rest_speed_rad_s: float = 0.005  # slower: at rest (friction no longer set by the speed; the law's tanh width)
    settle_s: float = 0.3  # at rest this long: held (its residual latched as the baseline)
    baseline_s: float = 0.25  # a held joint's baseline follows its residual with this time constant while quiet
    release_s: float = 0.5  # after a contact on an arm at rest, its joints are judged as released at least this long
    still_s: float = 0.5  # ... and until their residual stays within hysteresis·held_A of one value this long
    hysteresis: float = 0.5  # an event's joint is quiet below this fraction of its band
    clear_s: float = 0.05  # an event ends when all its joints are quiet this long
    arm_s: float = 0.2  # after arming, no decision for this long (the observer starts from the present momentum)
    scale: float = 1.0  # the bands × scale (1/sensitivity of the mode)


@dataclass
class ContactEvent:
    t_start_s: float
    t_end_s: float | None
    joints: list[int]
    peak_Nm: list[float]  # per joint of ``joints``: the largest |d|·K_t during the event
    peak_A: list[float]
    states: list[str]  # each joint's state at its first alarm

    def to_json(self, names: list[str]) -> dict[str, Any]:
        return {"t_start_s": round(self.t_start_s, 4),
                "t_end_s": None if self.t_end_s is None else round(self.t_end_s, 4),
                "joints": [names[j] for j in self.joints], "peak_Nm": [round(x, 3) for x in self.peak_Nm],
                "peak_A": [round(x, 3) for x in self.peak_A], "states": self.states}


class ContactDetector:
    """Momentum observer + per-joint bands + events for n joints (Model/Data style: settings constant, state here)."""

    def __init__(self, kt_Nm_per_A: np.ndarray, bands: ContactBands, settings: ContactSettings) -> None:
        n = kt_Nm_per_A.shape[0]
        self.n, self.kt, self.bands, self.s = n, np.asarray(kt_Nm_per_A, dtype=float), bands, settings
        # observer
        self.p0 = np.zeros(n)
        self.integ = np.zeros(n)
        self.r = np.zeros(n)  # residual [N·m]
        # per joint
        self.e = np.zeros(n)  # residual [A]
        self.d = np.zeros(n)  # deviation judged [A]
        self.band = np.zeros(n)  # the band it was judged against [A] (× scale)
        self.rest_s = np.zeros(n)
        self.state = np.zeros(n, dtype=np.int64)
        self.baseline = np.zeros(n)
        self.release_left_s = np.zeros(n)
        self.anchor = np.zeros(n)  # where the deviation has stayed (within hysteresis·held_A) for still_time
        self.still_time = np.zeros(n)
        self.over = np.zeros(n, dtype=bool)
        self.in_event = np.zeros(n, dtype=bool)
        self.peak = np.zeros(n)  # signed peak deviation of the event [A]
        self.first_state = np.zeros(n, dtype=np.int64)
        self.quiet_t = np.zeros(n)  # how long each joint of the event has been quiet
        self.pratio = np.zeros(n)  # each joint's largest |d|/band in the event (the dominant joint has the largest)
        # the band's features, low-passed like the residual: low-speed indicator, speed, acceleration, arm moving
        self.f_low = np.zeros(n)
        self.f_speed = np.zeros(n)
        self.f_acc = np.zeros(n)
        self.f_arm = np.zeros(n)  # (one value for the arm, kept per joint)
        self.dq_prev = np.zeros(n)
        # event
        self.active = False
        self.t_start = 0.0
        self.armed_at = math.inf
        self._t_last = 0.0
        self.events: list[ContactEvent] = []
        self._a = np.zeros(n)
        self._b = np.zeros(n)
        self._m = np.zeros(n, dtype=bool)
        self._m2 = np.zeros(n, dtype=bool)
        self._m3 = np.zeros(n, dtype=bool)
        self._m4 = np.zeros(n, dtype=bool)
        self._no_ref = np.zeros(n, dtype=bool)
        self._kernel: Any = None
        self._cycle_kernel: Any = None
        self._observe_kernel: Any = None
        self.tau_in = np.zeros(n)  # the model's τ_in of the last ``update_cycle`` [N·m]
        self.F: np.ndarray | None = None  # the packed model (``set_model``)
        self.FS = np.zeros(3)
        self._pack()

    def _pack(self) -> None:
        b = self.bands
        self.P = np.vstack([np.broadcast_to(np.asarray(x, dtype=float), (self.n,)) for x in (
            b.base_A, b.slow_A, b.speed_A_s_per_rad, b.accel_A_s2_per_rad, b.slow_speed_rad_s, b.settling_A,
            b.held_A, self.kt, b.held_moving_A)])
        s = self.s
        self.S = np.array([s.observer_gain_per_s, s.rest_speed_rad_s, s.settle_s, s.release_s, s.baseline_s,
                           s.hysteresis, s.clear_s, s.scale, s.still_s])

    def use_kernel(self, kernel: Any) -> None:
        """``update`` by the compiled kernel (``contact_kernel()``; the numpy in ``update`` is its reference)."""
        self._kernel = kernel

    def set_model(self, F: np.ndarray, FS: np.ndarray) -> None:
        """The identified model ``update_cycle`` computes τ_in with (``pack_model``)."""
        self.F, self.FS = np.ascontiguousarray(F, dtype=float), np.ascontiguousarray(FS, dtype=float)

    def use_cycle_kernels(self, kernels: dict[str, Any]) -> None:
        """``update_cycle`` and ``observe_cycle`` by the compiled kernels (``contact_kernels()``)."""
        self._cycle_kernel, self._observe_kernel = kernels["cycle"], kernels["observe"]

    def observe_cycle(self, t_s: float, dq: np.ndarray, p_Nms: np.ndarray, i_A: np.ndarray, g_Nm: np.ndarray,
                      C: np.ndarray) -> None:
        """The residual alone (``r``, ``e``), no bands or events: in drag, where it is the operator's hand."""
        if not self.armed:
            return
        assert self.F is not None, "ContactDetector.observe_cycle: set_model first"
        dt = self._elapsed(t_s)
        k = self._observe_kernel
        if k is not None:
            k(dt, dq, p_Nms, i_A, g_Nm, C, self.F, self.FS, self.tau_in, self.s.observer_gain_per_s, self.p0,
              self.integ, self.r, self.e)
            return
        contact_tau_in(dq, i_A, g_Nm, C, self.F, self.FS, self.tau_in)
        observer_step_np(dt, self.s.observer_gain_per_s, self.tau_in, p_Nms, self.p0, self.integ, self.r, self._a)
        np.divide(self.r, self.F[F_KT], out=self.e)

    def update_cycle(self, t_s: float, dq: np.ndarray, p_Nms: np.ndarray, i_A: np.ndarray, g_Nm: np.ndarray,
                     C: np.ndarray, ref_moving: np.ndarray | None = None) -> int:
        """``update`` with τ_in computed here from the measured current ``i_A``, gravity ``g_Nm`` and the Coriolis
        matrix ``C`` (the cycle's form: one compiled call after Pinocchio's; ``set_model`` first)."""
        if not self.armed:
            return QUIET
        assert self.F is not None, "ContactDetector.update_cycle: set_model first"
        k = self._cycle_kernel
        if k is None:
            contact_tau_in(dq, i_A, g_Nm, C, self.F, self.FS, self.tau_in)
            return self.update(t_s, dq, p_Nms, self.tau_in, ref_moving)
        rm = self._no_ref if ref_moving is None else ref_moving
        dt = self._elapsed(t_s)
        settled = t_s - self.armed_at >= self.s.arm_s
        code, self.active = k(
            dt, settled, self.active, dq, p_Nms, i_A, g_Nm, C, self.F, self.FS, self.tau_in, rm, self.P, self.S,
            self.p0, self.integ, self.r, self.e, self.d, self.band, self.rest_s, self.release_left_s, self.anchor,
            self.still_time, self.state, self.baseline, self.over, self.in_event, self.peak, self.first_state,
            self.quiet_t, self.pratio, self.f_low, self.f_speed, self.f_acc, self.f_arm, self.dq_prev)
        return self._bookkeep(code, t_s)

    def set_scale(self, scale: float) -> None:
        """The mode's bands × ``scale`` (1/sensitivity), from the next update on."""
        self.s = ContactSettings(**{**self.s.__dict__, "scale": float(scale)})
        self._pack()

    def arm(self, p_Nms: np.ndarray, t_s: float) -> None:
        """Start watching: the observer starts from the present momentum, every joint settling."""
        self.p0[:] = p_Nms
        for a in (self.integ, self.r, self.e, self.d, self.rest_s, self.baseline, self.release_left_s, self.anchor,
                  self.still_time, self.peak, self.quiet_t, self.pratio, self.f_speed, self.f_acc, self.f_arm):
            a.fill(0.0)
        self.f_low.fill(1.0)
        self.dq_prev.fill(np.nan)  # (the first update has no acceleration)
        self.state.fill(SETTLING)
        self.over.fill(False)
        self.in_event.fill(False)
        self.active = False
        self.armed_at = t_s
        self._t_last = t_s

    def disarm(self) -> None:
        self.armed_at = math.inf
        if self.active:
            self.active = False
            self.in_event.fill(False)
            if self.events and self.events[-1].t_end_s is None:
                self.events[-1].t_end_s = self._t_last

    @property
    def armed(self) -> bool:
        return self.armed_at != math.inf

    def _elapsed(self, t_s: float) -> float:
        dt = min(t_s - self._t_last, 0.05) if t_s > self._t_last else 0.0
        self._t_last = t_s
        return dt

    def update(self, t_s: float, dq: np.ndarray, p_Nms: np.ndarray, tau_in_Nm: np.ndarray,
               ref_moving: np.ndarray | None = None) -> int:
        """One sample: advance the observer, judge every joint; QUIET, ONSET (an event began: ``events[-1]``),
        ONGOING or ENDED (``events[-1]`` has its end). ``ref_moving``: joints whose commanded reference moves (a
        motion in TRACK): never at rest, whatever their speed (a commanded start moves the drive before the joint)."""
        if not self.armed:
            return QUIET
        rm = self._no_ref if ref_moving is None else ref_moving
        dt = self._elapsed(t_s)
        settled = t_s - self.armed_at >= self.s.arm_s
        if self._kernel is not None:
            code, self.active = self._kernel(
                dt, settled, self.active, dq, p_Nms, tau_in_Nm, rm, self.P, self.S, self.p0, self.integ,
                self.r, self.e, self.d, self.band, self.rest_s, self.release_left_s, self.anchor, self.still_time,
                self.state, self.baseline, self.over, self.in_event, self.peak, self.first_state, self.quiet_t,
                self.pratio, self.f_low, self.f_speed, self.f_acc, self.f_arm, self.dq_prev)
            return self._bookkeep(code, t_s)
        s, P, a, b, m, m2, m3, m4 = self.s, self.P, self._a, self._b, self._m, self._m2, self._m3, self._m4
        observer_step_np(dt, s.observer_gain_per_s, tau_in_Nm, p_Nms, self.p0, self.integ, self.r, a)
        np.divide(self.r, P[7], out=self.e)
        # the band's features through the observer's own filter (its Euler step: α = K_o·dt)
        alpha = min(s.observer_gain_per_s * dt, 1.0)
        np.subtract(dq, self.dq_prev, out=a)
        np.abs(a, out=a)
        a /= dt if dt > 0.0 else np.inf
        np.isfinite(a, out=m)
        np.logical_not(m, out=m)
        np.copyto(a, 0.0, where=m)  # (first sample, no time step)
        np.copyto(self.dq_prev, dq)
        a -= self.f_acc
        a *= alpha
        self.f_acc += a
        np.abs(dq, out=a)  # a = speed
        np.subtract(a, self.f_speed, out=b)
        b *= alpha
        self.f_speed += b
        np.divide(a, P[4], out=b)
        np.subtract(1.0, b, out=b)
        np.maximum(b, 0.0, out=b)
        b -= self.f_low
        b *= alpha
        self.f_low += b
        moving = 1.0 if float(a.max()) >= s.rest_speed_rad_s or rm.any() else 0.0
        np.subtract(moving, self.f_arm, out=b)
        b *= alpha
        self.f_arm += b
        # states: at rest → settling → held (latched baseline), released → held (latched anew); a joint of an
        # ongoing event keeps its state
        np.less(a, s.rest_speed_rad_s, out=m)  # m = at rest (and its reference too)
        np.logical_not(rm, out=m2)
        m &= m2
        self.rest_s += dt
        self.rest_s *= m
        self.release_left_s -= dt
        np.logical_not(self.in_event, out=m4)  # m4 = not in an event (kept below)
        np.logical_not(m, out=m2)
        m2 &= m4
        np.copyto(self.state, MOVING, where=m2)
        m4 &= m  # m4 = at rest, not in an event
        np.greater_equal(self.still_time, s.still_s, out=m3)
        m3 &= m4  # m3 = ... and still
        np.greater_equal(self.rest_s, s.settle_s, out=m2)
        m2 &= m3
        np.equal(self.state, SETTLING, out=m)
        m2 &= m  # settled: held, the baseline latched
        np.copyto(self.baseline, self.e, where=m2)
        np.copyto(self.state, HELD, where=m2)
        np.less_equal(self.release_left_s, 0.0, out=m2)
        m2 &= m3
        np.equal(self.state, RELEASED, out=m)
        m2 &= m  # the release is over: held, the baseline latched anew
        np.copyto(self.baseline, self.e, where=m2)
        np.copyto(self.state, HELD, where=m2)
        np.equal(self.state, MOVING, out=m2)
        m2 &= m4  # came to rest
        np.copyto(self.state, SETTLING, where=m2)
        # deviation and band
        np.copyto(self.d, self.e)
        np.greater_equal(self.state, HELD, out=m3)  # held or released: against the baseline
        np.subtract(self.e, self.baseline, out=self.d, where=m3)
        np.multiply(self.f_low, P[1], out=b)
        b += P[0]
        np.multiply(self.f_speed, P[2], out=a)
        b += a
        np.multiply(self.f_acc, P[3], out=a)
        b += a  # the moving band
        np.equal(self.state, SETTLING, out=m)
        np.copyto(b, P[5], where=m)
        np.equal(self.state, RELEASED, out=m)
        np.copyto(b, P[5], where=m)
        np.multiply(self.f_arm, P[8], out=a)
        a += P[6]
        np.equal(self.state, HELD, out=m)
        np.copyto(b, a, where=m)
        np.multiply(b, s.scale, out=self.band)
        # stillness: the deviation stays within hysteresis·held_A of an anchor
        np.multiply(P[6], s.hysteresis * s.scale, out=b)
        np.subtract(self.d, self.anchor, out=a)
        np.abs(a, out=a)
        np.greater(a, b, out=m2)
        np.copyto(self.anchor, self.d, where=m2)
        self.still_time += dt
        np.copyto(self.still_time, 0.0, where=m2)
        np.abs(self.d, out=a)  # a = |d| (kept below)
        np.greater(a, self.band, out=self.over)
        if not settled:
            self.over.fill(False)
        # a held (released) joint's baseline follows while nothing is pending (|d| below the hysteresis level)
        np.multiply(self.band, s.hysteresis, out=b)
        np.less(a, b, out=m2)  # m2 = below the hysteresis level (kept below)
        np.greater_equal(self.state, HELD, out=m)
        m &= m2
        np.logical_not(self.in_event, out=m4)
        m &= m4
        k = dt / s.baseline_s if s.baseline_s > 0.0 else 1.0
        np.subtract(self.e, self.baseline, out=b)
        b *= min(k, 1.0)
        b *= m
        self.baseline += b
        # events
        np.divide(a, self.band, out=b)  # b = |d|/band
        if not self.active:
            if self.over.any():
                self.active = True
                self.quiet_t.fill(0.0)
                np.copyto(self.in_event, self.over)
                np.copyto(self.peak, self.d)
                self.peak *= self.over
                np.multiply(b, self.over, out=self.pratio)
                np.copyto(self.first_state, self.state)
                return self._bookkeep(ONSET, t_s)
            return self._bookkeep(QUIET, t_s)
        # joints joining the event, peaks (at the largest |d|/band)
        np.logical_not(self.in_event, out=m)
        m &= self.over
        np.copyto(self.first_state, self.state, where=m)
        self.in_event |= self.over
        np.greater(b, self.pratio, out=m)
        m &= self.in_event
        np.copyto(self.peak, self.d, where=m)
        np.copyto(self.pratio, b, where=m)
        # quiet: below the hysteresis level; at rest also let go (across its baseline or under half its peak)
        np.multiply(self.d, self.peak, out=b)
        np.less(b, 0.0, out=m)  # across the baseline
        np.abs(self.peak, out=b)
        b *= 0.5
        np.less(a, b, out=m3)  # under half its peak
        m |= m3
        np.not_equal(self.state, MOVING, out=m3)  # m3 = at rest (kept below)
        m &= m3
        m |= m2
        m &= self.in_event
        self.quiet_t += dt
        self.quiet_t *= m
        # done: the dominant joint quiet (clear_s moving, settle_s at rest), every moving joint of the event too
        b.fill(-1.0)
        np.copyto(b, self.pratio, where=self.in_event)
        dom = int(np.argmax(b))
        need = s.settle_s if m3[dom] else s.clear_s
        np.greater_equal(self.quiet_t, s.clear_s, out=m)
        m |= m3
        np.logical_not(self.in_event, out=m4)
        m |= m4
        if self.quiet_t[dom] < need or not m.all():
            return self._bookkeep(ONGOING, t_s)
        # ended: every joint at rest of the event, and every held one, is released
        np.equal(self.state, HELD, out=m)
        np.logical_and(self.in_event, m3, out=m2)
        m |= m2
        self._release(m)
        self.in_event.fill(False)
        self.active = False
        return self._bookkeep(ENDED, t_s)

    def _release(self, m: np.ndarray) -> None:
        np.copyto(self.baseline, self.e, where=m)
        np.copyto(self.anchor, 0.0, where=m)
        np.copyto(self.still_time, 0.0, where=m)
        np.copyto(self.state, RELEASED, where=m)
        np.copyto(self.release_left_s, self.s.release_s, where=m)
        np.copyto(self.quiet_t, 0.0, where=m)

    def _bookkeep(self, code: int, t_s: float) -> int:
        """Event records (outside the arithmetic: lists change only at onset, when a joint joins, and at the end)."""
        if code == ONSET:
            self.t_start = t_s
            js = [int(j) for j in np.flatnonzero(self.in_event)]
            self.events.append(ContactEvent(t_s, None, js, [abs(float(self.peak[j] * self.kt[j])) for j in js],
                                            [abs(float(self.peak[j])) for j in js],
                                            [STATE_NAMES[int(self.first_state[j])] for j in js]))
        elif code in (ONGOING, ENDED) and self.events:
            ev = self.events[-1]
            if code == ENDED:
                ev.t_end_s = t_s
                return code
            if len(ev.joints) != int(np.count_nonzero(self.in_event)):  # (rare: a joint joined)
                js = [int(j) for j in np.flatnonzero(self.in_event)]
                ev.states = [ev.states[ev.joints.index(j)] if j in ev.joints else STATE_NAMES[int(self.first_state[j])]
                             for j in js]
                ev.joints = js
                ev.peak_A = [0.0] * len(js)
                ev.peak_Nm = [0.0] * len(js)
            for i, j in enumerate(ev.joints):
                ev.peak_A[i] = abs(float(self.peak[j]))
                ev.peak_Nm[i] = ev.peak_A[i] * float(self.kt[j])
        return code


def _contact_kernel(dt: float, settled: bool, active: bool, dq: np.ndarray, p: np.ndarray,
                    tau: np.ndarray, ref_moving: np.ndarray, P: np.ndarray, S: np.ndarray, p0: np.ndarray,
                    integ: np.ndarray, r: np.ndarray,
                    e: np.ndarray, d: np.ndarray, band: np.ndarray, rest_s: np.ndarray, release_left: np.ndarray,
                    anchor: np.ndarray, still_time: np.ndarray, state: np.ndarray, baseline: np.ndarray,
                    over: np.ndarray,
                    in_event: np.ndarray, peak: np.ndarray, first_state: np.ndarray, quiet_t: np.ndarray,
                    pratio: np.ndarray, f_low: np.ndarray,
                    f_speed: np.ndarray, f_acc: np.ndarray, f_arm: np.ndarray,
                    dq_prev: np.ndarray) -> tuple[int, bool]:
    """``ContactDetector.update``'s arithmetic joint by joint (its numpy is the reference): (code, active)."""
    n = dq.shape[0]
    k_o, rest_speed, settle_s, release_s, baseline_s, hyst, clear_s, scale, still_s = (
        S[0], S[1], S[2], S[3], S[4], S[5], S[6], S[7], S[8])
    observer_step(dt, k_o, tau, p, p0, integ, r)
    alpha = k_o * dt
    alpha = alpha if alpha <= 1.0 else 1.0
    k = dt / baseline_s if baseline_s > 0.0 else 1.0
    k = k if k <= 1.0 else 1.0
    top = abs(dq[0])
    for j in range(1, n):
        x = abs(dq[j])
        top = x if (x >= top or x != x) else top  # (np.max: NaN wins)
    for j in range(n):
        if ref_moving[j]:
            top = top if top >= rest_speed else rest_speed
    moving = 1.0 if top >= rest_speed else 0.0
    any_over = False
    for j in range(n):
        e[j] = r[j] / P[7, j]
        x = abs(dq[j] - dq_prev[j])
        x /= dt if dt > 0.0 else np.inf
        if not (x - x == 0.0):  # not finite
            x = 0.0
        dq_prev[j] = dq[j]
        x -= f_acc[j]
        x *= alpha
        f_acc[j] += x
        speed = abs(dq[j])
        x = speed - f_speed[j]
        x *= alpha
        f_speed[j] += x
        x = speed / P[4, j]
        x = 1.0 - x
        x = x if x >= 0.0 else 0.0
        x -= f_low[j]
        x *= alpha
        f_low[j] += x
        x = moving - f_arm[j]
        x *= alpha
        f_arm[j] += x
        rest = speed < rest_speed and not ref_moving[j]
        rest_s[j] = (rest_s[j] + dt) * (1.0 if rest else 0.0)
        release_left[j] -= dt
        if not rest and not in_event[j]:
            state[j] = MOVING
        if rest and not in_event[j] and rest_s[j] >= settle_s and still_time[j] >= still_s and state[j] == SETTLING:
            baseline[j] = e[j]
            state[j] = HELD
        if rest and not in_event[j] and release_left[j] <= 0.0 and still_time[j] >= still_s and state[j] == RELEASED:
            baseline[j] = e[j]
            state[j] = HELD
        if rest and state[j] == MOVING and not in_event[j]:
            state[j] = SETTLING
        d[j] = e[j] - baseline[j] if state[j] >= HELD else e[j]
        b = f_low[j] * P[1, j]
        b += P[0, j]
        b += f_speed[j] * P[2, j]
        b += f_acc[j] * P[3, j]
        if state[j] == SETTLING or state[j] == RELEASED:
            b = P[5, j]
        elif state[j] == HELD:
            b = f_arm[j] * P[8, j]
            b += P[6, j]
        band[j] = b * scale
        w = P[6, j] * (hyst * scale)
        if abs(d[j] - anchor[j]) > w:
            anchor[j] = d[j]
            still_time[j] = 0.0
        else:
            still_time[j] += dt
        a = abs(d[j])
        over[j] = a > band[j] and settled
        any_over = any_over or over[j]
        if a < band[j] * hyst and state[j] >= HELD and not in_event[j]:
            baseline[j] += (e[j] - baseline[j]) * k
    if not active:
        if any_over:
            for j in range(n):
                in_event[j] = over[j]
                peak[j] = d[j] * (1.0 if over[j] else 0.0)
                pratio[j] = (abs(d[j]) / band[j]) * (1.0 if over[j] else 0.0)
                first_state[j] = state[j]
                quiet_t[j] = 0.0
            return 1, True
        return 0, False
    dom = -1
    top = -1.0
    moving_quiet = True
    for j in range(n):
        if over[j] and not in_event[j]:
            first_state[j] = state[j]
        in_event[j] = in_event[j] or over[j]
        a = abs(d[j])
        x = a / band[j]
        if x > pratio[j] and in_event[j]:
            peak[j] = d[j]
            pratio[j] = x
        rest = state[j] != MOVING
        quiet = a < band[j] * hyst or (rest and (d[j] * peak[j] < 0.0 or a < abs(peak[j]) * 0.5))
        quiet = quiet and in_event[j]
        quiet_t[j] = (quiet_t[j] + dt) * (1.0 if quiet else 0.0)
        if in_event[j] and pratio[j] > top:
            top = pratio[j]
            dom = j
        if in_event[j] and not rest and quiet_t[j] < clear_s:
            moving_quiet = False
    need = settle_s if state[dom] != MOVING else clear_s
    if quiet_t[dom] < need or not moving_quiet:
        return 2, True
    for j in range(n):
        if state[j] == HELD or (in_event[j] and state[j] != MOVING):
            baseline[j] = e[j]
            anchor[j] = 0.0
            still_time[j] = 0.0
            state[j] = RELEASED
            release_left[j] = release_s
            quiet_t[j] = 0.0
        in_event[j] = False
    return 3, False


# rows of the packed model block (``pack_model``) the cycle computes τ_in from
(F_KT, F_COUL_POS, F_COUL_NEG, F_STAT_POS, F_STAT_NEG, F_STRIB_V, F_STRIB_EXP, F_VISC_POS, F_VISC_NEG,
 F_LOAD) = range(10)
N_MODEL_ROWS = 10


def pack_model(law: Any, kt_Nm_per_A: np.ndarray, load_friction_per_Nm: np.ndarray | None) -> tuple[np.ndarray,
                                                                                                     np.ndarray]:
    """(per-joint rows, scalars) of the identified friction (``law``, a LawParams: dragd's friction law at scale 1),
    K_t and the load-dependent friction k_L, for ``contact_tau_in``."""
    n = kt_Nm_per_A.shape[0]
    F = np.zeros((N_MODEL_ROWS, n))
    for row, a in ((F_KT, kt_Nm_per_A), (F_COUL_POS, law.coulomb_pos_A), (F_COUL_NEG, law.coulomb_neg_A),
                   (F_STAT_POS, law.static_pos_A), (F_STAT_NEG, law.static_neg_A),
                   (F_STRIB_V, law.stribeck_velocity_rad_s), (F_STRIB_EXP, law.stribeck_exponent),
                   (F_VISC_POS, law.viscous_pos_A_s_per_rad), (F_VISC_NEG, law.viscous_neg_A_s_per_rad)):
        F[row] = np.broadcast_to(np.asarray(a, dtype=float), (n,))
    if load_friction_per_Nm is not None:
        F[F_LOAD] = load_friction_per_Nm
    FS = np.array([law.smoothing_rad_s, law.deadband_rad_s, 1.0 if law.use_stribeck else 0.0])
    return F, FS


def contact_tau_in(dq: np.ndarray, i_A: np.ndarray, g: np.ndarray, C: np.ndarray, F: np.ndarray, FS: np.ndarray,
                   tau: np.ndarray) -> None:
    """τ_in = K_t·(I − I_f(q̇) − I_L(q, q̇)) − g + Cᵀq̇ joint by joint (the identified friction of dragd's law at
    scale 1 and the load-dependent term w·sign(q̇)·k_L·|g|/K_t; dragd/contact/model.py ``terms`` is the numpy
    reference). ``C``: the Coriolis matrix C(q, q̇) (Pinocchio's)."""
    n = dq.shape[0]
    smoothing, deadband, stribeck = FS[0], FS[1], FS[2] != 0.0
    for j in range(n):
        v = dq[j]
        speed = abs(v)
        pos = v >= 0.0
        c = F[F_COUL_POS, j] if pos else F[F_COUL_NEG, j]
        if stribeck:
            b = (F[F_STAT_POS, j] if pos else F[F_STAT_NEG, j]) - c
            b *= math.exp(-((speed / F[F_STRIB_V, j]) ** F[F_STRIB_EXP, j]))
            c += b
        x = speed - deadband
        x = x if (x >= 0.0 or x != x) else 0.0  # (np.maximum: NaN propagates)
        w = math.tanh(x / smoothing)
        fr = w * c
        fr += (F[F_VISC_POS, j] if pos else F[F_VISC_NEG, j]) * v
        if F[F_LOAD, j] != 0.0:
            x = w * abs(g[j])
            x *= F[F_LOAD, j]
            x /= F[F_KT, j]
            fr += math.copysign(x, v)
        a = i_A[j] - fr
        a *= F[F_KT, j]
        a -= g[j]
        s = 0.0
        for k in range(n):
            s += C[k, j] * dq[k]
        tau[j] = a + s


def _contact_cycle_kernel(dt: float, settled: bool, active: bool, dq: np.ndarray, p: np.ndarray, i_A: np.ndarray,
                          g: np.ndarray, C: np.ndarray, F: np.ndarray, FS: np.ndarray, tau: np.ndarray,
                          ref_moving: np.ndarray, P: np.ndarray, S: np.ndarray, p0: np.ndarray, integ: np.ndarray,
                          r: np.ndarray, e: np.ndarray, d: np.ndarray, band: np.ndarray, rest_s: np.ndarray,
                          release_left: np.ndarray, anchor: np.ndarray, still_time: np.ndarray, state: np.ndarray,
                          baseline: np.ndarray, over: np.ndarray, in_event: np.ndarray, peak: np.ndarray,
                          first_state: np.ndarray, quiet_t: np.ndarray, pratio: np.ndarray, f_low: np.ndarray,
                          f_speed: np.ndarray, f_acc: np.ndarray, f_arm: np.ndarray,
                          dq_prev: np.ndarray) -> tuple[int, bool]:
    """The cycle's whole contact step in one call: the model's τ_in from the measured current (``contact_tau_in``),
    then ``_contact_kernel``. Only Pinocchio's p = M̄q̇, g and C(q, q̇) come from outside."""
    contact_tau_in(dq, i_A, g, C, F, FS, tau)
    return _contact_kernel(dt, settled, active, dq, p, tau, ref_moving, P, S, p0, integ, r, e, d, band, rest_s,
                           release_left, anchor, still_time, state, baseline, over, in_event, peak, first_state,
                           quiet_t, pratio, f_low, f_speed, f_acc, f_arm, dq_prev)


def _contact_observe_kernel(dt: float, dq: np.ndarray, p: np.ndarray, i_A: np.ndarray, g: np.ndarray, C: np.ndarray,
                            F: np.ndarray, FS: np.ndarray, tau: np.ndarray, k_o: float, p0: np.ndarray,
                            integ: np.ndarray, r: np.ndarray, e: np.ndarray) -> None:
    """The residual alone (no bands, no events): τ_in, the observer step, e = r/K_t (drag: the hand's torque)."""
    contact_tau_in(dq, i_A, g, C, F, FS, tau)
    observer_step(dt, k_o, tau, p, p0, integ, r)
    for j in range(dq.shape[0]):
        e[j] = r[j] / F[F_KT, j]


def contact_kernels() -> dict[str, Any] | None:
    """The compiled kernels (once per process): ``contact`` (``_contact_kernel``: τ_in given, offline), ``cycle``
    (``_contact_cycle_kernel``: τ_in from the current, the daemon's) and ``tau_in`` (``contact_tau_in``); None where
    numba cannot be imported."""
    f, b, i = np.zeros(1), np.zeros(1, dtype=bool), np.zeros(1, dtype=np.int64)
    S = np.array([25.0, 0.005, 0.3, 0.5, 0.25, 0.5, 0.05, 1.0, 0.5])
    F = np.ones((N_MODEL_ROWS, 1))
    FS = np.array([0.005, 0.0, 1.0])
    state = {"r", "e", "d", "band", "rest_s", "release_left", "anchor", "still_time", "baseline", "peak", "quiet_t",
             "pratio", "f_low", "f_speed", "f_acc", "f_arm", "dq_prev", "p0", "integ", "tau"}
    given = {"dt": 1e-3, "settled": True, "active": False, "dq": f, "p": f, "i_A": f, "g": f, "C": np.zeros((1, 1)),
             "F": F, "FS": FS, "P": np.ones((9, 1)), "S": S, "ref_moving": b.copy(), "state": i.copy(), "k_o": 25.0,
             "first_state": i.copy(), "over": b.copy(), "in_event": b.copy()}

    def args(fn: Any) -> tuple[Any, ...]:
        names = fn.__code__.co_varnames[:fn.__code__.co_argcount]
        return tuple(given.get(nm, f.copy() if nm in state else None) for nm in names)

    kernel, cycle, tau_in, observe = (_contact_kernel, _contact_cycle_kernel, contact_tau_in,
                                      _contact_observe_kernel)  # (the Python functions)
    return compile_kernels(globals(), ("observer_step", "contact_tau_in", "_contact_kernel"), {
        "contact": (kernel, args(kernel)), "cycle": (cycle, args(cycle)), "observe": (observe, args(observe)),
        "tau_in": (tau_in, (f, f, f, np.zeros((1, 1)), F, FS, f.copy()))})


def contact_kernel() -> Any:
    """The compiled ``_contact_kernel`` (once per process), or None where numba cannot be imported."""
    k = contact_kernels()
    return None if k is None else k["contact"]
