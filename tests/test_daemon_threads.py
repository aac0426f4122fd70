"""Every thread of a daemon run as deployed has the scheduling policy meant for it: the cycle SCHED_FIFO 70, every
helper SCHED_FIFO 1 (below it, above every normal task), whether it started during boot (the SDO worker, the
telemetry forwarder), with the loop (the executor) or later (a record window's writer). A SCHED_OTHER helper,
preempted by the host's other work while it held the GIL, stalled the cycle for milliseconds (docs/DECISIONS.md).

On the lockstep clock: the policies do not depend on the clock, and the verdict does not depend on the machine's load.
Skipped where SCHED_FIFO is not permitted (the daemon says so in ``scheduler``).
"""

from __future__ import annotations

import os

import pytest

from dragd.lab.rig import DEPLOYED_PRIORITY, Rig

pytestmark = pytest.mark.lockstep


def test_every_daemon_thread_runs_with_its_policy_as_deployed(tmp_path) -> None:
    with Rig("threads", workdir=tmp_path, telemetry=tmp_path / "t.mcap", as_deployed=True, lockstep=True) as rig:
        rig.start_sim()
        rig.start_daemon()
        st = rig.must("status")
        if not str(st["scheduler"]).startswith("SCHED_FIFO"):
            pytest.skip(f"SCHED_FIFO not permitted here: {st['scheduler']}")
        rig.must("start")
        rig.must("record", action="start", path=str(tmp_path / "window.mcap"))
        rig.sleep(0.2)
        status = rig.must("status")
        threads = status["threads"]
        rig.must("record", action="stop")
        rig.must("stop")
    assert threads.pop("MainThread") == f"SCHED_FIFO {DEPLOYED_PRIORITY}", threads  # the cycle's (asyncio) thread
    assert {"dragd-sdo_0", "dragd-telemetry"} <= set(threads), threads  # (the two that start during boot)
    assert "dragd-control" in threads, threads  # the control socket's thread (below the cycle: the set below)
    assert any(name.startswith("dragd-exec") for name in threads), threads  # (the record window's writer opened)
    assert sum(name.startswith("dragd-telemetry") for name in threads) == 2, threads  # (the window's writer)
    assert set(threads.values()) == {"SCHED_FIFO 1"}, threads
    if os.geteuid() == 0:  # root may lock memory: the unit's claim
        assert status["memory_locked"] is True, status
    # PM QoS is opt-in (loop.cpu_latency_us), also as deployed: a default daemon leaves the CPUs' idle states alone
    assert status["cpu_latency"] == {"requested_us": None, "applied": False, "reason": "not requested",
                                     "effective_us": None}, status["cpu_latency"]
