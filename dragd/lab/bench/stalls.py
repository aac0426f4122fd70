"""The machine's own stalls beside a loop session, and which of the daemon's missed ticks they explain.

A virtual machine's host can stop all of its vCPUs for milliseconds (here, idle, measured with rt-tests' cyclictest at
SCHED_FIFO 80: 34 of 300,000 wake-ups over 1 ms late on each CPU, up to 11.7 ms; the long ones on both CPUs at the same
instant; docs/PERFORMANCE.md). No code in the guest can tick through that, so a missed-tick figure mixes the machine's
stalls with the daemon's own. `StallProbe` measures the machine in the same window: one probe process per CPU, pinned,
SCHED_FIFO above the daemon's cycle thread, waking on an absolute 1 kHz timerfd and noting every wake-up later than
``threshold_us`` (its deadline on CLOCK_MONOTONIC and how late). The probe does nothing else, so a wake-up that late is
the machine's: the hypervisor, or kernel work (the load's own system calls take tens of µs).

`attribute` splits the daemon's missed-tick episodes (the control socket's ``missed_ticks``: the late tick's
CLOCK_MONOTONIC time and the ticks it missed) into the ticks a probe's stall covers (the machine's, in whole periods)
and the rest, the daemon's own.
"""

from __future__ import annotations

import json
import math
import os
import select
import subprocess
import sys
import time
from collections.abc import Sequence
from typing import Any

PROBE_PRIORITY = 80  # above the cycle thread's 70 (docs/SYSTEMD.md) and the simulator's 60
PERIOD_US = 1000
THRESHOLD_US = 250  # idle here, 99.95 % of cyclictest's wake-ups are within 150 µs
MARGIN_S = 0.5e-3  # slack when matching a daemon episode to a probe's stall (the two clocks are one; ticks are not)
START_TIMEOUT_S = 10.0


class StallProbe:
    """Probe processes on every CPU of this process's affinity for the life of the ``with`` block."""

    def __init__(self, priority: int = PROBE_PRIORITY, period_us: int = PERIOD_US,
                 threshold_us: int = THRESHOLD_US) -> None:
        self.priority, self.period_us, self.threshold_us = priority, period_us, threshold_us
        self.cpus = sorted(os.sched_getaffinity(0))
        self._procs: list[subprocess.Popen[str]] = []
        self.results: list[dict[str, Any]] = []
        self.errors: list[str] = []

    def __enter__(self) -> StallProbe:
        if self._procs:
            raise RuntimeError("StallProbe: already running")
        try:
            for cpu in self.cpus:
                self._procs.append(subprocess.Popen(
                    [sys.executable, "-c", "from dragd.lab.bench.stalls import probe_main; probe_main()", str(cpu),
                     str(self.priority), str(self.period_us), str(self.threshold_us)],
                    stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
            for p in self._procs:  # each says it runs (or why not) before the window opens
                assert p.stdout is not None
                ready, _, _ = select.select([p.stdout], [], [], START_TIMEOUT_S)
                line = p.stdout.readline() if ready else ""
                if not line.startswith("ready"):
                    said = line.strip() or ("" if ready else f"no answer in {START_TIMEOUT_S:g} s")
                    self._stop()
                    raise OSError("stall probe: " + "; ".join([said] * bool(said) + self.errors))
        except BaseException:
            self._stop()
            self.results.clear()  # a partial set is no measurement of the machine
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop()

    def _stop(self) -> None:
        procs, self._procs = self._procs, []
        for p in procs:
            try:
                out, err = p.communicate("", timeout=10)  # EOF on stdin: the probe reports and exits
            except (subprocess.TimeoutExpired, OSError, ValueError):
                p.kill()
                out, err = p.communicate()
            lines = [ln for ln in (out or "").splitlines() if ln.startswith("{")]
            try:
                if p.returncode == 0 and lines:
                    self.results.append(json.loads(lines[-1]))
                    continue
            except ValueError:
                pass
            said = " ".join(ln for ln in (out or "").splitlines() if not ln.startswith(("{", "ready")))
            self.errors.append(f"stall probe exit {p.returncode}: {(said + ' ' + (err or '')).strip()[-300:]}")

    @property
    def pids(self) -> list[int]:
        """The running probes' process ids."""
        return [p.pid for p in self._procs]

    @property
    def complete(self) -> bool:
        """Every CPU's probe ran through and reported."""
        return len(self.results) == len(self.cpus) and not self.errors

    @property
    def stalls(self) -> list[list[tuple[float, float]]]:
        """Per probe: (deadline CLOCK_MONOTONIC s, lateness s) of each wake-up later than the threshold."""
        return [[(d, late) for d, late in r["stalls"]] for r in self.results]

    def summary(self) -> dict[str, Any]:
        """Wake-ups, late wake-ups per probe, the longest, and how many stalls every probe saw at once."""
        per = self.stalls
        wide = sum(1 for d, late in (per[0] if per else [])
                   if all(_overlap_s(d, d + late, other, 0.0) > 0.0 for other in per[1:]))
        return {"probes": len(per), "wakeups": sum(r["wakeups"] for r in self.results),
                "late_wakeups": [len(s) for s in per],
                "late_max_ms": max((late for s in per for _, late in s), default=0.0) * 1e3,
                "machine_wide_stalls": wide, "threshold_us": self.threshold_us}


def _overlap_s(t0: float, t1: float, stalls: Sequence[tuple[float, float]], margin_s: float) -> float:
    """How long the probe's late wake-ups (deadline, lateness) cover of [t0, t1], widened by ``margin_s``."""
    a, b = t0 - margin_s, t1 + margin_s
    return sum(max(0.0, min(b, d + late) - max(a, d)) for d, late in stalls)


def attribute(missed: Sequence[Sequence[float]], stalls: Sequence[Sequence[tuple[float, float]]], dt_s: float,
              margin_s: float = MARGIN_S) -> tuple[int, int]:
    """(ticks the daemon missed while a probe saw the machine stalled, the others).

    ``missed``: (CLOCK_MONOTONIC s of the late tick, ticks it missed) per episode; the cycle thread was kept from
    running somewhere in the ``ticks + 1`` periods before that tick. ``stalls``: per probe, (deadline, lateness).
    An episode's ticks are the machine's as far as a probe's stall covers its window (the longest cover over the
    probes, in whole periods rounded up, at most the episode's ticks); the rest are the daemon's own."""
    host = own = 0
    for t_tick, ticks in missed:
        n = int(ticks)
        t0 = t_tick - (n + 1) * dt_s
        cover = max((_overlap_s(t0, t_tick, s, margin_s) for s in stalls), default=0.0)
        k = min(n, math.ceil(cover / dt_s - 1e-9))
        host += k
        own += n - k
    return host, own


def probe_main() -> None:
    """One probe: ``python -c ... CPU PRIORITY PERIOD_US THRESHOLD_US``; runs until its stdin ends, then prints
    one JSON line: wake-ups, late wake-ups (deadline s, lateness s), the policy it ran under."""
    import gc

    from dragd.realtime import Ticker, set_realtime  # (imported before the priority is raised)

    cpu, priority, period_us, threshold_us = (int(a) for a in sys.argv[1:5])
    rt = set_realtime(priority, {cpu})
    bad = [v["reason"] for v in (rt["affinity"], rt["scheduler"]) if not v["applied"]]
    if bad:
        print(f"cannot run the probe on CPU {cpu} at SCHED_FIFO {priority}: {'; '.join(bad)}: the machine's stalls "
              "are not measured", flush=True)
        sys.exit(3)
    gc.disable()
    period_ns, threshold_ns = period_us * 1000, threshold_us * 1000
    ticker = Ticker(period_us * 1e-6)
    t0 = time.monotonic_ns() + period_ns
    ticker.start(t0)
    poll = select.poll()
    poll.register(ticker.fileno, select.POLLIN)
    poll.register(sys.stdin.fileno(), select.POLLIN | select.POLLHUP)
    stalls: list[tuple[float, float]] = []
    done = 0  # periods elapsed
    wakeups = 0
    print("ready", flush=True)
    while True:
        events = poll.poll()
        now = time.monotonic_ns()
        if any(fd != ticker.fileno for fd, _ in events):
            break
        try:
            n = int.from_bytes(os.read(ticker.fileno, 8), sys.byteorder)
        except BlockingIOError:
            continue
        late = now - (t0 + done * period_ns)  # from the first deadline this wake-up serves
        if late > threshold_ns:
            stalls.append(((t0 + done * period_ns) * 1e-9, late * 1e-9))
        done += n
        wakeups += 1
    ticker.close()
    print(json.dumps({"cpu": cpu, "wakeups": wakeups, "periods": done, "stalls": stalls}), flush=True)
