"""The catalogue of candidate effects: each a group of regressor columns with a documented signature.

Every effect is a current in amperes that the model lacks, linear in its parameters once its hyperparameters
(an order, a knee, a time constant, a Stribeck shape) are fixed; hyperparameters are chosen by the selection
(held-out error). Columns are built at the work rate from the prepared log (q̃, q̇, q̈, G, the URDF's dynamics)
and filtered by H like the current. ``params`` turns fitted coefficients into the params file's fields
(``joints[].friction``, ``joints[].effects``, ``payload``); ``predict`` evaluates an effect of a params file — the
same current the daemon's law adds (dragd/control/law.py ``effects_current``) and the simulator produces.

Signatures (what tells each effect from the others; docs/GAP.md has the full table):

- ``viscous_friction``  odd in q̇, grows linearly from zero speed, per direction.
- ``stribeck``          odd in q̇, a hump that decays with |q̇| (largest just after breakaway), independent of q.
- ``position_periodic`` a function of q alone (the same at every speed and direction), periodic: a peak in the
                        residual's angle-domain spectrum; its order c (cycles per joint revolution) from that peak.
- ``load_dependent_friction``  odd in q̇, even in load: ∝ sign(q̇)·|G(q)| (friction grows with gravity torque).
- ``inertia``           ∝ q̈ (and the URDF's M(q)q̈ + C q̇ when the model had no dynamics): zero at constant speed.
- ``temperature_drift`` the friction level drifting with time (warm-up), the same at the same position/speed:
                        passes through the same states disagree by when they happened.
- ``backlash``          where the tooth force of rotor and output changes sign (decelerations, reversals, load
                        reversals) the rotor crosses the play: the current is then the drive loop's, not what the
                        output's motion needs, and the impacts jump the output's velocity without a current impulse.
                        A physical predictor (``backlash.py``: the rotor simulated along the measured output), not
                        regressor columns: its fixed current is scored like any effect's.
- ``back_emf``          odd in q̇ but zero below a knee speed, linear above (voltage headroom); viscous starts at 0.
- ``payload_mass``      even in q̇: the gravity (and dynamics) of a flange mass, in the URDF's kinematic pattern
                        over joints 2..n at once (one shared mass and centre of mass); load friction is odd in q̇.
- ``current_offset``    a constant, the same in both directions and at rest (a Coulomb asymmetry changes only the
                        sliding levels); not separable from a fitted baseline's Coulomb levels while sliding.
- ``coulomb_friction``  odd in q̇ and constant in speed: the model's sliding levels are off (sign(q̇)·Δ); viscous grows
                        with speed, Stribeck decays, back-EMF starts at a knee, the offset is even.
- ``torque_constant``   the joint's gain is off: its whole torque current (gravity, payload, dynamics, rotor inertia,
                        load friction)/K_t scaled by one factor — gravity's shape *and* inertia's at once, per joint
                        (a payload is the URDF's kinematic pattern over joints; an offset is a constant).
"""

from __future__ import annotations

import hashlib
import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.ndimage import binary_dilation

from dragd.gap import EFFECT_NAMES
from dragd.gap import backlash as BL
from dragd.gap.context import GapData
from dragd.identify.methods import friction_columns

SMOOTH_RAD_S = 0.005  # the law's zero-crossing width (law.friction_smoothing_rad_s default)


@dataclass
class ModelInfo:
    """What effects need to know of the current model."""

    kt: np.ndarray  # (n,) N·m/A
    friction_A: np.ndarray  # (T, n) the model's friction current
    has_inertia: np.ndarray  # (n,) bool: the model has the URDF's dynamics (and a rotor inertia)
    coulomb_A: list[tuple[float, float]]  # per joint (pos, neg) sliding levels
    armature_kgm2: np.ndarray | None = None  # (n,) the model's rotor inertia at the joint (0: not known)
    has_backlash: np.ndarray | None = None  # (n,) bool: the model already predicts a play on the joint
    torque_A: np.ndarray | None = None  # (T, n) the model's current that is a joint torque / K_t (gravity, payload,
    #                                      dynamics, rotor inertia, load friction): what a K_t error scales
    viscous_A: np.ndarray | None = None  # (T, n) the viscous part of friction_A (None: the model has none)


@dataclass
class Cols:
    """Free columns (work rate, unfiltered), an optional fixed part that comes with the effect, and the samples the
    effect's prediction leaves too uncertain to fit or score other effects on (the play's crossings)."""

    X: np.ndarray  # (T, k)
    names: list[str]
    offset: np.ndarray | None = None  # (T,)
    exclude: np.ndarray | None = None  # (T,) bool


def weight(v: np.ndarray) -> np.ndarray:
    """The law's smooth zero crossing tanh(|q̇|/ε)."""
    return np.tanh(np.abs(v) / SMOOTH_RAD_S)


def _sgn(v: np.ndarray) -> np.ndarray:
    return np.sign(v) * weight(v)


class Effect(ABC):
    """A catalogue entry: a group of regressor columns with a documented signature (subclasses below)."""

    name = ""
    signature = ""
    shared = False  # one parameter vector for all joints (payload)
    extra_params = 0  # hyperparameters counted in the information criterion
    # its signature lives in the transients — low speeds, accelerations, the play's crossings, within the regression
    # filter's reach of a stop or reversal: judged on every sliding row; the others on the steady rows (select.py)
    transient = False

    def hypers(self, d: GapData, j: int, resid: np.ndarray, info: ModelInfo) -> list[Any]:
        return [None]

    @abstractmethod
    def columns(self, d: GapData, j: int, hyper: Any, info: ModelInfo) -> Cols | None:
        """The effect's regressor columns on joint j for one hyperparameter (None: not applicable)."""

    @abstractmethod
    def params(self, theta: np.ndarray, hyper: Any, d: GapData, j: int, info: ModelInfo) -> dict[str, Any]:
        """Fitted coefficients → the params-file entry (SI + A units in the keys)."""

    @abstractmethod
    def write(self, pf: dict[str, Any], joint: str, prm: dict[str, Any]) -> None:
        """Write ``prm`` into a params-file dict for ``joint``."""

    def predict(self, d: GapData, j: int, jp: dict[str, Any], kt: float) -> np.ndarray | None:
        """This effect's current on joint j from a params file's joint entry (None: not in it)."""
        return None

    def physical(self, theta: np.ndarray, info: ModelInfo, j: int) -> bool:
        """Whether fitted coefficients are physically possible (a wrong-signed fit explains something else)."""
        return True


def _friction(pf: dict[str, Any], joint: str) -> dict[str, Any]:
    return pf["joints"].setdefault(joint, {}).setdefault("friction", {})


def _effects(pf: dict[str, Any], joint: str) -> dict[str, Any]:
    return pf["joints"].setdefault(joint, {}).setdefault("effects", {})


class Viscous(Effect):
    name = "viscous_friction"
    signature = "odd in q̇, linear from zero speed, per direction"

    def columns(self, d, j, hyper, info):
        F, names = friction_columns(d.p.dq[:, j])
        return Cols(F[:, 2:4], ["viscous_pos_A_s_per_rad", "viscous_neg_A_s_per_rad"])

    def params(self, theta, hyper, d, j, info):
        return {"viscous_pos_A_s_per_rad": float(theta[0]), "viscous_neg_A_s_per_rad": float(theta[1])}

    def write(self, pf, joint, prm):
        f = _friction(pf, joint)
        for k in ("viscous_pos_A_s_per_rad", "viscous_neg_A_s_per_rad"):
            base = f.get(k)
            base = f.get("viscous_A_s_per_rad") if base is None else base
            f[k] = max(0.0, (base or 0.0) + prm[k])
        f["viscous_A_s_per_rad"] = None


class Stribeck(Effect):
    name = "stribeck"
    signature = "odd in q̇, a hump decaying with |q̇| (largest after breakaway), independent of q"
    extra_params = 2
    # v_s ≥ 2 × the sliding threshold (0.01 rad/s): a narrower hump has decayed before the joint counts as sliding and
    # is seen only through the regression filter's leakage of the reversals (where q̇ is estimated, not measured) —
    # fitted there it named a 3–6 A "hump" with v_s ≈ 0.005 on clean independent logs
    V_MIN = 0.02
    # δ ≤ 2 (the Stribeck exponents reported for gears and bearings lie in 0.5–2): a sharper "hump" at v_s ≈ V_MIN is
    # a step at breakaway — where q̇ is estimated through the 20 Hz position filter and the exact friction sign is not
    DELTA_MAX = 2.0
    GRID = [(vs, de) for vs in (0.02, 0.03, 0.05, 0.08, 0.12, 0.2) for de in (1.0, 1.5, 2.0)]

    def hypers(self, d, j, resid, info):
        return self.GRID

    def refine(self, sse: Any, hyper: tuple[float, float]) -> tuple[float, float]:
        """v_s, δ by Nelder–Mead on the fit's residual (variable projection: the levels are solved inside)."""
        from scipy.optimize import minimize

        def f(x: np.ndarray) -> float:
            vs, de = math.exp(x[0]), math.exp(x[1])
            return sse((vs, de)) if self.V_MIN <= vs < 1.0 and 0.5 <= de <= self.DELTA_MAX else float("inf")

        r = minimize(f, np.log(hyper), method="Nelder-Mead", options={"xatol": 0.02, "fatol": 1e-9, "maxfev": 40})
        return (float(math.exp(r.x[0])), float(math.exp(r.x[1]))) if np.isfinite(r.fun) else hyper

    MIN_ROWS = 20  # fit rows (12.5 Hz) inside the hump, |q̇| < 2·v_s, for its shape to be seen at all

    def columns(self, d, j, hyper, info):
        v = d.p.dq[:, j]
        if int(np.count_nonzero(np.abs(v[d.fit_rows(j)]) < 2.0 * hyper[0])) < self.MIN_ROWS:
            return None  # the hump's speeds are not on the fit rows: only the filter's leakage of breakaways shows it
        e = np.exp(-(np.abs(v) / hyper[0]) ** hyper[1]) * weight(v)
        return Cols(np.column_stack([e * (v > 0), e * (v < 0)]), ["dstatic_pos_A", "dstatic_neg_A"])

    def physical(self, theta, info, j):
        return bool(theta[0] > 0 and theta[1] < 0)

    def params(self, theta, hyper, d, j, info):
        cp, cn = info.coulomb_A[j]
        return {"static_pos_A": float(cp + theta[0]), "static_neg_A": float(cn + theta[1]),
                "stribeck_velocity_rad_s": float(hyper[0]), "stribeck_exponent": float(hyper[1])}

    def write(self, pf, joint, prm):
        f = _friction(pf, joint)
        cp = f.get("coulomb_pos_A") or 0.0
        cn = f.get("coulomb_neg_A") or 0.0
        f["static_pos_A"] = max(prm["static_pos_A"], cp)
        f["static_neg_A"] = min(prm["static_neg_A"], cn)
        f["stribeck_velocity_rad_s"] = prm["stribeck_velocity_rad_s"]
        f["stribeck_exponent"] = prm["stribeck_exponent"]


class PositionPeriodic(Effect):
    name = "position_periodic"
    signature = "a function of q alone, periodic: a peak in the residual's angle-domain spectrum"
    extra_params = 1

    def hypers(self, d, j, resid, info):
        return spectrum_peaks(d, j, resid)[:3]

    def columns(self, d, j, hyper, info):
        if hyper is None:
            return None
        q = d.p.q[:, j]
        return Cols(np.column_stack([np.sin(hyper * q), np.cos(hyper * q)]), ["sin_A", "cos_A"])

    def params(self, theta, hyper, d, j, info):
        return {"cycles_per_rev": float(hyper), "sin_A": float(theta[0]), "cos_A": float(theta[1])}

    def write(self, pf, joint, prm):
        _effects(pf, joint).setdefault("position_periodic", []).append(dict(prm))

    def predict(self, d, j, jp, kt):
        terms = (jp.get("effects") or {}).get("position_periodic") or []
        if not terms:
            return None
        q = d.p.q[:, j]
        return sum(h["sin_A"] * np.sin(h["cycles_per_rev"] * q) + h["cos_A"] * np.cos(h["cycles_per_rev"] * q)
                   for h in terms)


class LoadFriction(Effect):
    name = "load_dependent_friction"
    signature = "odd in q̇, ∝ |gravity torque|: sign(q̇)·|G(q)|"

    def columns(self, d, j, hyper, info):
        g = np.abs(d.G[:, j])
        if np.ptp(g) < 1.0:  # N·m: no load change on this joint
            return None
        return Cols((_sgn(d.p.dq[:, j]) * g)[:, None], ["load_A_per_Nm"])

    def physical(self, theta, info, j):
        return bool(theta[0] > 0)

    def params(self, theta, hyper, d, j, info):
        return {"load_friction_per_Nm": float(theta[0] * info.kt[j])}

    def write(self, pf, joint, prm):
        e = _effects(pf, joint)
        e["load_friction_per_Nm"] = max(0.0, (e.get("load_friction_per_Nm") or 0.0) + prm["load_friction_per_Nm"])

    def predict(self, d, j, jp, kt):
        k = (jp.get("effects") or {}).get("load_friction_per_Nm") or 0.0
        return None if not k else _sgn(d.p.dq[:, j]) * np.abs(d.G[:, j]) * k / kt


class Inertia(Effect):
    name = "inertia"
    transient = True
    signature = ("∝ q̈ (rotor inertia; with the URDF's M(q)q̈ + C q̇ when the model had no dynamics): "
                 "zero at constant speed")

    def columns(self, d, j, hyper, info):
        off = None if info.has_inertia[j] else d.tau_dyn[:, j] / info.kt[j]
        return Cols(d.p.ddq[:, j:j + 1], ["armature_A_s2_per_rad"], off)

    def physical(self, theta, info, j):
        return bool(theta[0] > 0 or info.has_inertia[j])  # a correction may lower a known rotor inertia

    def params(self, theta, hyper, d, j, info):
        return {"armature_kgm2": float(theta[0] * info.kt[j])}

    def write(self, pf, joint, prm):
        e = _effects(pf, joint)
        e["armature_kgm2"] = max(0.0, (e.get("armature_kgm2") or 0.0) + prm["armature_kgm2"])

    def predict(self, d, j, jp, kt):
        ja = (jp.get("effects") or {}).get("armature_kgm2")
        return None if ja is None else (d.tau_dyn[:, j] + ja * d.p.ddq[:, j]) / kt


class TemperatureDrift(Effect):
    name = "temperature_drift"
    signature = ("the friction level drifting with time: I_f·(1 − e^(−t/τ)), its viscous part by its own factor; "
                 "passes through the same states disagree")
    extra_params = 1

    def hypers(self, d, j, resid, info):
        T = float(d.t_rel[-1])
        return [T * f for f in (0.125, 0.25, 0.5, 1.0, 2.0, 4.0)]

    def columns(self, d, j, hyper, info):
        f = info.friction_A[:, j]
        if not np.any(f):
            return None
        g = 1.0 - np.exp(-d.t_rel / hyper)
        v = info.viscous_A[:, j] if info.viscous_A is not None else None
        if v is None or not np.any(v) or not np.any(f - v):
            return Cols((f * g)[:, None], ["friction_change"])
        # the lubricant's viscosity falls faster with temperature than the contact (Coulomb/Stribeck) friction
        return Cols(np.column_stack([(f - v) * g, v * g]), ["friction_change", "viscous_change"])

    def params(self, theta, hyper, d, j, info):
        out = {"friction_change": float(theta[0]), "time_constant_s": float(hyper)}
        if theta.size > 1:
            out["viscous_change"] = float(theta[1])
        return out

    def physical(self, theta, info, j):
        return bool(np.all((theta > -0.95) & (theta < 5.0)))  # a relative change the params file can hold

    def write(self, pf, joint, prm):
        _effects(pf, joint)["temperature_drift"] = dict(prm)

    def current(self, d: GapData, jp: dict[str, Any], friction_A: np.ndarray,
                viscous_A: np.ndarray | None) -> np.ndarray | None:
        """The drift's current on a joint from its params entry, the model's friction current and its viscous part."""
        td = (jp.get("effects") or {}).get("temperature_drift")
        if not td:
            return None
        g = 1.0 - np.exp(-d.t_rel / td["time_constant_s"])
        out = td["friction_change"] * g * friction_A
        if td.get("viscous_change") is not None and viscous_A is not None:
            out += (td["viscous_change"] - td["friction_change"]) * g * viscous_A
        return out


class Backlash(Effect):
    name = "backlash"
    transient = True
    signature = ("where the rotor-output tooth force changes sign the rotor crosses the play: the current is the drive "
                 "loop's (ŝ − k_p·q − k_d·q̇), the impacts jump the output's velocity without a current impulse")
    extra_params = 5  # play, output friction share, two loop gains, the loop-input bandwidth
    MIN_GAIN = 0.02  # a play that explains less than 2 % of the residual energy is not fitted further

    def hypers(self, d, j, resid, info):
        if info.has_backlash is not None and info.has_backlash[j]:
            return []  # one play per joint: a given play is refitted from the model without it, not stacked
        model_A = d.p.i[:, j] - resid
        key = ("backlash", j, hashlib.blake2b(model_A.tobytes(), digest_size=16).hexdigest())
        if key not in d.cache:
            path = joint_path(d, j, model_A, info)
            ja = 0.0 if info.armature_kgm2 is None else float(info.armature_kgm2[j])
            inertias = [ja / info.kt[j]] if ja > 0 else [f * float(np.median(path.output_inertia_A_s2_per_rad))
                                                          for f in (0.1, 0.3)]
            fits = [f for J in inertias if (f := BL.fit(path, resid, J, self.MIN_GAIN)) is not None]
            d.cache[key] = min(fits, key=lambda f: f.sse_after) if fits else None
        fit = d.cache[key]
        return [fit] if fit is not None else []

    def columns(self, d, j, hyper, info):
        if hyper is None or not np.any(hyper.column):
            return None
        # inside the crossings the current follows the drive's unobserved reference: no rigid-body effect is to be
        # fitted to what is left there (± the regression filter's reach)
        reach = max(1, int(round(d.p.fs / d.p.cutoff_Hz)))
        exclude = binary_dilation(hyper.loop, iterations=reach)
        return Cols(np.zeros((d.T, 0)), [], hyper.column, exclude)

    def params(self, theta, hyper, d, j, info):
        return BL.params_dict(hyper.params, float(info.kt[j]))

    def write(self, pf, joint, prm):
        _effects(pf, joint).update({k: (list(v) if isinstance(v, (list, tuple)) else v) for k, v in prm.items()})

    def predict_on(self, d: GapData, j: int, jp: dict[str, Any], kt: float, model_A: np.ndarray,
                   info: ModelInfo) -> np.ndarray | None:
        """The current a params file's play adds to ``model_A`` (the rest of the model) on joint j (None: no play)."""
        e = jp.get("effects") or {}
        if not e.get("backlash_rad") or not e.get("backlash_loop_A_per_rad"):
            return None
        J = e.get("backlash_inertia_kgm2") or e.get("armature_kgm2") or 0.0
        kp, kd = e["backlash_loop_A_per_rad"]
        prm = BL.BacklashParams(float(e["backlash_rad"]), float(J) / kt, float(kp), float(kd),
                                float(e.get("backlash_output_friction_fraction") or 0.0),
                                float(e.get("backlash_cutoff_Hz") or BL.LOOP_CUTOFF_HZ))
        return BL.predict(joint_path(d, j, model_A, info), prm)[0]


class BackEmf(Effect):
    name = "back_emf"
    signature = "odd in q̇, zero below a knee speed and linear above (voltage headroom); viscous starts at zero"
    extra_params = 1

    def hypers(self, d, j, resid, info):
        v = np.abs(d.p.dq[d.fit_rows(j), j])
        if v.size < 20:
            return []
        return sorted({round(float(x), 3) for x in np.quantile(v, [0.15, 0.3, 0.45, 0.6, 0.75])})

    def refine(self, sse: Any, hyper: float) -> float:
        """The knee as a continuous value (the grid is the speeds' quantiles): bounded search on the fit's residual
        (variable projection: the slope is solved inside), within a factor of two of the grid's best."""
        from scipy.optimize import minimize_scalar

        if hyper <= 0.0:
            return hyper
        r = minimize_scalar(lambda k: sse(round(float(k), 4)), bounds=(0.5 * hyper, 2.0 * hyper), method="bounded",
                            options={"xatol": 2e-3, "maxiter": 25})
        return round(float(r.x), 4) if np.isfinite(r.fun) and r.fun < sse(hyper) else hyper

    def columns(self, d, j, hyper, info):
        v = d.p.dq[:, j]
        return Cols((np.sign(v) * np.maximum(np.abs(v) - hyper, 0.0))[:, None], ["A_s_per_rad"])

    def physical(self, theta, info, j):
        return bool(theta[0] > 0)

    def params(self, theta, hyper, d, j, info):
        return {"A_s_per_rad": float(theta[0]), "knee_rad_s": float(hyper)}

    def write(self, pf, joint, prm):
        _effects(pf, joint)["back_emf"] = {"A_s_per_rad": max(0.0, prm["A_s_per_rad"]), "knee_rad_s": prm["knee_rad_s"]}

    def predict(self, d, j, jp, kt):
        b = (jp.get("effects") or {}).get("back_emf")
        if not b:
            return None
        v = d.p.dq[:, j]
        return b["A_s_per_rad"] * np.sign(v) * np.maximum(np.abs(v) - b["knee_rad_s"], 0.0)


class PayloadMass(Effect):
    name = "payload_mass"
    signature = "even in q̇: a flange mass's gravity/dynamics over joints 2..n at once (shared mass and centre)"
    shared = True

    def columns(self, d, j, hyper, info):
        Y = d.payload_regressor()[:, j, :] / info.kt[j]
        if np.abs(Y).max() < 1e-6:
            return None
        return Cols(Y, ["m_kg", "mcx_kgm", "mcy_kgm", "mcz_kgm"])

    def physical(self, theta, info, j):
        return bool(theta[0] > 0)

    def params(self, theta, hyper, d, j, info):
        m = float(theta[0])
        com = [float(x / m) if abs(m) > 1e-6 else 0.0 for x in theta[1:4]]
        return {"mass_kg": m, "com_m": com}

    def write(self, pf, joint, prm):
        if prm["mass_kg"] > 0:
            pf["payload"] = {"mass_kg": prm["mass_kg"], "com_m": list(prm["com_m"])}

    @staticmethod
    def predict_all(d: GapData, payload: dict[str, Any] | None, kt: np.ndarray) -> np.ndarray | None:
        if not payload or not payload.get("mass_kg"):
            return None
        m = payload["mass_kg"]
        th = np.array([m] + [m * c for c in payload.get("com_m", (0.0, 0.0, 0.0))])
        return d.payload_regressor() @ th / kt


class CurrentOffset(Effect):
    name = "current_offset"
    signature = "a constant: the same in both directions and at rest"

    def columns(self, d, j, hyper, info):
        return Cols(np.ones((d.T, 1)), ["current_offset_A"])

    def params(self, theta, hyper, d, j, info):
        return {"current_offset_A": float(theta[0])}

    def write(self, pf, joint, prm):
        e = _effects(pf, joint)
        e["current_offset_A"] = (e.get("current_offset_A") or 0.0) + prm["current_offset_A"]

    def predict(self, d, j, jp, kt):
        c = (jp.get("effects") or {}).get("current_offset_A") or 0.0
        return None if not c else np.full(d.T, c)


class CoulombFriction(Effect):
    name = "coulomb_friction"
    signature = "odd in q̇, constant in speed: the sliding levels are off by ±Δ (viscous grows, Stribeck decays)"

    def columns(self, d, j, hyper, info):
        return Cols(_sgn(d.p.dq[:, j])[:, None], ["coulomb_change_A"])

    def physical(self, theta, info, j):
        cp, cn = info.coulomb_A[j]
        return bool(cp + theta[0] > 0 and cn - theta[0] < 0)

    def params(self, theta, hyper, d, j, info):
        cp, cn = info.coulomb_A[j]
        return {"coulomb_pos_A": float(cp + theta[0]), "coulomb_neg_A": float(cn - theta[0]),
                "change_A": float(theta[0])}

    def write(self, pf, joint, prm):
        f = _friction(pf, joint)
        dc = prm["change_A"]
        f["coulomb_pos_A"] = max(prm["coulomb_pos_A"], 0.0)
        f["coulomb_neg_A"] = min(prm["coulomb_neg_A"], 0.0)
        if f.get("static_pos_A") is not None:  # the hump above the level is kept
            f["static_pos_A"] = max(f["static_pos_A"] + dc, f["coulomb_pos_A"])
        if f.get("static_neg_A") is not None:
            f["static_neg_A"] = min(f["static_neg_A"] - dc, f["coulomb_neg_A"])


class TorqueConstant(Effect):
    name = "torque_constant"
    transient = True
    signature = ("the joint's gain is off: its torque current (gravity, payload, dynamics, rotor inertia)/K_t scaled "
                 "by one factor — gravity's and inertia's shape at once, on one joint")

    def columns(self, d, j, hyper, info):
        if info.torque_A is None or not np.any(info.torque_A[:, j]):
            return None
        return Cols(info.torque_A[:, j:j + 1], ["gain_change"])

    def physical(self, theta, info, j):
        return bool(-0.8 < theta[0] < 4.0)  # K_t within a factor 5 of the belief

    def params(self, theta, hyper, d, j, info):
        return {"torque_constant_Nm_per_A": float(info.kt[j] / (1.0 + theta[0])),
                "relative_to_model": float(1.0 / (1.0 + theta[0]) - 1.0)}

    def write(self, pf, joint, prm):
        pf["joints"].setdefault(joint, {})["torque_constant_Nm_per_A"] = prm["torque_constant_Nm_per_A"]


CATALOGUE: dict[str, Effect] = {e.name: e for e in (Viscous(), Stribeck(), PositionPeriodic(), LoadFriction(),
                                                      Inertia(), TemperatureDrift(), Backlash(), BackEmf(),
                                                      PayloadMass(), CurrentOffset(), CoulombFriction(),
                                                      TorqueConstant())}
NAMES = tuple(CATALOGUE)
if NAMES != EFFECT_NAMES:
    raise ImportError(f"dragd.gap.EFFECT_NAMES {EFFECT_NAMES} is not the catalogue {NAMES}: list the effects there too")


# ------------------------------------------------------------------------------------------ helpers


PERIODS_MIN = 1.0  # the longest period looked for: the travelled range (a stroke of 1.1 periods shows a whole wave)


def spectrum_peaks(d: GapData, j: int, resid: np.ndarray, max_peaks: int = 3) -> list[float]:
    """Orders c (cycles per joint revolution) of the largest peaks of the residual's angle-domain spectrum.

    Lomb–Scargle periodogram of the residual against q over the sliding samples (q is not uniformly sampled), for c
    from one period over the travelled range (PERIODS_MIN) up to what the regression filter passes at the typical
    speed; whether a peak is real is the selection's test (held-out error, BIC), not the spectrum's.
    """
    from scipy.signal import lombscargle

    m = d.slide[:, j]
    if m.sum() < 200:
        return []
    q, r = d.p.q[m, j], resid[m]
    rng = float(np.ptp(q))
    if rng < 0.05:
        return []
    v = float(np.median(np.abs(d.p.dq[m, j])))
    c_min = PERIODS_MIN * 2.0 * math.pi / rng
    c_max = min(400.0, 2.0 * math.pi * 0.8 * d.p.cutoff_Hz / max(v, 1e-3))
    if c_max <= c_min:
        return []
    step = 2.0 * math.pi / rng / 8.0
    cs = np.arange(c_min, c_max, step)
    step_k = max(1, r.size // 4000)  # a subsample is plenty for locating a peak
    pw = lombscargle(q[::step_k], r[::step_k] - r[::step_k].mean(), cs)
    peaks = [k for k in range(1, cs.size - 1) if pw[k] >= pw[k - 1] and pw[k] >= pw[k + 1]]
    peaks.sort(key=lambda k: -pw[k])
    out = []
    for k in peaks[:max_peaks]:
        # parabolic refinement of the peak
        a, b, c = pw[k - 1], pw[k], pw[k + 1]
        den = a - 2 * b + c
        off = 0.5 * (a - c) / den if den != 0 else 0.0
        out.append(float(cs[k] + off * step))
    return out


def joint_path(d: GapData, j: int, model_A: np.ndarray, info: ModelInfo) -> BL.JointPath:
    """The backlash predictor's inputs for joint j: the output path (q, and q̇, q̈ as its derivatives), the model's
    current ``model_A`` along it, the model's friction law (Coulomb and viscous per direction, fitted to its friction
    current), the URDF's M_jj/K_t, stretches and the fit mask."""
    p = d.p
    q = p.q[:, j]
    v = np.empty_like(q)
    a = np.empty_like(q)
    for s in p.segments:
        if s.stop - s.start > 2:
            v[s.start:s.stop] = np.gradient(q[s.start:s.stop], 1.0 / p.fs)
            a[s.start:s.stop] = np.gradient(v[s.start:s.stop], 1.0 / p.fs)
        else:
            v[s.start:s.stop] = a[s.start:s.stop] = 0.0
    f = info.friction_A[:, j]
    m = np.abs(v) > 0.02
    X = friction_columns(v)[0][m]
    fr = (0.0, 0.0, 0.0, 0.0)
    if m.sum() > 10 and np.any(f[m]):
        th, *_ = np.linalg.lstsq(X, f[m], rcond=None)
        fr = (max(float(th[0]), 0.0), min(float(th[1]), 0.0), max(float(th[2]), 0.0), max(float(th[3]), 0.0))
    return BL.JointPath(q, v, a, np.asarray(model_A, dtype=float), fr, d.inertia_diag()[:, j] / float(info.kt[j]),
                        p.fs, [(s.start, s.stop) for s in p.segments], d.slide[:, j],
                        1.0 / p.deriv_cutoff_Hz)  # impacts: the width of the zero-phase q̈ filter's response
