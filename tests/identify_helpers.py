"""Shared data for the identification tests: short plans run offline on the sim, generated once and kept (the first
worker that needs a log generates it under a lock, the others read it) in a folder named by a hash of everything
that makes the log — dragd/, sim/, config/, this file and gap_helpers.py, the Python, numpy and Pinocchio
versions — so a later run of the same sources reads it and any change generates it again, as the benchmarks' cached
logs do. ``$DRAGD_TEST_CACHE`` (default ``~/.cache/dragd/test-logs``); ``DRAGD_TEST_CACHE=off``: a folder per run."""

from __future__ import annotations

import fcntl
import functools
import hashlib
import os
import platform
import shutil
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from dragd.config import load_config
from dragd.identify import excitation as E
from dragd.model import RobotModel

START = np.array([0.0, -0.6, 1.2, -0.6, 1.5708, 0.0])
_REPO = Path(__file__).resolve().parents[1]
_KEEP_S = 2 * 86400.0  # a cached folder not used for this long is removed (another source tree's)


def _source_key() -> str:
    """A hash of every file that makes the logs: dragd/, sim/, config/ (all files, not only Python), this file and
    gap_helpers.py (the plans and truths), and the versions of Python, numpy and Pinocchio."""
    import pinocchio

    h = hashlib.sha256(f"{platform.python_version()} {np.__version__} {pinocchio.__version__}".encode())
    files = [Path(__file__).resolve(), Path(__file__).resolve().with_name("gap_helpers.py")]
    for root in ("dragd", "sim", "config"):
        files += (p for p in (_REPO / root).rglob("*") if p.is_file() and "__pycache__" not in p.parts)
    for f in sorted(files):
        h.update(f.relative_to(_REPO).as_posix().encode() + b"\0" + f.read_bytes() + b"\0")
    return h.hexdigest()[:16]


def _folder() -> Path:
    cache = os.environ.get("DRAGD_TEST_CACHE", str(Path.home() / ".cache" / "dragd" / "test-logs"))
    if cache == "off":  # one folder per test run, shared by its xdist workers (PYTEST_XDIST_TESTRUNUID)
        run = os.environ.get("PYTEST_XDIST_TESTRUNUID")
        return (Path(tempfile.gettempdir()) / f"dragd-identify-tests-{run}" if run
                else Path(tempfile.mkdtemp(prefix="dragd-identify-tests-")))
    root = Path(cache)
    root.mkdir(parents=True, exist_ok=True)
    now = time.time()
    for old in root.iterdir():  # other source trees' folders, unused for days
        try:
            if old.is_dir() and now - old.stat().st_mtime > _KEEP_S:
                shutil.rmtree(old, ignore_errors=True)
        except OSError:
            pass
    out = root / _source_key()
    out.mkdir(exist_ok=True)
    os.utime(out)  # (used now)
    return out


TMP = _folder()
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


def cached_npz(stem: str, make: Callable[[], dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """The arrays of ``TMP/stem.npz``, made by ``make()`` under a lock by the first process that needs them."""
    raw = TMP / f"{stem}.npz"
    with open(TMP / f"{stem}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # (another process making it: wait for its file)
        if not raw.exists():
            data = make()
            np.savez(TMP / f"{stem}.tmp.npz", **data)
            os.replace(TMP / f"{stem}.tmp.npz", raw)
            return data
    with np.load(raw) as z:
        return {k: z[k] for k in z.files}


def _generate(plan: E.Plan, name: str, seed: int, fmt: str = "mcap", interp: bool = True) -> Path:
    """Offline log of a plan. ``interp``: drives that interpolate CSP targets over each SYNC period (60C2h) —
    the estimators' accuracy without sim/drive.py's CSP sawtooth sampling bias (see test_identify_methods)."""
    from sim.offline import generate, write_log
    from sim.truth import load_truth

    stem = f"{name}-{seed}-{'i' if interp else 'n'}"
    out = TMP / f"{stem}.{fmt}"
    with open(TMP / f"{stem}.{fmt}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # (another worker writing it: wait for its file)
        if not out.exists():  # (one simulated run, the .npz, serves every format)
            data = cached_npz(stem, lambda: generate(plan.t_s, plan.q_rad, load_truth(), seed=seed,
                                                     csp_interpolation=interp, config=_feed_forward_config()))
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
