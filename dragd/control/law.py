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
  offset, the friction warm-up drift I_f·Δ·(1 − e^(−t/τ)), and a knee on the back-EMF term. Inertia (rotor
  inertia) and backlash are prediction/simulation-only: drag compensates no q̈ term (the hand feels the arm's
  inertia on purpose, and a q̈ estimate at 1 kHz is noise) and the output encoder cannot see the lost motion.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np

from dragd.config import Config

TWO_PI = 2.0 * np.pi


@dataclass(frozen=True)
class LawParams:
    """The law's constants as per-joint arrays (shape (n,)), plus the switches of each term."""

    kt_Nm_per_A: np.ndarray
    current_limit_A: np.ndarray
    coulomb_pos_A: np.ndarray
    coulomb_neg_A: np.ndarray  # negative numbers
    static_pos_A: np.ndarray
    static_neg_A: np.ndarray  # negative numbers
    stribeck_velocity_rad_s: np.ndarray
    stribeck_exponent: np.ndarray
    viscous_pos_A_s_per_rad: np.ndarray
    viscous_neg_A_s_per_rad: np.ndarray
    startup_amp_pos_A: np.ndarray
    startup_amp_neg_A: np.ndarray
    startup_freq_Hz: np.ndarray
    rest_threshold_rad_s: np.ndarray
    fade_width_rad_s: np.ndarray
    back_emf_A_s_per_rad: np.ndarray
    damping_A_s_per_rad: np.ndarray
    breakout_slip_rad: np.ndarray  # 0: no break-out latch on that joint
    breakout_hold_s: np.ndarray
    settle_s: np.ndarray
    friction_scale: float = 0.95  # < 1: under-compensate so that belief errors never make a released joint run away
    smoothing_rad_s: float = 0.005
    deadband_rad_s: float = 0.0
    use_gravity: bool = True
    use_friction: bool = True
    use_stribeck: bool = True
    use_startup: bool = True
    use_back_emf: bool = False
    use_damping: bool = True
    startup_square: bool = False  # square wave of the same amplitude (the peers' dither) instead of the sine
    startup_abrupt: bool = False  # seed 001 eq. 28: switch at |q̇| = Φ instead of fading over [Φ, Φ + width]
    use_breakout: bool = True  # the break-out latch (needs a BreakoutState fed by breakout_update)
    gravity_uncertainty: float = 0.02  # fraction of |G| the latch assumes the gravity model can be off
    effects: EffectArrays | None = None  # model-gap effects (docs/GAP.md); None: none in the model

    @property
    def n(self) -> int:
        return int(self.kt_Nm_per_A.shape[0])

    def replace(self, **changes: object) -> LawParams:
        """A copy with some fields changed (arrays are converted)."""
        arrays = {f.name for f in fields(self) if f.type == "np.ndarray"}
        conv = {k: (np.array(v, dtype=float) if k in arrays else v) for k, v in changes.items()}
        return replace(self, **conv)

    @classmethod
    def from_config(cls, cfg: Config) -> LawParams:
        js = cfg.joints

        def arr(get) -> np.ndarray:  # noqa: ANN001
            return np.array([float(get(j)) for j in js], dtype=float)

        fs_pos = arr(lambda j: j.friction.static_pos_A if j.friction.static_pos_A is not None else j.friction.coulomb_pos_A)
        fs_neg = arr(lambda j: j.friction.static_neg_A if j.friction.static_neg_A is not None else j.friction.coulomb_neg_A)
        scale = cfg.law.startup_scale
        amp_pos = np.array([j.startup.amplitude_pos_A if j.startup.amplitude_pos_A is not None else scale * fs_pos[i]
                            for i, j in enumerate(js)], dtype=float)
        amp_neg = np.array([j.startup.amplitude_neg_A if j.startup.amplitude_neg_A is not None else -scale * fs_neg[i]
                            for i, j in enumerate(js)], dtype=float)
        return cls(
            kt_Nm_per_A=arr(lambda j: j.kt_Nm_per_A),
            current_limit_A=arr(lambda j: j.current_limit_A),
            coulomb_pos_A=arr(lambda j: j.friction.coulomb_pos_A),
            coulomb_neg_A=arr(lambda j: j.friction.coulomb_neg_A),
            static_pos_A=fs_pos,
            static_neg_A=fs_neg,
            stribeck_velocity_rad_s=arr(lambda j: j.friction.stribeck_velocity_rad_s),
            stribeck_exponent=arr(lambda j: j.friction.stribeck_exponent),
            viscous_pos_A_s_per_rad=arr(lambda j: j.friction.viscous_pos_A_s_per_rad),
            viscous_neg_A_s_per_rad=arr(lambda j: j.friction.viscous_neg_A_s_per_rad),
            startup_amp_pos_A=amp_pos,
            startup_amp_neg_A=amp_neg,
            startup_freq_Hz=arr(lambda j: j.startup.frequency_Hz),
            rest_threshold_rad_s=arr(lambda j: j.startup.rest_threshold_rad_s),
            fade_width_rad_s=arr(lambda j: j.startup.fade_width_rad_s),
            back_emf_A_s_per_rad=arr(lambda j: j.back_emf.constant_V_s_per_rad * j.gear_ratio / j.back_emf.resistance_ohm),
            damping_A_s_per_rad=arr(lambda j: j.drag_damping_Nm_s_per_rad / j.kt_Nm_per_A),
            breakout_slip_rad=arr(lambda j: j.breakout_slip_rad),
            breakout_hold_s=arr(lambda j: j.startup.breakout_hold_s),
            settle_s=arr(lambda j: j.startup.settle_s),
            friction_scale=cfg.law.friction_scale,
            smoothing_rad_s=cfg.law.friction_smoothing_rad_s,
            deadband_rad_s=cfg.law.friction_deadband_rad_s,
            use_gravity=cfg.law.gravity,
            use_friction=cfg.law.friction,
            use_stribeck=cfg.law.stribeck,
            use_startup=cfg.law.startup,
            use_back_emf=cfg.law.back_emf,
            use_damping=cfg.law.damping,
            startup_square=cfg.law.startup_waveform == "square",
            startup_abrupt=cfg.law.startup_handover == "abrupt",
            use_breakout=cfg.law.startup_breakout,
            gravity_uncertainty=cfg.law.gravity_uncertainty,
            effects=EffectArrays.from_config(cfg),
        ).replace(**_back_emf_from_effects(cfg))


def _back_emf_from_effects(cfg: Config) -> dict[str, object]:
    """An identified back-EMF effect (``joints[].effects.back_emf``) sets that joint's term and switches it on."""
    js = cfg.joints
    if not any(j.effects.back_emf is not None for j in js):
        return {}
    base = [j.back_emf.constant_V_s_per_rad * j.gear_ratio / j.back_emf.resistance_ohm for j in js]
    return {"back_emf_A_s_per_rad": [j.effects.back_emf.A_s_per_rad if j.effects.back_emf is not None else b
                                     for j, b in zip(js, base)], "use_back_emf": True}


@dataclass(frozen=True)
class EffectArrays:
    """The model-gap effects of every joint as arrays (shape (n,) or (n, K) for K periodic harmonics) + scratch."""

    periodic_cycles: np.ndarray  # (n, K) cycles per joint revolution (0: unused slot)
    periodic_sin_A: np.ndarray  # (n, K)
    periodic_cos_A: np.ndarray  # (n, K)
    load_friction_A_per_Nm: np.ndarray  # k_L/K_t
    offset_A: np.ndarray
    drift_change: np.ndarray  # relative friction change at t → ∞
    drift_time_constant_s: np.ndarray  # inf: no drift
    back_emf_knee_rad_s: np.ndarray
    scratch: np.ndarray  # (2, n, K)
    drift_warm_now: np.ndarray | None = None  # 1 where Δ < 0 (apply the warm level at once), else 0

    def __post_init__(self) -> None:
        if self.drift_warm_now is None:  # frozen: set once here
            object.__setattr__(self, "drift_warm_now", (self.drift_change < 0.0).astype(float))

    @classmethod
    def from_config(cls, cfg: Config) -> EffectArrays | None:
        from dragd.config import JointEffects

        js = cfg.joints
        effs = [j.effects for j in js]
        if all(e == JointEffects() for e in effs):
            return None
        n, k = len(js), max([len(e.position_periodic) for e in effs] + [1])
        cyc, sa, ca = np.zeros((n, k)), np.zeros((n, k)), np.zeros((n, k))
        for i, e in enumerate(effs):
            for h, term in enumerate(e.position_periodic):
                cyc[i, h], sa[i, h], ca[i, h] = term.cycles_per_rev, term.sin_A, term.cos_A
        td = [e.temperature_drift for e in effs]
        return cls(periodic_cycles=cyc, periodic_sin_A=sa, periodic_cos_A=ca,
                   load_friction_A_per_Nm=np.array([e.load_friction_per_Nm / j.kt_Nm_per_A for e, j in zip(effs, js)]),
                   offset_A=np.array([e.current_offset_A for e in effs], dtype=float),
                   drift_change=np.array([0.0 if d is None else d.friction_change for d in td]),
                   drift_time_constant_s=np.array([np.inf if d is None else d.time_constant_s for d in td]),
                   back_emf_knee_rad_s=np.array([0.0 if e.back_emf is None else e.back_emf.knee_rad_s for e in effs]),
                   scratch=np.zeros((2, n, k)))


class Workspace:
    """Scratch arrays for one law evaluation (like Pinocchio's Data: allocate once, reuse every cycle)."""

    def __init__(self, n: int) -> None:
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
        return cls(*(np.zeros(n) for _ in range(6)), clamped=np.zeros(n, dtype=bool), effects_A=np.zeros(n))


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
    # viscous, direction-dependent slope
    np.copyto(c, p.viscous_neg_A_s_per_rad)
    np.copyto(c, p.viscous_pos_A_s_per_rad, where=pos)
    c *= dq_rad_s
    out += c
    if p.friction_scale != 1.0:
        out *= p.friction_scale
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
