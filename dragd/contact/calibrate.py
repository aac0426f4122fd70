"""``dragd contact calibrate``: the detector's bands from free-motion logs (docs/CONTACT.md).

The detector runs over every log with unbounded bands (it judges nothing, its states and residuals are what the cycle
would have), then per joint:

* **moving**: the band base + slow·L + speed·V + accel·A (dragd/control/contact.py) that covers ``margin``·|d| at
  every moving sample with the least total band — a linear programme (coefficients ≥ 0; scipy's HiGHS);
* **settling**: ``margin`` × the largest |d| of a joint that has just stopped, and at least ``margin`` × the
  identified static friction level (a stuck joint can hold anything within it, whether these logs show it or not);
* **held**: ``margin`` × the largest departure from the latched baseline of a joint at rest.

``margin`` 1.25 leaves every calibration sample at ≤ 0.8 of its band. Left out: the first ``arm_s`` of each log (the
observer starting) and each log's last stop (``END_STOP_S`` around the last sample where a joint moves): a
controller's own end-of-program stop, which on the dataset's UR runs is abrupt (the velocity jumps by up to
0.16 rad/s within one 10 ms sample, a torque pulse the 100 Hz current sample misses). The daemon suspends the
detector while it commands a stop itself.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from dragd.control.contact import HELD, MOVING, SETTLING, ContactBands, ContactSettings

MARGIN = 1.25
END_STOP_S = (0.5, 1.0)  # left out before and after a log's last motion sample


class CalibrationError(ValueError):
    """Logs that cannot set a band (the message names the joint and what is missing)."""


@dataclass
class Calibration:
    bands: ContactBands
    report: dict[str, Any] = field(default_factory=dict)


def usable(run: Any, settings: ContactSettings, rest_speed: float | None = None) -> tuple[np.ndarray, list[float]]:
    """Samples of a run calibration may use: after arming, outside the log's last stop; (mask, [from, to] left out)."""
    t = run.t - run.t[0]
    ok = t >= settings.arm_s
    moving = np.flatnonzero((run.speed >= (rest_speed or settings.rest_speed_rad_s)).any(axis=1))
    cut: list[float] = []
    if moving.size:
        te = float(t[moving[-1]])
        cut = [max(te - END_STOP_S[0], 0.0), te + END_STOP_S[1]]
        ok &= ~((t >= cut[0]) & (t <= cut[1]))
    return ok, cut


def static_levels(model: Any) -> np.ndarray:
    """Per joint the largest identified static (else Coulomb) friction level [A]."""
    law = model.law
    return np.max(np.abs(np.vstack([law.static_pos_A, law.static_neg_A, law.coulomb_pos_A, law.coulomb_neg_A])),
                  axis=0)


FEATURES = ("slow", "speed", "accel")


def calibrate(model: Any, runs: list[tuple[str, Any]], settings: ContactSettings, margin: float = MARGIN,
              slow_speed_rad_s: float = 0.1, features: tuple[str, ...] = FEATURES) -> Calibration:
    """Bands from detector runs over free-motion logs (``run_log`` with unbounded bands), per joint."""
    from scipy.optimize import linprog

    names = model.names
    n = len(names)
    masks = {name: usable(run, settings) for name, run in runs}
    out = {k: np.zeros(n) for k in ("base", "slow", "speed", "accel", "settling", "held", "held_moving")}
    rep: dict[str, Any] = {"margin": margin, "logs": {name: {"samples": int(run.t.shape[0]),
                                                             "left_out_s": masks[name][1]} for name, run in runs},
                           "joints": {}}
    floor = static_levels(model) * margin
    for j, nm in enumerate(names):
        X, y, settle, held = [], [], [], []
        for name, run in runs:
            ok = masks[name][0]
            st = run.state[:, j]
            sel = ok & (st == MOVING)
            X.append(np.column_stack([np.ones(sel.sum()), run.features[sel, j, :3]]))
            y.append(margin * np.abs(run.d_A[sel, j]))
            settle.append(np.abs(run.d_A[ok & (st == SETTLING), j]))
            hs = ok & (st == HELD)
            held.append(np.column_stack([np.abs(run.d_A[hs, j]), run.features[hs, j, 3]]))
        Xa, ya = np.concatenate(X), np.concatenate(y)
        jr: dict[str, Any] = {"moving_samples": int(ya.size)}
        if ya.size < 50:
            raise CalibrationError(f"{nm}: moves in {ya.size} usable samples of the logs given (need ≥ 50): "
                                   "calibrate with free-motion logs in which every joint moves")
        # least total band over the samples, covering margin·|d| everywhere
        use = [0] + [1 + FEATURES.index(f) for f in features]
        bounds = [(0, None) if k in use else (0, 0) for k in range(Xa.shape[1])]
        res = linprog(Xa.sum(axis=0), A_ub=-Xa, b_ub=-ya, bounds=bounds, method="highs")
        if res.status != 0:
            raise CalibrationError(f"{nm}: the moving band's linear programme failed: {res.message}")
        c = np.maximum(res.x, 0.0)
        out["base"][j], out["slow"][j], out["speed"][j], out["accel"][j] = c
        sa, ha = np.concatenate(settle), np.concatenate(held)
        smax = float(sa.max()) if sa.size else 0.0
        out["settling"][j] = max(margin * smax, float(floor[j]))
        if not ha.size:
            raise CalibrationError(f"{nm}: never held at rest for {settings.settle_s:g} s in the logs given: calibrate "
                                   "with logs that rest (the identification runs start and end at rest, p1..p10 hold)")
        hmax = float(ha[:, 0].max())
        # held: held_A + held_moving_A·(the arm moves, filtered), the least total band covering margin·|d|
        Xh = np.column_stack([np.ones(ha.shape[0]), ha[:, 1]])
        rh = linprog(Xh.sum(axis=0), A_ub=-Xh, b_ub=-margin * ha[:, 0], bounds=[(0, None)] * 2, method="highs")
        if rh.status != 0:
            raise CalibrationError(f"{nm}: the held band's linear programme failed: {rh.message}")
        out["held"][j], out["held_moving"][j] = np.maximum(rh.x, 0.0)
        band = Xa @ c
        jr.update({"moving_max_ratio": round(float(np.max(ya / margin / band)), 3),
                   "moving_band_A": {"median": round(float(np.median(band)), 3), "max": round(float(band.max()), 3)},
                   "settling_samples": int(sa.size), "settling_max_A": round(smax, 3),
                   "settling_from": "static friction" if floor[j] > margin * smax else "data",
                   "held_samples": int(ha.size), "held_max_A": round(hmax, 3)})
        rep["joints"][nm] = jr
    bands = ContactBands(out["base"], out["slow"], out["speed"], out["accel"], np.full(n, slow_speed_rad_s),
                         out["settling"], out["held"], out["held_moving"])
    return Calibration(bands, rep)


# ------------------------------------------------------------------------------------------ the params file's block

BAND_FIELDS = ("base_A", "slow_A", "speed_A_s_per_rad", "accel_A_s2_per_rad", "slow_speed_rad_s", "settling_A",
               "held_A", "held_moving_A")


def to_params(cal: Calibration, names: list[str], settings: ContactSettings) -> Any:
    """The params file's ``contact`` block of a calibration."""
    from dragd.config import ContactParams

    b = cal.bands
    joints = {nm: {f: round(float(getattr(b, f)[j]), 6) for f in BAND_FIELDS} for j, nm in enumerate(names)}
    return ContactParams.model_validate({"observer_gain_per_s": settings.observer_gain_per_s,
                                         "margin": cal.report.get("margin", MARGIN), "joints": joints,
                                         "calibration": cal.report})


def from_params(params: Any, names: list[str], source: str = "params") -> tuple[ContactBands, float]:
    """(bands, the observer gain they were calibrated for) from a params file's ``contact`` block."""
    c = getattr(params, "contact", None)
    if c is None:
        raise CalibrationError(f"{source}: no contact bands: run dragd contact calibrate --params {source} --log "
                               "FREE.csv [--log ...] --out P2 on free-motion logs of this arm first")
    missing = [nm for nm in names if nm not in c.joints]
    if missing:
        raise CalibrationError(f"{source}: contact.joints: no bands for {', '.join(missing)} (expected every joint "
                               f"of the robot: {', '.join(names)})")
    rows = {f: np.array([float(getattr(c.joints[nm], f)) for nm in names]) for f in BAND_FIELDS}
    return ContactBands(**rows), float(c.observer_gain_per_s)
