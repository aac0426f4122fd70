"""tests/cli_fork.py's fork servers for the lockstep tier's simulator and daemon: a forked child is what Popen would
have started (exit status, output, signals), and the daemon's server loads nothing the daemon would not."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cli_fork
import pytest

from dragd.lab.rig import multicast_group

pytestmark = pytest.mark.unit


@pytest.fixture(autouse=True)
def _own_servers():
    """Servers of this test's own (closed after it), in the environment the tiers' servers start with."""
    if os.environ.get("DRAGD_TEST_CLI") == "exec":
        pytest.skip("DRAGD_TEST_CLI=exec: no fork servers")
    yield
    cli_fork.close_spawners()


def _env() -> dict[str, str]:
    return dict(cli_fork.BASE_ENV or os.environ)


def test_an_exit_status_and_the_output_are_those_of_a_fresh_interpreter(tmp_path: Path) -> None:
    argv = [sys.executable, "-m", "sim", "run", "--bogus"]
    proc = cli_fork.launch(argv, tmp_path, _env(), tmp_path / "sim.log")
    assert isinstance(proc, cli_fork.ForkedProcess)
    fresh = subprocess.run(argv, capture_output=True, text=True, cwd=tmp_path, env=_env(), timeout=120)
    assert proc.wait(120) == fresh.returncode == 2
    assert (tmp_path / "sim.log").read_text() == fresh.stdout + fresh.stderr
    assert "unrecognized arguments: --bogus" in fresh.stderr


def test_a_running_child_is_alive_until_its_signal_and_reports_it_as_popen_does(tmp_path: Path) -> None:
    log = tmp_path / "sim.log"
    log.touch()  # (as the rig's Child makes it: the child appends)
    argv = [sys.executable, "-m", "sim", "run", "--bus", f"udp_multicast:{multicast_group('fork-test')}",
            "--control", str(tmp_path / "sim.sock"), "--lockstep", "--period-ms", "1"]
    proc = cli_fork.launch(argv, tmp_path, _env(), log)
    assert proc is not None
    end = time.monotonic() + 120  # (a hang guard: the lockstep simulator idles until a SYNC)
    while "sim: running" not in log.read_text() and time.monotonic() < end:
        assert proc.poll() is None, log.read_text()
        time.sleep(0.05)
    assert proc.poll() is None and Path(f"/proc/{proc.pid}").is_dir()
    with pytest.raises(subprocess.TimeoutExpired):
        proc.wait(0.2)
    proc.send_signal(signal.SIGKILL)
    assert proc.wait(60) == -signal.SIGKILL and proc.returncode == -signal.SIGKILL
    proc.send_signal(signal.SIGTERM)  # (a reaped child: nothing is sent, nothing raised)


def test_the_daemons_server_never_maps_scipy(tmp_path: Path) -> None:
    """The daemon never loads scipy (tests/test_daemon_track.py reads its memory map): neither does its server, whose
    memory the forked daemon starts with; its numba kernels are loaded."""
    proc = cli_fork.launch([sys.executable, "-m", "dragd", "--version"], tmp_path, _env(), tmp_path / "v.log")
    assert proc is not None and proc.wait(120) == 0
    assert (tmp_path / "v.log").read_text().startswith("dragd ")
    server = cli_fork._spawners["dragd"].proc.pid
    maps = Path(f"/proc/{server}/maps").read_text()
    assert "/scipy/" not in maps and "/numba/" in maps


def test_what_a_server_cannot_be_starts_fresh(tmp_path: Path) -> None:
    """Another environment than the server's, another module or interpreter: None (the rig starts it with Popen)."""
    log = tmp_path / "x.log"
    assert cli_fork.launch([sys.executable, "-m", "dragd", "--version"], tmp_path, {**_env(), "DRAGD_X": "1"},
                           log) is None
    assert cli_fork.launch([sys.executable, "-m", "pytest", "--version"], tmp_path, _env(), log) is None
    assert cli_fork.launch(["/bin/true"], tmp_path, _env(), log) is None
    assert cli_fork._spawners == {}
