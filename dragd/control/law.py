"""The compensation law: per-joint motor current [A] that makes the arm weightless under the hand.

    I = G(q)/K_t + I_friction(q̇) + I_startup(t, q̇) + I_back_emf(q̇) + I_damping(q̇)   (+ extra terms), clamped.

Pure functions over numpy arrays; no I/O. Each takes an ``out`` array (and a ``Workspace`` of scratch arrays)
so the 1 kHz cycle evaluates the law without allocating; called without them they allocate and return.

Terms
- gravity: I_g = G(q)/K_t.
- friction (seed 001 eq. 19 with seed 000 eq. 25 / seed 002 eq. 5 direction-dependent levels):
      I_f = w(q̇)·[F_c,d + (F_s,d − F_c,d)·exp(−(|q̇|/v_s)^δ)] + F_v,d·q̇,   d = sign of q̇
  with the smooth zero crossing w = tanh(max(|q̇| − v_lim, 0)/ε): w = 0 at rest and inside seed 000's
  velocity band ±v_lim, → 1 once |q̇| ≫ v_lim + ε. The level of the side the joint moves to is used, so
  asymmetric levels (e.g. +0.89 A / −1.27 A) never bias a joint at rest. The whole term is scaled by
  ``friction_scale`` (default 0.95): a believed level above the true one would otherwise push a released joint
  along for ever (measured: 0.05 rad/s on joint 1 with a 7 % over-estimate); under-compensation stops it.
- start-up (seed 001 eq. 25/28): I_s = r(|q̇|)·A_d·sin(2πft), A_d = amplitude of the half-wave's direction.
  Seed 001 switches abruptly between I_s and friction at |q̇| = Φ; here r fades from 1 at Φ to 0 at
  Φ + width (smoothstep) and the friction level is weighted by (1 − r)·w, so it fades in as the start-up
  term fades out: the hand-over never steps the current.
  Break-out latch (ours, beyond seed 001): a joint pushed just hard enough that the sine's peaks break it loose
  only micro-slips (a count or two per period at ~0.003 rad/s, far below Φ), so the velocity hand-over never
  fires and the joint merely ratchets. The latch watches the *position*: once the joint has crept
  ``breakout_slip_rad`` from where it settled, the sine is held at its peak in that direction (blended over
  ``BREAKOUT_RAMP_S``) for at most ``breakout_hold_s`` — enough to carry the joint past Φ, where friction
  compensation takes over. It re-arms only after the joint has been still — no velocity and not one slip
  distance of creep — for ``settle_s``, so a joint coasting or creeping to rest never latches, and a latch that
  did not lead to motion moves the joint at most (Φ + width)·hold ≈ 3 mrad. It fires only where the sine's margin
  below the believed static level exceeds ``gravity_uncertainty``·|G|/K_t (a gravity-model error could otherwise
  creep the joint and the latch would start it by itself). The fade weight r is slew-limited (``REST_WEIGHT_STEP``
  per cycle) so velocity-estimate noise never steps the current.
  Options for comparison: ``startup_square`` (a square wave of the same amplitude, the peers' dither) and
  ``startup_abrupt`` (seed 001's switch at Φ).
- back-EMF headroom (seed 000 eq. 26, I = I_s − K_b·ω/R_m): the command adds K_b·n·q̇/R_m so that a drive
  whose current falls with the motor's back-EMF still delivers the intended current. Off by default.
- damping: I_d = −b·q̇/K_t, a virtual viscous damper that sets the arm's "feel": with friction compensated the
  arm is a free mass that coasts when let go; b makes it come to rest (the drag effort it adds is b·q̇).
- clamp: |I| ≤ the joint's current limit; clamped joints are flagged.
- model-gap effects (``joints[].effects``, added by ``dragd gap``, docs/GAP.md; :class:`EffectArrays`):
  position-periodic harmonics Σ s·sin(c·q) + k·cos(c·q), load-dependent friction w·d·k_L·|G|/K_t, the current
  offset, the friction warm-up drift I_f·Δ·(1 − e^(−t/τ)) (its viscous part by its own Δ_v when given), and a
  knee on the back-EMF term. Inertia (rotor inertia) and backlash are prediction/simulation-only: drag compensates
  no q̈ term (the hand feels the arm's inertia on purpose, and a q̈ estimate at 1 kHz is noise) and the output
  encoder cannot see the lost motion.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dragd.control.breakout import REST_WEIGHT_STEP, BreakoutState
from dragd.control.params import LawParams

TWO_PI = 2.0 * np.pi


class Workspace:
    """Scratch arrays for one law evaluation (like Pinocchio's Data: allocate once, reuse every cycle); of shape
    (n,) for a cycle, or (T, n) to evaluate a whole log at once."""

    def __init__(self, n: int | tuple[int, ...]) -> None:
        self.a = np.zeros(n)
        self.b = np.zeros(n)
        self.c = np.zeros(n)
        self.total = np.zeros(n)
        self.rest = np.zeros(n)
        self.pos = np.zeros(n, dtype=bool)


@dataclass
class LawOutput:
    """Per-joint components [A]; ``current_A`` = clamp(sum of components + extra)."""

    current_A: np.ndarray
    gravity_A: np.ndarray
    friction_A: np.ndarray
    startup_A: np.ndarray
    back_emf_A: np.ndarray
    damping_A: np.ndarray
    clamped: np.ndarray  # bool

    effects_A: np.ndarray | None = None  # model-gap effects (docs/GAP.md)

    @classmethod
    def zeros(cls, n: int) -> LawOutput:
        z = np.zeros
        return cls(current_A=z(n), gravity_A=z(n), friction_A=z(n), startup_A=z(n), back_emf_A=z(n), damping_A=z(n),
                   clamped=np.zeros(n, dtype=bool), effects_A=z(n))


def _out(out: np.ndarray | None, n: int) -> np.ndarray:
    return np.zeros(n) if out is None else out


def gravity_current(tau_g_Nm: np.ndarray, kt_Nm_per_A: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """I_g = G(q)/K_t."""
    out = _out(out, tau_g_Nm.shape[0])
    np.divide(tau_g_Nm, kt_Nm_per_A, out=out)
    return out


def _sliding_weight(abs_v: np.ndarray, p: LawParams, out: np.ndarray, tmp: np.ndarray,
                    rest_weight: np.ndarray | None) -> np.ndarray:
    """w·(1 − r): the smooth zero crossing / seed 000 dead band w = tanh(max(|v| − v_lim, 0)/ε), faded in by the
    start-up weight r when given (``tmp`` is scratch; ``out`` may be ``abs_v``)."""
    np.subtract(abs_v, p.deadband_rad_s, out=out)
    np.maximum(out, 0.0, out=out)
    out /= p.smoothing_rad_s
    np.tanh(out, out=out)
    if rest_weight is not None:
        np.subtract(1.0, rest_weight, out=tmp)
        out *= tmp
    return out


def friction_current(dq_rad_s: np.ndarray, p: LawParams, out: np.ndarray | None = None,
                     ws: Workspace | None = None, rest_weight: np.ndarray | None = None) -> np.ndarray:
    """Direction-dependent Coulomb/Stribeck/viscous friction current with a smooth zero crossing.

    With ``rest_weight`` r (the start-up term's weight) the Coulomb/Stribeck level is further weighted by
    (1 − r), so it fades in exactly as the start-up term fades out.
    """
    n = dq_rad_s.shape[0]
    out = _out(out, n)
    ws = ws or Workspace(n)
    a, b, c, pos = ws.a, ws.b, ws.c, ws.pos
    np.greater_equal(dq_rad_s, 0.0, out=pos)
    np.abs(dq_rad_s, out=a)  # a = |v|
    # level of the side moved to: c = F_c,d (+ Stribeck hump)
    np.copyto(c, p.coulomb_neg_A)
    np.copyto(c, p.coulomb_pos_A, where=pos)
    if p.use_stribeck:
        np.copyto(b, p.static_neg_A)
        np.copyto(b, p.static_pos_A, where=pos)
        b -= c  # F_s - F_c
        np.divide(a, p.stribeck_velocity_rad_s, out=out)
        np.power(out, p.stribeck_exponent, out=out)
        np.negative(out, out=out)
        np.exp(out, out=out)
        b *= out
        c += b
    _sliding_weight(a, p, b, a, rest_weight)
    np.multiply(b, c, out=out)
    out += viscous_current(dq_rad_s, p, pos, c)
    if p.friction_scale != 1.0:
        out *= p.friction_scale
    return out


def viscous_current(dq_rad_s: np.ndarray, p: LawParams, pos: np.ndarray, out: np.ndarray) -> np.ndarray:
    """The viscous part of the friction term before ``friction_scale``: the direction's slope × q̇ (``pos``: q̇ ≥ 0,
    as the caller has it)."""
    np.copyto(out, p.viscous_neg_A_s_per_rad)
    np.copyto(out, p.viscous_pos_A_s_per_rad, where=pos)
    out *= dq_rad_s
    return out


def startup_weight(dq_rad_s: np.ndarray, p: LawParams, out: np.ndarray | None = None,
                   ws: Workspace | None = None) -> np.ndarray:
    """r(|q̇|) = 1 − x²(3 − 2x), x = clip((|q̇| − Φ)/width, 0, 1): 1 at rest, 0 from Φ + width on."""
    n = dq_rad_s.shape[0]
    out = _out(out, n)
    x = (ws or Workspace(n)).a
    np.abs(dq_rad_s, out=x)
    if p.startup_abrupt:  # seed 001 eq. 28: 1 below Φ, 0 from Φ on
        np.less(x, p.rest_threshold_rad_s, out=out, casting="unsafe")
        return out
    x -= p.rest_threshold_rad_s
    x /= p.fade_width_rad_s
    np.maximum(x, 0.0, out=x)
    np.minimum(x, 1.0, out=x)
    np.multiply(x, 2.0, out=out)
    out -= 3.0
    out *= x
    out *= x
    out += 1.0
    return out


def startup_current(t_s: float, dq_rad_s: np.ndarray, p: LawParams, out: np.ndarray | None = None,
                    ws: Workspace | None = None, rest_weight: np.ndarray | None = None,
                    breakout: BreakoutState | None = None) -> np.ndarray:
    """Seed 001's start-up term A_d·sin(2πft) for joints at rest, faded out over [Φ, Φ + width].

    With ``breakout`` (and ``use_breakout``) the waveform blends into the held peak of a latched joint.
    """
    n = dq_rad_s.shape[0]
    out = _out(out, n)
    ws = ws or Workspace(n)
    a, s, pos = ws.a, ws.c, ws.pos
    r = rest_weight if rest_weight is not None else startup_weight(dq_rad_s, p, ws.b, ws)
    np.multiply(p.startup_freq_Hz, TWO_PI * t_s, out=s)
    np.sin(s, out=s)
    if p.startup_square:
        np.sign(s, out=s)
    if breakout is not None and p.use_breakout:  # s += w·(held − s)
        np.subtract(breakout.held, s, out=a)
        a *= breakout.weight
        s += a
    np.greater_equal(s, 0.0, out=pos)
    np.copyto(a, p.startup_amp_neg_A)
    np.copyto(a, p.startup_amp_pos_A, where=pos)
    np.multiply(a, s, out=out)
    out *= r
    return out


def back_emf_current(dq_rad_s: np.ndarray, p: LawParams, out: np.ndarray | None = None) -> np.ndarray:
    """Back-EMF headroom K_b·n·q̇/R_m (inverse of seed 000 eq. 26); with a knee (an identified effect, docs/GAP.md)
    K_b·n/R_m·(|q̇| − knee)⁺·sign q̇."""
    out = _out(out, dq_rad_s.shape[0])
    if p.effects is not None:
        np.abs(dq_rad_s, out=out)
        out -= p.effects.back_emf_knee_rad_s
        np.maximum(out, 0.0, out=out)
        np.copysign(out, dq_rad_s, out=out)
        out *= p.back_emf_A_s_per_rad
        return out
    np.multiply(p.back_emf_A_s_per_rad, dq_rad_s, out=out)
    return out


def effects_current(q_rad: np.ndarray, dq_rad_s: np.ndarray, tau_g_Nm: np.ndarray, t_s: float, p: LawParams,
                    friction_A: np.ndarray, out: np.ndarray | None = None, ws: Workspace | None = None,
                    rest_weight: np.ndarray | None = None) -> np.ndarray:
    """The model-gap effects' current (docs/GAP.md): position-periodic + load-dependent friction + offset + the
    warm-up drift of ``friction_A`` (the friction term already evaluated). Friction-like terms carry the friction
    term's smooth zero crossing, start-up fade and ``friction_scale``."""
    n = dq_rad_s.shape[0]
    out = _out(out, n)
    e = p.effects
    if e is None:
        out.fill(0.0)
        return out
    ws = ws or Workspace(n)
    a, b = ws.a, ws.b
    ph, tmp = e.scratch[0], e.scratch[1]
    np.multiply(e.periodic_cycles, q_rad[:, None], out=ph)
    np.sin(ph, out=tmp)
    tmp *= e.periodic_sin_A
    np.sum(tmp, axis=1, out=out)
    np.cos(ph, out=tmp)
    tmp *= e.periodic_cos_A
    np.sum(tmp, axis=1, out=a)
    out += a
    out += e.offset_A
    if p.use_friction:
        # load-dependent friction: w·(1 − r)·sign(q̇)·k_L·|G|/K_t·scale, w as in friction_current
        np.abs(dq_rad_s, out=b)
        _sliding_weight(b, p, b, a, rest_weight)
        np.abs(tau_g_Nm, out=a)
        a *= e.load_friction_A_per_Nm
        a *= b
        np.copysign(a, dq_rad_s, out=a)
        a *= p.friction_scale
        out += a
        # warm-up drift of the friction term: I_f·Δ·(1 − e^(−t/τ)), t the daemon's time since start. Only where
        # friction grows as the joint warms (Δ > 0: a restart on a warm arm under-compensates, safe); where it
        # falls (Δ < 0) the warm level from the start — the cold level on a warm arm would over-compensate
        np.divide(-t_s, e.drift_time_constant_s, out=a)
        np.exp(a, out=a)
        np.subtract(1.0, a, out=a)
        if e.drift_viscous_change is not None and (vwarm := e.drift_viscous_warm_now) is not None:
            # the viscous part's own change: (Δ_v·g_v − Δ·g)·I_visc on top of Δ·g·I_f below
            np.greater_equal(dq_rad_s, 0.0, out=ws.pos)
            c = viscous_current(dq_rad_s, p, ws.pos, ws.c)
            c *= p.friction_scale  # I_visc as in friction_current
            np.maximum(a, vwarm, out=b)
            b *= e.drift_viscous_change
            b *= c
            out += b
            np.maximum(a, e.drift_warm_now, out=b)
            b *= e.drift_change
            b *= c
            out -= b
        np.maximum(a, e.drift_warm_now, out=a)
        a *= e.drift_change
        a *= friction_A
        out += a
    return out


def damping_current(dq_rad_s: np.ndarray, p: LawParams, out: np.ndarray | None = None) -> np.ndarray:
    """Virtual damping −b·q̇/K_t."""
    out = _out(out, dq_rad_s.shape[0])
    np.multiply(p.damping_A_s_per_rad, dq_rad_s, out=out)
    np.negative(out, out=out)
    return out


def clamp_current(current_A: np.ndarray, limit_A: np.ndarray, out: np.ndarray | None = None,
                  clamped: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Clamp |I| ≤ limit per joint; return (clamped current, mask of joints that hit their limit)."""
    n = current_A.shape[0]
    out = _out(out, n)
    clamped = np.zeros(n, dtype=bool) if clamped is None else clamped
    np.abs(current_A, out=out)
    np.greater(out, limit_A, out=clamped)
    np.minimum(current_A, limit_A, out=out)
    np.negative(out, out=out)  # the lower bound as an upper bound on -I: no temporary array
    np.minimum(out, limit_A, out=out)
    np.negative(out, out=out)
    return out, clamped


def compensate(tau_g_Nm: np.ndarray, dq_rad_s: np.ndarray, t_s: float, p: LawParams,
               out: LawOutput | None = None, ws: Workspace | None = None,
               extra_A: np.ndarray | None = None, breakout: BreakoutState | None = None,
               q_rad: np.ndarray | None = None) -> LawOutput:
    """Evaluate every enabled term and the clamped total. ``extra_A`` (e.g. safety walls) adds before the clamp.

    ``breakout``: the latch state, advanced by the caller with :func:`breakout_update` in its estimate step.
    ``q_rad``: joint positions, for the model-gap effects (``p.effects``; position-periodic terms need q).
    """
    n = dq_rad_s.shape[0]
    out = out or LawOutput.zeros(n)
    ws = ws or Workspace(n)
    if p.use_gravity:
        gravity_current(tau_g_Nm, p.kt_Nm_per_A, out.gravity_A)
    else:
        out.gravity_A.fill(0.0)
    rest = None
    if p.use_startup:
        rest = startup_weight(dq_rad_s, p, ws.rest, ws)
        if breakout is not None and not p.startup_abrupt:  # slew-limit the faded hand-over: velocity noise must
            np.subtract(breakout.rest, REST_WEIGHT_STEP, out=ws.a)  # not step the current (seed 001's abrupt
            np.fmax(rest, ws.a, out=rest)  # switch stays as published); fmax/fmin: a NaN never sticks
            np.add(breakout.rest, REST_WEIGHT_STEP, out=ws.a)
            np.fmin(rest, ws.a, out=rest)
            breakout.rest[:] = rest
        startup_current(t_s, dq_rad_s, p, out.startup_A, ws, rest, breakout)
    else:
        out.startup_A.fill(0.0)
    if p.use_friction:
        friction_current(dq_rad_s, p, out.friction_A, ws, rest)
    else:
        out.friction_A.fill(0.0)
    if p.effects is not None and out.effects_A is not None:
        if q_rad is None:
            raise ValueError("compensate: the params' effects need q_rad")
        effects_current(q_rad, dq_rad_s, tau_g_Nm, t_s, p, out.friction_A,
                        out.effects_A, ws, rest)
    if p.use_back_emf:
        back_emf_current(dq_rad_s, p, out.back_emf_A)
    else:
        out.back_emf_A.fill(0.0)
    if p.use_damping:
        damping_current(dq_rad_s, p, out.damping_A)
    else:
        out.damping_A.fill(0.0)
    total = ws.total
    np.add(out.gravity_A, out.friction_A, out=total)
    total += out.startup_A
    total += out.back_emf_A
    total += out.damping_A
    if p.effects is not None and out.effects_A is not None:
        total += out.effects_A
    if extra_A is not None:
        total += extra_A
    clamp_current(total, p.current_limit_A, out.current_A, out.clamped)
    return out
