"""The machine-stall probes of the loop benchmarks and the split of the daemon's missed ticks by cause.

The attribution is checked on constructed episodes; the probes and the daemon's `missed_recent` on real processes,
stopped with SIGSTOP: a stop of the daemon alone is the daemon's own, a stop of the daemon and every probe at once
is what a stall of the whole machine looks like.
"""

from __future__ import annotations

import os
import signal
import time

import pytest

from dragd.lab.bench.stalls import StallProbe, attribute
from dragd.lab.rig import Rig

from daemon_helpers import wait_for

DT = 1e-3


@pytest.mark.unit
def test_missed_ticks_are_the_machines_only_when_a_probe_was_late_then() -> None:
    probe_a = [(10.0005, 0.012)]  # late 12 ms from 10.0005 s
    probe_b = [(10.0004, 0.0121), (20.0, 0.0003)]
    # a tick at 10.0125 that missed 11: the cycle was held in [10.0005, 10.0125] → the machine's
    assert attribute([(10.0125, 11)], [probe_a, probe_b], DT) == (11, 0)
    # the same episode with the probes on time: the daemon's own
    assert attribute([(10.0125, 11)], [[], [(30.0, 0.0004)]], DT) == (0, 11)
    # one probe's stall is enough (a vCPU the hypervisor stopped while the other ran)
    assert attribute([(20.0008, 1)], [[], probe_b], DT) == (1, 0)
    # an episode that ended before the probe's stall began, or began after it ended, is not explained by it
    assert attribute([(9.990, 3)], [probe_a], DT) == (0, 3)
    assert attribute([(10.0200, 1)], [probe_a], DT) == (0, 1)
    # several episodes are split one by one; no probe at all: everything is the daemon's
    assert attribute([(10.0125, 11), (15.0, 2), (20.0008, 1)], [probe_a, probe_b], DT) == (12, 2)
    assert attribute([(10.0125, 11)], [], DT) == (0, 11)


def _stop_for(pids: list[int], seconds: float) -> tuple[float, float]:
    t0 = time.monotonic()
    for pid in pids:
        os.kill(pid, signal.SIGSTOP)
    time.sleep(seconds)
    for pid in pids:
        os.kill(pid, signal.SIGCONT)
    return t0, time.monotonic()


def _fifo_permitted() -> bool:
    try:
        os.sched_param(80)
        return os.sched_get_priority_max(os.SCHED_FIFO) >= 80 and (os.geteuid() == 0 or
                                                                    os.getrlimit(os.RLIMIT_RTPRIO)[0] >= 80)
    except (AttributeError, OSError):
        return False


needs_fifo = pytest.mark.skipif(not _fifo_permitted(), reason="the probes run SCHED_FIFO 80: needs root or "
                                                             "RLIMIT_RTPRIO >= 80")


@pytest.mark.rig
@needs_fifo
def test_a_stopped_probe_reports_when_and_how_long() -> None:
    with StallProbe() as probe:
        time.sleep(0.3)
        t0, t1 = _stop_for([p.pid for p in probe._procs], 0.030)
        time.sleep(0.3)
    assert not probe.errors and len(probe.results) == len(probe.cpus)
    for r, stalls in zip(probe.results, probe.stalls, strict=True):
        assert r["wakeups"] > 400  # ~0.6 s at 1 kHz, the stop aside
        long = [(d, late) for d, late in stalls if late > 0.02]
        assert len(long) == 1, stalls
        d, late = long[0]
        assert t0 - 0.002 <= d <= t1 and 0.025 <= late <= (t1 - t0) + 0.1 and d + late >= t1 - 0.002
    assert probe.summary()["machine_wide_stalls"] >= 1  # both stopped at once: seen on every CPU


@pytest.mark.rig
@needs_fifo
def test_the_daemons_missed_ticks_are_split_into_its_own_and_the_machines(tmp_path) -> None:
    rig = Rig("stalls", workdir=tmp_path)
    try:
        rig.start_sim()
        rig.start_daemon()
        wait_for(lambda: rig.must("status")["cycles"] > 300, 20.0, "the daemon's cycle to run")
        daemon = rig.daemon.proc.pid
        with StallProbe() as probe:
            time.sleep(0.3)
            before = rig.must("status")
            own0, own1 = _stop_for([daemon], 0.030)  # the daemon alone
            time.sleep(0.3)
            host0, host1 = _stop_for([daemon] + [p.pid for p in probe._procs], 0.030)  # as the machine stalls
            time.sleep(0.3)
            after = rig.must("status")
    finally:
        rig.close()
    new = after["missed_episodes"] - before["missed_episodes"]
    episodes = after["missed_recent"][-new:]
    own_ep = [e for e in episodes if own0 <= e[0] <= own1 + 0.01 and e[1] >= 20]
    host_ep = [e for e in episodes if host0 <= e[0] <= host1 + 0.01 and e[1] >= 20]
    assert len(own_ep) == 1 and len(host_ep) == 1, (episodes, (own0, own1), (host0, host1))
    assert own_ep[0][1] <= (own1 - own0) * 1e3 + 10 and host_ep[0][1] <= (host1 - host0) * 1e3 + 10
    assert attribute(host_ep, probe.stalls, DT) == (host_ep[0][1], 0)
    host, own = attribute(own_ep, probe.stalls, DT)
    # the probes ran on through the daemon's own stop: at most a real stall of the machine in those 30 ms (a short
    # one: the long ones are a few a minute) would be counted to it, rightly
    overlapping = [late for s in probe.stalls for d, late in s if own0 - 0.002 <= d <= own1 + 0.002]
    assert (host, own) == (0, own_ep[0][1]) or max(overlapping) < 0.005, (host, own, overlapping)
    assert sum(ticks for _, ticks in episodes) <= after["missed_cycles"] - before["missed_cycles"]
