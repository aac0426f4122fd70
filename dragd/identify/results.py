"""Least squares with honest uncertainty, and the identification result (JSON, params file).

Every estimate carries a standard deviation from the residual covariance, cov = σ̂²·(AᵀWA)⁻¹ with
σ̂² = RSS/(N − p) on decimated rows (residuals ≈ white after the regression filter). Columns the data cannot
separate (variance inflation above ``VIF_LIMIT``) or cannot see at all are removed and their parameters
reported as null with the reason.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from dragd.config import FrictionParams

VIF_LIMIT = 1.0e4

#: the identified friction values of a joint: the fields of ``FrictionParams`` (dragd/config.py), which are
#: ``FrictionConfig``'s plus one viscous slope for both directions (tests/test_config.py keeps the two in step)
FRICTION_KEYS: tuple[str, ...] = tuple(FrictionParams.model_fields)


def _key(name: str) -> str:
    """A friction key by name, checked against the model when the module loads (a misspelt key fails at import)."""
    if name not in FrictionParams.model_fields:
        raise KeyError(f"{name!r} is not a field of FrictionParams ({', '.join(FRICTION_KEYS)})")
    return name


COULOMB_POS_A = _key("coulomb_pos_A")
COULOMB_NEG_A = _key("coulomb_neg_A")
VISCOUS_A_S_PER_RAD = _key("viscous_A_s_per_rad")
VISCOUS_POS_A_S_PER_RAD = _key("viscous_pos_A_s_per_rad")
VISCOUS_NEG_A_S_PER_RAD = _key("viscous_neg_A_s_per_rad")
STATIC_POS_A = _key("static_pos_A")
STATIC_NEG_A = _key("static_neg_A")
STRIBECK_VELOCITY_RAD_S = _key("stribeck_velocity_rad_s")
STRIBECK_EXPONENT = _key("stribeck_exponent")


@dataclass
class LinearFit:
    names: list[str]
    theta: np.ndarray
    cov: np.ndarray
    sigma: float  # residual standard deviation (weighted units)
    rows: int
    cond: float  # condition number of the column-normalised regressor
    dropped: dict[str, str]  # column -> reason
    residual: np.ndarray

    def value(self, name: str) -> float | None:
        return float(self.theta[self.names.index(name)]) if name in self.names else None

    def std(self, name: str) -> float | None:
        return float(np.sqrt(max(self.cov[self.names.index(name)][self.names.index(name)], 0.0))) \
            if name in self.names else None

    def estimate(self, name: str) -> tuple[float, float] | None:
        """(value, standard deviation) of a term in the model; None when it is not."""
        v, s = self.value(name), self.std(name)
        return None if v is None or s is None else (v, s)


def condition_number(A: np.ndarray) -> float:
    if A.shape[1] == 0 or A.shape[0] == 0:
        return float("inf")
    norms = np.linalg.norm(A, axis=0)
    s = np.linalg.svd(A / np.where(norms > 0, norms, 1.0), compute_uv=False)
    return float(s[0] / s[-1]) if s[-1] > 0 else float("inf")


def linear_fit(A: np.ndarray, y: np.ndarray, names: list[str], w: np.ndarray | None = None,
               keep: tuple[str, ...] = (), vif_limit: float = VIF_LIMIT,
               explain: dict[str, str] | None = None, prefer_drop: tuple[str, ...] = (),
               priority: list[str] | None = None) -> LinearFit:
    """(Weighted) least squares y ≈ A·θ; drops unseen and inseparable columns (not those in ``keep``).

    Among inseparable columns, those in ``prefer_drop`` go first (e.g. a viscous slope before its Coulomb level).
    """
    names = list(names)
    dropped: dict[str, str] = {}
    sw = None if w is None else np.sqrt(w)
    Aw = A if sw is None else A * sw[:, None]
    yw = y if sw is None else y * sw
    norms = np.linalg.norm(Aw, axis=0)
    scale = max(norms.max(initial=0.0), 1e-300)
    live = [k for k in range(len(names)) if norms[k] > 1e-9 * scale and norms[k] > 0]
    for k in range(len(names)):
        if k not in live:
            dropped[names[k]] = (explain or {}).get(names[k], "no data excites this term")
    if priority is not None:
        live = _greedy(Aw, norms, names, live, priority, vif_limit, dropped, explain)
    while True:
        if not live:
            return LinearFit([], np.zeros(0), np.zeros((0, 0)), float(np.std(yw)) if yw.size else float("nan"),
                             int(y.shape[0]), float("inf"), dropped, y.copy())
        B = Aw[:, live] / norms[live]
        G = B.T @ B
        try:
            Ginv = np.linalg.inv(G)
            vif = np.diag(Ginv)
            ok = bool(np.all(np.isfinite(vif)) and np.all(vif > 0))
        except np.linalg.LinAlgError:
            ok = False
        if not ok:
            vif = np.full(len(live), np.inf)
        cand = [(vif[i], i) for i in range(len(live)) if names[live[i]] not in keep]
        worst = max(cand) if cand else (0.0, -1)
        pref = [c for c in cand if names[live[c[1]]] in prefer_drop and c[0] > vif_limit]
        if worst[0] > vif_limit and pref:
            worst = max(pref)
        elif worst[0] > vif_limit and priority is not None:
            # among the inseparable columns drop the least important one (last in ``priority``)
            over = [c for c in cand if c[0] > vif_limit]
            rank = {nm: k for k, nm in enumerate(priority)}
            worst = max(over, key=lambda c: rank.get(names[live[c[1]]], len(priority)))
        if worst[0] <= vif_limit:
            break
        k = live.pop(worst[1])
        others = [names[live[i]] for i in np.argsort(-np.abs(_corr_row(B, worst[1])))[:2] if i < len(live)]
        base = (explain or {}).get(names[k])
        dropped[names[k]] = base or (f"not separable from {', '.join(others) or 'the other terms'} in this data "
                                     f"(variance inflation {worst[0]:.3g} > {vif_limit:g})")
    B = Aw[:, live] / norms[live]
    theta_s, *_ = np.linalg.lstsq(B, yw, rcond=None)
    res_w = yw - B @ theta_s
    dof = max(1, B.shape[0] - B.shape[1])
    sigma = float(np.sqrt(res_w @ res_w / dof))
    cov_s = sigma**2 * np.linalg.inv(B.T @ B)
    theta = theta_s / norms[live]
    cov = cov_s / np.outer(norms[live], norms[live])
    resid = y - A[:, live] @ theta
    return LinearFit([names[k] for k in live], theta, cov, sigma, int(y.shape[0]), condition_number(B), dropped, resid)


def _greedy(Aw: np.ndarray, norms: np.ndarray, names: list[str], live: list[int], priority: list[str],
            vif_limit: float, dropped: dict[str, str], explain: dict[str, str] | None) -> list[int]:
    """Keep columns in ``priority`` order while each adds a direction the kept ones do not span (Gram–Schmidt).

    A column whose part orthogonal to the kept columns has squared norm below 1/vif_limit (normalised) would have
    a variance inflation above the limit: it is dropped, naming the kept columns it is most aligned with.
    """
    order = sorted(live, key=lambda k: priority.index(names[k]) if names[k] in priority else len(priority) + k)
    Q = np.zeros((Aw.shape[0], 0))
    kept: list[int] = []
    for k in order:
        b = Aw[:, k] / norms[k]
        r = b - Q @ (Q.T @ b) if Q.shape[1] else b
        r = r - Q @ (Q.T @ r) if Q.shape[1] else r  # re-orthogonalise (numerical safety)
        rn = float(r @ r)
        if rn < 1.0 / vif_limit:
            c = np.abs(np.array([Aw[:, i] @ b / norms[i] for i in kept])) if kept else np.zeros(0)
            top = [names[kept[i]] for i in np.argsort(-c)[:2]]
            dropped[names[k]] = (explain or {}).get(names[k]) or (
                f"not separable from {', '.join(top) or 'the other terms'} in this data (variance inflation "
                f"{1 / max(rn, 1e-300):.3g} > {vif_limit:g})")
            continue
        Q = np.column_stack([Q, r / np.sqrt(rn)])
        kept.append(k)
    return sorted(kept)


def _corr_row(B: np.ndarray, i: int) -> np.ndarray:
    """|cosine| of column i with the others (after its removal, indices shift: used only for naming)."""
    c = B.T @ B[:, i]
    c = np.delete(c, i)
    return c


# ------------------------------------------------------------------------------------------ results


@dataclass
class JointResult:
    name: str
    torque_constant_Nm_per_A: float | None = None
    friction: dict[str, float | None] = field(default_factory=lambda: {k: None for k in FRICTION_KEYS})
    std: dict[str, float] = field(default_factory=dict)
    reasons: dict[str, str] = field(default_factory=dict)
    diagnostics: dict[str, Any] = field(default_factory=dict)

    def set(self, key: str, value: float | None, std: float | None = None, reason: str | None = None) -> None:
        if key == "torque_constant_Nm_per_A":
            self.torque_constant_Nm_per_A = value
        else:
            self.friction[key] = value
        if value is not None and std is not None and np.isfinite(std):
            self.std[key] = float(std)
        if value is None and reason:
            self.reasons[key] = reason
        elif value is not None:
            self.reasons.pop(key, None)

    def null_all(self, reason: str) -> None:
        self.set("torque_constant_Nm_per_A", None, reason=reason)
        for k in FRICTION_KEYS:
            self.set(k, None, reason=reason)

    def to_json(self) -> dict[str, Any]:
        return {"torque_constant_Nm_per_A": _r(self.torque_constant_Nm_per_A),
                "friction": {k: _r(v) for k, v in self.friction.items()},
                "std": {k: _r(v) for k, v in self.std.items()},
                "reasons": dict(self.reasons), "diagnostics": _jsonable(self.diagnostics)}


@dataclass
class FitResult:
    method: str
    joints: list[JointResult]
    log: str
    robot: str
    warnings: list[str] = field(default_factory=list)
    notes: dict[str, Any] = field(default_factory=dict)
    elapsed_s: float | None = None

    def joint(self, name: str) -> JointResult:
        return next(j for j in self.joints if j.name == name)

    def to_json(self) -> dict[str, Any]:
        return {"method": self.method, "log": self.log, "robot": self.robot,
                "joints": {j.name: j.to_json() for j in self.joints}, "warnings": list(self.warnings),
                "notes": _jsonable(self.notes),
                "elapsed_s": None if self.elapsed_s is None else round(self.elapsed_s, 3)}

    def to_params(self):  # noqa: ANN201
        """The params file (dragd.config.ParamsFile) the model, daemon and sim load."""
        from dragd.config import FrictionParams, JointEffects, JointParams, ParamsFile

        joints = {}
        for j in self.joints:
            fr = {k: v for k, v in j.friction.items() if v is not None}
            std = {k: float(v) for k, v in j.std.items()}
            if j.reasons:
                std["null_reasons"] = dict(j.reasons)
            effects = JointEffects()
            k = j.diagnostics.get("load_friction_A_per_Nm")
            if k is not None and j.torque_constant_Nm_per_A is not None:  # (k_L: friction torque per gravity torque)
                effects = JointEffects(load_friction_per_Nm=float(k) * float(j.torque_constant_Nm_per_A))
            joints[j.name] = JointParams(torque_constant_Nm_per_A=j.torque_constant_Nm_per_A,
                                         friction=FrictionParams(**fr), std=std, effects=effects)
        notes = {"log": self.log, "warnings": list(self.warnings), **_jsonable(self.notes)}
        return ParamsFile(method=self.method, robot=self.robot, joints=joints, notes=notes)


def _r(v: Any) -> Any:
    if v is None:
        return None
    v = float(v)
    return None if not np.isfinite(v) else float(f"{v:.7g}")


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, (np.floating, float)):
        return _r(x)
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def prior_fit(A: np.ndarray, y: np.ndarray, names: list[str], prior_std: dict[str, float],
              w: np.ndarray | None = None) -> LinearFit:
    """Least squares with a zero-mean Gaussian prior on some parameters (Bayesian linear regression).

    Minimises Σ wᵢ(yᵢ − Aᵢθ)²/σ² + Σ_k θ_k²/s_k² over the parameters named in ``prior_std`` (std s_k); σ is the
    residual standard deviation, estimated from a first unregularised pass. The covariance is the posterior one,
    σ²·(AᵀWA + σ²·diag(1/s²))⁻¹: a parameter the data does not determine keeps a std close to its prior.
    """
    names = list(names)
    sw = np.ones(y.shape[0]) if w is None else np.sqrt(w)
    Aw, yw = A * sw[:, None], y * sw
    norms = np.linalg.norm(Aw, axis=0)
    live = [k for k in range(len(names)) if norms[k] > 1e-12 * max(norms.max(initial=0.0), 1e-300)]
    dropped = {names[k]: "no data excites this term" for k in range(len(names)) if k not in live}
    Al = Aw[:, live]
    th0, *_ = np.linalg.lstsq(Al, yw, rcond=None)
    r0 = yw - Al @ th0
    sigma = float(np.sqrt(r0 @ r0 / max(1, Al.shape[0] - Al.shape[1])))
    P = np.diag([(sigma / prior_std[names[k]]) ** 2 if names[k] in prior_std else 0.0 for k in live])
    G = Al.T @ Al + P
    theta_l = np.linalg.solve(G, Al.T @ yw)
    res_w = yw - Al @ theta_l
    sigma = float(np.sqrt(res_w @ res_w / max(1, Al.shape[0] - Al.shape[1])))
    cov = sigma**2 * np.linalg.inv(G)
    resid = y - A[:, live] @ theta_l
    return LinearFit([names[k] for k in live], theta_l, cov, sigma, int(y.shape[0]),
                     condition_number(Al), dropped, resid)
