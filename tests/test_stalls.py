"""The machine-stall probes of the loop benchmarks and the split of the daemon's missed ticks by cause.

The attribution is checked on constructed episodes; the probes and the daemon's episodes (`missed_ticks`) on real
processes, stopped with SIGSTOP: a stop of the daemon alone is the daemon's own, a stop of the daemon and every probe
at once is what a stall of the whole machine looks like.
"""

from __future__ import annotations

import contextlib
import os
import signal
import time
from collections.abc import Iterator

import pytest

from dragd.lab.bench.stalls import StallProbe, attribute
from dragd.lab.rig import Rig

from daemon_helpers import wait_for

DT = 1e-3


@pytest.mark.unit
def test_missed_ticks_are_the_machines_as_far_as_a_probe_was_late_then() -> None:
    probe_a = [(10.0005, 0.012)]  # late 12 ms from 10.0005 s
    probe_b = [(10.0004, 0.0121), (20.0, 0.0012)]
    # a tick at 10.0125 that missed 11: the cycle was held in [10.0005, 10.0125], which the probes cover → the machine's
    assert attribute([(10.0125, 11)], [probe_a, probe_b], DT) == (11, 0)
    # the same episode with the probes on time: the daemon's own
    assert attribute([(10.0125, 11)], [[], [(30.0, 0.0004)]], DT) == (0, 11)
    # one probe's stall is enough (a vCPU the hypervisor stopped while the other ran)
    assert attribute([(20.0008, 1)], [[], probe_b], DT) == (1, 0)
    # a short stall of the machine inside a long one of the daemon explains only its own length (whole periods)
    assert attribute([(40.030, 29)], [[(40.010, 0.0003)]], DT) == (1, 28)
    assert attribute([(40.030, 29)], [[(40.010, 0.0052)], [(40.012, 0.0031)]], DT) == (6, 23)
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


@contextlib.contextmanager
def _probe() -> Iterator[StallProbe]:
    """Probes running, or the test skipped saying why (SCHED_FIFO 80 needs root or RLIMIT_RTPRIO >= 80)."""
    try:
        probe = StallProbe().__enter__()
    except OSError as e:
        pytest.skip(str(e))
    try:
        yield probe
    finally:
        probe.__exit__(None, None, None)


@pytest.mark.rig
def test_a_stopped_probe_reports_when_and_how_long() -> None:
    with _probe() as probe:
        time.sleep(0.3)
        t0, t1 = _stop_for(probe.pids, 0.030)
        time.sleep(0.3)
    assert probe.complete, probe.errors
    for r, stalls in zip(probe.results, probe.stalls, strict=True):
        assert r["wakeups"] > 400  # ~0.6 s at 1 kHz, the stop aside
        ours = [(d, late) for d, late in stalls if t0 - 0.002 <= d <= t1]
        assert len(ours) == 1, stalls  # the stop: one late wake-up, from the first deadline it covered
        d, late = ours[0]
        assert 0.025 <= late <= (t1 - t0) + 0.1 and d + late >= t1 - 0.002
    assert probe.summary()["machine_wide_stalls"] >= 1  # both stopped at once: seen on every CPU


@pytest.mark.rig
def test_the_daemons_missed_ticks_are_split_into_its_own_and_the_machines(tmp_path) -> None:
    # as deployed (SCHED_FIFO): the probes need real-time priority anyway, and a daemon at SCHED_OTHER beside a busy
    # machine is starved before and after each stop (45 ticks for a 30 ms stop beside two busy loops): its episodes
    # would be the scheduler's, not the stops this test makes (#28)
    rig = Rig("stalls", workdir=tmp_path, as_deployed=True)
    try:
        rig.start_sim()
        rig.start_daemon()
        wait_for(lambda: rig.must("status")["cycles"] > 300, 20.0, "the daemon's cycle to run")
        daemon = rig.daemon.proc.pid
        with _probe() as probe:
            time.sleep(0.3)
            before = rig.must("status")
            own0, own1 = _stop_for([daemon], 0.030)  # the daemon alone
            time.sleep(0.3)
            host0, host1 = _stop_for([daemon] + probe.pids, 0.030)  # as the machine stalls
            time.sleep(0.3)
            after = rig.must("status")
            log = rig.must("missed_ticks", since=before["missed_episodes"])
            bad = rig.call("missed_ticks", since=-1)
    finally:
        rig.close()
    assert probe.complete, probe.errors
    assert not bad["ok"] and "since: expected an episode number >= 0, got -1" in bad["error"]
    assert log["lost"] == 0 and len(log["episodes"]) >= after["missed_episodes"] - before["missed_episodes"] >= 2
    episodes = log["episodes"]
    own_ep = [e for e in episodes if own0 <= e[0] <= own1 + 0.01 and e[1] >= 20]
    host_ep = [e for e in episodes if host0 <= e[0] <= host1 + 0.01 and e[1] >= 20]
    assert len(own_ep) == 1 and len(host_ep) == 1, (episodes, (own0, own1), (host0, host1))
    assert own_ep[0][1] <= (own1 - own0) * 1e3 + 10 and host_ep[0][1] <= (host1 - host0) * 1e3 + 10
    n = host_ep[0][1]
    host, own = attribute(host_ep, probe.stalls, DT)
    assert host + own == n and own <= 1, (host, own)  # the probes' stop covers the daemon's (±1 tick of skew)
    # the probes ran on through the daemon's own stop: only a real stall of the machine in those 30 ms would be
    # counted to it, and no more than its length: what one probe was late in all, summed over its late wake-ups
    # in the episode's window (a loaded host stalls a probe more than once in 30 ms)
    t_tick, n = own_ep[0]
    host, own = attribute(own_ep, probe.stalls, DT)
    covered = max((sum(late for d, late in s if d + late >= t_tick - (n + 1) * DT - 0.001 and d <= t_tick + 0.001)
                   for s in probe.stalls), default=0.0)
    assert host + own == n and host <= covered / DT + 1, (host, own, covered, probe.stalls)
    assert sum(ticks for _, ticks in episodes) >= after["missed_cycles"] - before["missed_cycles"]


@pytest.mark.unit
def test_the_daemon_keeps_its_last_episodes_and_counts_those_it_lost() -> None:
    import types

    import numpy as np

    from dragd.daemon.cycle import MISSED_LOG, Cycle

    n = MISSED_LOG + 40
    log = np.zeros((MISSED_LOG, 2))
    for k in range(n):  # as the tick writes them: episode k in row k % MISSED_LOG
        log[k % MISSED_LOG] = (100.0 + k, 1 + k % 3)
    cy = types.SimpleNamespace(missed_episodes=n, _missed_log=log)
    rows, lost = Cycle.missed_since(cy, 0)  # type: ignore[arg-type]
    assert lost == 40 and len(rows) == MISSED_LOG and rows[0] == [140.0, 1 + 40 % 3] and rows[-1][0] == 100.0 + n - 1
    rows, lost = Cycle.missed_since(cy, n - 5)  # type: ignore[arg-type]
    assert lost == 0 and [r[0] for r in rows] == [100.0 + k for k in range(n - 5, n)]
    assert Cycle.missed_since(cy, n) == ([], 0) and Cycle.missed_since(cy, n + 7) == ([], 0)  # type: ignore[arg-type]
