"""The identification methods: seed 000 (low speed), seed 001 (symmetric), seed 002 (synchronous), full dynamics.

All work on a :class:`~dragd.identify.data.Prepared` log, joint by joint (each joint has its own torque constant),
in amperes of motor current. Friction uses dragd's law (dragd/control/law.py) so the result plugs straight in:

    I_f(q̇) = d·[F_c,d + (F_s,d − F_c,d)·exp(−(|q̇|/v_s)^δ)] + F_v,d·q̇,   d = sign q̇

Every regression is the same zero-phase filter H on both sides: H(i) ≈ Σ θ_k·H(column_k(q̃, q̇, q̈)).
See docs/IDENTIFICATION.md for the equations and how each method follows its seed.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial import cKDTree

from dragd.identify.data import Log, LogError, Prepared, motion_summary, prepare, sliding
from dragd.identify.regressors import RegressorModel
from dragd.identify.results import (
    COULOMB_NEG_A,
    COULOMB_POS_A,
    FRICTION_KEYS,
    STATIC_NEG_A,
    STATIC_POS_A,
    STRIBECK_EXPONENT,
    STRIBECK_VELOCITY_RAD_S,
    VISCOUS_A_S_PER_RAD,
    VISCOUS_NEG_A_S_PER_RAD,
    VISCOUS_POS_A_S_PER_RAD,
    FitResult,
    JointResult,
    LinearFit,
    linear_fit,
    prior_fit,
)

METHODS = ("lowspeed", "symmetric", "synchronous", "full", "auto")
PRIOR_REL = 0.05  # full dynamics: prior std of a base parameter relative to its URDF value (CAD masses)
ARMATURE_PRIOR_KGM2 = 1.0  # ... and of a rotor inertia (not in a URDF), reflected to the joint
PRIOR_GRAVITY_REL = 0.01  # ... and of a gravity parameter (the K_t reference; see fit_full)
RESOLUTION_A = 0.05  # a friction term whose uncertainty moves the current by more than this over the data is null ...
DETERMINED_REL = 0.2  # ... unless it is determined to this fraction of its value (a 5σ estimate on noisy real logs)
KT_MAX_REL_STD = 0.05  # a torque constant not determined to 5 % is null
MIN_ROWS = 20


@dataclass
class Options:
    cutoff_Hz: float = 5.0  # regression filter H (zero-phase), both sides
    deriv_cutoff_Hz: float = 20.0  # positions before differentiation
    v_rest: float = 0.005  # |q̇| below this: at rest / stuck [rad/s]
    v_min: float = 0.01  # steady sliding above this [rad/s]
    a_max: float = 0.3  # quasi-static: every joint's |H(q̈)| below this [rad/s²] (inertia is in the model)
    lowspeed_max: float = 0.06  # seed 000: "low speed" up to this [rad/s] (≈ 3.4°/s)
    lowspeed_cutoff_Hz: float = 0.5  # seed 000 samples at 10 ms and fits straight lines: a slow H
    stribeck_exponent: float | None = None  # δ; None: fitted when the data has low-speed sliding
    pair_tol_rad: float = 0.004  # symmetric: positions within this are "the same position"
    pair_speed_tol: float = 0.15  # symmetric: |q̇_a + q̇_b| ≤ tol·|q̇_a|
    never_moves_rad: float = 0.5 * math.pi / 180  # a joint whose range stays below this never moves
    torque_constants: list[float | None] | None = None  # joint-side K_t known to the user (full method), per joint
    load_friction: bool = False  # full method: also fit a load-dependent Coulomb term sign(q̇)·|G| where it helps


# ------------------------------------------------------------------------------------------ context


class Context:
    """A prepared log plus the robot's regressors, shared by the methods."""

    def __init__(self, log: Log, robot: Any, opts: Options, rm: RegressorModel | None = None) -> None:
        log.check_robot(robot.joint_names, str(robot.urdf_path or "robot"))
        self.log = log
        self.opts = opts
        self.robot = robot
        self.p: Prepared = prepare(log, opts.cutoff_Hz, opts.deriv_cutoff_Hz)
        self.rm = rm or RegressorModel(robot)
        self.names = list(robot.joint_names)
        self.n = len(self.names)
        self.warnings = list(self.p.warnings)
        self.iH = self.p.regfilter(self.p.i)
        self.ddqH = self.p.regfilter(self.p.ddq)
        self.rows = self.p.rows()
        self.motion = motion_summary(self.p)
        self._tau: np.ndarray | None = None
        self._grav: np.ndarray | None = None
        self._tauH: np.ndarray | None = None
        self._gravH: np.ndarray | None = None

    @property
    def tau(self) -> np.ndarray:
        """The URDF's rigid-body torque RNEA(q̃, q̇, q̈) [N·m] (no rotor inertia, no friction)."""
        if self._tau is None:
            self._tau = self.rm.rnea(self.p.q, self.p.dq, self.p.ddq)
        return self._tau

    @property
    def tauH(self) -> np.ndarray:
        if self._tauH is None:
            self._tauH = self.p.regfilter(self.tau)
        return self._tauH

    @property
    def grav(self) -> np.ndarray:
        if self._grav is None:
            self._grav = self.rm.gravity(self.p.q)
        return self._grav

    @property
    def gravH(self) -> np.ndarray:
        if self._gravH is None:
            self._gravH = self.p.regfilter(self.grav)
        return self._gravH

    def never_moves(self, j: int) -> str | None:
        m = self.motion[j]
        if m["range_rad"] < self.opts.never_moves_rad or m["max_speed_rad_s"] < self.opts.v_min:
            return (f"{self.names[j]} never moves in this log (range {math.degrees(m['range_rad']):.2f}°, max speed "
                    f"{m['max_speed_rad_s']:.4f} rad/s): its parameters are not identifiable from it")
        return None

    def steady(self, j: int, guard_s: float | None = None) -> np.ndarray:
        """Joint j sliding steadily (±guard) while no joint accelerates (H-filtered q̈): quasi-static rows."""
        p, o = self.p, self.opts
        guard = int(round((guard_s if guard_s is not None else 1.5 / o.cutoff_Hz) * p.fs))
        m = sliding(p.dq[:, j:j + 1], o.v_min, guard)[:, 0]
        calm = np.all(np.abs(self.ddqH) < o.a_max, axis=1)
        calm = sliding(calm[:, None].astype(float), 0.5, guard)[:, 0]
        return m & calm

    def sliding(self, j: int, guard_s: float | None = None) -> np.ndarray:
        p, o = self.p, self.opts
        guard = int(round((guard_s if guard_s is not None else 1.5 / o.cutoff_Hz) * p.fs))
        return sliding(p.dq[:, j:j + 1], o.v_rest, guard)[:, 0]


# ------------------------------------------------------------------------------------------ friction model


def friction_columns(v: np.ndarray, direction: np.ndarray | None = None, vs: float | None = None,
                     delta: float = 2.0, viscous: bool = True) -> tuple[np.ndarray, list[str]]:
    """Columns of dragd's friction law: F_c±, F_v±, (F_s − F_c)± for a given v_s, δ; ``direction`` = sign source."""
    d = np.sign(v) if direction is None else np.sign(direction)
    pos, neg = (d > 0).astype(float), (d < 0).astype(float)
    cols, names = [pos, neg], [COULOMB_POS_A, COULOMB_NEG_A]
    if viscous:
        cols += [v * pos, v * neg]
        names += [VISCOUS_POS_A_S_PER_RAD, VISCOUS_NEG_A_S_PER_RAD]
    if vs is not None:
        e = np.exp(-(np.abs(v) / vs) ** delta)
        cols += [pos * e, neg * e]
        names += ["dstatic_pos_A", "dstatic_neg_A"]
    return np.column_stack(cols), names


def friction_value(v: np.ndarray, fr: dict[str, float | None]) -> np.ndarray:
    """I_f(v) of a friction dict (None terms count as zero; no hump without v_s)."""
    g = {k: float(fr.get(k) or 0.0) for k in FRICTION_KEYS}
    pos = v > 0
    out = np.where(pos, g[COULOMB_POS_A], g[COULOMB_NEG_A])
    vp = fr.get(VISCOUS_POS_A_S_PER_RAD)
    vn = fr.get(VISCOUS_NEG_A_S_PER_RAD)
    vv = fr.get(VISCOUS_A_S_PER_RAD) or 0.0
    out = out + np.where(pos, vp if vp is not None else vv, vn if vn is not None else vv) * v
    if fr.get(STRIBECK_VELOCITY_RAD_S) and fr.get(STATIC_POS_A) is not None and fr.get(STATIC_NEG_A) is not None:
        delta = fr.get(STRIBECK_EXPONENT) or 2.0
        e = np.exp(-(np.abs(v) / fr[STRIBECK_VELOCITY_RAD_S]) ** delta)
        out = out + np.where(pos, g[STATIC_POS_A] - g[COULOMB_POS_A], g[STATIC_NEG_A] - g[COULOMB_NEG_A]) * e
    return np.where(v == 0, 0.0, out)


def _set_friction_from_fit(jr: JointResult, fit: LinearFit, vmax: float, reason_prefix: str = "",
                           v: np.ndarray | None = None) -> None:
    """Coulomb/viscous levels of a linear fit into the result (with resolution checks and reasons).

    When a direction's viscous slope is inseparable from its Coulomb level (one speed only), the level the fit
    found is the friction *at that speed*: both terms are null then, the level goes to the diagnostics.
    """
    for d, sgn in (("pos", 1), ("neg", -1)):
        vk, ck = f"viscous_{d}_A_s_per_rad", f"coulomb_{d}_A"
        if vk in fit.dropped and "not separable" in fit.dropped[vk] and fit.value(ck) is not None:
            speed = (float(np.mean(np.abs(v[np.sign(v) == sgn]))) if v is not None and np.any(np.sign(v) == sgn)
                     else None)
            level = fit.value(ck)
            at = f" at |q̇| ≈ {speed:.3f} rad/s" if speed is not None else ""
            jr.diagnostics[f"friction_level_{d}_A"] = level
            why = (f"{reason_prefix}one speed only{at}: Coulomb and viscous are not separable (friction level there "
                   f"{level:.4f} A); add passes at other speeds")
            jr.set(ck, None, reason=why)
            jr.set(vk, None, reason=why)
    for key in (COULOMB_POS_A, COULOMB_NEG_A):
        if key in jr.reasons and "one speed only" in jr.reasons[key]:
            continue
        est = fit.estimate(key)
        if est is None:
            jr.set(key, None, reason=reason_prefix + fit.dropped.get(key, "not in the model"))
            continue
        val, sd = est
        if sd > RESOLUTION_A and sd > DETERMINED_REL * abs(val):
            jr.set(key, None, reason=f"{reason_prefix}not determined: {val:.4f} ± {sd:.4f} A")
        else:
            jr.set(key, val, sd)
    vis: dict[str, tuple[float, float]] = {}
    for key in (VISCOUS_POS_A_S_PER_RAD, VISCOUS_NEG_A_S_PER_RAD):
        if key in jr.reasons and "one speed only" in jr.reasons[key]:
            continue
        est = fit.estimate(key)
        if est is None:
            jr.set(key, None, reason=reason_prefix + fit.dropped.get(key, "not in the model"))
            continue
        val, sd = est
        if sd * vmax > RESOLUTION_A and sd > DETERMINED_REL * abs(val):
            jr.set(key, None, reason=f"{reason_prefix}not determined: {val:.4f} ± {sd:.4f} A·s/rad over speeds up to "
                                     f"{vmax:.3f} rad/s")
        else:
            jr.set(key, val, sd)
            vis[key] = (val, sd)
    if len(vis) == 2:
        (a, sa), (b, sb) = vis.values()
        wa, wb = 1 / max(sa, 1e-12) ** 2, 1 / max(sb, 1e-12) ** 2
        jr.set(VISCOUS_A_S_PER_RAD, (a * wa + b * wb) / (wa + wb), math.sqrt(1 / (wa + wb)))
    elif len(vis) == 1:
        (a, sa), = vis.values()
        jr.set(VISCOUS_A_S_PER_RAD, a, sa)
    else:
        jr.set(VISCOUS_A_S_PER_RAD, None, reason=jr.reasons.get(VISCOUS_POS_A_S_PER_RAD, "not determined"))


def _physical(jr: JointResult) -> None:
    """Signs the params schema requires; an estimate of the wrong sign is zero when within 2σ, else null."""
    rules = {COULOMB_POS_A: 1, COULOMB_NEG_A: -1, STATIC_POS_A: 1, STATIC_NEG_A: -1,
             VISCOUS_A_S_PER_RAD: 1, VISCOUS_POS_A_S_PER_RAD: 1, VISCOUS_NEG_A_S_PER_RAD: 1}
    for key, sign in rules.items():
        v = jr.friction.get(key)
        if v is None or v * sign >= 0:
            continue
        s = jr.std.get(key, 0.0)
        if abs(v) <= 2 * s:
            jr.friction[key] = 0.0
        else:
            jr.set(key, None, reason=f"estimate {v:.4g} ± {s:.2g} has the wrong sign for this term (model mismatch)")
            jr.std.pop(key, None)
    for key in (STRIBECK_VELOCITY_RAD_S, STRIBECK_EXPONENT):
        v = jr.friction.get(key)
        if v is not None and not v > 0:
            jr.set(key, None, reason=f"estimate {v:.4g} is not positive")
    d = jr.friction.get(STRIBECK_EXPONENT)
    if d is not None and not 0.3 <= d <= 4.0:  # the law's schema: δ in (0, 4]
        jr.set(STRIBECK_EXPONENT, None, reason=f"estimate {d:.3g} outside the plausible 0.3…4 (hump not determined)")
        jr.std.pop(STRIBECK_EXPONENT, None)
    kt = jr.torque_constant_Nm_per_A
    if kt is not None and not kt > 0:
        jr.set("torque_constant_Nm_per_A", None, reason=f"estimate {kt:.4g} N·m/A is not positive (model mismatch)")
        jr.std.pop("torque_constant_Nm_per_A", None)


def _kt_from_slope(jr: JointResult, a: float | None, sa: float | None, reason_null: str) -> None:
    """K_t = 1/a from a current-per-torque slope a (delta-method std); null unless determined to 5 %."""
    if a is None:
        jr.set("torque_constant_Nm_per_A", None, reason=reason_null)
        return
    if sa is not None and abs(a) > 0 and sa / abs(a) > KT_MAX_REL_STD:
        jr.set("torque_constant_Nm_per_A", None, reason=f"not determined: slope {a:.3g} ± {sa:.2g} A/(N·m) "
                                                        "(too little gravity-torque change along the motion)")
        return
    if not a > 0:
        jr.set("torque_constant_Nm_per_A", None, reason=f"current falls as gravity torque rises (slope {a:.4g} A/N·m): "
                                                        "model mismatch")
        return
    kt, skt = 1.0 / a, (sa or 0.0) / a**2
    if skt / kt > KT_MAX_REL_STD:
        jr.set("torque_constant_Nm_per_A", None, reason=f"not determined: {kt:.4g} ± {skt:.2g} N·m/A "
                                                        f"(> {KT_MAX_REL_STD:.0%}); too little gravity-torque change")
        return
    jr.set("torque_constant_Nm_per_A", kt, skt)


PREFER_DROP = ("dstatic_pos_A", "dstatic_neg_A", VISCOUS_POS_A_S_PER_RAD, VISCOUS_NEG_A_S_PER_RAD)

NO_GRAVITY = ("no gravity torque change on this joint along the motion (range {rng:.3f} N·m): K_t is not "
              "identifiable from current (only the friction lines are, seed 002 §3.2)")


# ------------------------------------------------------------------------------------------ seed 000


def fit_lowspeed(ctx: Context) -> FitResult:
    """Seed 000 eq. 20: n·K_m·i = M_g·f(θ) + τ_f per direction, at low speed, by least squares.

    Per joint: rows where its mean velocity (H at ``lowspeed_cutoff_Hz``) is low (≤ ``lowspeed_max``) with a
    steady sign; i = G(q)/K_t + b_d (d = direction). The seed fits each direction on its own (its eqs. 22/23, two
    slopes, then takes K ≈ their mean, eq. 24): both per-direction lines are in the diagnostics; the result uses
    one slope with two intercepts (the better-posed form of the same model). Regressing i on G (not G on i as
    printed) keeps the Hall noise in the dependent variable, so the slope is not attenuated.
    """
    p, o = ctx.p, ctx.opts
    fc = o.lowspeed_cutoff_Hz
    rows = p.rows(fc)
    guard = int(round(2.0 / fc * p.fs))
    iH = p.regfilter(p.i, fc)
    gH = p.regfilter(ctx.grav, fc)
    vbar = p.regfilter(p.dq, fc)
    out = []
    for j, name in enumerate(ctx.names):
        jr = JointResult(name)
        out.append(jr)
        why = ctx.never_moves(j)
        if why:
            jr.null_all(why)
            continue
        low = (np.abs(vbar[:, j]) > 0.2 * o.v_min) & (np.abs(vbar[:, j]) <= o.lowspeed_max)
        sgn = np.sign(vbar[:, j])
        # a steady direction for ±guard: erosion of each direction's mask
        posm = sliding(np.where(low & (sgn > 0), 1.0, 0.0)[:, None], 0.5, guard)[:, 0]
        negm = sliding(np.where(low & (sgn < 0), 1.0, 0.0)[:, None], 0.5, guard)[:, 0]
        sel = rows[(posm | negm)[rows]]
        if sel.size < MIN_ROWS:
            jr.null_all(f"no low-speed motion of {name} (mean speed 0.2·v_min..{o.lowspeed_max} rad/s held for "
                        f"{2 / fc:.0f} s) in this log: seed 000's method needs ≤ 2°/s reciprocation")
            continue
        # the friction's direction everywhere (not only on the selected rows), then H like the current
        d = np.where(np.abs(vbar[:, j]) > 0.2 * o.v_min, sgn, 0.0)
        F = p.regfilter(np.column_stack([(d > 0).astype(float), (d < 0).astype(float)]), fc)
        A = np.column_stack([gH[sel, j], F[sel]])
        gr = float(np.ptp(ctx.grav[sel, j]))
        explain = {"gravity": NO_GRAVITY.format(rng=gr)}
        if gr < 1e-6:
            A[:, 0] = 0.0
        fit = linear_fit(A, iH[sel, j], ["gravity", COULOMB_POS_A, COULOMB_NEG_A], explain=explain)
        _kt_from_slope(jr, fit.value("gravity"), fit.std("gravity"), fit.dropped.get("gravity", "not determined"))
        speed = float(np.mean(np.abs(vbar[sel, j])))
        for key in (COULOMB_POS_A, COULOMB_NEG_A):
            v, s = fit.value(key), fit.std(key)
            if v is None:
                jr.set(key, None, reason=fit.dropped.get(key, "no motion in this direction"))
            else:
                jr.set(key, v, s)
        model_note = ("seed 000's model has one constant friction level per direction (the level at the test speed, "
                      f"mean {speed:.4f} rad/s, ≈ the static level); this term is not part of it")
        for key in (VISCOUS_A_S_PER_RAD, VISCOUS_POS_A_S_PER_RAD, VISCOUS_NEG_A_S_PER_RAD, STATIC_POS_A,
                    STATIC_NEG_A, STRIBECK_VELOCITY_RAD_S, STRIBECK_EXPONENT):
            jr.set(key, None, reason=model_note)
        lines = {}
        for dname, m in (("pos", posm[sel]), ("neg", negm[sel])):
            if m.sum() >= 8 and gr >= 0.5:
                f1 = linear_fit(np.column_stack([gH[sel][m, j], np.ones(m.sum())]), iH[sel][m, j], ["a", "b"])
                a, b = f1.value("a"), f1.value("b")
                if a and b is not None and a > 0:
                    lines[dname] = {"K_Nm_per_A": 1 / a, "friction_Nm": b / a, "friction_A": b,
                                    "seed_form": f"M_g·f(θ) = {1 / a:.4f}·i {-b / a:+.4f}"}
        jr.diagnostics = {"rows": int(sel.size), "condition_number": fit.cond, "residual_A": fit.sigma,
                          "gravity_range_Nm": gr, "mean_speed_rad_s": speed, "per_direction_lines": lines}
        _physical(jr)
    return FitResult("lowspeed", out, ctx.log.path, str(ctx.robot.urdf_path), list(ctx.warnings))


# ------------------------------------------------------------------------------------------ seed 002


def _stribeck_residual(x: np.ndarray, ctx: Context, j: int, sel: np.ndarray, exponent: float | None) -> np.ndarray:
    """The quasi-static fit's residual at (ln v_s, ln δ) = ``x`` (δ fixed where ``exponent`` is given)."""
    f, _ = _quasistatic_fit(ctx, j, sel, (math.exp(x[0]), exponent or math.exp(x[1])))
    return f.residual


def _quasistatic_fit(ctx: Context, j: int, sel: np.ndarray, stribeck: tuple[float, float] | None,
                     use_tau: bool = True) -> tuple[LinearFit, float]:
    """i = τ(q)/K_t + friction(q̇) on quasi-static rows (H on both sides); returns the fit and the τ range."""
    p = ctx.p
    v = p.dq[:, j]
    F, fnames = friction_columns(v, vs=None if stribeck is None else stribeck[0],
                                 delta=2.0 if stribeck is None else stribeck[1])
    FH = p.regfilter(F)
    tau = ctx.tauH[:, j] if use_tau else ctx.gravH[:, j]
    rng = float(np.ptp(tau[sel]))
    # the joint's own q̈ with a free coefficient: the rotor inertia J_a/K_t (not in a URDF) of the residual
    # accelerations that quasi-static rows still have; dropped first when the data cannot separate it
    A = np.column_stack([tau[sel], FH[sel], ctx.ddqH[sel, j]])
    explain = {"gravity": NO_GRAVITY.format(rng=rng), "armature": "too little acceleration in these rows"}
    if rng < 1e-6:
        A[:, 0] = 0.0
    return linear_fit(A, ctx.iH[sel, j], ["gravity"] + fnames + ["armature"], explain=explain,
                      prefer_drop=("armature",) + PREFER_DROP), rng


def fit_synchronous(ctx: Context) -> FitResult:
    """Seed 002 §3.4: K_t and forward/reverse friction from the linear fit of friction-free current vs gravity torque.

    The seed removes the friction step at each reversal (step 1), fits the friction-free current against the
    model's gravity torque (step 3: slope = 1/K_t) and reads the forward/reverse friction from the intercepts at the
    reversals (step 4); joints without gravity load get viscous lines I = F_v·v + F_c·sgn v (its eq. 3). Here the
    steps are one least-squares problem on the quasi-static rows — i = τ(q, q̇, q̈)/K_t + F_c,d + F_v,d·q̇ — whose
    solution is the fixed point of the seed's alternation; τ is the URDF's rigid-body torque (gravity at these
    speeds). The seed's r² of the friction-free current against the gravity torque is in the diagnostics.
    """
    out = []
    for j, name in enumerate(ctx.names):
        jr = JointResult(name)
        out.append(jr)
        why = ctx.never_moves(j)
        if why:
            jr.null_all(why)
            continue
        sel = ctx.rows[ctx.steady(j)[ctx.rows]]
        if sel.size < MIN_ROWS:
            jr.null_all(f"no steady motion of {name} (|q̇| > {ctx.opts.v_min} rad/s at |q̈| < {ctx.opts.a_max} rad/s² "
                        f"for {1.5 / ctx.opts.cutoff_Hz:.1f} s) in this log")
            continue
        fit, rng = _quasistatic_fit(ctx, j, sel, None)
        _kt_from_slope(jr, fit.value("gravity"), fit.std("gravity"), fit.dropped.get("gravity", "not determined"))
        vmax = float(np.abs(ctx.p.dq[sel, j]).max())
        _set_friction_from_fit(jr, fit, vmax, v=ctx.p.dq[sel, j])
        for key in (STATIC_POS_A, STATIC_NEG_A, STRIBECK_VELOCITY_RAD_S, STRIBECK_EXPONENT):
            jr.set(key, None, reason="seed 002's friction model is Coulomb + viscous per direction (no Stribeck "
                                     "term); use the symmetric or auto method for it")
        diag: dict[str, Any] = {"rows": int(sel.size), "condition_number": fit.cond, "residual_A": fit.sigma,
                                "gravity_range_Nm": rng,
                                "speed_range_rad_s": [float(np.abs(ctx.p.dq[sel, j]).min()), vmax]}
        a = fit.value("gravity")
        if a is not None:
            fric = ctx.iH[sel, j] - fit.residual - a * ctx.tauH[sel, j]
            i_ff = ctx.iH[sel, j] - fric
            c = np.corrcoef(i_ff, ctx.tauH[sel, j])[0, 1]
            diag["r2_friction_free_vs_gravity"] = float(c * c)
        fc = {k: jr.friction[k] for k in (COULOMB_POS_A, COULOMB_NEG_A, VISCOUS_POS_A_S_PER_RAD,
                                           VISCOUS_NEG_A_S_PER_RAD)}
        if fc[COULOMB_POS_A] is not None and fc[VISCOUS_POS_A_S_PER_RAD] is not None:
            diag["line_pos"] = f"I = {fc[VISCOUS_POS_A_S_PER_RAD]:.4f}·v + {fc[COULOMB_POS_A]:.4f} A (v > 0, rad/s)"
        if fc[COULOMB_NEG_A] is not None and fc[VISCOUS_NEG_A_S_PER_RAD] is not None:
            diag["line_neg"] = f"I = {fc[VISCOUS_NEG_A_S_PER_RAD]:.4f}·v {fc[COULOMB_NEG_A]:+.4f} A (v < 0, rad/s)"
        jr.diagnostics = diag
        _physical(jr)
    return FitResult("synchronous", out, ctx.log.path, str(ctx.robot.urdf_path), list(ctx.warnings))


# ------------------------------------------------------------------------------------------ seed 001


def find_pairs(ctx: Context) -> tuple[np.ndarray, np.ndarray]:
    """Sample pairs (a, b) at the same position crossed in opposite directions at the same speed, both quasi-static.

    Seed 001 eq. 7: q(t₁) = q(t₂), q̇(t₁) = −q̇(t₂), q̈ = 0. Candidates are rows where some joint slides steadily and no
    joint accelerates; they are grouped by direction signature (sign of each moving joint's velocity) and each row
    is matched to its nearest neighbour in position among the rows of the opposite signature.
    """
    p, o = ctx.p, ctx.opts
    steady = np.column_stack([ctx.steady(j) for j in range(ctx.n)])
    resting = np.abs(p.dq) < o.v_rest
    calm = np.all(np.abs(ctx.ddqH) < o.a_max, axis=1)
    cand = calm & steady.any(axis=1) & np.all(steady | resting, axis=1)
    idx = np.nonzero(cand)[0]
    if idx.size < 2:
        return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
    sig = np.where(steady[idx], np.sign(p.dq[idx]), 0).astype(np.int8)
    keys: dict[bytes, list[int]] = {}
    for k, s in enumerate(map(bytes, sig)):
        keys.setdefault(s, []).append(k)
    anchors = set(ctx.rows.tolist())
    A, B = [], []
    for s, members in keys.items():
        opp = bytes((-np.frombuffer(s, dtype=np.int8)).astype(np.int8))
        if opp not in keys or s > opp:
            continue  # each unordered pair of signatures once
        ia = idx[np.array(members)]
        ib = idx[np.array(keys[opp])]
        ia_anchor = np.array([a for a in ia if a in anchors], dtype=int)
        if ia_anchor.size == 0:
            continue
        tree = cKDTree(p.q[ib])
        dist, nb = tree.query(p.q[ia_anchor], k=1, distance_upper_bound=o.pair_tol_rad)
        ok = np.isfinite(dist)
        a_ok, b_ok = ia_anchor[ok], ib[nb[ok]]
        va, vb = p.dq[a_ok], p.dq[b_ok]
        speed_ok = np.linalg.norm(va + vb, axis=1) <= o.pair_speed_tol * np.linalg.norm(va, axis=1)
        A.append(a_ok[speed_ok])
        B.append(b_ok[speed_ok])
    if not A:
        return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
    return np.concatenate(A), np.concatenate(B)


def _row_gravity_columns(ctx: Context, j: int) -> np.ndarray:
    """Joint j's minimal gravity regressor columns (current units come from the fit), at the work rate."""
    rm = ctx.rm
    base = rm.row_gravity[j]
    out = np.empty((ctx.p.q.shape[0], base.r))
    for s in range(0, ctx.p.q.shape[0], 20000):
        Y = rm.torque_regressor(ctx.p.q[s:s + 20000])
        out[s:s + 20000] = Y[:, j, base.cols]
    return out


def stribeck_lm(v: np.ndarray, f: np.ndarray, delta: float | None, v_s0: float = 0.02) -> dict[str, Any]:
    """Seed 001 eq. 29 by Levenberg–Marquardt, per direction: f = d·[F_c,d + (F_s,d − F_c,d)e^{−(|v|/v_s)^δ}] + F_v,d·v.

    Parameters [F_c+, F_c−, ΔS+, ΔS−, F_v+, F_v−, ln v_s (, ln δ)] (seed: [f_v, f_c, f_s − f_c, 1/v_s], symmetric,
    δ fixed). Returns values, standard deviations (σ̂²(JᵀJ)⁻¹), and which terms the data determines.
    """
    pos = v > 0
    x0 = [float(np.median(f[pos])) if pos.any() else 0.1, float(np.median(f[~pos])) if (~pos).any() else -0.1,
          0.0, 0.0, 0.0, 0.0, math.log(v_s0)] + ([] if delta is not None else [math.log(1.5)])

    def model(x: np.ndarray) -> np.ndarray:
        fcp, fcn, dsp, dsn, fvp, fvn, lvs = x[:7]
        dl = delta if delta is not None else math.exp(x[7])
        e = np.exp(-(np.abs(v) / math.exp(lvs)) ** dl)
        return np.where(pos, fcp + dsp * e + fvp * v, fcn + dsn * e + fvn * v)

    res = least_squares(lambda x: model(x) - f, np.array(x0), method="lm", x_scale="jac", max_nfev=4000)
    J = res.jac
    dof = max(1, f.size - J.shape[1])
    s2 = float(res.fun @ res.fun / dof)
    try:
        cov = s2 * np.linalg.inv(J.T @ J)
        std = np.sqrt(np.maximum(np.diag(cov), 0))
    except np.linalg.LinAlgError:
        std = np.full(J.shape[1], np.inf)
    x = res.x
    out = {COULOMB_POS_A: (x[0], std[0]), COULOMB_NEG_A: (x[1], std[1]),
           "dstatic_pos_A": (x[2], std[2]), "dstatic_neg_A": (x[3], std[3]),
           VISCOUS_POS_A_S_PER_RAD: (x[4], std[4]), VISCOUS_NEG_A_S_PER_RAD: (x[5], std[5]),
           STRIBECK_VELOCITY_RAD_S: (math.exp(x[6]), math.exp(x[6]) * std[6]),
           STRIBECK_EXPONENT: (delta, 0.0) if delta is not None else (math.exp(x[7]), math.exp(x[7]) * std[7]),
           "residual_A": math.sqrt(s2), "samples": int(f.size), "success": bool(res.success)}
    return out


def friction_curve(v: np.ndarray, f: np.ndarray, delta: float | None, slow_rad_s: float = 0.1) -> dict[str, Any]:
    """Friction samples (v, f) → the linear Coulomb + viscous fit, and the Stribeck LM fit when slow sliding exists.

    The LM result is kept only when it determines the hump (finite covariance, v_s to better than 50 %);
    otherwise ``why`` says what the data lacks.
    """
    F, names = friction_columns(v)
    out: dict[str, Any] = {"linear": linear_fit(F, f, names, prefer_drop=PREFER_DROP)}
    slow = np.abs(v) < slow_rad_s
    if slow.sum() < MIN_ROWS or slow.mean() < 0.02:
        out["why"] = (f"no steady sliding below {slow_rad_s:g} rad/s in the friction samples (slowest "
                      f"{float(np.abs(v).min()):.3f} rad/s): the Stribeck hump is not observable")
        return out
    s = stribeck_lm(v, f, delta)
    vs, svs = s[STRIBECK_VELOCITY_RAD_S]
    if not (np.isfinite(svs) and svs < 0.5 * vs and s["success"]):
        out["why"] = f"the Stribeck hump is not determined by the friction samples (v_s ≈ {vs:.3g} ± {svs:.2g} rad/s)"
        return out
    out["stribeck"] = s
    return out


def _apply_stribeck(jr: JointResult, sfit: dict[str, Any], v: np.ndarray) -> None:
    """Set Coulomb/viscous/static/Stribeck from an LM fit, nulling what the data does not determine."""
    vmin = float(np.abs(v).min()) if v.size else float("inf")
    vmax = float(np.abs(v).max()) if v.size else 0.0
    vs, svs = sfit[STRIBECK_VELOCITY_RAD_S]
    hump_seen = vmin < 2.0 * vs and np.isfinite(svs) and svs < 0.5 * vs
    for key in (COULOMB_POS_A, COULOMB_NEG_A):
        val, s = sfit[key]
        jr.set(key, val if s <= RESOLUTION_A else None, s,
               reason=None if s <= RESOLUTION_A else f"not determined: {val:.4f} ± {s:.4f} A")
    vis = []
    for key in (VISCOUS_POS_A_S_PER_RAD, VISCOUS_NEG_A_S_PER_RAD):
        val, s = sfit[key]
        ok = s * vmax <= RESOLUTION_A
        jr.set(key, val if ok else None, s, reason=None if ok else f"not determined: {val:.4f} ± {s:.4f} A·s/rad")
        if ok:
            vis.append((val, s))
    if vis:
        w = np.array([1 / max(s, 1e-12) ** 2 for _, s in vis])
        jr.set(VISCOUS_A_S_PER_RAD, float(np.sum(w * [a for a, _ in vis]) / w.sum()), float(math.sqrt(1 / w.sum())))
    else:
        jr.set(VISCOUS_A_S_PER_RAD, None, reason="not determined by the friction samples")
    why = (f"the friction samples reach down to {vmin:.4f} rad/s only; the Stribeck hump (v_s ≈ {vs:.3g} ± {svs:.2g} "
           "rad/s) is not seen by steady sliding")
    for d in ("pos", "neg"):
        dval, ds = sfit[f"dstatic_{d}_A"]
        c = jr.friction[f"coulomb_{d}_A"]
        if hump_seen and c is not None and ds <= RESOLUTION_A:
            jr.set(f"static_{d}_A", c + dval, math.hypot(ds, jr.std.get(f"coulomb_{d}_A", 0.0)))
        else:
            jr.set(f"static_{d}_A", None, reason=why)
    if hump_seen:
        jr.set(STRIBECK_VELOCITY_RAD_S, vs, svs)
        dl, sdl = sfit[STRIBECK_EXPONENT]
        jr.set(STRIBECK_EXPONENT, dl, sdl)
    else:
        jr.set(STRIBECK_VELOCITY_RAD_S, None, reason=why)
        jr.set(STRIBECK_EXPONENT, None, reason=why)


def breakaway_levels(ctx: Context, j: int, i_free: np.ndarray, min_stick_s: float = 0.08,
                     hold_rad: float = 3e-5) -> dict[str, Any]:
    """Static (breakaway) friction from stick → slip events: the friction-free current just before each slip.

    A joint held by stiction while its command ramps (low-speed tracking, stick–slip) breaks away when the motor
    current beyond gravity reaches the static level. Events: the (anti-aliased, not otherwise filtered) position
    stays within ±``hold_rad`` for ≥ ``min_stick_s``, then leaves it; the level is the mean over the last 20 ms.
    Only slow ramps count — a command step (e.g. a feed-forward switching on) breaks the joint away above its level.
    """
    p = ctx.p
    q = p.q_raw[:, j] if p.q_raw is not None else p.q[:, j]
    n20 = max(2, int(0.02 * p.fs))
    nmin = max(3, int(min_stick_s * p.fs))
    levels: dict[str, list[float]] = {"pos": [], "neg": []}
    dq = np.abs(np.diff(q))
    still = np.concatenate([[False], dq < hold_rad / 4])
    ends = np.nonzero(np.diff(still.astype(np.int8)) == -1)[0] + 1  # first moving sample after a still run
    for s in ends:
        run = 0
        while s - 1 - run >= 0 and still[s - 1 - run]:
            run += 1
        if run < nmin or s + 5 >= q.shape[0] or s - 3 * n20 < 0:
            continue
        ref = q[s - 1]
        seg = q[s - run:s]
        if np.ptp(seg) > hold_rad:
            continue
        after = q[s:s + int(0.05 * p.fs)] - ref
        k = np.nonzero(np.abs(after) > 2 * hold_rad)[0]
        if k.size == 0:
            continue
        d = "pos" if after[k[0]] > 0 else "neg"
        lvl = float(np.mean(i_free[s - n20:s]))
        before = float(np.mean(i_free[s - 3 * n20:s - 2 * n20]))
        if abs(lvl - before) > max(0.05 * abs(lvl), 0.02):
            continue  # a step, not a ramp
        if (d == "pos") == (lvl > 0):
            levels[d].append(lvl)
    out: dict[str, Any] = {}
    for d, xs in levels.items():
        if len(xs) >= 3:
            a = np.array(xs)
            out[d] = (float(np.median(a)), float(1.2533 * a.std(ddof=1) / math.sqrt(a.size)), int(a.size))
    return out


def fit_symmetric(ctx: Context) -> FitResult:
    """Seed 001: gravity = half-sum, friction = half-difference of opposite passes through the same positions.

    Gravity (eq. 8, 9, 17): per joint, the half-sums of the current at paired samples are fitted with the joint's
    row of the minimal gravity regressor (computed numerically from Pinocchio's joint-torque regressor at
    q̇ = q̈ = 0, QR with pivoting) — current-based, K_t not needed — plus a constant: the direction asymmetry
    (F₊ + F₋)/2 that the seed's odd-friction assumption puts into the half-sum. Friction (eq. 21): the current
    minus the identified gravity current at the paired samples, fitted per direction with the Stribeck model by
    Levenberg–Marquardt (eq. 29). K_t is then the ratio of the URDF's gravity torque to the identified gravity
    current (what the daemon's G(q)/K_t needs); static levels come from breakaway events when the Stribeck hump
    is not seen in steady sliding.
    """
    p, o = ctx.p, ctx.opts
    a_idx, b_idx = find_pairs(ctx)
    out = []
    notes: dict[str, Any] = {"pairs": int(a_idx.size), "minimal_gravity_parameters": {}}
    rb = ctx.rm.base_gravity
    notes["global_minimal_gravity_set"] = {"count": rb.r, "names": rb.names,
                                           "urdf_values": (rb.E @ ctx.rm.pi_urdf).tolist()}
    for j, name in enumerate(ctx.names):
        jr = JointResult(name)
        out.append(jr)
        why = ctx.never_moves(j)
        if why:
            jr.null_all(why)
            continue
        sl = ctx.steady(j)
        m = sl[a_idx] & sl[b_idx]
        a, b = a_idx[m], b_idx[m]
        if a.size < MIN_ROWS:
            jr.null_all(f"too few position pairs of {name} crossed in both directions at the same steady speed "
                        f"({a.size}; seed 001's symmetric extraction needs forward/backward passes)")
            continue
        Yg = _row_gravity_columns(ctx, j)
        YgH = p.regfilter(Yg) if Yg.shape[1] else Yg
        y = 0.5 * (ctx.iH[a, j] + ctx.iH[b, j])
        cols = 0.5 * (YgH[a] + YgH[b])
        base = ctx.rm.row_gravity[j]
        A = np.column_stack([cols, np.ones(a.size)])
        names = [f"beta{k}" for k in range(base.r)] + ["asymmetry_A"]
        fit = linear_fit(A, y, names, priority=names[:-1] + ["asymmetry_A"],
                         explain={"asymmetry_A": "the direction asymmetry (F₊ + F₋)/2 is not separable from the "
                                                 "gravity terms along these passes (seed 001's odd-friction "
                                                 "assumption applies)"})
        beta = np.array([fit.value(f"beta{k}") or 0.0 for k in range(base.r)])
        live = [k for k in range(base.r) if fit.value(f"beta{k}") is not None]
        ghat = Yg @ beta  # identified gravity current [A], unfiltered
        # K_t from the URDF reference: a = argmin Σ(Ĝ_A − a·G_urdf)², linear in β -> std from cov(β)
        gu = ctx.grav[a, j]
        rng = float(np.ptp(gu))
        if rng > 1e-9 and live:  # determined or not: the slope's relative std decides (KT_MAX_REL_STD)
            wvec = (gu @ Yg[a][:, live]) / (gu @ gu)
            idx = [fit.names.index(f"beta{k}") for k in live]
            slope = float(wvec @ beta[live])
            sslope = float(np.sqrt(wvec @ fit.cov[np.ix_(idx, idx)] @ wvec))
            _kt_from_slope(jr, slope, sslope, "")
            jr.diagnostics["kt_source"] = ("URDF gravity torque / identified gravity current (reference: the URDF's "
                                           "masses)")
        else:
            jr.set("torque_constant_Nm_per_A", None, reason=NO_GRAVITY.format(rng=rng)
                   if rng <= 1e-9 else "no identifiable gravity parameters in this joint's row")
        notes["minimal_gravity_parameters"][name] = {
            "names": [base.names[k] for k in range(base.r)],
            "current_A": [fit.value(f"beta{k}") for k in range(base.r)],
            "std_A": [fit.std(f"beta{k}") for k in range(base.r)],
            "urdf_Nm": (base.E @ ctx.rm.pi_urdf).tolist(),
            "dropped": fit.dropped}
        # friction = half-difference (eq. 21): gravity cancels exactly, whatever the gravity fit; it is the
        # symmetric part (F₊(|v|) − F₋(|v|))/2 at speed |v|; the asymmetry constant c of the half-sum fit gives
        # the direction levels F_±,c = ±F_c,sym + c (viscous and Stribeck stay symmetric: one slope, one hump)
        c = fit.value("asymmetry_A")
        cs = fit.std("asymmetry_A") or 0.0
        hd = 0.5 * (ctx.iH[a, j] - ctx.iH[b, j])
        sp = np.abs(p.dq[a, j])
        vv = np.concatenate([sp, -sp])  # mirrored: the per-direction model fitted to symmetric data is symmetric
        ff = np.concatenate([hd * np.sign(p.dq[a, j]), -hd * np.sign(p.dq[a, j])])
        curve = friction_curve(vv, ff, o.stribeck_exponent)
        if "stribeck" in curve:
            sfit = curve["stribeck"]
            _apply_stribeck(jr, sfit, vv)
            jr.diagnostics["stribeck_fit_residual_A"] = sfit["residual_A"]
        else:
            lin = curve["linear"]
            _set_friction_from_fit(jr, lin, float(sp.max()), v=vv)
            why = curve["why"]
            for key in (STATIC_POS_A, STATIC_NEG_A, STRIBECK_VELOCITY_RAD_S, STRIBECK_EXPONENT):
                jr.set(key, None, reason=why)
            jr.diagnostics["friction_fit_residual_A"] = lin.sigma
        # the mirrored samples count twice: the stds of the symmetric curve are √2 too small
        for key in list(jr.std):
            if key != "torque_constant_Nm_per_A":
                jr.std[key] *= math.sqrt(2.0)
        shift = c if c is not None else 0.0
        for key in (COULOMB_POS_A, COULOMB_NEG_A, STATIC_POS_A, STATIC_NEG_A):
            level = jr.friction[key]
            if level is not None:
                jr.friction[key] = level + shift
                jr.std[key] = math.hypot(jr.std.get(key, 0.0), cs)
        why_v = ("symmetric extraction (half-differences) gives the mean slope of both directions only; see "
                 + VISCOUS_A_S_PER_RAD)
        for key in (VISCOUS_POS_A_S_PER_RAD, VISCOUS_NEG_A_S_PER_RAD):
            jr.friction[key] = None
            jr.std.pop(key, None)
            jr.reasons[key] = why_v
        if c is None:
            jr.diagnostics["asymmetry"] = ("not determined: levels reported symmetric (seed 001's odd-friction "
                                           "assumption)")
        if jr.friction[STATIC_POS_A] is None or jr.friction[STATIC_NEG_A] is None:
            brk = breakaway_levels(ctx, j, p.i[:, j] - ghat)
            for d, (lvl, s, cnt) in brk.items():
                if jr.friction[f"static_{d}_A"] is None:
                    jr.set(f"static_{d}_A", lvl, s)
                    jr.diagnostics[f"static_{d}_source"] = f"breakaway: {cnt} stick→slip events"
        jr.diagnostics.update({"pairs": int(a.size), "gravity_condition_number": fit.cond,
                               "gravity_residual_A": fit.sigma, "asymmetry_A": c,
                               "asymmetry_std_A": fit.std("asymmetry_A"),
                               "half_difference_mean_abs_A": float(np.mean(np.abs(hd))),
                               "friction_speed_range_rad_s": [float(sp.min()), float(sp.max())]})
        _physical(jr)
    return FitResult("symmetric", out, ctx.log.path, str(ctx.robot.urdf_path), list(ctx.warnings), notes)


# ------------------------------------------------------------------------------------------ full dynamics


def _row_full_columns(ctx: Context, j: int) -> tuple[np.ndarray, np.ndarray]:
    """Joint j's per-row base rigid-body columns (and their gravity part) at the work rate."""
    rm = ctx.rm
    base = rm.row_full[j]
    T = ctx.p.q.shape[0]
    full = np.empty((T, base.r))
    grav = np.empty((T, base.r))
    for s in range(0, T, 10000):
        sl = slice(s, s + 10000)
        Y = rm.torque_regressor(ctx.p.q[sl], ctx.p.dq[sl], ctx.p.ddq[sl])
        full[sl] = Y[:, j, base.cols]
        Yg = rm.torque_regressor(ctx.p.q[sl])
        grav[sl] = Yg[:, j, base.cols]
    return full, grav


def _fit_full_joint(ctx: Context, j: int, name: str, notes: dict[str, Any], stribeck_grid: bool) -> JointResult:
    """One joint of ``fit_full`` (its docstring); ``notes`` collects the base parameters and rotor inertias."""
    p, o = ctx.p, ctx.opts
    jr = JointResult(name)
    why = ctx.never_moves(j)
    if why:
        jr.null_all(why)
        return jr
    # rows where the joint slides throughout the regression filter's support (stiction is not a function of q̇);
    # smooth reversals without sticking stay in (the sign columns are filtered like the current)
    sel = ctx.rows[ctx.sliding(j, guard_s=0.6 / o.cutoff_Hz)[ctx.rows]]
    if sel.size < MIN_ROWS:
        jr.null_all(f"{name} hardly slides in this log ({sel.size} rows)")
        return jr
    Yf, Yg = _row_full_columns(ctx, j)
    base = ctx.rm.row_full[j]
    beta_urdf = base.E @ ctx.rm.pi_urdf
    YfH = p.regfilter(Yf)
    tauH = YfH @ beta_urdf
    v = p.dq[:, j]
    acc_level = float(np.percentile(np.abs(ctx.ddqH[sel, j]), 90))
    names_rb = [f"dbeta{k}" for k in range(base.r)]

    # stage 1: the URDF's torque scaled, friction, and the joint's own q̈ (rotor inertia): the scale c₀ ≈ 1/K_t
    F0, f0names = friction_columns(v)
    F0H = p.regfilter(F0)
    arm0 = p.regfilter(p.ddq[:, j:j + 1])
    s1 = linear_fit(np.column_stack([tauH[sel], arm0[sel], F0H[sel]]), ctx.iH[sel, j], ["urdf", "arm"] + f0names,
                    prefer_drop=PREFER_DROP)
    given = None if o.torque_constants is None else o.torque_constants[j]
    # K_t given: the URDF's current is τ_URDF/K_t (the scale is known, not fitted) and the gravity parameters are
    # no longer the K_t reference: they take the CAD prior of every inertial parameter (the data moves them as far
    # as it determines them)
    c0 = 1.0 / float(given) if given else (abs(s1.value("urdf") or 0.0) or 0.1)
    # prior on the corrections: 30 % of the URDF's value (in current, via c₀), at least what moves the current
    # by ~20 mA over this data — CAD values are that uncertain; the data moves what it determines
    colmax = np.maximum(np.abs(YfH[sel]).max(axis=0), 1e-12)
    prior = {names_rb[k]: max(PRIOR_REL * c0 * abs(beta_urdf[k]), 0.02 / colmax[k]) for k in range(base.r)}
    gcol = np.abs(Yg[sel]).max(axis=0)
    for k, nm_ in enumerate(base.names):
        if ".armature" in nm_:  # rotor inertias are not in the URDF: up to ~1 kg·m² reflected
            prior[names_rb[k]] = max(prior[names_rb[k]], c0 * ARMATURE_PRIOR_KGM2)
        elif gcol[k] > 1e-9:  # gravity parameters: the K_t reference (1 %), or with K_t given CAD-uncertain
            # like every inertial parameter (PRIOR_REL, at least what moves the current by RESOLUTION_A)
            rel, floor = (PRIOR_REL, RESOLUTION_A) if given else (PRIOR_GRAVITY_REL, 0.002)
            prior[names_rb[k]] = max(rel * c0 * abs(beta_urdf[k]), floor / colmax[k])
    y_sel = ctx.iH[sel, j] - (c0 * tauH[sel] if given else 0.0)  # K_t given: the URDF's current is known

    # load-dependent friction (harmonic drives: the Coulomb level grows with the transmitted torque): a column
    # sign(q̇)·|G(q)| where the joint carries a changing gravity load; kept only when it lowers the residual
    g_abs = np.abs(ctx.grav[:, j])
    load_col = p.regfilter((np.sign(v) * g_abs)[:, None])[:, 0] if o.load_friction and np.ptp(g_abs[sel]) > 1.0 \
        else None

    def solve(stb: tuple[float, float] | None, load: bool = False) -> LinearFit:
        F, fnames = friction_columns(v, vs=None if stb is None else stb[0], delta=2.0 if stb is None else stb[1])
        FH = p.regfilter(F)
        extra = [load_col[sel]] if load and load_col is not None else []
        A = np.column_stack(([] if given else [tauH[sel]]) + [YfH[sel], FH[sel]] + extra)
        nm = ([] if given else ["urdf"]) + names_rb + fnames + (["load_A_per_Nm"] if extra else [])
        f0 = prior_fit(A, y_sel, nm, prior)
        hi = np.abs(ctx.ddqH[sel, j]) > max(acc_level * 0.5, 0.05)
        w = np.ones(sel.size)
        if hi.sum() > MIN_ROWS and (~hi).sum() > MIN_ROWS:  # WLS: each regime weighted by its residual variance
            w[hi] = 1 / max(float(np.std(f0.residual[hi])), 1e-9) ** 2
            w[~hi] = 1 / max(float(np.std(f0.residual[~hi])), 1e-9) ** 2
            w /= w.mean()
        return prior_fit(A, y_sel, nm, prior, w=w)

    fit = solve(None)
    best: tuple[float, tuple[float, float] | None, LinearFit] = (fit.sigma, None, fit)
    vmin_sel = float(np.abs(v[sel]).min())
    slow_share = float(np.mean(np.abs(v[sel]) < 0.1))
    if stribeck_grid and slow_share > 0.05:
        deltas = [o.stribeck_exponent] if o.stribeck_exponent else [1.0, 1.5, 2.0]
        for dl in deltas:
            for vs in (0.005, 0.008, 0.012, 0.018, 0.025, 0.035, 0.05):
                if vs < 0.5 * vmin_sel:
                    continue
                f2 = solve((vs, dl))
                hump = [f2.estimate(f"dstatic_{d}_A") for d in ("pos", "neg")]
                # a hump enters only if it is determined and lowers the residual clearly (5 %)
                if (hump[0] is not None and hump[1] is not None and hump[0][1] <= RESOLUTION_A
                        and hump[1][1] <= RESOLUTION_A and f2.sigma < best[0] * 0.95 and hump[0][0] > 0 > hump[1][0]):
                    best = (f2.sigma, (vs, dl), f2)
    fit, stb = best[2], best[1]
    if load_col is not None:  # with the load-dependent term: kept when positive and 2 % better
        f3 = solve(stb, load=True)
        k3 = f3.value("load_A_per_Nm")
        if k3 is not None and k3 > 0 and f3.sigma < 0.98 * fit.sigma:
            fit = f3
            jr.diagnostics["load_friction_A_per_Nm"] = k3
            jr.diagnostics["load_friction_std_A_per_Nm"] = f3.std("load_A_per_Nm")
    vmax = float(np.abs(v[sel]).max())
    _set_friction_from_fit(jr, fit, vmax, v=v[sel])
    if stb is not None:
        for d in ("pos", "neg"):
            c, hump_d = jr.friction[f"coulomb_{d}_A"], fit.estimate(f"dstatic_{d}_A")
            if c is not None and hump_d is not None:
                dv, ds = hump_d
                jr.set(f"static_{d}_A", c + dv, math.hypot(ds, jr.std.get(f"coulomb_{d}_A", 0)))
            else:
                jr.set(f"static_{d}_A", None, reason="Stribeck hump not determined")
        jr.set(STRIBECK_VELOCITY_RAD_S, stb[0], None)
        jr.set(STRIBECK_EXPONENT, stb[1], None)
        jr.diagnostics["stribeck"] = "variable projection over a v_s × δ grid (grid resolution, no std)"
    else:
        why_s = ("too little sliding below 0.1 rad/s to see a Stribeck hump" if slow_share <= 0.05 else
                 "a determined Stribeck hump does not lower the residual")
        for key in (STATIC_POS_A, STATIC_NEG_A, STRIBECK_VELOCITY_RAD_S, STRIBECK_EXPONENT):
            jr.set(key, None, reason=why_s)
    # identified base parameters β̂ = c·β_URDF + δβ and their covariance (J·cov·Jᵀ)
    names = fit.names
    Jm = np.zeros((base.r, len(names)))
    if "urdf" in names:
        Jm[:, names.index("urdf")] = beta_urdf
    kept = []
    for k in range(base.r):
        if f"dbeta{k}" in names:
            Jm[k, names.index(f"dbeta{k}")] = 1.0
            kept.append(k)
    beta = Jm @ fit.theta + (c0 * beta_urdf if given else 0.0)
    cov_b = Jm @ fit.cov @ Jm.T
    gu = ctx.grav[sel, j]
    rng = float(np.ptp(gu))
    if given is not None:
        jr.set("torque_constant_Nm_per_A", float(given), None)
        jr.diagnostics["kt_source"] = "given (--torque-constants or the configuration)"
    elif rng > 1e-9 and "urdf" in names:  # determined or not: the slope's relative std decides (KT_MAX_REL_STD)
        wvec = (gu @ Yg[sel]) / (gu @ gu)
        slope = float(wvec @ beta)
        sslope = float(np.sqrt(max(wvec @ cov_b @ wvec, 0.0)))
        _kt_from_slope(jr, slope, sslope, "")
        if slope > 0:
            jr.diagnostics["kt_estimate_Nm_per_A"] = 1.0 / slope
            jr.diagnostics["kt_relative_std"] = sslope / slope
        jr.diagnostics["kt_source"] = "URDF gravity torque / identified gravity part (reference: the URDF's masses)"
    else:
        jr.set("torque_constant_Nm_per_A", None, reason=NO_GRAVITY.format(rng=rng) if rng <= 1e-9 else
               "the URDF's rigid-body torque is not separable from the other terms in this data")
    kt = jr.torque_constant_Nm_per_A
    own = f"{name}.armature"
    k_arm = next((k for k, nm_ in enumerate(base.names) if nm_.split(" ")[0] == own), None)  # separable
    if k_arm is not None and k_arm in kept:
        arm_A = float(beta[k_arm])
        notes["armature_kgm2"][name] = None if kt is None else arm_A * kt
        jr.diagnostics["armature_A_s2_per_rad"] = arm_A
        jr.diagnostics["armature_std_A_s2_per_rad"] = float(np.sqrt(cov_b[k_arm, k_arm]))
    elif any(own in nm_ for nm_ in base.names):
        jr.diagnostics["armature"] = ("rotor inertia merged with link inertia in a base parameter (not separable)"
                                      if k_arm is None else "rotor inertia not determined by this data")
    sd = np.sqrt(np.maximum(np.diag(cov_b), 0.0))
    notes["base_parameters"][name] = {
        "names": base.names, "current_A": beta.tolist(), "std_A": sd.tolist(), "urdf_Nm": beta_urdf.tolist(),
        "from_data": [k in kept for k in range(base.r)],
        "kept_at_urdf": {base.names[k]: fit.dropped.get(f"dbeta{k}", "") for k in range(base.r) if k not in kept}}
    jr.diagnostics.update({"rows": int(sel.size), "condition_number": fit.cond, "residual_A": fit.sigma,
                           "base_parameters": base.r, "base_parameters_from_data": len(kept),
                           "gravity_range_Nm": rng, "acceleration_p90_rad_s2": acc_level})
    if len(kept) < base.r:
        ctx.warnings.append(f"{name}: {base.r - len(kept)} of {base.r} base parameters not determined by this log "
                            f"(kept at the URDF's values); excite more (fourier plan)")
    _physical(jr)
    return jr


def fit_full(ctx: Context, stribeck_grid: bool = True) -> FitResult:
    """Full dynamics: base parameters of the rigid-body model + rotor inertia + friction, per joint, in amperes.

    Joint j's row of Pinocchio's joint-torque regressor, extended by the rotor inertias (J_a·q̈) and reduced to its
    base columns (numerical QR; a rotor inertia that merges with a link inertia stays merged), Y_j·β_j. The
    parameters are written as the URDF's scaled by c_j = 1/K_t plus corrections,

        i_j = c_j·Y_j(q̃, q̇, q̈)·β_URDF + Y_j·δβ_j + I_f,j(q̇_j)

    and solved by least squares with a Gaussian prior on the corrections (Bayesian linear regression): 5 % of the
    URDF value for inertial parameters, ~1 kg·m² for rotor inertias (not in a URDF), at least what moves the current
    by 20 mA for parameters the URDF has at zero, and 1 % for gravity parameters — they are the K_t reference and,
    with the excitation a 6-joint Fourier plan reaches (regressor condition ~10⁴), they trade off against the
    friction levels; a log that determines them moves them anyway. With K_t given (``Options.torque_constants``,
    ``--torque-constants``) the scale is fixed, c_j = 1/K_t, and the gravity parameters are no longer the K_t
    reference: their prior is the CAD uncertainty of every inertial parameter (``PRIOR_REL``, ≥ ``RESOLUTION_A`` of
    current; docs/IDENTIFICATION.md "Real robot logs"). Directions the data determines move freely,
    the others stay near the URDF instead of absorbing noise. All columns and the current go through the same
    zero-phase filter H; rows where the joint slides (stiction is not a function of q̇); weighted least squares
    (the accelerating and the steady rows each by the inverse of their residual variance, two-step); standard
    deviations from the posterior covariance. K_t: the ratio of the URDF's gravity torque to the identified gravity
    part (linear in the parameters, so its std follows). A Stribeck hump is chosen by variable projection over a
    (v_s, δ) grid when enough slow sliding is present and it lowers the residual by 5 %.
    """
    notes: dict[str, Any] = {"base_parameters": {}, "armature_kgm2": {}, "global_base_count": ctx.rm.base_full.r}
    out = [_fit_full_joint(ctx, j, name, notes, stribeck_grid) for j, name in enumerate(ctx.names)]
    return FitResult("full", out, ctx.log.path, str(ctx.robot.urdf_path), list(ctx.warnings), notes)


# ------------------------------------------------------------------------------------------ auto


def fit_auto(ctx: Context) -> FitResult:
    """The best estimate the log supports, per joint.

    Quasi-static logs (plans lowspeed/symmetric/friction/synchronous): the synchronous model on every steady row,
    i = τ(q)/K_t + F_c,d + (F_s,d − F_c,d)·e^{−(|q̇|/v_s)^δ} + F_v,d·q̇ — K_t, Coulomb and viscous by least squares,
    v_s and δ by Levenberg–Marquardt over the linear solution (variable projection) when slow steady sliding is
    present, static levels from breakaway events otherwise. Logs with real accelerations (a fourier plan): the
    full-dynamics method.
    """
    p, o = ctx.p, ctx.opts
    moving = np.abs(p.dq) > o.v_min
    steady = np.column_stack([ctx.steady(j) for j in range(ctx.n)])
    steady_share = float(steady.sum() / max(1, moving.sum()))
    if steady_share < 0.15 and moving.any():
        res = fit_full(ctx)
        res.method = "auto"
        res.notes["auto"] = (f"full dynamics: only {steady_share:.0%} of the moving samples are "
                             "steady (constant speed); "
                             "the log excites the rigid-body dynamics")
        return res
    movers = [j for j in range(ctx.n) if not ctx.never_moves(j)]
    seed000: list[str] = []
    out = []
    for j, name in enumerate(ctx.names):
        jr = JointResult(name)
        out.append(jr)
        why = ctx.never_moves(j)
        if why:
            jr.null_all(why)
            continue
        sel = ctx.rows[ctx.steady(j)[ctx.rows]]
        if sel.size < MIN_ROWS:
            jr.null_all(f"no steady motion of {name} (|q̇| > {o.v_min} rad/s at |q̈| < {o.a_max} rad/s²) in this log")
            continue
        fit0, rng = _quasistatic_fit(ctx, j, sel, None)
        vsel = p.dq[sel, j]
        vmin = float(np.abs(vsel).min())
        best = fit0
        stb = None
        if vmin < 0.05:
            # variable projection: the linear parameters solved inside, (ln v_s, ln δ) by LM
            x0 = np.array([math.log(0.02), math.log(1.5)])
            try:
                r = least_squares(_stribeck_residual, x0, method="lm", max_nfev=60, diff_step=0.05,
                                  args=(ctx, j, sel, o.stribeck_exponent))
                dl = o.stribeck_exponent or math.exp(r.x[1])
                f2, _ = _quasistatic_fit(ctx, j, sel, (math.exp(r.x[0]), dl))
                if f2.sigma < fit0.sigma * 0.995 and f2.value("dstatic_pos_A") is not None:
                    J = r.jac
                    s2 = float(r.fun @ r.fun / max(1, r.fun.size - J.shape[1] - len(f2.names)))
                    try:
                        cx = s2 * np.linalg.inv(J.T @ J)
                        sx = np.sqrt(np.maximum(np.diag(cx), 0))
                    except np.linalg.LinAlgError:
                        sx = np.full(2, np.inf)
                    cand = (math.exp(r.x[0]), dl, math.exp(r.x[0]) * sx[0], 0.0 if o.stribeck_exponent else dl * sx[1])
                    if np.isfinite(cand[2]) and cand[2] < 0.5 * cand[0]:  # only a determined hump enters the model
                        best, stb = f2, cand
            except (ValueError, np.linalg.LinAlgError):
                pass
        if stb is None:
            # no hump in the model: rows slow enough to feel one (|q̇| < 0.08 rad/s, ~3 v_s) would bias
            # Coulomb/viscous; leave them out when enough faster rows remain
            fast = sel[np.abs(p.dq[sel, j]) >= 0.08]
            if fast.size >= max(MIN_ROWS, sel.size // 2) and fast.size < sel.size:
                best, _ = _quasistatic_fit(ctx, j, fast, None)
                jr.diagnostics["rows_below_0.08_rad_s_excluded"] = int(sel.size - fast.size)
        fit = best
        _kt_from_slope(jr, fit.value("gravity"), fit.std("gravity"), fit.dropped.get("gravity", "not determined"))
        vmax = float(np.abs(vsel).max())
        _set_friction_from_fit(jr, fit, vmax, v=vsel)
        if len(movers) == 1 and all(f"friction_level_{d}_A" in jr.diagnostics for d in ("pos", "neg")):
            # seed 000's experiment (one joint, one constant speed each way): its model, one friction level per
            # direction = the current at the test speed less gravity (eq. 20) — the Coulomb levels of the law
            sp = {d: float(np.mean(np.abs(vsel[np.sign(vsel) == s]))) for d, s in (("pos", 1), ("neg", -1))}
            for d in ("pos", "neg"):
                jr.set(f"coulomb_{d}_A", jr.diagnostics[f"friction_level_{d}_A"], fit.std(f"coulomb_{d}_A"))
            why = (f"seed 000's model (one joint, one speed each way): one friction level per direction, the level at "
                   f"the test speed (+{sp['pos']:.3f}/−{sp['neg']:.3f} rad/s); viscous friction is not separable "
                   "from it at one speed — add passes at other speeds to identify it")
            for key in (VISCOUS_A_S_PER_RAD, VISCOUS_POS_A_S_PER_RAD, VISCOUS_NEG_A_S_PER_RAD):
                jr.set(key, None, reason=why)
            jr.diagnostics["model"] = "seed 000 (level at the test speed)"
            seed000.append(f"seed-000 experiment recognised: one joint ({name}), one speed each way; Coulomb = level "
                           f"at {sp['pos']:.2f} rad/s (+) and {sp['neg']:.2f} rad/s (−): "
                           f"{jr.friction[COULOMB_POS_A]:+.4f}/{jr.friction[COULOMB_NEG_A]:+.4f} A, gravity "
                           "removed with the fitted K_t (seed 000 eq. 20)")
        if stb is not None and stb[2] < 0.5 * stb[0]:
            for d in ("pos", "neg"):
                c, hump_d = jr.friction[f"coulomb_{d}_A"], fit.estimate(f"dstatic_{d}_A")
                if c is not None and hump_d is not None and hump_d[1] <= RESOLUTION_A:
                    dv, ds = hump_d
                    jr.set(f"static_{d}_A", c + dv, math.hypot(ds, jr.std.get(f"coulomb_{d}_A", 0.0)))
            jr.set(STRIBECK_VELOCITY_RAD_S, stb[0], stb[2])
            jr.set(STRIBECK_EXPONENT, stb[1], stb[3])
            jr.diagnostics["stribeck_source"] = "steady sliding, variable projection (LM)"
        else:
            why_s = (f"no steady sliding below {vmin:.3f} rad/s (stick–slip or no slow passes): the Stribeck curve is "
                     "not observable in steady motion")
            jr.set(STRIBECK_VELOCITY_RAD_S, None, reason=why_s)
            jr.set(STRIBECK_EXPONENT, None, reason=why_s)
        for d in ("pos", "neg"):
            if jr.friction[f"static_{d}_A"] is None:
                jr.set(f"static_{d}_A", None, reason="no breakaway events and no steady slow sliding")
        if jr.friction[STATIC_POS_A] is None or jr.friction[STATIC_NEG_A] is None:
            a = fit.value("gravity") or 0.0
            brk = breakaway_levels(ctx, j, p.i[:, j] - a * ctx.grav[:, j])  # at rest: gravity only
            for d, (lvl, s, cnt) in brk.items():
                if jr.friction[f"static_{d}_A"] is None:
                    jr.set(f"static_{d}_A", lvl, s)
                    jr.diagnostics[f"static_{d}_source"] = f"breakaway: {cnt} stick→slip events"
        jr.diagnostics.update({"rows": int(sel.size), "condition_number": fit.cond, "residual_A": fit.sigma,
                               "gravity_range_Nm": rng, "speed_range_rad_s": [vmin, vmax]})
        _physical(jr)
    res = FitResult("auto", out, ctx.log.path, str(ctx.robot.urdf_path), list(ctx.warnings))
    res.notes["auto"] = (f"quasi-static: {steady_share:.0%} of the moving samples are steady; synchronous model on "
                         "every steady row, Stribeck by variable projection, breakaway static levels")
    if seed000:
        res.notes["auto"] = seed000[0] + "; " + res.notes["auto"]
    return res


# ------------------------------------------------------------------------------------------ entry point


FITTERS = {"lowspeed": fit_lowspeed, "symmetric": fit_symmetric, "synchronous": fit_synchronous, "full": fit_full,
           "auto": fit_auto}


def identify(log: Log, robot: Any, method: str = "auto", opts: Options | None = None,
             rm: RegressorModel | None = None) -> FitResult:
    """Run one method on a loaded log; the result has per-joint values, std, reasons for nulls, diagnostics."""
    if method not in FITTERS:
        raise ValueError(f"--method: expected one of {', '.join(METHODS)}, got '{method}'")
    t0 = time.perf_counter()
    ctx = Context(log, robot, opts or Options(), rm)
    res = FITTERS[method](ctx)
    never = [jr.name for jr in res.joints if any("never moves" in r for r in jr.reasons.values())]
    for nm in never:
        res.warnings.append(f"{nm} never moves in this log: its parameters are reported unidentifiable (null)")
    res.notes.setdefault("processing", {"rate_Hz": ctx.p.source_rate_Hz, "work_rate_Hz": ctx.p.fs,
                                        "regression_filter_Hz": ctx.p.cutoff_Hz,
                                        "derivative_filter_Hz": ctx.p.deriv_cutoff_Hz,
                                        "duration_s": float(ctx.log.t[-1] - ctx.log.t[0]),
                                        "samples": int(ctx.log.t.shape[0])})
    res.elapsed_s = time.perf_counter() - t0
    return res


__all__ = ["METHODS", "Options", "Context", "identify", "find_pairs", "stribeck_lm", "friction_columns",
           "friction_value", "friction_curve", "breakaway_levels", "LogError"]
