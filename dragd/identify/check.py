"""``dragd identify check``: predict the motor current of another log from a params file (seed 001 Table VIII).

Prediction per joint, in amperes, at the log's own rate:

    î = τ(q̃, q̇, q̈)/K_t + I_f(q̇) (+ J_a·q̈/K_t when the params file carries rotor inertia)

with τ the URDF's rigid-body torque (``--terms rigid``, default; ``gravity`` for G(q) only, what the daemon
compensates), I_f dragd's friction law (dragd/control/law.py) with the identified values, and q̃, q̇, q̈ from zero-phase
filtered positions. The measured current is the raw Hall reading (noise included): RMSE, MAE and max error per
joint over the evaluation mask — by default steady motion (the joint slides at |q̇| > v_min, no joint
accelerates, reversals and stiction excluded: the seed validates at constant low speed).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dragd.identify.data import Log, lowpass, prepare, sliding

MASKS = ("steady", "moving", "all")


@dataclass
class CheckResult:
    rmse_A: float | None
    joints: dict[str, dict[str, Any]]
    mask: str
    terms: str
    warnings: list[str] = field(default_factory=list)
    series: dict[str, np.ndarray] = field(default_factory=dict)  # for plots

    def to_json(self) -> dict[str, Any]:
        def r(x: Any) -> Any:
            if isinstance(x, float):
                return None if not math.isfinite(x) else float(f"{x:.6g}")
            if isinstance(x, dict):
                return {k: r(v) for k, v in x.items()}
            return x

        return {"rmse_A": r(self.rmse_A), "joints": r(self.joints), "mask": self.mask, "terms": self.terms,
                "warnings": list(self.warnings)}


def law_from_params(params: Any, names: list[str], cfg: Any | None = None) -> tuple[Any, list[str]]:
    """dragd's LawParams from a params file: overlaid on ``cfg`` when given, else from the file alone."""
    from dragd.config import apply_params
    from dragd.control.params import LawParams

    warnings: list[str] = []
    if cfg is not None:  # the friction *model* (the daemon under-compensates in drag by friction_scale)
        law = LawParams.from_config(apply_params(cfg, params, "params"))
        return law.replace(friction_scale=1.0) if hasattr(law, "friction_scale") else law, warnings
    n = len(names)
    arr = {k: np.zeros(n) for k in ("kt", "cp", "cn", "sp", "sn", "vs", "de", "vp", "vn")}
    arr["kt"][:] = np.nan
    arr["vs"][:] = 0.02
    arr["de"][:] = 2.0
    for i, nm in enumerate(names):
        jp = params.joints.get(nm)
        if jp is None:
            warnings.append(f"{nm}: not in the params file: predicted with K_t unknown")
            continue
        f = jp.friction
        if jp.torque_constant_Nm_per_A is not None:
            arr["kt"][i] = jp.torque_constant_Nm_per_A
        missing = [k for k in ("coulomb_pos_A", "coulomb_neg_A") if getattr(f, k) is None]
        if missing:
            warnings.append(f"{nm}: {', '.join(missing)} null in the params file: taken as 0 (give --config to use "
                            "the configuration's values)")
        arr["cp"][i] = f.coulomb_pos_A or 0.0
        arr["cn"][i] = f.coulomb_neg_A or 0.0
        arr["sp"][i] = f.static_pos_A if f.static_pos_A is not None else arr["cp"][i]
        arr["sn"][i] = f.static_neg_A if f.static_neg_A is not None else arr["cn"][i]
        arr["vs"][i] = f.stribeck_velocity_rad_s or 0.02
        arr["de"][i] = f.stribeck_exponent or 2.0
        vv = f.viscous_A_s_per_rad or 0.0
        arr["vp"][i] = f.viscous_pos_A_s_per_rad if f.viscous_pos_A_s_per_rad is not None else vv
        arr["vn"][i] = f.viscous_neg_A_s_per_rad if f.viscous_neg_A_s_per_rad is not None else vv
    z = np.zeros(n)
    law = LawParams(kt_Nm_per_A=arr["kt"], current_limit_A=np.full(n, np.inf), coulomb_pos_A=arr["cp"],
                    coulomb_neg_A=arr["cn"], static_pos_A=arr["sp"], static_neg_A=arr["sn"],
                    stribeck_velocity_rad_s=arr["vs"], stribeck_exponent=arr["de"], viscous_pos_A_s_per_rad=arr["vp"],
                    viscous_neg_A_s_per_rad=arr["vn"], startup_amp_pos_A=z, startup_amp_neg_A=z,
                    startup_freq_Hz=np.ones(n), rest_threshold_rad_s=np.full(n, 0.01),
                    fade_width_rad_s=np.full(n, 0.02), back_emf_A_s_per_rad=z, damping_A_s_per_rad=z,
                    breakout_slip_rad=z, breakout_hold_s=np.full(n, 0.1), settle_s=np.full(n, 0.1))
    if hasattr(law, "friction_scale"):
        law = law.replace(friction_scale=1.0)
    return law, warnings


def _base_current(rm: Any, params: Any, names: list[str], q: np.ndarray,
                  motion: tuple[np.ndarray, np.ndarray] | None) -> dict[int, np.ndarray]:
    """Joint j's rigid-body current from the params' identified base parameters (current space, amperes):
    Y_j(q, q̇, q̈)[base columns]·β̂_j (``motion``: (q̇, q̈); None: gravity alone). Only joints whose stored base names
    match this robot's."""
    bp = (getattr(params, "notes", {}) or {}).get("base_parameters") or {}
    use = {}
    for j, nm in enumerate(names):
        b = bp.get(nm)
        if b and list(b.get("names", [])) == list(rm.row_full[j].names) and all(v is not None for v in b["current_A"]):
            use[j] = np.asarray(b["current_A"], dtype=float)
    out = {j: np.empty(q.shape[0]) for j in use}
    if not use:
        return out
    for s in range(0, q.shape[0], 5000):
        sl = slice(s, s + 5000)
        Y = rm.torque_regressor(q[sl]) if motion is None else rm.torque_regressor(q[sl], motion[0][sl], motion[1][sl])
        for j, beta in use.items():
            out[j][sl] = Y[:, j, rm.row_full[j].cols] @ beta
    return out


def check(log: Log, robot: Any, params: Any, cfg: Any | None = None, terms: str = "rigid", mask: str = "steady",
          v_min: float = 0.01, a_max: float = 0.3, guard_s: float = 0.3, deriv_cutoff_Hz: float = 20.0,
          keep_series: bool = False, dynamics: str = "base") -> CheckResult:
    """Per-joint RMSE/MAE/max error of the predicted against the measured current (see the module docstring).

    ``dynamics``: ``base`` — joints with identified base parameters (a full-dynamics fit) are predicted with them
    (the fit's own current-space model; no K_t needed), the others with the model's torque / K_t; ``inertials`` —
    every joint with the robot model (with the params' link inertials applied by the caller) / K_t, what the daemon
    compensates; a joint whose K_t is unknown then falls back to its base parameters."""
    from dragd.control.law import Workspace, friction_current
    from dragd.identify.regressors import RegressorModel

    if mask not in MASKS:
        raise ValueError(f"--mask: expected one of {', '.join(MASKS)}, got '{mask}'")
    if terms not in ("rigid", "gravity"):
        raise ValueError(f"--terms: expected rigid or gravity, got '{terms}'")
    names = list(robot.joint_names)
    log.check_robot(names, str(robot.urdf_path or "robot"))
    law, warnings = law_from_params(params, names, cfg)
    warnings = list(log.warnings) + warnings
    p = prepare(log, cutoff_Hz=5.0, deriv_cutoff_Hz=deriv_cutoff_Hz, work_rate_Hz=log.rate_Hz * 1.5)
    if dynamics not in ("base", "inertials"):
        raise ValueError(f"--dynamics: expected base or inertials, got '{dynamics}'")
    rm = RegressorModel(robot)  # the fit's base parameter sets (same samples and seed)
    tau = rm.gravity(p.q) if terms == "gravity" else rm.rnea(p.q, p.dq, p.ddq)
    fr = np.empty_like(p.dq)
    friction_current(p.dq, law, fr, Workspace(p.dq.shape))  # the law's arrays broadcast over the samples
    armature = (getattr(params, "notes", {}) or {}).get("armature_kgm2") or {}
    # load-dependent friction (effects.load_friction_per_Nm, identify fit --method full or dragd gap): the law's
    # w·sign(q̇)·k_L·|G|/K_t with the same sliding weight as the Coulomb level
    k_load = np.array([float(getattr(getattr(params.joints.get(nm), "effects", None), "load_friction_per_Nm", 0.0)
                             or 0.0) if params.joints.get(nm) is not None else 0.0 for nm in names])
    if k_load.any():
        from dragd.control.law import _sliding_weight

        w = np.empty_like(p.dq)
        a_ = np.abs(p.dq)
        _sliding_weight(a_, law, w, a_.copy(), None)
        on = k_load != 0.0  # (a joint without K_t carries no load term: its friction stays as it is)
        fr[:, on] += (w * np.sign(p.dq) * np.abs(rm.gravity(p.q)))[:, on] * (k_load / law.kt_Nm_per_A)[on]
    with np.errstate(invalid="ignore"):
        pred = tau / law.kt_Nm_per_A + fr
    for j, nm in enumerate(names):
        if armature.get(nm) is not None and terms == "rigid" and np.isfinite(law.kt_Nm_per_A[j]):
            pred[:, j] += armature[nm] * p.ddq[:, j] / law.kt_Nm_per_A[j]
    base_i = _base_current(rm, params, names, p.q, None if terms == "gravity" else (p.dq, p.ddq))
    source = {nm: "model torque / K_t" for nm in names}
    for j, cur in base_i.items():
        if dynamics == "base" or not np.isfinite(law.kt_Nm_per_A[j]):
            pred[:, j] = cur + fr[:, j]
            source[names[j]] = "identified base parameters (current space)"
    guard = int(round(guard_s * p.fs))
    ddqH = p.regfilter(p.ddq)
    calm = np.all(np.abs(ddqH) < a_max, axis=1)
    calm = sliding(calm[:, None].astype(float), 0.5, guard)[:, 0]
    meas = p.i
    win = 20  # seed 001 §4.3: a window filter of length 20 on the measured current
    kern = np.ones(win) / win
    joints: dict[str, dict[str, Any]] = {}
    sq, cnt = 0.0, 0
    masks = np.zeros_like(meas, dtype=bool)
    for j, nm in enumerate(names):
        if mask == "all":
            m = np.ones(meas.shape[0], dtype=bool)
        elif mask == "moving":
            m = sliding(p.dq[:, j:j + 1], v_min, guard)[:, 0]
        else:
            m = sliding(p.dq[:, j:j + 1], v_min, guard)[:, 0] & calm
        if not np.all(np.isfinite(pred[:, j])):
            joints[nm] = {"rmse_A": None, "mae_A": None, "max_A": None, "samples": 0,
                          "reason": "K_t unknown (null in the params file and no --config) and no identified base "
                                    "parameters (fit with --method full)"}
            continue
        if m.sum() < 10:
            joints[nm] = {"rmse_A": None, "mae_A": None, "max_A": None, "samples": int(m.sum()),
                          "reason": f"{nm} has no {mask} motion in this log"}
            continue
        masks[:, j] = m
        e = meas[m, j] - pred[m, j]
        filt = np.convolve(meas[:, j], kern, mode="same")
        ef = filt[m] - pred[m, j]
        hp = meas[:, j] - lowpass(meas[:, j], 0.1 * p.fs, p.fs)
        noise = float(np.std(hp) / math.sqrt(0.8))
        joints[nm] = {"rmse_A": float(np.sqrt(np.mean(e * e))), "mae_A": float(np.mean(np.abs(e))),
                      "max_A": float(np.max(np.abs(e))), "bias_A": float(np.mean(e)), "samples": int(m.sum()),
                      "rmse_window20_A": float(np.sqrt(np.mean(ef * ef))), "mae_window20_A": float(np.mean(np.abs(ef))),
                      "max_window20_A": float(np.max(np.abs(ef))), "noise_estimate_A": noise,
                      "model": source[nm]}
        sq += float(e @ e)
        cnt += e.size
    res = CheckResult(math.sqrt(sq / cnt) if cnt else None, joints, mask, terms, warnings)
    if keep_series:
        res.series = {"t": p.t, "measured": meas, "predicted": pred, "mask": masks, "dq": p.dq}
    return res


def plot(res: CheckResult, names: list[str], out_dir: str | Path, max_points: int = 20000) -> list[str]:
    """PNG per joint: measured (raw and window-filtered) and predicted current, the evaluation mask, residual."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    s = res.series
    t = s["t"]
    step = max(1, t.shape[0] // max_points)
    files = []
    for j, nm in enumerate(names):
        meas, pred, m = s["measured"][:, j], s["predicted"][:, j], s["mask"][:, j]
        filt = np.convolve(meas, np.ones(20) / 20, mode="same")
        fig, ax = plt.subplots(2, 1, figsize=(12, 6), sharex=True, gridspec_kw={"height_ratios": [3, 1]})
        ax[0].plot(t[::step], meas[::step], color="0.75", lw=0.4, label="measured (Hall)")
        ax[0].plot(t[::step], filt[::step], color="C0", lw=0.8, label="measured, 20-sample window")
        ax[0].plot(t[::step], pred[::step], color="C3", lw=0.8, label="predicted")
        ax[0].fill_between(t[::step], 0, 1, where=m[::step], transform=ax[0].get_xaxis_transform(), color="C2",
                           alpha=0.08, label=f"evaluated ({res.mask})")
        st = res.joints.get(nm, {})
        title = (f"{nm}: RMSE {st['rmse_A'] * 1e3:.1f} mA, MAE {st['mae_A'] * 1e3:.1f} mA, "
                 f"max {st['max_A'] * 1e3:.1f} mA" if st.get("rmse_A") is not None
                 else f"{nm}: {st.get('reason', 'not evaluated')}")
        ax[0].set_title(title)
        ax[0].set_ylabel("current [A]")
        ax[0].legend(loc="upper right", fontsize=8)
        r = np.where(m, meas - pred, np.nan)
        ax[1].plot(t[::step], r[::step] * 1e3, color="C1", lw=0.4)
        ax[1].set_ylabel("error [mA]")
        ax[1].set_xlabel("t [s]")
        fig.tight_layout()
        f = out / f"{nm}.png"
        fig.savefig(f, dpi=90)
        plt.close(fig)
        files.append(str(f))
    return files


def check_params(log: Any, model: Any, params: Any, params_name: str = "params", **kw: Any) -> Any:
    """``identify check``'s pipeline: the params' link inertials applied to ``model`` (the identified arm,
    docs/MODEL.md), then :func:`dragd.identify.check.check` (``kw``: cfg, terms, mask, keep_series, dynamics).
    Raises ValueError for inertials that do not fit the model."""
    if params.inertials:
        model.apply_inertials(params.inertials, params_name)
    return check(log, model, params, **kw)
