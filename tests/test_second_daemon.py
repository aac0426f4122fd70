"""A second daemon refuses to start and leaves the running arm untouched: the run lock (same control socket) and,
on another socket, the listen for another master's SYNC/heartbeat before any NMT.

On the lockstep clock the running arm's bus is silent while its time stands still (its SYNCs and the drives'
heartbeats come with granted time), so the clock runs freely (``dragd clock run``) while the second daemon starts:
its 0.3 s listen (wall time: it has no clock yet) then hears the first master as it would on a wall-clock bus. The
running arm is not at real-time priority here: with its clock running freely it would be a SCHED_FIFO busy loop, which
starves every thread below it (its own control socket's, the second daemon, another test's processes) for as long as
it runs. The policies as deployed are tests/test_daemon_threads.py's, on granted time."""

from __future__ import annotations

import subprocess
import sys

import pytest

from dragd.lab.rig import Rig

pytestmark = pytest.mark.lockstep


def _second(rig: Rig, socket: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "dragd", "run", "--bus", rig.bus, "--socket", socket],
                          capture_output=True, text=True, timeout=240, cwd=str(rig.workdir))


def test_second_daemon_refuses_and_leaves_the_running_arm_alone(tmp_path):
    with Rig("second", workdir=tmp_path) as rig:
        rig.start_sim()
        rig.start_daemon()
        rig.must("start")
        rig.wait_for(lambda: rig.must("status")["mode"] == "hold", 5.0, "hold")
        before = rig.sim_call("drives")["drives"]
        status0 = rig.must("status")
        with rig.running():  # (the first master's SYNCs and heartbeats on the bus while the second listens)
            other = _second(rig, str(tmp_path / "other" / "dragd.sock"))  # another socket: the bus tells
        assert other.returncode == 1, other.stderr
        assert "another CANopen master is running" in other.stderr and "before any NMT" in other.stderr, other.stderr
        assert "Traceback" not in other.stderr
        same = _second(rig, rig.socket)  # the same socket: the run lock tells, before a bus is opened
        assert same.returncode == 1 and "another dragd holds" in same.stderr, same.stderr
        rig.sleep(0.3)
        after = rig.sim_call("drives")["drives"]
        status = rig.must("status")
    # no NMT reached the drives, nothing was reconfigured, the arm still holds with the same fault count
    assert all(after[k]["nmt_commands"] == before[k]["nmt_commands"] for k in before), (before, after)
    assert all(d["state"] == "OPERATION_ENABLED" and d["nmt"] == "OPERATIONAL" for d in after.values()), after
    assert status["mode"] == "hold" and status["drives_enabled"], status
    assert status["fault_count"] == status0["fault_count"], status["faults"]
