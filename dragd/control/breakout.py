"""The start-up term's break-out latch (ours, beyond seed 001): a position-based hand-over for micro-slipping joints.

See dragd/control/law.py for how the latch enters the start-up term.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from dragd.control.params import LawParams

BREAKOUT_RAMP_S = 0.005  # the sine blends into (and back out of) the held peak over this time
STILL_FRACTION = 0.25  # "still" (for re-arming the latch) is |q̇| below this fraction of Φ
REST_WEIGHT_STEP = 0.1  # with a BreakoutState the start-up weight r changes by at most this per cycle (≥ 10 ms
# for a full hand-over): the steep fade over [Φ, Φ + width] would turn velocity-estimate noise into current steps


class BreakoutState:
    """Per-joint state of the break-out latch (allocate once; ``breakout_update`` advances it each cycle)."""

    def __init__(self, n: int) -> None:
        self.anchor_rad = np.zeros(n)  # where the joint settled (valid while armed)
        self.still_ref_rad = np.full(n, np.nan)  # where the current stillness began (NaN: not yet seen)
        self.armed = np.zeros(n, dtype=bool)
        self.still_since_s = np.zeros(n)
        self.latch = np.zeros(n)  # −1, 0, +1: the direction held
        self.latch_t0_s = np.zeros(n)
        self.held = np.zeros(n)  # direction of the blend (kept while the blend fades out)
        self.weight = np.zeros(n)  # blend sine → held peak, in [0, 1]
        self.rest = np.ones(n)  # the slew-limited start-up weight r of the last cycle
        self.latches = np.zeros(n, dtype=np.int64)  # count of latches fired, per joint
        self.suppressed = np.zeros(n, dtype=np.int64)  # ... and of creeps the gravity uncertainty could explain
        self.t_prev_s = 0.0
        self._m = np.zeros(n, dtype=bool)
        self._k = np.zeros(n, dtype=bool)
        self._x = np.zeros(n)
        self.speed = np.zeros(n)
        self.active = False  # a latch or its blend is under way somewhere
        self.fade_end_rad_s = np.zeros(n)  # Φ + width; thresholds filled by ``configure``
        self.still_rad_s = np.zeros(n)
        self.slip_rad = np.full(n, np.inf)

    def configure(self, p: LawParams) -> BreakoutState:
        """Precompute the thresholds of ``p`` (once, outside the cycle)."""
        np.add(p.rest_threshold_rad_s, p.fade_width_rad_s, out=self.fade_end_rad_s)
        np.multiply(p.rest_threshold_rad_s, STILL_FRACTION, out=self.still_rad_s)
        self.slip_rad[:] = np.where(p.breakout_slip_rad > 0.0, p.breakout_slip_rad, np.inf)
        return self

    def reset(self, t_s: float) -> None:
        """Disarm everything (entering drag): the latch arms once each joint has been still for ``settle_s``."""
        self.armed.fill(False)
        self.still_since_s.fill(t_s)
        self.still_ref_rad.fill(np.nan)
        self.latch.fill(0.0)
        self.held.fill(0.0)
        self.weight.fill(0.0)
        self.rest.fill(1.0)
        self.active = False
        self.t_prev_s = t_s


def breakout_update(q_rad: np.ndarray, dq_rad_s: np.ndarray, t_s: float, p: LawParams, st: BreakoutState,
                    tau_g_Nm: np.ndarray | None = None) -> None:
    """Advance the break-out latch by one cycle (allocation-free; a dozen ufuncs while nothing is latched).

    With ``tau_g_Nm`` a joint latches only where the sine's margin below the believed static level covers the
    gravity model's uncertainty (``gravity_uncertainty``·|G|/K_t): there a creep is the hand's; where gravity
    errors alone could make the joint creep, a latch could start it by itself, so it stays on seed 001's hand-over.
    """
    m, k, x, speed = st._m, st._k, st._x, st.speed
    dt = max(t_s - st.t_prev_s, 0.0)
    st.t_prev_s = t_s
    np.abs(dq_rad_s, out=speed)
    if st.active:
        # a latch ends after its hold time, or once the joint is past the fade (friction compensation has it)
        np.subtract(t_s, st.latch_t0_s, out=x)
        np.greater_equal(x, p.breakout_hold_s, out=m)
        np.greater(speed, st.fade_end_rad_s, out=k)
        m |= k
        np.not_equal(st.latch, 0.0, out=k)
        m &= k
        np.copyto(st.latch, 0.0, where=m)
        np.copyto(st.still_since_s, t_s, where=m)
    # clear motion (|q̇| > Φ) disarms; any motion above the still level restarts the settle time
    np.less_equal(speed, p.rest_threshold_rad_s, out=k)
    st.armed &= k
    np.greater(speed, st.still_rad_s, out=k)
    np.subtract(q_rad, st.still_ref_rad, out=x)
    np.abs(x, out=x)
    np.less_equal(x, st.slip_rad, out=m)  # a creep of counts (too slow for the velocity estimate) is not still;
    np.logical_not(m, out=m)  # (nor is the first cycle after a reset: NaN reference)
    k |= m
    np.copyto(st.still_since_s, t_s, where=k)
    np.copyto(st.still_ref_rad, q_rad, where=k)
    # arm where still for settle_s and not latched: the anchor is where the joint settled
    if np.count_nonzero(st.armed) < st.armed.shape[0]:  # (count_nonzero: 6× cheaper than .all()/.any())
        np.subtract(t_s, st.still_since_s, out=x)
        np.greater_equal(x, p.settle_s, out=m)
        np.equal(st.latch, 0.0, out=k)
        m &= k
        np.greater(m, st.armed, out=m)  # m and not armed
        np.copyto(st.anchor_rad, q_rad, where=m)
        st.armed |= m
    # fire where an armed joint crept beyond the slip distance (slip 0: latch off)
    np.subtract(q_rad, st.anchor_rad, out=x)
    np.abs(x, out=speed)
    np.greater(speed, st.slip_rad, out=m)
    m &= st.armed
    if np.count_nonzero(m):
        if tau_g_Nm is not None and p.gravity_uncertainty > 0.0:  # rare branch: a joint crept
            for j in range(m.shape[0]):  # (no index array: nothing allocates in the cycle)
                if not m[j]:
                    continue
                pos = x[j] > 0.0
                static = p.static_pos_A[j] if pos else -p.static_neg_A[j]
                amp = p.startup_amp_pos_A[j] if pos else p.startup_amp_neg_A[j]
                if p.gravity_uncertainty * abs(tau_g_Nm[j]) / p.kt_Nm_per_A[j] >= static - amp:
                    m[j] = False
                    st.suppressed[j] += 1
        np.sign(x, out=x)
        np.copyto(st.latch, x, where=m)
        np.copyto(st.held, x, where=m)
        np.copyto(st.latch_t0_s, t_s, where=m)
        np.greater(st.armed, m, out=st.armed)  # armed and not fired
        st.latches += m
        st.active = True
    if st.active:  # the blend weight moves toward 1 while latched, toward 0 after
        step = min(dt, 2e-3) / BREAKOUT_RAMP_S  # a late tick does not jump the blend
        np.not_equal(st.latch, 0.0, out=m)
        np.add(st.weight, step, out=x)
        np.subtract(st.weight, step, out=speed)
        np.logical_not(m, out=k)
        np.copyto(x, speed, where=k)
        np.clip(x, 0.0, 1.0, out=st.weight)
        st.active = bool(np.count_nonzero(m) or np.count_nonzero(st.weight))
