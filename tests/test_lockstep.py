"""The lockstep clock end to end: the daemon and the simulated arm as real processes over the real bus, their time
simulated (dragd/clock.py, sim/lockstep.py). The same seed gives the same telemetry bit for bit, with two busy loops
on the machine's cores beside it or without; another seed does not; a run reports its real-time factor; a silent
simulator is an error after the guard, not a hang; the golden trace recorded in lockstep is what the processes do
today, bit for bit."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from dragd.lab.rig import ProcessError, Rig
from dragd.telemetry.digest import digest

from conftest import REPO

pytestmark = pytest.mark.lockstep

TRUTH = REPO / "sim" / "config" / "seed_cobot.yaml"


def scenario(workdir: Path, sim_config: Path | None = None) -> dict[str, Any]:
    """Enable, drag, a push and its release, lost frames, hold, a record window, stop: the telemetry's digest."""
    mcap = workdir / "run.mcap"
    with Rig("determinism", workdir=workdir, telemetry=mcap, sim_config=sim_config, lockstep=True) as rig:
        rig.start_sim()
        rig.start_daemon()
        rig.must("start")
        rig.sleep(0.3)
        rig.must("mode", mode="drag")
        rig.sleep(0.2)
        rig.sim_call("operator", scenario={"name": "push", "segments": [
            {"kind": "push", "joint": "joint2", "torque_Nm": 12.0, "duration_s": 0.4},
            {"kind": "release", "duration_s": 0.0}]})
        rig.sleep(0.6)
        rig.sim_call("inject", kind="burst_loss", frames=20)  # a few TPDOs lost: stale joints, a late cycle
        rig.sleep(0.4)
        rig.must("record", action="start", path=str(workdir / "window.mcap"), label="determinism")
        rig.must("mode", mode="hold")
        rig.sleep(0.5)
        rig.must("record", action="stop")
        status = rig.must("status")
        sim = rig.sim_call("state")
        rig.must("stop")
        rig.sleep(0.1)
    return {"telemetry": digest(mcap), "window": digest(workdir / "window.mcap"), "status": status, "sim": sim}


def hog(n: int) -> list[subprocess.Popen[bytes]]:
    """``n`` busy loops (a second test run, a build) competing for the cores."""
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]


def test_same_seed_same_telemetry_bit_for_bit_loaded_or_quiet(tmp_path: Path) -> None:
    quiet = scenario(tmp_path / "quiet")
    busy = hog(os.cpu_count() or 2)
    try:
        loaded = scenario(tmp_path / "loaded")
    finally:
        for p in busy:
            p.kill()
            p.wait()
    assert quiet["telemetry"]["messages"] > 2500  # every cycle, the events and the Foxglove channels
    assert quiet["telemetry"] == loaded["telemetry"]
    assert quiet["window"] == loaded["window"]
    s = quiet["status"]
    assert s["mode"] == "hold" and s["late_tpdo_cycles"] > 0 and s["feedback_holds"] >= 0
    for key in ("cycles", "late_tpdo_cycles", "feedback_holds", "t_s", "q_rad", "current_A", "faults"):
        assert s[key] == loaded["status"][key], key
    assert quiet["sim"]["q_rad"] == loaded["sim"]["q_rad"] and quiet["sim"]["t"] == loaded["sim"]["t"]
    assert s["clock"]["rtf"] > 0  # the real-time factor the run reached (wall time while the clock ran)
    # the sim's Hall noise with another seed: another telemetry (the comparison above can fail)
    data = yaml.safe_load(TRUTH.read_text())
    data["noise_seed"] = 2
    other = tmp_path / "seed2.yaml"
    other.write_text(yaml.safe_dump(data, sort_keys=False))
    reseeded = scenario(tmp_path / "seed2", sim_config=other)
    assert reseeded["telemetry"]["sha256"] != quiet["telemetry"]["sha256"]
    assert reseeded["status"]["cycles"] == s["cycles"]  # (the same script: only the noise differs)
    assert not np.allclose(reseeded["status"]["current_A"], s["current_A"], rtol=0, atol=1e-9)


def test_the_lockstep_golden_trace_is_recorded_again_bit_for_bit(tmp_path: Path) -> None:
    """tests/golden/lockstep.npz recorded again from the real processes: every frame on the bus, cycle by cycle, and
    the daemon's telemetry equal the committed trace (its open-loop replay is tests/test_golden_trace.py). A change
    of the simulator's or the daemon's behaviour shows here; on purpose, it is a new recording
    (``python tests/golden/record.py lockstep``) with its reason in the commit."""
    sys.path.insert(0, str(REPO / "tests"))
    from golden.live import record_lockstep
    from golden.trace import arithmetic, trace_path

    with np.load(trace_path("lockstep")) as z:
        if str(z["arithmetic"]) != arithmetic():
            pytest.skip("this machine's float arithmetic is not the recording's: a closed loop amplifies the last bit")
        now = record_lockstep(tmp_path)
        # (the configuration's text is an input: a key added to config/default.yaml is no change of behaviour; one that
        # changes behaviour shows in the frames and the telemetry)
        differ = [k for k in z.files if k != "config" and not np.array_equal(np.asarray(now[k]), z[k])]
    assert not differ, f"the lockstep golden trace differs in {differ}"


def test_a_silent_simulator_is_an_error_not_a_hang(tmp_path: Path) -> None:
    with Rig("silent", workdir=tmp_path, lockstep=True, daemon_args=["--lockstep-guard-s", "2"]) as rig:
        rig.start_sim()
        rig.start_daemon()
        rig.sim.proc.send_signal(19)  # SIGSTOP: alive, silent
        try:
            with pytest.raises(ProcessError) as err:
                rig.sleep(1.0)
        finally:
            rig.sim.proc.send_signal(18)  # SIGCONT
        rig.daemon.proc.wait(30)
        log = rig.daemon.output()
    assert rig.daemon.proc.returncode == 1
    assert "no TIME frame from the simulator for SYNC" in log and "within 2 s of wall time" in log, log[-2000:]
    assert "lockstep" in str(err.value)
