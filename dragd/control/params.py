"""The law's constants as per-joint arrays (built once from the configuration, constant while the cycle runs)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, fields, replace
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # the schema stays out of the cycle's modules at run time
    from dragd.config import Config


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
        conv: dict[str, Any] = {k: (np.array(v, dtype=float) if k in arrays else v) for k, v in changes.items()}
        return replace(self, **conv)

    @classmethod
    def from_config(cls, cfg: Config) -> LawParams:
        js = cfg.joints

        def arr(get: Callable[[Any], float]) -> np.ndarray:
            return np.array([float(get(j)) for j in js], dtype=float)

        fs_pos = arr(lambda j: j.friction.coulomb_pos_A if j.friction.static_pos_A is None else j.friction.static_pos_A)
        fs_neg = arr(lambda j: j.friction.coulomb_neg_A if j.friction.static_neg_A is None else j.friction.static_neg_A)
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
            back_emf_A_s_per_rad=arr(lambda j: j.back_emf.constant_V_s_per_rad * j.gear_ratio
                                     / j.back_emf.resistance_ohm),
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
                                     for j, b in zip(js, base, strict=True)], "use_back_emf": True}


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
    drift_viscous_change: np.ndarray | None = None  # the viscous part's own change (None: drift_change for all)
    drift_warm_now: np.ndarray = field(init=False)  # 1 where Δ < 0 (apply the warm level at once), else 0
    drift_viscous_warm_now: np.ndarray | None = field(init=False)  # the same for the viscous part's change

    def __post_init__(self) -> None:  # frozen: set once
        object.__setattr__(self, "drift_warm_now", (self.drift_change < 0.0).astype(float))
        v = self.drift_viscous_change
        object.__setattr__(self, "drift_viscous_warm_now", None if v is None else (v < 0.0).astype(float))

    @classmethod
    def from_config(cls, cfg: Config) -> EffectArrays | None:
        js = cfg.joints
        effs = [j.effects for j in js]
        if all(e == type(e)() for e in effs):  # every joint at the schema defaults: no effects
            return None
        n, k = len(js), max([len(e.position_periodic) for e in effs] + [1])
        cyc, sa, ca = np.zeros((n, k)), np.zeros((n, k)), np.zeros((n, k))
        for i, e in enumerate(effs):
            for h, term in enumerate(e.position_periodic):
                cyc[i, h], sa[i, h], ca[i, h] = term.cycles_per_rev, term.sin_A, term.cos_A
        td = [e.temperature_drift for e in effs]
        return cls(periodic_cycles=cyc, periodic_sin_A=sa, periodic_cos_A=ca,
                   load_friction_A_per_Nm=np.array([e.load_friction_per_Nm / j.kt_Nm_per_A
                                                    for e, j in zip(effs, js, strict=True)]),
                   offset_A=np.array([e.current_offset_A for e in effs], dtype=float),
                   drift_change=np.array([0.0 if d is None else d.friction_change for d in td]),
                   drift_time_constant_s=np.array([np.inf if d is None else d.time_constant_s for d in td]),
                   back_emf_knee_rad_s=np.array([0.0 if e.back_emf is None else e.back_emf.knee_rad_s for e in effs]),
                   scratch=np.zeros((2, n, k)),
                   drift_viscous_change=None if all(d is None or d.viscous_change is None for d in td) else
                   np.array([0.0 if d is None else d.friction_change if d.viscous_change is None else d.viscous_change
                             for d in td]))
