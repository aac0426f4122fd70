"""The baseline: the model as given (a params file over the configuration) or seed 000's structure fitted on the data.

Given model, per joint j (amperes, work rate):

    î_j = G_j(q; payload)/K_t + I_f(q̇) [+ (M(q)q̈ + C q̇)_j/K_t + J_a·q̈_j/K_t when it has ``effects.armature_kgm2``]
          [+ (M(q)q̈ + C q̇)_j/K_t when the params carry identified ``inertials``: the identified arm's dynamics]
          + the params' effects (position-periodic, load friction, offset, drift × I_f, back-EMF knee term)
          + a play's current (``effects.backlash_*``: the rotor simulated along the output, on the rest of the model)

with I_f dragd's friction law (dragd/control/law.py, ``friction_scale`` 1: the friction *model*, not the drag setting).
Seed 000 (no ``--model``): î_j = a_j·G_j(q) + F_+·[q̇ > 0] + F_−·[q̇ < 0] with a_j = 1/K_t (where the data
determine it: relative standard deviation ≤ 5 %, else the configuration's K_t and a_j·G_j fixed) and the two levels
fitted on the data (nothing else) — they stay free while effects are added.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from dragd.gap.context import GapData
from dragd.gap.effects import CATALOGUE, Backlash, ModelInfo, PayloadMass, TemperatureDrift, weight


@dataclass
class Baseline:
    """The fixed part of the model, and (seed 000) the free base columns per joint."""

    kind: str  # "given" or "seed000"
    fixed: np.ndarray  # (T, n) A
    free: list[np.ndarray | None]  # per joint (T, k) unfiltered free columns, or None
    free_names: list[list[str]]
    kt: np.ndarray  # (n,) N·m/A used to turn currents into torques
    kt_known: np.ndarray  # (n,) bool: from the params file / determined by the data
    friction_A: np.ndarray  # (T, n) friction current of the model
    has_inertia: np.ndarray  # (n,) bool
    coulomb_A: list[tuple[float, float]]
    params: dict[str, Any]  # the params file (mapping) the extended model is written into
    armature_kgm2: np.ndarray | None = None  # (n,) the model's rotor inertia at each joint (0: not known)
    has_backlash: np.ndarray | None = None  # (n,) bool: the model predicts a play on the joint
    torque_A: np.ndarray | None = None  # (T, n) the part of ``fixed`` that is a joint torque / K_t
    viscous_A: np.ndarray | None = None  # (T, n) the viscous part of friction_A

    def info(self) -> ModelInfo:
        return ModelInfo(self.kt, self.friction_A, self.has_inertia, self.coulomb_A, self.armature_kgm2,
                         self.has_backlash, self.torque_A, self.viscous_A)


def given(d: GapData, params: Any, cfg: Any) -> Baseline:
    """The model of a params file overlaid on the configuration ``cfg`` (K_t/friction the file leaves null)."""
    from dragd.config import apply_params
    from dragd.control.law import Workspace, friction_current, viscous_current
    from dragd.identify.check import law_from_params

    law, _ = law_from_params(params, d.names, cfg)
    cfg2 = apply_params(cfg, params, "params")
    kt = np.array([j.kt_Nm_per_A for j in cfg2.joints])
    fr = np.empty_like(d.p.dq)
    friction_current(d.p.dq, law, fr, Workspace(d.p.dq.shape))
    visc = viscous_current(d.p.dq, law, d.p.dq >= 0.0, np.empty_like(d.p.dq))
    pf = params.model_dump(mode="json")
    pred = d.G / kt + fr
    torque = d.G / kt  # what a K_t error scales (torque_constant's column)
    has_inertia = np.zeros(d.n, dtype=bool)
    for j, nm in enumerate(d.names):
        jp = pf["joints"].get(nm, {})
        for name, eff in CATALOGUE.items():
            if isinstance(eff, TemperatureDrift):
                x = eff.current(d, jp, fr[:, j], visc[:, j])
                if x is not None:
                    pred[:, j] += x
                continue
            x = eff.predict(d, j, jp, kt[j])
            if x is not None:
                pred[:, j] += x
                has_inertia[j] |= name == "inertia"
                if name in ("inertia", "load_dependent_friction"):
                    torque[:, j] += x
    if pf.get("inertials"):  # an identified arm (identify fit --method full): its dynamics are part of the model
        for j in range(d.n):
            if not has_inertia[j]:
                pred[:, j] += d.tau_dyn[:, j] / kt[j]
                torque[:, j] += d.tau_dyn[:, j] / kt[j]
                has_inertia[j] = True
    pl = PayloadMass.predict_all(d, pf.get("payload"), kt)
    if pl is not None:
        pred += pl
        torque += pl
    coul = [(float(law.coulomb_pos_A[j]), float(law.coulomb_neg_A[j])) for j in range(d.n)]
    armature = np.array([float((pf["joints"].get(nm, {}).get("effects") or {}).get("armature_kgm2") or 0.0)
                         for nm in d.names])
    base = Baseline("given", pred, [None] * d.n, [[] for _ in range(d.n)], kt, np.ones(d.n, dtype=bool), fr,
                    has_inertia, coul, pf, armature, torque_A=torque, viscous_A=visc if np.any(visc) else None)
    backlash = CATALOGUE["backlash"]
    assert isinstance(backlash, Backlash)
    base.has_backlash = np.zeros(d.n, dtype=bool)
    for j, nm in enumerate(d.names):  # a play acts on the rest of the model's current: added last
        x = backlash.predict_on(d, j, pf["joints"].get(nm, {}), float(kt[j]), pred[:, j], base.info())
        if x is not None:
            pred[:, j] += x
            base.has_backlash[j] = True
    return base


def seed000(d: GapData, cfg: Any) -> Baseline:
    """Seed 000's structure: a·G + direction levels per joint, free (fitted with the effects on the data)."""
    free: list[np.ndarray | None] = []
    names: list[list[str]] = []
    for j in range(d.n):
        w = weight(d.p.dq[:, j])
        cols = [w * (d.p.dq[:, j] > 0), w * (d.p.dq[:, j] < 0)]
        nm = ["coulomb_pos_A", "coulomb_neg_A"]
        if _kt_determined(d, j, np.column_stack([d.G[:, j]] + cols), float(cfg.joints[j].kt_Nm_per_A)):
            cols.insert(0, d.G[:, j])
            nm.insert(0, "inv_kt")
        free.append(np.column_stack(cols))
        names.append(nm)
    kt = np.array([jc.kt_Nm_per_A for jc in cfg.joints])
    pf = {"version": 1, "method": "gap", "robot": None, "joints": {nm: {} for nm in d.names}}
    fixed = np.zeros((d.T, d.n))
    for j in range(d.n):  # gravity over the configuration's K_t where the data do not determine it
        if names[j][0] != "inv_kt":
            fixed[:, j] = d.G[:, j] / kt[j]
    return Baseline("seed000", fixed, free, names, kt, np.zeros(d.n, dtype=bool),
                    np.zeros((d.T, d.n)), np.zeros(d.n, dtype=bool), [(0.0, 0.0)] * d.n, pf, torque_A=d.G / kt)


KT_REL_STD_MAX = 0.05  # seed 000: 1/K_t is fitted where the data determine it to 5 % (relative standard deviation)


def _kt_determined(d: GapData, j: int, X: np.ndarray, kt_cfg: float) -> bool:
    """Whether the log determines joint j's 1/K_t (the first column of X, gravity, beside the direction levels): the
    standard deviation of its least-squares estimate on the filtered fit rows (residual RMS × √(XᵀX)⁻¹₀₀), relative
    to the configuration's 1/K_t, ≤ KT_REL_STD_MAX — no fixed N·m range of gravity."""
    r = d.fit_rows(j)
    if r.size < 30 or not np.any(np.ptp(d.G[:, j])):
        return False
    XH = d.H(X)[r]
    y = d.iH[r, j]
    th, *_ = np.linalg.lstsq(XH, y, rcond=None)
    e = y - XH @ th
    s2 = float(e @ e) / max(r.size - X.shape[1], 1)
    try:
        var = s2 * float(np.linalg.inv(XH.T @ XH)[0, 0])
    except np.linalg.LinAlgError:
        return False
    return bool(th[0] > 0 and np.sqrt(max(var, 0.0)) * kt_cfg <= KT_REL_STD_MAX)


def update_seed000(b: Baseline, d: GapData, j: int, theta: np.ndarray) -> None:
    """After a fit: the free base coefficients of joint j → K_t (when determined), levels, friction current."""
    names = b.free_names[j]
    th = dict(zip(names, theta[:len(names)], strict=True))
    a = th.get("inv_kt")
    if a is not None and a > 0:
        b.kt[j] = 1.0 / a
        b.kt_known[j] = True
    cp, cn = float(th["coulomb_pos_A"]), float(th["coulomb_neg_A"])
    b.coulomb_A[j] = (cp, cn)
    X = b.free[j]
    if X is None:
        raise ValueError(f"update_seed000: joint {j} has no free base columns (a '{b.kind}' baseline)")
    k = len(names)
    b.friction_A[:, j] = X[:, k - 2] * cp + X[:, k - 1] * cn
