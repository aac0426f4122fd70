"""The ``dragd`` command line as such: --version, negative number lists, ``dragd sim`` pass-through, operator errors
as one line, ``$DRAGD_SOCKET``."""

from __future__ import annotations

import os
import subprocess
import sys
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import pytest

import dragd
from dragd.cli.app import build_parser
from dragd.cli.common import DEFAULT_SOCKET

pytestmark = pytest.mark.unit


def dragd_proc(*args: str, env: dict[str, str] | None = None,
               timeout: float = 600.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "dragd", *args], capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, **(env or {})})


def assert_one_line_error(proc: subprocess.CompletedProcess[str], *expected: str) -> None:
    assert proc.returncode != 0, proc.stdout
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("dragd: "), proc.stderr
    assert "Traceback" not in proc.stderr
    for text in expected:
        assert text in lines[0], lines[0]


# --------------------------------------------------------------------------------------------- --version


def test_version() -> None:
    try:
        want = version("dragd")
    except PackageNotFoundError:
        want = dragd.__version__
    proc = dragd_proc("--version")
    assert proc.returncode == 0 and proc.stdout == f"dragd {want}\n", proc


def test_the_tests_cli_runs_fork_from_the_server_on_either_rig_clock(monkeypatch: pytest.MonkeyPatch) -> None:
    """tests/conftest.py's run_cli forks ``python -m dragd`` from the worker's server (tests/cli_fork.py) unless
    DRAGD_TEST_CLI=exec: the rig clock the tiers set for each test is no reason for a fresh interpreter (it was, and
    every call of every tier paid the interpreter's start and imports again)."""
    import cli_fork

    if os.environ.get("DRAGD_TEST_CLI") == "exec":
        pytest.skip("DRAGD_TEST_CLI=exec: every call is a fresh interpreter, as asked")
    for clock in ("wall", "lockstep"):
        monkeypatch.setenv("DRAGD_RIG_CLOCK", clock)
        proc = cli_fork.run(("--version",), None, None, 60.0)
        assert proc is not None, f"DRAGD_RIG_CLOCK={clock}: run_cli would start a fresh interpreter"
        assert proc.returncode == 0 and proc.stdout.startswith("dragd "), proc


# --------------------------------------------------------------------------------------------- light commands

HEAVY = ("scipy", "pinocchio", "numpy", "pydantic", "canopen", "can", "yaml", "asyncio")


@pytest.mark.parametrize("argv", [["--help"], ["status", "--json"], ["mode", "drag"], ["start"], ["stop"]])
def test_socket_commands_import_no_numerics(argv: list[str], tmp_path: Path) -> None:
    """The operator's socket commands (and the help) load neither the numerics nor the schema nor CAN: a status
    call on a loaded controller (or in the vcan guest, where an import costs 20x) is a socket round trip."""
    code = ("import sys\nfrom dragd.cli.app import main\ntry:\n    main(sys.argv[1:])\nexcept SystemExit:\n    pass\n"
            f"print('imported:', ','.join(m for m in {HEAVY!r} if m in sys.modules))")
    sock = ["--socket", str(tmp_path / "none.sock")] if argv != ["--help"] else []
    proc = subprocess.run([sys.executable, "-c", code, *argv, *sock], capture_output=True, text=True, timeout=60)
    assert "Traceback" not in proc.stderr, proc.stderr
    last = proc.stdout.splitlines()[-1]
    assert last == "imported: ", f"{argv}: {last}"


# The offline tools load what they use and no more: no JIT (numba), no viewer (rerun), no ROS 2 (rclpy) outside the
# commands that run them; the model and its optimiser only where a command evaluates the model. The forked CLI of
# the tests (tests/cli_fork.py) loads all of that before a command runs, so only a fresh interpreter can tell.
NEVER_OFFLINE = ("numba", "rerun", "rclpy")


@pytest.mark.parametrize("argv, absent", [
    (["config", "check", "--config", "config/default.yaml"], NEVER_OFFLINE),
    (["config", "init", "--robot", "seed_cobot"], (*NEVER_OFFLINE, "canopen")),
    (["model", "gravity", "--q", "0,0,0,0,0,0"], (*NEVER_OFFLINE, "scipy", "canopen")),
    (["identify", "plan", "--kind", "synchronous", "--start", "0,0,0,0,0,0", "--out", "{tmp}/p.npz"],
     (*NEVER_OFFLINE, "scipy", "canopen")),
    (["log", "summary", "{log}"], (*NEVER_OFFLINE, "pinocchio", "scipy", "canopen", "pydantic")),
])
def test_offline_tools_import_only_what_they_use(argv: list[str], absent: tuple[str, ...], tmp_path: Path) -> None:
    from identify_helpers import sync_log

    log = str(sync_log("mcap")) if "{log}" in argv else ""
    argv = [a.format(tmp=tmp_path, log=log) for a in argv]
    code = ("import sys\nfrom dragd.cli.app import main\nstatus = main(sys.argv[1:])\n"
            f"print('imported:', ','.join(m for m in {absent!r} if m in sys.modules), 'status:', status)")
    proc = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, timeout=600,
                          cwd=Path(__file__).resolve().parents[1])
    assert "Traceback" not in proc.stderr, proc.stderr
    assert proc.stdout.splitlines()[-1] == "imported:  status: 0", f"{argv}: {proc.stdout.splitlines()[-1]}"


# --------------------------------------------------------------------------------------------- number lists


@pytest.mark.parametrize("argv, dest, value", [
    (["model", "gravity", "--q", "-0.5,0.2,0,0,0,0"], "q", "-0.5,0.2,0,0,0,0"),
    (["model", "current", "--q", "-1,0", "--dq", "-.5,-1e-3"], "dq", "-.5,-1e-3"),
    (["model", "current", "--q", "-1,", "--dq", "0"], "q", "-1,"),
    (["identify", "plan", "--kind", "lowspeed", "--start", "-0.1,0.2,-0.3", "--out", "p.npz"], "start",
     "-0.1,0.2,-0.3"),
    (["config", "init", "--robot", "seed_cobot", "--gravity", "-9.81,0,0"], "gravity", "-9.81,0,0"),
    (["model", "current", "--q", "0", "--dq", "0", "--t", "-2"], "t", -2.0),
])
def test_lists_starting_with_minus_are_values(argv: list[str], dest: str, value: object) -> None:
    assert getattr(build_parser().parse_args(argv), dest) == value


def test_options_are_still_options(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(["model", "gravity", "--q", "--json"])
    assert exc.value.code == 2 and "--q: expected one argument" in capsys.readouterr().err


def test_model_gravity_negative_pose_runs() -> None:
    proc = dragd_proc("model", "gravity", "--q", "-0.5,0.2,0,0,0,0", "--json")
    assert proc.returncode == 0, proc.stderr
    assert '"gravity_Nm"' in proc.stdout


# --------------------------------------------------------------------------------------------- dragd sim


def test_sim_takes_every_argument() -> None:
    argv = ["sim", "--bus", "udp_multicast:239.74.163.2", "--control", "/tmp/s.sock", "--seconds", "1", "--json"]
    assert build_parser().parse_args(argv).sim_args == argv[1:]
    assert build_parser().parse_args(["sim", "--help"]).sim_args == ["--help"]


def test_sim_help_lists_the_simulator_options() -> None:
    proc = dragd_proc("sim", "--help")
    assert proc.returncode == 0, proc.stderr
    for option in ("--bus", "--control", "--config", "--scenario", "--seconds"):
        assert option in proc.stdout


# --------------------------------------------------------------------------------------------- operator errors


def test_missing_can_interface_is_one_line(tmp_path: Path) -> None:
    proc = dragd_proc("run", "--bus", "socketcan:nocan9", "--socket", str(tmp_path / "d.sock"), timeout=60)
    assert_one_line_error(proc, "nocan9")


def test_non_utf8_config_is_one_line(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_bytes(b"robot:\n  urdf: \xff\xfe\n")
    assert_one_line_error(dragd_proc("config", "check", "--config", str(bad)), "UTF-8")


@pytest.mark.parametrize("argv", [
    ["config", "check", "--config", "{tmp}/none.yaml"],
    ["config", "check", "--config", "{tmp}"],
    ["model", "gravity", "--q", "0,0,0,0,0,0", "--config", "{tmp}/none.yaml"],
    ["log", "summary", "{tmp}/none.mcap"],
    ["teach", "show", "{tmp}/none.yaml"],
    ["identify", "fit", "--log", "{tmp}/none.csv", "--out", "{tmp}/p.yaml"],
])
def test_missing_file_is_one_line(tmp_path: Path, argv: list[str]) -> None:
    proc = dragd_proc(*(a.format(tmp=tmp_path) for a in argv))
    assert_one_line_error(proc, str(tmp_path))


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads every file")
def test_unreadable_config_is_one_line(tmp_path: Path) -> None:
    cfg = tmp_path / "secret.yaml"
    cfg.write_text("robot: {}\n")
    cfg.chmod(0)
    assert_one_line_error(dragd_proc("config", "check", "--config", str(cfg)), str(cfg))


# --------------------------------------------------------------------------------------------- $DRAGD_SOCKET


CLIENTS = [["status"], ["start"], ["stop"], ["mode", "drag"], ["teach", "mark"], ["teach", "list"],
           ["replay", "pick"], ["identify", "run", "--plan", "standard", "--out", "x.mcap"]]


@pytest.mark.parametrize("argv", CLIENTS)
def test_socket_default_from_environment(monkeypatch: pytest.MonkeyPatch, argv: list[str]) -> None:
    monkeypatch.delenv("DRAGD_SOCKET", raising=False)
    assert build_parser().parse_args(argv).socket == DEFAULT_SOCKET
    monkeypatch.setenv("DRAGD_SOCKET", "/tmp/elsewhere.sock")
    assert build_parser().parse_args(argv).socket == "/tmp/elsewhere.sock"
    assert build_parser().parse_args([*argv, "--socket", "/tmp/given.sock"]).socket == "/tmp/given.sock"


def test_daemon_socket_from_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("DRAGD_SOCKET", raising=False)
    assert build_parser().parse_args(["run"]).socket is None  # the config's control.socket
    monkeypatch.setenv("DRAGD_SOCKET", "/tmp/elsewhere.sock")
    assert build_parser().parse_args(["run"]).socket == "/tmp/elsewhere.sock"


def test_status_asks_the_environment_socket(tmp_path: Path) -> None:
    sock = tmp_path / "none.sock"
    assert_one_line_error(dragd_proc("status", env={"DRAGD_SOCKET": str(sock)}), str(sock))
