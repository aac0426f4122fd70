"""The model-gap workflow end to end: baseline → localise → name (forward selection) → add → show (docs/GAP.md)."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from dragd.gap import baseline as B
from dragd.gap.context import GapData, load_gap_data
from dragd.gap.effects import CATALOGUE
from dragd.gap.localise import localise
from dragd.gap.select import Selector
from dragd.identify.data import Log


@dataclass
class GapResult:
    data: GapData
    baseline_kind: str
    baseline_rmse: tuple[np.ndarray, float]
    final_rmse: tuple[np.ndarray, float]
    effects: list[dict[str, Any]]
    params: Any  # dragd.config.ParamsFile of the extended model
    before: np.ndarray  # (T, n) work-rate prediction of the baseline
    after: np.ndarray
    localisation: dict[str, Any]
    localisation_after: dict[str, Any]
    steps: list[Any]
    elapsed_s: float
    warnings: list[str] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        """Exactly: baseline {rmse_A, joints}, effects [{effect, joints, params, rmse_A, ambiguous_with}], final
        {rmse_A}; ``ambiguous_with``: [{effect, joints}] that explain those joints as well (docs/GAP.md §4)."""
        names = self.data.names
        per0, all0 = self.baseline_rmse
        return {
            "baseline": {"rmse_A": _f(all0), "joints": {nm: {"rmse_A": _f(per0[j]), "noise_A": _f(self.data.noise_A[j])}
                                                        for j, nm in enumerate(names)}},
            "effects": [{k: e[k] for k in ("effect", "joints", "params", "rmse_A", "ambiguous_with")}
                        for e in self.effects],
            "final": {"rmse_A": _f(self.final_rmse[1])},
        }

    def details(self) -> dict[str, Any]:
        """Everything else: baseline kind, noise, per-joint final RMSE, the selection's evidence, localisation."""
        names = self.data.names
        return {"baseline_kind": self.baseline_kind, "noise_A": _f(float(np.sqrt(np.mean(self.data.noise_A ** 2)))),
                "final_joints": {nm: {"rmse_A": _f(self.final_rmse[0][j])} for j, nm in enumerate(names)},
                "evidence": [{"effect": e["effect"], "evidence": e["evidence"],
                              "ambiguity": e["ambiguity_evidence"]} for e in self.effects],
                "localisation_before": self.localisation, "localisation_after": self.localisation_after,
                "elapsed_s": round(self.elapsed_s, 3), "warnings": list(self.warnings)}

    @property
    def rmse_ratio(self) -> float:
        """Final RMSE / the current noise (all joints)."""
        return float(self.final_rmse[1] / np.sqrt(np.mean(self.data.noise_A ** 2)))


def _f(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else float(f"{x:.6g}")


def _round(x: Any) -> Any:
    if isinstance(x, float):
        return float(f"{x:.6g}")
    if isinstance(x, dict):
        return {k: _round(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_round(v) for v in x]
    return x


def analyse(log: Log, robot: Any, cfg: Any, params: Any | None = None,
            effects: tuple[str, ...] | None = None) -> GapResult:
    """Run the workflow on a loaded log. ``params``: the model as given (ParamsFile), else seed 000 fitted on it."""
    from dragd.config import ConfigError, ParamsFile

    t0 = time.perf_counter()
    d = load_gap_data(log, robot)
    base = B.given(d, params, cfg) if params is not None else B.seed000(d, cfg)
    sel = Selector(d, base, effects)
    before = sel.snapshots[0]
    loc0 = localise(d, before)
    sel.run()
    after = sel.predict()
    out_effects = []
    eparams = sel.effect_params()
    for k, (st, (name, joints, prm)) in enumerate(zip(sel.steps, eparams, strict=True)):
        out_effects.append({"effect": name, "joints": joints, "params": _round(prm),
                            "rmse_A": float(f"{d.raw_rmse(sel.snapshots[k + 1])[1]:.6g}"),
                            "ambiguous_with": [{"effect": a, "joints": sorted(v, key=d.names.index)}
                                               for a, v in st.ambiguous.items()],
                            "evidence": _round(st.gain), "ambiguity_evidence": _round(st.ambiguous)})
    # the extended model as a params file
    pf = base.params
    if base.kind == "seed000":
        pf["robot"] = str(robot.urdf_path) if robot.urdf_path else None
        for j, nm in enumerate(d.names):
            jp = pf["joints"].setdefault(nm, {})
            if base.kt_known[j]:
                jp["torque_constant_Nm_per_A"] = float(base.kt[j])
            cp, cn = base.coulomb_A[j]
            jp.setdefault("friction", {}).update({"coulomb_pos_A": max(cp, 0.0), "coulomb_neg_A": min(cn, 0.0)})
    for name, _joints, prm in eparams:
        eff = CATALOGUE[name]
        if eff.shared:
            eff.write(pf, "", prm)
        else:
            for nm, pj in prm.items():
                eff.write(pf, nm, pj)
    pf.setdefault("notes", {})["gap"] = {"baseline": base.kind, "effects": [e["effect"] for e in out_effects],
                                         "log": log.path}
    try:
        params_out = ParamsFile.model_validate(pf)
    except Exception as exc:  # a fitted value outside the schema: say which
        raise ConfigError(f"gap: the extended model does not validate as a params file: {exc}") from None
    res = GapResult(d, base.kind, d.raw_rmse(before), d.raw_rmse(after), out_effects, params_out, before, after,
                    loc0, localise(d, after), sel.steps, time.perf_counter() - t0, list(d.warnings))
    return res
