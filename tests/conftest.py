"""Shared fixtures: paths, the default config, a CLI runner that runs the real `dragd` entry point; the test tiers.

Tiers (markers registered in pyproject.toml; ``./dev test`` selects them):

- ``unit``: no simulator/daemon processes, no wall-clock timing (a ``dragd`` CLI subprocess that only computes is
  fine): runs in parallel (pytest-xdist);
- ``lockstep``: the simulator and the daemon as processes on the lockstep clock: every ``Rig`` the test makes runs
  there (``DRAGD_RIG_CLOCK=lockstep``, set here per test), its time passes only through ``Rig.sleep`` /
  ``Rig.wait_for``: the verdict does not depend on scheduling, so these run in parallel too;
- ``rig``: processes on the wall clock (real-time behaviour itself: missed ticks, host stalls, scheduling policy,
  stall probes, a late TPDO as timing, a daemon killed under the drives), or fixed sockets/groups: runs serially;
- ``slow``: more than ~30 s: only with ``./dev test --all`` (CI).

A test marked none of ``unit``, ``lockstep``, ``rig`` counts as ``rig`` (the safe choice: serial, wall clock); rig
tests refuse to run on more than one xdist worker. One tier per module (``-m`` selects by every marker a test
carries): a wall-clock test of a lockstep subject lives in a ``rig`` module of its own.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import cli_fork  # i28-unit: run_cli's fork server
import pytest

# One BLAS/OpenMP thread per process, set before anything imports numpy (children inherit it): the tests run as
# parallel workers and process pairs on few cores, where OpenBLAS's own threads (one per core, spinning while they
# wait) fight the other processes for the cores: a 200×66 SVD in identify's inertials fit cost 8x its CPU time with
# two threads on this 2-core machine under load (25 s against 2.9 s for one test). An explicit setting wins.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
cli_fork.BASE_ENV = dict(os.environ)  # i28-unit: the fork server's environment (never a test's monkeypatched one)

REPO = Path(__file__).resolve().parents[1]
DEFAULT_CONFIG = REPO / "config" / "default.yaml"


def run_cli(*args: str, check: bool = True, timeout: float = 600.0,
            env: dict[str, str] | None = None, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    """Run ``python -m dragd ARGS`` as a real process (in ``cwd``: default the test's). ``timeout`` is a hang guard,
    not a clock: wall seconds, so far above a run's CPU time (``dragd gap`` of 8 s of CPU took 120+ s at load 16 on 2
    cores and failed a unit test's fixture) and below the unit tier's pytest-timeout (900 s), so a hung child is
    killed and named."""
    # i28-unit: forked from a server that has imported the package (tests/cli_fork.py: same entry point, own
    # process, without ~1.5 s of imports each); a fresh interpreter where the environment differs from the server's
    proc = cli_fork.run(args, env, cwd, timeout)
    if proc is None:
        proc = subprocess.run([sys.executable, "-m", "dragd", *args], capture_output=True, text=True,
                              timeout=timeout, env=env, cwd=cwd)
    if check and proc.returncode != 0:
        raise AssertionError(f"dragd {' '.join(args)} failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}")
    return proc


def run_sim(*args: str, check: bool = True, timeout: float = 600.0,
            cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    """i28-unit: ``python -m sim ARGS`` as ``run_cli`` runs dragd's (forked from the server where it can be)."""
    proc = cli_fork.run(args, None, cwd, timeout, module="sim")
    if proc is None:
        proc = subprocess.run([sys.executable, "-m", "sim", *args], capture_output=True, text=True, timeout=timeout,
                              cwd=cwd)
    if check and proc.returncode != 0:
        raise AssertionError(f"python -m sim {' '.join(args)} failed ({proc.returncode}):\n{proc.stdout}\n"
                             f"{proc.stderr}")
    return proc


def cli_json(*args: str) -> dict:
    return json.loads(run_cli(*args, "--json").stdout)


@pytest.fixture
def default_config_path() -> Path:
    return DEFAULT_CONFIG


# --------------------------------------------------------------------------------------------- tiers


TIERS = ("unit", "lockstep", "rig")
HANG_GUARD_S = 900  # s, unit and lockstep tests (see pytest_collection_modifyitems)


def tier(item: pytest.Item) -> str:
    """The closest of the tier markers (function, then class, then module)."""
    for m in item.iter_markers():
        if m.name in TIERS:
            return m.name
    return "rig"


def _compile_kernels() -> None:
    """Compile every numba kernel once, into numba's on-disk cache (the package's __pycache__): ~8 s of CPU in a fresh
    clone, ~0.5 s once cached. Without it each xdist worker and each simulator/daemon process started before the
    cache exists compiles the same kernels at the same time. (Add a module here when it gets compiled kernels.)"""
    try:
        from dragd.control import contact, contact_watch, fused, guard, safety
        from dragd.daemon import kernels
        from sim import kernels as sim_kernels
    except ImportError:  # pragma: no cover - a broken checkout: the tests say what is wrong
        return
    for compile_ in (fused._compiled, guard._kernels, safety.safety_kernel, contact.contact_kernel,
                     contact_watch._kernels, kernels.kernels, sim_kernels.hold_kernel):
        compile_()


def pytest_configure(config: pytest.Config) -> None:
    """With xdist workers (``-n``): the kernels compiled once here, in the controller, before the workers start."""
    if not hasattr(config, "workerinput") and getattr(config.option, "numprocesses", None) not in (None, 0, "0"):
        _compile_kernels()


@pytest.hookimpl(tryfirst=True)  # before -m deselects: an unmarked test is selected by -m rig, never by -m unit
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        if tier(item) == "rig" and item.get_closest_marker("rig") is None:
            item.add_marker(pytest.mark.rig)
        # pytest-timeout (pyproject: 300 s) is a guard against hangs, and wall time: the verdicts of the unit and
        # lockstep tiers must not depend on the machine's load, and tests of 13-27 s of CPU took 300+ s at load 20
        # (2 cores): 900 s for those tiers; the rig tier keeps 300 s
        if tier(item) in ("unit", "lockstep") and item.get_closest_marker("timeout") is None:
            item.add_marker(pytest.mark.timeout(HANG_GUARD_S))
        # xdist (./dev test: --dist loadgroup): a module whose tests share a module- or class-scoped fixture (a rig
        # session, simulated logs) stays on one worker; every other test goes to whichever worker is free
        defs = getattr(getattr(item, "_fixtureinfo", None), "name2fixturedefs", {})
        if any(d.scope in ("module", "class", "package") for fds in defs.values() for d in fds):
            item.add_marker(pytest.mark.xdist_group(item.module.__name__ if item.module else item.nodeid))


@pytest.hookimpl(tryfirst=True)  # before the fixtures (a module-scoped rig is made in the first test's setup)
def pytest_runtest_setup(item: pytest.Item) -> None:
    """The rig clock for this test's tier (lockstep or wall); a rig test fails at once when pytest-xdist runs more
    than one worker (DRAGD_PARALLEL_RIG=1 overrides)."""
    t = tier(item)
    os.environ["DRAGD_RIG_CLOCK"] = "lockstep" if t == "lockstep" else "wall"
    # the lockstep tier's simulator and daemon fork from servers that have imported them (tests/cli_fork.py); the
    # rig tier's start as the deployed ones do (real-time behaviour is its subject, fresh processes its condition)
    from dragd.lab import rig as rig_module

    rig_module.LAUNCHER = cli_fork.launch if t == "lockstep" else None
    workers = int(getattr(item.config, "workerinput", {}).get("workercount", 1))
    if workers > 1 and t == "rig" and os.environ.get("DRAGD_PARALLEL_RIG") != "1":
        pytest.fail(f"a rig test (or one without a unit/rig marker) on {workers} xdist workers: rig tests start "
                    "processes and depend on timing, so they run serially (./dev test runs unit tests with -n, rig "
                    "tests without; select -m unit for -n)", pytrace=False)
