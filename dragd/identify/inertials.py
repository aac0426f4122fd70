"""Identified base parameters → a physically consistent set of link inertials (the least change from the URDF).

A body's 10 inertial parameters π = (m, m·c, I at the joint frame) are physically consistent when its pseudo-inertia

    J = [[Σ, h], [hᵀ, m]],  Σ = ½·tr(I)·1 − I,  h = m·c

is positive definite (Wensing, Kim, Slotine 2017: positive mass, inertia satisfying the triangle inequalities and
a mass distribution that can exist). The log-Cholesky parameterisation (Rucker & Wensing 2022) writes
J = e^{2α}·U·Uᵀ with U upper triangular, unit (4,4) entry and diagonal e^{d₁..₃}: every real vector x ∈ ℝ¹⁰ is a
consistent body and every consistent body has one x. Rotor inertias (armature) are a = y² ≥ 0.

The mapping solves, over x (all bodies, plus armatures), by scipy least squares (trust region reflective)

    min  Σ_j ‖ W·s_j ⊙ (E_j·π(x) − b_j) ‖²  +  Σ_bodies ‖ (π(x) − π_URDF) / scale ‖²

with E_j the per-row base map of joint j (dragd.identify.regressors.Base), b_j its identified base parameters in
N·m units (current-space estimates × K_t), s_j the torque each unit of a base parameter makes at most over the data
(so a residual is N·m of torque error), W large (the base parameters must be reproduced; the URDF distance only
picks among the inertials that reproduce them), and the scales the URDF's own mass, m·L, m·L² with L the body's
radius of gyration (≥ 5 cm). An inconsistent target (e.g. noise implying a negative mass) gets the consistent
inertials nearest to it in that weighted sense; the residual is reported.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.optimize import least_squares

BASE_WEIGHT = 1.0e3  # W: 1 mN·m of base-parameter torque error costs as much as 100 % of a URDF mass change
STD_WEIGHT = 3.0  # W with residuals in standard deviations: 1/3 σ costs as much as 100 % of a URDF mass change


def pseudo_inertia(pi: np.ndarray) -> np.ndarray:
    """4×4 pseudo-inertia of Pinocchio's dynamic parameters (m, mcx, mcy, mcz, Ixx, Ixy, Iyy, Ixz, Iyz, Izz)."""
    m, h = pi[0], pi[1:4]
    Ixx, Ixy, Iyy, Ixz, Iyz, Izz = pi[4:10]
    inertia = np.array([[Ixx, Ixy, Ixz], [Ixy, Iyy, Iyz], [Ixz, Iyz, Izz]])
    S = 0.5 * np.trace(inertia) * np.eye(3) - inertia
    J = np.zeros((4, 4))
    J[:3, :3], J[:3, 3], J[3, :3], J[3, 3] = S, h, h, m
    return J


def params_from_pseudo(J: np.ndarray) -> np.ndarray:
    S, h, m = J[:3, :3], J[:3, 3], J[3, 3]
    inertia = np.trace(S) * np.eye(3) - S
    return np.array([m, h[0], h[1], h[2], inertia[0, 0], inertia[0, 1], inertia[1, 1], inertia[0, 2], inertia[1, 2],
                     inertia[2, 2]])


def _U(x: np.ndarray) -> np.ndarray:
    a, d1, d2, d3, s12, s23, s13, t1, t2, t3 = x
    return np.exp(a) * np.array([[np.exp(d1), s12, s13, t1],
                                 [0.0, np.exp(d2), s23, t2],
                                 [0.0, 0.0, np.exp(d3), t3],
                                 [0.0, 0.0, 0.0, 1.0]])


def params_from_logchol(x: np.ndarray) -> np.ndarray:
    U = _U(x)
    return params_from_pseudo(U @ U.T)


_DU_INDEX = ((0, 0), (1, 1), (2, 2), (0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3))  # entries of d1..t3


def logchol_jacobian(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """π(x) and dπ/dx (10 × 10): J = U·Uᵀ, dJ = dU·Uᵀ + U·dUᵀ, π linear in J."""
    U = _U(x)
    out = np.empty((10, 10))
    J = U @ U.T
    out[:, 0] = params_from_pseudo(2.0 * J)  # ∂/∂α: U scales with e^α
    for k, (r, c) in enumerate(_DU_INDEX):
        dU = np.zeros((4, 4))
        dU[r, c] = U[r, c] if k < 3 else np.exp(x[0])  # diagonal: ∂e^{α+d}/∂d; off-diagonal: e^α
        dJ = dU @ U.T
        out[:, k + 1] = params_from_pseudo(dJ + dJ.T)
    return params_from_pseudo(J), out


def logchol_from_params(pi: np.ndarray, floor: float = 1e-9) -> np.ndarray:
    """x with params_from_logchol(x) ≈ π; an inconsistent or degenerate π is first made positive definite."""
    J = pseudo_inertia(pi)
    J = 0.5 * (J + J.T)
    w, V = np.linalg.eigh(J)
    scale = max(abs(J[3, 3]), 1e-6)
    J = (V * np.maximum(w, floor * scale)) @ V.T
    # J = U·Uᵀ with U upper triangular: the Cholesky factor of the reversed matrix, reversed back
    P = np.eye(4)[::-1]
    L = np.linalg.cholesky(P @ J @ P)
    U = P @ L @ P
    a = np.log(U[3, 3])
    U = U / U[3, 3]
    return np.array([a, np.log(U[0, 0]), np.log(U[1, 1]), np.log(U[2, 2]), U[0, 1], U[1, 2], U[0, 2],
                     U[0, 3], U[1, 3], U[2, 3]])


def is_consistent(pi: np.ndarray, tol: float = 1e-9) -> bool:
    """Positive mass and a positive semidefinite pseudo-inertia (implies the triangle inequalities)."""
    J = pseudo_inertia(pi)
    return bool(pi[0] > 0 and np.linalg.eigvalsh(0.5 * (J + J.T)).min() >= -tol * max(1.0, abs(pi[0])))


def triangle_ok(I_c: np.ndarray, tol: float = 1e-9) -> bool:
    """Principal moments of a 3×3 inertia satisfy a + b ≥ c (and are ≥ 0)."""
    e = np.linalg.eigvalsh(0.5 * (I_c + I_c.T))
    s = e.sum()
    return bool(e.min() >= -tol and all(s - 2 * v >= -tol * max(1.0, s) for v in e))


@dataclass
class RowTarget:
    """Joint j's identified base parameters: β = E·π (r × p, p = 11·n with the armatures last), in N·m units."""

    E: np.ndarray
    beta: np.ndarray
    scale: np.ndarray | None = None  # torque per unit of each base parameter over the data (default 1)
    std: np.ndarray | None = None  # the estimate's standard deviations: when given, residuals are weighted by 1/std


@dataclass
class MappingResult:
    pi: np.ndarray  # (10·n,) consistent body parameters (Pinocchio order, at the joint frames)
    armature: np.ndarray  # (n,) ≥ 0
    gains: np.ndarray  # (n,) factor applied to each row's target (1 unless free_gain)
    residual_Nm: list[np.ndarray]  # per row: s ⊙ (E·π − g·b)
    relative_residual: list[float]  # per row: ‖E·π − g·b‖ / ‖g·b‖
    consistent: bool
    cost: float
    nfev: int
    notes: dict[str, Any] = field(default_factory=dict)

    @property
    def max_residual_Nm(self) -> float:
        return float(max((np.abs(r).max(initial=0.0) for r in self.residual_Nm), default=0.0))


def _body_scales(pi_urdf: np.ndarray, n: int) -> np.ndarray:
    out = np.empty(10 * n)
    for i in range(n):
        p = pi_urdf[10 * i:10 * i + 10]
        m = max(abs(p[0]), 1e-2)
        tr = abs(p[4] + p[6] + p[9])
        L = max(np.sqrt(tr / m) if tr > 0 else 0.0, 0.05)
        out[10 * i] = m
        out[10 * i + 1:10 * i + 4] = m * L
        out[10 * i + 4:10 * i + 10] = m * L * L
    return out


def consistent_inertials(targets: list[RowTarget | None], pi_urdf: np.ndarray, armature_urdf: np.ndarray | None = None,
                         base_weight: float = BASE_WEIGHT, max_nfev: int = 500) -> MappingResult:
    """The consistent inertials nearest to the URDF's (``pi_urdf``, 10·n) that reproduce the targets (module doc).

    1. The linear problem (consistency not imposed) in closed form; when every body is consistent, that is the answer.
    2. Otherwise the log-Cholesky problem by trust-region least squares (analytic Jacobian), started from the linear
       answer with its pseudo-inertias' negative eigenvalues clipped.
    """
    n = pi_urdf.shape[0] // 10
    arm0 = np.zeros(n) if armature_urdf is None else np.asarray(armature_urdf, dtype=float)
    rows = [(j, t) for j, t in enumerate(targets) if t is not None and t.beta.size]
    scales = _body_scales(pi_urdf, n)
    arm_scale = np.maximum(np.abs(arm0), 0.05)
    wts = [(1.0 / np.maximum(np.asarray(t.std, dtype=float), 1e-12) if t.std is not None else
            np.ones(t.beta.size) if t.scale is None else np.asarray(t.scale, dtype=float)) for _, t in rows]
    weight = [base_weight]

    def unpack(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        pi = np.concatenate([params_from_logchol(x[10 * i:10 * i + 10]) for i in range(n)])
        return pi, x[10 * n:11 * n] ** 2, np.ones(n)

    def resid_of(pi: np.ndarray, arm: np.ndarray, g: np.ndarray) -> np.ndarray:
        full = np.concatenate([pi, arm])
        out = [weight[0] * w * (t.E @ full - g[j] * t.beta) for (j, t), w in zip(rows, wts, strict=True)]
        out.append((pi - pi_urdf) / scales)
        out.append((arm - arm0) / arm_scale)
        return np.concatenate(out)

    def resid(x: np.ndarray) -> np.ndarray:
        return resid_of(*unpack(x))

    def jac(x: np.ndarray) -> np.ndarray:
        D = np.zeros((11 * n, x.size))  # d(π, armature)/dx
        for i in range(n):
            D[10 * i:10 * i + 10, 10 * i:10 * i + 10] = logchol_jacobian(x[10 * i:10 * i + 10])[1]
        D[10 * n:, 10 * n:11 * n] = np.diag(2.0 * x[10 * n:11 * n])
        out = []
        for (_j, t), w in zip(rows, wts, strict=True):
            out.append(weight[0] * w[:, None] * (t.E @ D))
        out.append(D[:10 * n] / scales[:, None])
        out.append(D[10 * n:] / arm_scale[:, None])
        return np.vstack(out)

    def logchol_all(pi: np.ndarray) -> np.ndarray:
        return np.concatenate([logchol_from_params(pi[10 * i:10 * i + 10]) for i in range(n)])

    nfev, stages = 0, []
    pi = arm = None
    g = np.ones(n)
    A = [base_weight * w[:, None] * t.E for (_, t), w in zip(rows, wts, strict=True)]
    y = [base_weight * w * t.beta for (_, t), w in zip(rows, wts, strict=True)]
    A.append(np.hstack([np.diag(1.0 / scales), np.zeros((10 * n, n))]))
    y.append(pi_urdf / scales)
    A.append(np.hstack([np.zeros((n, 10 * n)), np.diag(1.0 / arm_scale)]))
    y.append(arm0 / arm_scale)
    lin = np.linalg.lstsq(np.vstack(A), np.concatenate(y), rcond=None)[0]
    if all(is_consistent(lin[10 * i:10 * i + 10], tol=0.0) for i in range(n)) and lin[10 * n:].min() >= 0:
        pi, arm = lin[:10 * n], lin[10 * n:]
        stages.append("linear (consistent as solved)")
    else:
        x = np.concatenate([logchol_all(lin[:10 * n]), np.sqrt(np.maximum(lin[10 * n:], 0.0))])
        sol = least_squares(resid, x, jac=jac, method="trf", x_scale=1.0, max_nfev=max_nfev, xtol=1e-12,
                            ftol=1e-15, gtol=1e-12)
        nfev += int(sol.nfev)
        pi, arm, g = unpack(sol.x)
        stages.append("linear answer inconsistent → log-Cholesky least squares")
    weight[0] = base_weight
    cost = 0.5 * float(np.sum(resid_of(pi, arm, g) ** 2))
    full = np.concatenate([pi, arm])
    res_nm, rel, chi = [], [], []
    for j, t in enumerate(targets):
        if t is None or not t.beta.size:
            res_nm.append(np.zeros(0))
            rel.append(0.0)
            chi.append(0.0)
            continue
        d = t.E @ full - g[j] * t.beta
        w = np.ones(t.beta.size) if t.scale is None else np.asarray(t.scale, dtype=float)
        res_nm.append(w * d)
        rel.append(float(np.linalg.norm(d)) / max(float(np.linalg.norm(g[j] * t.beta)), 1e-300))
        chi.append(float(np.abs(d / np.maximum(t.std, 1e-12)).max()) if t.std is not None else float("nan"))
    ok = all(is_consistent(pi[10 * i:10 * i + 10]) for i in range(n)) and bool(np.all(arm >= 0))
    return MappingResult(pi, arm, g, res_nm, rel, ok, cost, nfev, {"solve": stages, "max_residual_over_std": chi})


def body_inertial(pi: np.ndarray) -> dict[str, Any]:
    """A params-file inertial (mass_kg, com_m, inertia_kgm2 about the COM: ixx, ixy, ixz, iyy, iyz, izz)."""
    import pinocchio as pin

    body = pin.Inertia.FromDynamicParameters(np.asarray(pi, dtype=float))
    Ic = body.inertia
    return {"mass_kg": float(body.mass), "com_m": [float(v) for v in body.lever],
            "inertia_kgm2": [float(Ic[0, 0]), float(Ic[0, 1]), float(Ic[0, 2]), float(Ic[1, 1]), float(Ic[1, 2]),
                             float(Ic[2, 2])]}


def inertials_from_fit(res: Any, robot: Any, rm: Any,
                       kt_fallback: Sequence[float | None] | None = None) -> dict[str, Any] | None:
    """The consistent link inertials of a full-dynamics fit (``res.notes['base_parameters']``, current space).

    Joint j's target is its identified base parameters × the K_t the law will use for it: the result's (given or
    determined), else ``kt_fallback[j]`` (the configuration's), else the fit's undetermined point estimate. Returns
    ``{"inertials": {link: {...}}, "mapping": {...}}`` or None when the result has no base parameters.
    """
    bp = (getattr(res, "notes", {}) or {}).get("base_parameters") or {}
    if not bp:
        return None
    n = rm.n
    targets: list[RowTarget | None] = []
    kts: dict[str, Any] = {}
    for j, jr in enumerate(res.joints):
        b = bp.get(jr.name)
        base = rm.row_full[j]
        if b is None or list(b["names"]) != list(base.names):
            targets.append(None)
            continue
        kt, src = jr.torque_constant_Nm_per_A, "fit"
        if kt is None and kt_fallback is not None and kt_fallback[j] is not None:
            kt, src = kt_fallback[j], "configuration"
        if kt is None:
            kt, src = jr.diagnostics.get("kt_estimate_Nm_per_A"), "undetermined estimate (URDF reference)"
        if kt is None or not kt > 0:
            targets.append(None)
            continue
        kts[jr.name] = {"torque_constant_Nm_per_A": float(kt), "source": src}
        beta = np.array([np.nan if v is None else v for v in b["current_A"]], dtype=float) * kt
        std = np.array([np.nan if v is None else v for v in b.get("std_A", [])], dtype=float) * kt
        if not np.all(np.isfinite(beta)) or std.shape != beta.shape or not np.all(np.isfinite(std)):
            targets.append(None)
            continue
        # weighted by the estimates' own std: what the data determine is reproduced, what the fit's prior held
        # near the URDF may give way where other rows determine it (rows share the links' parameters)
        targets.append(RowTarget(base.E, beta, rm.row_scale[j], np.maximum(std, 1e-6 * np.abs(beta).max())))
    if not any(t is not None for t in targets):
        return None
    pi_urdf = rm.pi_urdf[:10 * n]
    arm_urdf = rm.pi_urdf[10 * n:]
    m = consistent_inertials(targets, pi_urdf, arm_urdf, base_weight=STD_WEIGHT)
    links = robot.link_names()
    inertials = {links[i]: body_inertial(m.pi[10 * i:10 * i + 10]) for i in range(n)}
    names = [jr.name for jr in res.joints]
    mapping = {
        "consistent": m.consistent, "solve": m.notes.get("solve"), "evaluations": m.nfev,
        "torque_constants": kts,
        "max_base_residual_Nm": m.max_residual_Nm,
        "base_residual_over_std": {names[j]: m.notes["max_residual_over_std"][j] for j in range(n)
                                   if targets[j] is not None},
        "base_residual_Nm": {names[j]: float(np.abs(r).max(initial=0.0)) for j, r in enumerate(m.residual_Nm)
                             if targets[j] is not None},
        "base_relative_residual": {names[j]: m.relative_residual[j] for j in range(n) if targets[j] is not None},
        "mass_change": {links[i]: float(m.pi[10 * i] / pi_urdf[10 * i] - 1.0) if pi_urdf[10 * i] > 0 else None
                        for i in range(n)},
        "armature_kgm2": {names[i]: float(m.armature[i]) for i in range(n)},
    }
    return {"inertials": inertials, "mapping": mapping}
