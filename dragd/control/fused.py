"""The drag law compiled: the break-out latch and the compensation law as two numba kernels.

The numpy functions in dragd/control/breakout.py and law.py are the reference: these kernels compute the same
arithmetic in the same order, joint by joint, in one call each instead of ~70 ufunc calls on six-element arrays
(each ~0.5–1 µs of dispatch in the cycle, against nanoseconds of arithmetic). tests/test_fused.py holds them to the
reference over long randomised sequences (latches firing and suppressed, every switch of ``LawParams``), and the
golden traces replay with them. ``exp``/``tanh``/``sin`` are libm's here and numpy's own SIMD versions there: they
may differ in the last bit (≤ 1 ulp), far below the drives' per-mille quantisation.

Model-gap effects (``LawParams.effects``) stay on the numpy path (``compensate``): ``DragLaw`` uses the kernels
only when the params carry none. Compiled ahead at construction (``cache=True``: once per machine, then loaded
from numba's cache in ~0.1 s), never on the first cycle.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from dragd.control.breakout import BREAKOUT_RAMP_S, REST_WEIGHT_STEP, BreakoutState, breakout_update
from dragd.control.law import LawOutput, Workspace, compensate
from dragd.control.params import LawParams
from dragd.jit import compile_kernels

# rows of the packed per-joint parameters
(KT, LIMIT, COUL_POS, COUL_NEG, STAT_POS, STAT_NEG, STRIB_V, STRIB_EXP, VISC_POS, VISC_NEG, AMP_POS, AMP_NEG, FREQ,
 REST_THR, FADE_W, BACK_EMF, DAMPING, HOLD_S, SETTLE_S) = range(19)
N_PARAM_ROWS = 19
# rows of the break-out state's float block (BreakoutState's arrays are views of these rows)
(B_ANCHOR, B_STILL_REF, B_STILL_SINCE, B_LATCH, B_LATCH_T0, B_HELD, B_WEIGHT, B_REST, B_FADE_END, B_STILL,
 B_SLIP) = range(11)
# rows of the law's output block (LawOutput's arrays are views of these rows)
O_CURRENT, O_GRAVITY, O_FRICTION, O_STARTUP, O_BACK_EMF, O_DAMPING = range(6)
# switches
(F_GRAVITY, F_FRICTION, F_STRIBECK, F_STARTUP, F_BACK_EMF, F_DAMPING, F_SQUARE, F_ABRUPT, F_BREAKOUT) = range(9)


def available() -> bool:
    """Whether the compiled kernels can be used here (numba, a pinned dependency, imports; imported on first use:
    the CLI's other commands do not pay for it)."""
    return _compiled() is not None


def _compiled() -> dict[str, Any] | None:
    """The jitted kernels (compiled once per process), or None where numba cannot be imported."""
    z, rows = np.zeros(1), np.ones((N_PARAM_ROWS, 1))
    return compile_kernels(globals(), ("_maximum", "_minimum", "_fmax", "_fmin", "_sign"), {
        "breakout": (_breakout_kernel, (z, z, 0.0, 0.0, True, rows, np.zeros((11, 1)), np.zeros(1, dtype=bool),
                                        np.zeros((2, 1), dtype=np.int64), z, True, 0.0)),
        "law": (_law_kernel, (z, z, 0.0, rows, np.zeros(9, dtype=np.int64), np.ones(4), np.zeros((11, 1)), z,
                              np.zeros((6, 1)), np.zeros(1, dtype=bool)))})


def pack_params(p: LawParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(per-joint rows, switches, scalars) of ``p`` for the kernels."""
    rows = np.empty((N_PARAM_ROWS, p.n))
    for i, a in enumerate((p.kt_Nm_per_A, p.current_limit_A, p.coulomb_pos_A, p.coulomb_neg_A, p.static_pos_A,
                           p.static_neg_A, p.stribeck_velocity_rad_s, p.stribeck_exponent, p.viscous_pos_A_s_per_rad,
                           p.viscous_neg_A_s_per_rad, p.startup_amp_pos_A, p.startup_amp_neg_A, p.startup_freq_Hz,
                           p.rest_threshold_rad_s, p.fade_width_rad_s, p.back_emf_A_s_per_rad, p.damping_A_s_per_rad,
                           p.breakout_hold_s, p.settle_s)):
        rows[i] = np.broadcast_to(np.asarray(a, dtype=float), (p.n,))
    flags = np.array([p.use_gravity, p.use_friction, p.use_stribeck, p.use_startup, p.use_back_emf, p.use_damping,
                      p.startup_square, p.startup_abrupt, p.use_breakout], dtype=np.int64)
    scalars = np.array([p.friction_scale, p.smoothing_rad_s, p.deadband_rad_s, p.gravity_uncertainty])
    return rows, flags, scalars




def _maximum(a: float, b: float) -> float:  # np.maximum: NaN propagates
    return a if (a >= b or a != a) else b


def _minimum(a: float, b: float) -> float:  # np.minimum
    return a if (a <= b or a != a) else b


def _fmax(a: float, b: float) -> float:  # np.fmax: a NaN loses
    return a if (a >= b or b != b) else b


def _fmin(a: float, b: float) -> float:  # np.fmin
    return a if (a <= b or b != b) else b


def _sign(x: float) -> float:  # np.sign
    if x > 0.0:
        return 1.0
    if x < 0.0:
        return -1.0
    return x  # ±0 and NaN as they are


def _breakout_kernel(q: np.ndarray, dq: np.ndarray, t: float, t_prev: float, active: bool, P: np.ndarray,
                     B: np.ndarray, armed: np.ndarray, counts: np.ndarray, tau_g: np.ndarray, use_tau_g: bool,
                     gravity_uncertainty: float) -> bool:
    """``breakout_update`` (dragd/control/breakout.py) for every joint; returns the new ``active``."""
    n = q.shape[0]
    dt = max(t - t_prev, 0.0)
    if active:
        for j in range(n):
            speed = abs(dq[j])
            m = (t - B[B_LATCH_T0, j] >= P[HOLD_S, j]) or (speed > B[B_FADE_END, j])
            if m and B[B_LATCH, j] != 0.0:
                B[B_LATCH, j] = 0.0
                B[B_STILL_SINCE, j] = t
    n_armed = 0
    for j in range(n):
        speed = abs(dq[j])
        armed[j] = armed[j] and speed <= P[REST_THR, j]
        k = speed > B[B_STILL, j]
        if not (abs(q[j] - B[B_STILL_REF, j]) <= B[B_SLIP, j]):  # NaN reference: not still
            k = True
        if k:
            B[B_STILL_SINCE, j] = t
            B[B_STILL_REF, j] = q[j]
        n_armed += 1 if armed[j] else 0
    if n_armed < n:
        for j in range(n):
            if t - B[B_STILL_SINCE, j] >= P[SETTLE_S, j] and B[B_LATCH, j] == 0.0 and not armed[j]:
                B[B_ANCHOR, j] = q[j]
                armed[j] = True
    fired = False
    for j in range(n):
        x = q[j] - B[B_ANCHOR, j]
        if not (abs(x) > B[B_SLIP, j] and armed[j]):
            continue
        if use_tau_g and gravity_uncertainty > 0.0:
            pos = x > 0.0
            static = P[STAT_POS, j] if pos else -P[STAT_NEG, j]
            amp = P[AMP_POS, j] if pos else P[AMP_NEG, j]
            if gravity_uncertainty * abs(tau_g[j]) / P[KT, j] >= static - amp:
                counts[1, j] += 1
                fired = True  # (the numpy reference marks the latch active once any joint crept)
                continue
        s = _sign(x)
        B[B_LATCH, j] = s
        B[B_HELD, j] = s
        B[B_LATCH_T0, j] = t
        armed[j] = False
        counts[0, j] += 1
        fired = True
    if fired:
        active = True
    if active:
        step = min(dt, 2e-3) / BREAKOUT_RAMP_S
        any_latched = False
        any_weight = False
        for j in range(n):
            latched = B[B_LATCH, j] != 0.0
            w = B[B_WEIGHT, j] + step if latched else B[B_WEIGHT, j] - step
            w = _minimum(_maximum(w, 0.0), 1.0)
            B[B_WEIGHT, j] = w
            any_latched = any_latched or latched
            any_weight = any_weight or w != 0.0
        active = any_latched or any_weight
    return active


def _law_kernel(tau_g: np.ndarray, dq: np.ndarray, t: float, P: np.ndarray, flags: np.ndarray, S: np.ndarray,
                B: np.ndarray, extra: np.ndarray, out: np.ndarray, clamped: np.ndarray) -> None:
    """``compensate`` (dragd/control/law.py) without model-gap effects, for every joint."""
    friction_scale, smoothing, deadband = S[0], S[1], S[2]
    two_pi_t = 2.0 * math.pi * t
    for j in range(dq.shape[0]):
        v = dq[j]
        speed = abs(v)
        pos = v >= 0.0
        gravity = tau_g[j] / P[KT, j] if flags[F_GRAVITY] else 0.0
        r = 0.0
        startup = 0.0
        if flags[F_STARTUP]:
            if flags[F_ABRUPT]:
                r = 1.0 if speed < P[REST_THR, j] else 0.0
            else:
                x = (speed - P[REST_THR, j]) / P[FADE_W, j]
                x = _minimum(_maximum(x, 0.0), 1.0)
                r = (x * 2.0 - 3.0) * x * x + 1.0
                # the slew limit of the faded hand-over
                r = _fmin(_fmax(r, B[B_REST, j] - REST_WEIGHT_STEP), B[B_REST, j] + REST_WEIGHT_STEP)
                B[B_REST, j] = r
            s = math.sin(P[FREQ, j] * two_pi_t)
            if flags[F_SQUARE]:
                s = _sign(s)
            if flags[F_BREAKOUT]:
                s += (B[B_HELD, j] - s) * B[B_WEIGHT, j]
            amp = P[AMP_POS, j] if s >= 0.0 else P[AMP_NEG, j]
            startup = amp * s * r
        friction = 0.0
        if flags[F_FRICTION]:
            c = P[COUL_POS, j] if pos else P[COUL_NEG, j]
            if flags[F_STRIBECK]:
                b = (P[STAT_POS, j] if pos else P[STAT_NEG, j]) - c
                b *= math.exp(-((speed / P[STRIB_V, j]) ** P[STRIB_EXP, j]))
                c += b
            w = math.tanh(_maximum(speed - deadband, 0.0) / smoothing)
            if flags[F_STARTUP]:
                w *= 1.0 - r
            friction = w * c + (P[VISC_POS, j] if pos else P[VISC_NEG, j]) * v
            if friction_scale != 1.0:
                friction *= friction_scale
        back_emf = P[BACK_EMF, j] * v if flags[F_BACK_EMF] else 0.0
        damping = -(P[DAMPING, j] * v) if flags[F_DAMPING] else 0.0
        total = gravity + friction
        total += startup
        total += back_emf
        total += damping
        total += extra[j]
        lim = P[LIMIT, j]
        clamped[j] = abs(total) > lim
        out[O_CURRENT, j] = -_minimum(-_minimum(total, lim), lim)
        out[O_GRAVITY, j] = gravity
        out[O_FRICTION, j] = friction
        out[O_STARTUP, j] = startup
        out[O_BACK_EMF, j] = back_emf
        out[O_DAMPING, j] = damping


class DragLaw:
    """The drag law for one arm: ``breakout`` and ``compensate`` by the kernels where they apply, else numpy.

    The law's outputs and the latch's state live in blocks whose rows are ``out``'s and ``state``'s arrays, so
    everything that reads them (telemetry, the guard, tests) sees the same arrays either way.
    """

    def __init__(self, params: LawParams, compiled: bool = True) -> None:
        n = params.n
        kernels = _compiled() if compiled else None
        self.compiled = kernels is not None
        if kernels is not None:
            self._breakout_kernel, self._law_kernel = kernels["breakout"], kernels["law"]
        self._out_block = np.zeros((6, n))
        rows = self._out_block
        self.out = LawOutput(current_A=rows[O_CURRENT], gravity_A=rows[O_GRAVITY], friction_A=rows[O_FRICTION],
                             startup_A=rows[O_STARTUP], back_emf_A=rows[O_BACK_EMF], damping_A=rows[O_DAMPING],
                             clamped=np.zeros(n, dtype=bool), effects_A=np.zeros(n))
        self.state = BreakoutState(n)
        self._b_block = np.empty((11, n))
        for row, name in ((B_ANCHOR, "anchor_rad"), (B_STILL_REF, "still_ref_rad"), (B_STILL_SINCE, "still_since_s"),
                          (B_LATCH, "latch"), (B_LATCH_T0, "latch_t0_s"), (B_HELD, "held"), (B_WEIGHT, "weight"),
                          (B_REST, "rest"), (B_FADE_END, "fade_end_rad_s"), (B_STILL, "still_rad_s"),
                          (B_SLIP, "slip_rad")):
            self._b_block[row] = getattr(self.state, name)
            setattr(self.state, name, self._b_block[row])
        self._counts = np.zeros((2, n), dtype=np.int64)
        self.state.latches, self.state.suppressed = self._counts[0], self._counts[1]
        self.ws = Workspace(n)
        self._params: LawParams | None = None
        self.configure(params)

    def configure(self, params: LawParams) -> None:
        """Use ``params`` (the latch's thresholds and the packed rows follow them)."""
        self._params = params
        self.state.configure(params)
        self._P, self._flags, self._S = pack_params(params)

    def breakout(self, q: np.ndarray, dq: np.ndarray, t: float, params: LawParams, tau_g: np.ndarray | None) -> None:
        """``breakout_update`` of the arm's latch."""
        if params is not self._params:
            self.configure(params)
        st = self.state
        if not self.compiled:
            breakout_update(q, dq, t, params, st, tau_g)
            return
        t_prev, st.t_prev_s = st.t_prev_s, t
        st.active = self._breakout_kernel(q, dq, t, t_prev, st.active, self._P, self._b_block, st.armed, self._counts,
                                          q if tau_g is None else tau_g, tau_g is not None, params.gravity_uncertainty)

    def compensate(self, tau_g: np.ndarray, dq: np.ndarray, t: float, params: LawParams, extra: np.ndarray,
                   q: np.ndarray) -> LawOutput:
        """``compensate`` with the arm's latch: the law's outputs in ``out``."""
        if params is not self._params:
            self.configure(params)
        if not self.compiled or params.effects is not None:
            return compensate(tau_g, dq, t, params, self.out, self.ws, extra, self.state, q)
        self._law_kernel(tau_g, dq, t, self._P, self._flags, self._S, self._b_block, extra, self._out_block,
                         self.out.clamped)
        return self.out
