"""Shared data for the identification tests: short plans run offline on the sim (generated once per test run, for
every xdist worker of it: the first worker that needs a log generates it under a lock, the others read it)."""

from __future__ import annotations

import fcntl
import functools
import os
import tempfile
from pathlib import Path

import numpy as np

from dragd.config import load_config
from dragd.identify import excitation as E
from dragd.model import RobotModel

START = np.array([0.0, -0.6, 1.2, -0.6, 1.5708, 0.0])
# one folder per test run, shared by its xdist workers (PYTEST_XDIST_TESTRUNUID: the same in every worker of a run)
_RUN = os.environ.get("PYTEST_XDIST_TESTRUNUID")
TMP = (Path(tempfile.gettempdir()) / f"dragd-identify-tests-{_RUN}" if _RUN
       else Path(tempfile.mkdtemp(prefix="dragd-identify-tests-")))
TMP.mkdir(exist_ok=True)


@functools.cache
def robot() -> RobotModel:
    return RobotModel.from_urdf("seed_cobot")


@functools.cache
def limits() -> E.Limits:
    return E.Limits.from_model(robot(), load_config())


@functools.cache
def truth() -> dict:
    from sim.offline import truth_summary
    from sim.truth import load_truth

    return truth_summary(load_truth())


def _generate(plan: E.Plan, name: str, seed: int, fmt: str = "mcap", interp: bool = True) -> Path:
    """Offline log of a plan. ``interp``: drives that interpolate CSP targets over each SYNC period (60C2h) —
    the estimators' accuracy without sim/drive.py's CSP sawtooth sampling bias (see test_identify_methods)."""
    from sim.offline import generate, write_log
    from sim.truth import load_truth

    stem = f"{name}-{seed}-{'i' if interp else 'n'}"
    out = TMP / f"{stem}.{fmt}"
    with open(TMP / f"{stem}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # (another worker generating it: wait for its file)
        if not out.exists():
            raw = TMP / f"{stem}.npz"
            if raw.exists():  # one run serves both formats
                with np.load(raw) as z:
                    data = {k: z[k] for k in z.files}
            else:
                data = generate(plan.t_s, plan.q_rad, load_truth(), seed=seed, csp_interpolation=interp,
                                config=_feed_forward_config())
                np.savez(TMP / f"{stem}.tmp.npz", **data)
                os.replace(TMP / f"{stem}.tmp.npz", raw)
            write_log(TMP / f"{stem}.tmp.{fmt}", data)
            os.replace(TMP / f"{stem}.tmp.{fmt}", out)
    return out


@functools.cache
def _feed_forward_config() -> Path:
    """The default configuration with the TRACK feed-forward's friction scale pinned at 0.9, the value the
    estimators' bounds were set with: the logs must not move with the drag law's tuning (the full method's
    joint-2 Coulomb level moves 6-9 % with it on the short Fourier log; the measurement is in the diary docs/NOTES.md,
    in git history)."""
    import yaml

    from dragd.config import default_config_path

    src = default_config_path()
    data = yaml.safe_load(src.read_text())
    data.setdefault("law", {})["friction_scale"] = 0.9
    urdf = data.get("robot", {}).get("urdf")
    if urdf and not Path(urdf).is_absolute() and (src.parent / urdf).exists():
        data["robot"]["urdf"] = str((src.parent / urdf).resolve())
    out = TMP / "feed_forward.yaml"
    part = TMP / f"feed_forward.{os.getpid()}.yaml"  # (workers write the same text: each replaces it whole)
    part.write_text(yaml.safe_dump(data, sort_keys=False))
    os.replace(part, out)
    return out


@functools.cache
def sync_plan() -> E.Plan:
    """Seed 002 style: joints 2 and 4 reciprocate at two speeds, one pose (~40 s)."""
    b = E.PlanBuilder(START, limits())
    E.add_synchronous(b, [1, 3], speeds=(0.15, 0.45), cycles=1, half_range_deg=30.0)
    return b.build("test-sync")


@functools.cache
def sync_log(fmt: str = "mcap", seed: int = 3, interp: bool = True) -> Path:
    return _generate(sync_plan(), "sync", seed, fmt, interp)


@functools.cache
def symmetric_log(seed: int = 4) -> Path:
    b = E.PlanBuilder(START, limits())
    E.add_symmetric(b, passes=4, speed=0.25, rng=np.random.default_rng(seed))
    return _generate(b.build("test-symmetric"), "symmetric", seed)


@functools.cache
def lowspeed_log() -> Path:
    b = E.PlanBuilder(START, limits())
    E.add_lowspeed(b, [1], seconds_per_joint=40.0, cycles=1)
    return _generate(b.build("test-lowspeed"), "lowspeed", 5)


def rel(a: float, b: float) -> float:
    return abs(a - b) / abs(b)


@functools.cache
def fourier_log() -> Path:
    b = E.PlanBuilder(START, limits())
    E.add_fourier(b, robot(), periods=5, maxiter=20, seed=3)
    return _generate(b.build("test-fourier"), "fourier", 6)


def run_plan(rig, plan: E.Plan, tmp_path: Path) -> tuple[dict, Path]:  # noqa: ANN001
    """``dragd identify run`` of a plan through a rig's daemon (CSP); returns its JSON and the MCAP path. On the
    lockstep clock, time runs freely meanwhile (the CLI polls the daemon on the wall clock; the plan runs on the
    daemon's)."""
    import json

    pf = tmp_path / "plan.npz"
    plan.save(pf)
    rig.wait_for(lambda: rig.must("status")["mode"] == "hold", 5.0, "hold before the run")
    out = tmp_path / "run.mcap"
    with rig.running():
        proc = rig.cli("identify", "run", "--plan", str(pf), "--out", str(out), "--no-progress", "--json",
                       timeout_s=300.0)
    assert proc.returncode == 0, proc.stderr + proc.stdout
    return json.loads(proc.stdout), out
