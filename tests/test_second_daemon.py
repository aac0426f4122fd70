"""A second daemon refuses to start and leaves the running arm untouched: the run lock (same control socket) and,
on another socket, the listen for another master's SYNC/heartbeat before any NMT."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest

from dragd.lab.rig import Rig

pytestmark = pytest.mark.rig


def _second(rig: Rig, socket: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "dragd", "run", "--bus", rig.bus, "--socket", socket],
                          capture_output=True, text=True, timeout=60, cwd=str(rig.workdir))


def test_second_daemon_refuses_and_leaves_the_running_arm_alone(tmp_path):
    with Rig("second", workdir=tmp_path, daemon_args=["--realtime-priority", "70"],
             sim_args=["--realtime-priority", "60"]) as rig:
        rig.start_sim()
        rig.start_daemon()
        rig.ensure_hold()
        before = rig.sim_call("drives")["drives"]
        status0 = rig.must("status")
        other = _second(rig, str(tmp_path / "other" / "dragd.sock"))  # another socket: the bus tells
        assert other.returncode == 1, other.stderr
        assert "another CANopen master is running" in other.stderr and "before any NMT" in other.stderr, other.stderr
        assert "Traceback" not in other.stderr
        same = _second(rig, rig.socket)  # the same socket: the run lock tells, before a bus is opened
        assert same.returncode == 1 and "another dragd holds" in same.stderr, same.stderr
        time.sleep(0.3)
        after = rig.sim_call("drives")["drives"]
        status = rig.must("status")
    # no NMT reached the drives, nothing was reconfigured, the arm still holds with the same fault count
    assert all(after[k]["nmt_commands"] == before[k]["nmt_commands"] for k in before), (before, after)
    assert all(d["state"] == "OPERATION_ENABLED" and d["nmt"] == "OPERATIONAL" for d in after.values()), after
    assert status["mode"] == "hold" and status["drives_enabled"], status
    assert status["fault_count"] == status0["fault_count"], status["faults"]
    if os.geteuid() == 0 and status["scheduler"].startswith("SCHED_FIFO"):  # root may lock memory: the unit's claim
        assert status["memory_locked"] is True, status
    # PM QoS is opt-in (loop.cpu_latency_us), also as deployed: a default daemon leaves the CPUs' idle states alone
    assert status["cpu_latency"] == {"requested_us": None, "applied": False, "reason": "not requested",
                                     "effective_us": None}, \
        status["cpu_latency"]
