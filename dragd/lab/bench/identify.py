"""Identification benchmarks (registered with ``dragd bench``): speed and accuracy against the simulator's truth.

dragd never imports ``sim``: the truth and the logs come through a process boundary —
``python -m sim truth --json`` (K_t, friction in amperes) and ``python -m sim log --plan P --out F --seed N`` (the
offline, faster-than-real-time CSP run of a plan). Logs are cached under ``$DRAGD_BENCH_CACHE`` (default
``~/.cache/dragd/identify``), keyed by the plan, the sim's truth/source and the seed: the first run generates
them (~3 min), later runs only fit.

- training log: 10 min of a 6-joint 1 kHz daemon-format MCAP (synchronous + symmetric + friction passes, Hall noise
  20 mA, quantisation) fitted with ``--method auto``;
- held-out log: another symmetric plan (other poses, other seed), all joints together at constant speed —
  predicted with the identified params (seed 001 Table VIII form).
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from dragd.lab.bench import benchmark
from dragd.resources import config_path


def _sim_dir() -> Path:
    """The installed simulator's folder (a lab tool: dragd itself never imports sim)."""
    spec = importlib.util.find_spec("sim")
    if spec is None or spec.origin is None:
        raise ImportError("dragd bench: the simulator package 'sim' is not installed (pip install -e . installs it)")
    return Path(spec.origin).parent


SIM_DIR = _sim_dir()
_CACHE: dict[str, Any] = {}
START = (0.0, -0.6, 1.2, -0.6, 1.5708, 0.0)  # the sim's initial pose


def _cache_dir() -> Path:
    d = Path(os.environ.get("DRAGD_BENCH_CACHE", Path.home() / ".cache" / "dragd" / "identify"))
    d.mkdir(parents=True, exist_ok=True)
    return d


def _sim(*args: str, timeout: float = 1800.0) -> str:
    proc = subprocess.run([sys.executable, "-m", "sim", *args], capture_output=True, text=True, timeout=timeout)
    if proc.returncode != 0:
        raise RuntimeError(f"python -m sim {' '.join(args)} failed ({proc.returncode}):\n{proc.stderr[-2000:]}")
    return proc.stdout


def _source_key() -> str:
    h = hashlib.sha256()
    for f in sorted(SIM_DIR.glob("*.py")) + sorted((SIM_DIR / "config").glob("*.yaml")) + [config_path()]:
        h.update(f.read_bytes())
    return h.hexdigest()[:12]


def _plans() -> tuple[Any, Any]:
    from dragd.config import load_config
    from dragd.identify import excitation as E
    from dragd.model import RobotModel

    model = RobotModel.from_urdf("seed_cobot")
    lim = E.Limits.from_model(model, load_config(config_path()))
    q0 = np.array(START)
    b = E.PlanBuilder(q0, lim)
    E.add_synchronous(b, list(range(6)), speeds=(0.15, 0.45), cycles=1)
    E.add_symmetric(b, passes=4, rng=np.random.default_rng(5))
    E.add_friction(b, list(range(6)), speeds=(0.006, 0.03, 0.1, 0.3), cruise_s=1.5)
    train = b.build("bench-train")
    v = E.PlanBuilder(q0, lim)
    E.add_symmetric(v, passes=6, speed=0.25, rng=np.random.default_rng(17))
    valid = v.build("bench-validation")
    return train, valid


def _interpolate() -> bool:
    """``DRAGD_BENCH_CSP_INTERPOLATE=1``: logs from drives that interpolate CSP targets (see docs/IDENTIFICATION.md)."""
    return os.environ.get("DRAGD_BENCH_CSP_INTERPOLATE", "") not in ("", "0")


def _log(plan: Any, seed: int, seconds: float | None) -> Path:
    interp = _interpolate()
    h = hashlib.sha256(plan.q_rad.tobytes() + plan.t_s.tobytes()
                       + f"{seed}:{seconds}:{interp}:{_source_key()}".encode())
    key = h.hexdigest()[:16]
    d = _cache_dir()
    out = d / f"{plan.name}-{key}.mcap"
    if not out.exists():
        for old in sorted(d.glob(f"{plan.name}-*"), key=lambda f: f.stat().st_mtime)[:-6]:
            old.unlink(missing_ok=True)  # keep the cache small: the last few generations per plan
        pf = d / f"{plan.name}-{key}.npz"
        plan.save(pf)
        tmp = d / f"{plan.name}-{key}.partial.mcap"
        args = ["log", "--plan", str(pf), "--out", str(tmp), "--seed", str(seed)]
        if seconds is not None:
            args += ["--seconds", str(seconds)]
        if interp:
            args.append("--csp-interpolate")
        _sim(*args)
        tmp.rename(out)
    return out


def _truth() -> dict[str, Any]:
    if "truth" not in _CACHE:
        _CACHE["truth"] = json.loads(_sim("truth", "--json"))
    return _CACHE["truth"]


def _run() -> dict[str, Any]:
    """Generate/cached logs, fit the training log (timed), check the held-out log; memoised per process."""
    if "run" in _CACHE:
        return _CACHE["run"]
    from dragd.config import ParamsFile, load_config
    from dragd.identify.check import check
    from dragd.identify.data import load_log
    from dragd.identify.methods import identify
    from dragd.model import RobotModel

    train, valid = _plans()
    train_log = _log(train, seed=101, seconds=600.0)
    valid_log = _log(valid, seed=202, seconds=None)
    robot = RobotModel.from_urdf("seed_cobot")
    t0 = time.perf_counter()
    res = identify(load_log(train_log), robot, "auto")
    fit_s = time.perf_counter() - t0
    params = res.to_params()
    truth = _truth()
    vlog = load_log(valid_log)
    cfg = load_config(config_path())  # what the daemon overlays the params on
    chk = check(vlog, robot, params, cfg=cfg)
    # the floor: the same prediction with the true parameters (Hall noise + quantisation + the drives' own
    # high-frequency current ripple — what no K_t/friction model can predict)
    tp = ParamsFile.model_validate({"joints": {
        nm: {"torque_constant_Nm_per_A": j["torque_constant_Nm_per_A"],
             "friction": {k: j["friction"][k] for k in ("coulomb_pos_A", "coulomb_neg_A", "static_pos_A",
                                                        "static_neg_A", "stribeck_velocity_rad_s", "stribeck_exponent",
                                                        "viscous_pos_A_s_per_rad", "viscous_neg_A_s_per_rad")}}
        for nm, j in truth["joints"].items()}})
    floor = check(vlog, robot, tp, cfg=cfg)
    _CACHE["run"] = {"fit_s": fit_s, "result": res, "check": chk, "floor": floor, "truth": truth,
                     "train_log": str(train_log), "valid_log": str(valid_log)}
    return _CACHE["run"]


def _errors(key: str) -> list[tuple[str, float]]:
    r = _run()
    out = []
    for jr in r["result"].joints:
        t = r["truth"]["joints"][jr.name]
        if key == "kt":
            if jr.torque_constant_Nm_per_A is not None:
                ref = t["torque_constant_Nm_per_A"]
                out.append((jr.name, 100 * (jr.torque_constant_Nm_per_A - ref) / ref))
            continue
        pairs = {"coulomb": (("coulomb_pos_A", "coulomb_pos_A"), ("coulomb_neg_A", "coulomb_neg_A")),
                 "viscous": (("viscous_pos_A_s_per_rad", "viscous_pos_A_s_per_rad"),
                             ("viscous_neg_A_s_per_rad", "viscous_neg_A_s_per_rad"))}[key]
        for mine, ref_key in pairs:
            v = jr.friction.get(mine)
            if v is not None:
                ref = t["friction"][ref_key]
                out.append((f"{jr.name}.{mine}", 100 * (v - ref) / abs(ref)))
    return out


def details() -> dict[str, Any]:
    """Everything the benchmarks measured (for docs/IDENTIFICATION.md)."""
    r = _run()
    return {"fit_s": r["fit_s"], "kt_error_pct": _errors("kt"), "coulomb_error_pct": _errors("coulomb"),
            "viscous_error_pct": _errors("viscous"), "check": r["check"].to_json(), "floor": r["floor"].to_json(),
            "train_log": r["train_log"], "valid_log": r["valid_log"]}


def _worst(kind: str) -> float:
    """Largest |error| [%] of one parameter kind against the sim truth (NaN: none determined)."""
    e = _errors(kind)
    return max(abs(x) for _, x in e) if e else float("nan")


@benchmark("identify_10min_s", "s")
def identify_10min_s(opts: dict) -> float:
    """Wall time to load and fit (auto) a 10 min, 6-joint, 1 kHz MCAP log (generated once, cached)."""
    return float(_run()["fit_s"])


@benchmark("identify_kt_error_pct", "%")
def identify_kt_error_pct(opts: dict) -> float:
    """Largest |K_t error| against the sim truth over the joints whose K_t the data determines (target ≤ 1 %)."""
    return _worst("kt")


@benchmark("identify_coulomb_error_pct", "%")
def identify_coulomb_error_pct(opts: dict) -> float:
    """Largest |Coulomb level error| (both directions, all joints) against the sim truth (target ≤ 3 %)."""
    return _worst("coulomb")


@benchmark("identify_viscous_error_pct", "%")
def identify_viscous_error_pct(opts: dict) -> float:
    """Largest |viscous slope error| (both directions, all joints) against the sim truth (target ≤ 10 %)."""
    return _worst("viscous")


@benchmark("identify_rmse_ratio", "x")
def identify_rmse_ratio(opts: dict) -> float:
    """Held-out RMSE of the predicted current / the floor (same prediction with the true parameters) (≤ 1.1)."""
    r = _run()
    return float(r["check"].rmse_A / r["floor"].rmse_A)


@benchmark("identify_rmse_mA", "mA")
def identify_rmse_mA(opts: dict) -> float:
    """Held-out RMSE of the predicted current over all joints, raw Hall current (20 mA noise included)."""
    return float(_run()["check"].rmse_A * 1e3)


@benchmark("identify_rmse_max_joint_ratio", "x")
def identify_rmse_max_joint_ratio(opts: dict) -> float:
    """Worst joint's held-out RMSE / that joint's floor (true-parameter prediction)."""
    r = _run()
    ratios = [r["check"].joints[nm]["rmse_A"] / f["rmse_A"] for nm, f in r["floor"].joints.items()
              if f.get("rmse_A") and r["check"].joints[nm].get("rmse_A")]
    return max(ratios) if ratios else float("nan")
