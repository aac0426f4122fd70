"""``dragd identify fit``'s pipeline, for the CLI and the benchmarks: the fit, its params file, the link inertials."""

from __future__ import annotations

from typing import Any

from dragd.identify.inertials import inertials_from_fit
from dragd.identify.methods import identify
from dragd.identify.regressors import RegressorModel
from dragd.identify.results import _jsonable


def fit_params(log: Any, model: Any, method: str, opts: Any, cfg_kt: list[float] | None = None
               ) -> tuple[Any, Any, dict[str, Any] | None]:
    """``identify fit``'s pipeline on a loaded (or stacked) log: the fit, its params file content and — for a
    full-dynamics fit — the link inertials mapped from the identified base parameters (None otherwise)."""
    res = identify(log, model, method, opts)
    params = res.to_params()
    mapped = None
    if res.notes.get("base_parameters"):  # full dynamics (or auto that chose it): the identified arm is the model
        mapped = inertials_from_fit(res, model, RegressorModel(model), cfg_kt)
        if mapped is not None:
            pd = params.model_dump(mode="python")
            pd["inertials"] = mapped["inertials"]
            pd["notes"] = {**pd["notes"], "inertials_mapping": _jsonable(mapped["mapping"])}
            params = type(params).model_validate(pd)
    return res, params, mapped
