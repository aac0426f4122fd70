"""Experiment (issue 17): the break-out latch as a numba kernel beside dragd's numpy version.

Needs numba (not a dragd dependency): ``pip install --target /tmp/nb numba==0.68.1`` then
``PYTHONPATH=.:/tmp/nb python docs/experiments/numba_breakout.py``. Runs 60 000 cycles of rests, creeps (latches
fire, gravity suppression included) and motions through both, asserts every state array identical bit for bit each
cycle, and prints the thread CPU per call of each. Findings: docs/DECISIONS.md ("The cycle"; the measurements in git: docs/PERFORMANCE.md before 3f63959).
"""
import time

import numba as nb
import numpy as np

from dragd.config import load_config
from dragd.control.breakout import BREAKOUT_RAMP_S, BreakoutState, breakout_update
from dragd.control.params import LawParams


@nb.njit(cache=False, nogil=True)
def _kernel(q, dq, t, dt, active, hold_s, rest_thr, settle_s, fade_end, still_rad_s, slip, latch, latch_t0,
            still_since, still_ref, armed, anchor, held, weight, latches, speed, x, m, ramp):
    n = q.shape[0]
    for j in range(n):
        speed[j] = abs(dq[j])
        if active:
            mj = (t - latch_t0[j]) >= hold_s[j] or speed[j] > fade_end[j]
            if mj and latch[j] != 0.0:
                latch[j] = 0.0
                still_since[j] = t
        armed[j] = armed[j] and speed[j] <= rest_thr[j]
        k = speed[j] > still_rad_s[j]
        d = abs(q[j] - still_ref[j])
        if not (d <= slip[j]):
            k = True
        if k:
            still_since[j] = t
            still_ref[j] = q[j]
    n_armed = 0
    for j in range(n):
        if armed[j]:
            n_armed += 1
    if n_armed < n:
        for j in range(n):
            if (t - still_since[j]) >= settle_s[j] and latch[j] == 0.0 and not armed[j]:
                anchor[j] = q[j]
                armed[j] = True
    fired = 0
    for j in range(n):
        x[j] = q[j] - anchor[j]
        speed[j] = abs(x[j])
        m[j] = speed[j] > slip[j] and armed[j]
        if m[j]:
            fired += 1
    return fired

def update_nb(q, dq, t, p, st, tau_g, arrs):
    hold_s, rest_thr, settle_s = arrs
    dt = max(t - st.t_prev_s, 0.0)
    st.t_prev_s = t
    fired = _kernel(q, dq, t, dt, st.active, hold_s, rest_thr, settle_s, st.fade_end_rad_s, st.still_rad_s, st.slip_rad,
                    st.latch, st.latch_t0_s, st.still_since_s, st.still_ref_rad, st.armed, st.anchor_rad, st.held,
                    st.weight, st.latches, st.speed, st._x, st._m, BREAKOUT_RAMP_S)
    m, x, k, speed = st._m, st._x, st._k, st.speed
    if fired:  # rare: as the numpy version
        if tau_g is not None and p.gravity_uncertainty > 0.0:
            for j in range(m.shape[0]):
                if not m[j]:
                    continue
                pos = x[j] > 0.0
                static = p.static_pos_A[j] if pos else -p.static_neg_A[j]
                amp = p.startup_amp_pos_A[j] if pos else p.startup_amp_neg_A[j]
                if p.gravity_uncertainty * abs(tau_g[j]) / p.kt_Nm_per_A[j] >= static - amp:
                    m[j] = False
                    st.suppressed[j] += 1
        np.sign(x, out=x)
        np.copyto(st.latch, x, where=m)
        np.copyto(st.held, x, where=m)
        np.copyto(st.latch_t0_s, t, where=m)
        np.greater(st.armed, m, out=st.armed)
        st.latches += m
        st.active = True
    if st.active:
        step = min(dt, 2e-3) / BREAKOUT_RAMP_S
        np.not_equal(st.latch, 0.0, out=m)
        np.add(st.weight, step, out=x)
        np.subtract(st.weight, step, out=speed)
        np.logical_not(m, out=k)
        np.copyto(x, speed, where=k)
        np.clip(x, 0.0, 1.0, out=st.weight)
        st.active = bool(np.count_nonzero(m) or np.count_nonzero(st.weight))

cfg = load_config(None)
p = LawParams.from_config(cfg)
n = 6
arrs = tuple(np.ascontiguousarray(np.broadcast_to(np.asarray(v, float), n)) for v in
             (p.breakout_hold_s, p.rest_threshold_rad_s, p.settle_s))
a, b = BreakoutState(n).configure(p), BreakoutState(n).configure(p)
a.reset(0.0); b.reset(0.0)
rng = np.random.default_rng(3)
q = np.zeros(n); K = 60000
qs, dqs = np.empty((K, n)), np.empty((K, n))
for k in range(K):  # rests, slow creeps, motions
    phase = (k // 3000) % 4
    dq = {0: rng.normal(0, 1e-4, n), 1: rng.normal(0, 1e-4, n) + 2e-3, 2: rng.normal(0, 0.05, n), 3: rng.normal(0, 1e-3, n)}[phase]
    q = q + dq * 1e-3
    if phase == 1: q += 2e-6
    qs[k], dqs[k] = q, dq
tau = rng.normal(0, 20, n)
fields = ["anchor_rad", "still_ref_rad", "armed", "still_since_s", "latch", "latch_t0_s", "held", "weight", "latches", "suppressed"]
for k in range(K):
    t = k * 1e-3
    breakout_update(qs[k], dqs[k], t, p, a, tau)
    update_nb(qs[k], dqs[k], t, p, b, tau, arrs)
    for f in fields:
        if not np.array_equal(getattr(a, f), getattr(b, f), equal_nan=True):
            raise SystemExit(f"differs at {k}: {f} {getattr(a, f)} {getattr(b, f)}")
    assert a.active == b.active
print("identical over", K, "cycles; latches", a.latches, "suppressed", a.suppressed)
for name, fn in (("numpy", lambda k: breakout_update(qs[k], dqs[k], k * 1e-3, p, a, tau)),
                 ("numba", lambda k: update_nb(qs[k], dqs[k], k * 1e-3, p, b, tau, arrs))):
    a.reset(0.0); b.reset(0.0); a.t_prev_s = b.t_prev_s = 0.0
    t0 = time.thread_time_ns()
    for k in range(K): fn(k)
    print(name, f"{(time.thread_time_ns() - t0) / K / 1e3:.2f} us per call (thread CPU)")
