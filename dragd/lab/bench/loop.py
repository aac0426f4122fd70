"""Loop benchmarks: the daemon's 1 kHz cycle with the simulated robot beside it (separate processes).

One session (default 60 s of drag, `--seconds`) yields ``loop_period_p99_us``, ``loop_missed_ratio``,
``loop_compute_us``, ``sim_rtf``, ``daemon_cpu_pct``, ``sim_cpu_pct`` and the CPU time per cycle
(``daemon_cpu_us_per_cycle``, ``sim_cpu_us_per_cycle``: far less sensitive to other load on the machine than the
latency figures); running several of them in one ``dragd bench`` call shares the session. ``--config`` gives the
daemon's configuration (several buses: one private multicast group each), ``--sim-config`` the simulator's truth
(e.g. config/loop_2khz.yaml with sim/config/seed_cobot_two_buses.yaml: the 2 kHz figures), ``--profile DIR``
samples both processes with py-spy over the session.
``bus_load`` is the worst-case load of the configured PDO layout (no session needed).

Every session also measures the machine's own stalls in its window (dragd/lab/bench/stalls.py: a probe process per
CPU at SCHED_FIFO 80, or 10 above ``--realtime-priority``): ``loop_missed_ratio_own`` counts only the missed ticks no
probe's stall explains, ``host_stall_max_ms`` is the longest stall. The probes cost the daemon a few µs a cycle (their
wake-ups preempt it), which weighs against its figures, never for them.

The session runs as deployed (docs/SYSTEMD.md): the daemon's cycle thread SCHED_FIFO 70 and the simulator's
threads 60, where the system permits it (`--realtime-priority 0`: both SCHED_OTHER). The policy in force is
printed on stderr (``dragd status`` → ``scheduler``).

The lockstep session (``lockstep_rtf``, ``lockstep_daemon_cpu_us_per_cycle``, ``lockstep_sim_cpu_us_per_cycle``)
runs the same drag on the lockstep clock (dragd/clock.py): ``--seconds`` of simulated time granted at once, as fast
as both processes go; the real-time factor and the CPU each process spent per cycle. Every CPU-per-cycle figure
carries the run's yardstick (dragd/lab/bench/yardstick.py) in its ``detail``: the figure in yardsticks compares
across machines.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from functools import lru_cache
from pathlib import Path

from dragd.lab.bench import BenchError, benchmark
from dragd.lab.bench.stalls import PROBE_PRIORITY, StallProbe, attribute
from dragd.lab.bench.yardstick import yardstick_us_once

REALTIME_PRIORITY = 70  # the cycle thread's SCHED_FIFO priority as deployed (docs/SYSTEMD.md); the sim's is 10 below
# (at least 1: with --realtime-priority 1..10 both run at the same priority)


def process_cpu_s(pid: int) -> float:
    """CPU time (user + system, all threads) the process ``pid`` has used so far, from /proc/<pid>/stat."""
    with open(f"/proc/{pid}/stat", "rb") as f:
        fields = f.read().rsplit(b")", 1)[1].split()  # after the command name (which may hold spaces)
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime, stime (fields 14, 15)


def _py_spy(profile: str | None, seconds: float, pids: dict[str, int]) -> list[subprocess.Popen]:
    """Start one py-spy sampler per process for the session: DIR/<name>.txt, collapsed stacks per thread."""
    if not profile:
        return []
    exe = shutil.which("py-spy") or str(Path(sys.executable).with_name("py-spy"))
    if not Path(exe).exists():
        raise BenchError("--profile: py-spy is not installed here (pip install 'dragd[profile]'; ./dev installs it)")
    out = Path(profile)
    out.mkdir(parents=True, exist_ok=True)
    return [subprocess.Popen([exe, "record", "-r", "250", "-d", str(max(1, round(seconds))), "-f", "raw", "--threads",
                              "--nonblocking", "-o", str(out / f"{name}.txt"), "-p", str(pid)],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL) for name, pid in pids.items()]


def profile_summary(stacks: Path, top: int = 25) -> str:
    """Self and inclusive sample shares per function from py-spy's collapsed stacks (``frame;frame;... count``)."""
    own: dict[str, int] = {}
    incl: dict[str, int] = {}
    total = 0
    for line in stacks.read_text().splitlines():
        path, _, n = line.rpartition(" ")
        if not path or not n.isdigit():
            continue
        count = int(n)
        frames = [f.split(" (")[0] + " (" + f.split(" (")[-1].split(":")[0].rsplit("/", 1)[-1] + ")" if " (" in f else f
                  for f in path.split(";")]
        total += count
        own[frames[-1]] = own.get(frames[-1], 0) + count
        for f in set(frames):
            incl[f] = incl.get(f, 0) + count
    lines = [f"{stacks.stem}: {total} samples"]
    for title, d in (("self", own), ("inclusive", incl)):
        lines.append(f"  top {title}:")
        lines += [f"    {100 * c / max(1, total):5.1f} %  {f}"
                  for f, c in sorted(d.items(), key=lambda kv: -kv[1])[:top]]
    return "\n".join(lines)


TELEMETRY = {  # session variant -> `dragd run` telemetry options (None: no telemetry file)
    "off": None,
    "foxglove": [],  # as configured by default: every cycle + Foxglove channels at 30 Hz
    "plain": ["--no-foxglove"],
    "view": None,  # no telemetry file; `dragd view` beside the daemon (its own process, polling status at 50 Hz)
}


@lru_cache(maxsize=8)
def _session(seconds: float, config: str | None, priority: int, profile: str | None = None,
             sim_config: str | None = None, telemetry: str = "off") -> dict:
    import tempfile

    from dragd.config import load_config
    from dragd.lab.rig import ProcessError, Rig, multicast_group, timing_fault

    yardstick_us_once()  # (measured before the session's processes start: the same run, a quiet moment of it)
    rt = ["--realtime-priority", str(priority)] if priority else []
    sim_rt = ["--realtime-priority", str(max(1, priority - 10))] if priority else []
    cfg = load_config(config)
    n_buses = len(cfg.buses)
    tel_args = TELEMETRY[telemetry]
    tmp = Path(tempfile.mkdtemp(prefix="dragd-bench-tel-"))
    tel_path = tmp / "telemetry.mcap" if tel_args is not None else None
    with Rig("bench", config=Path(config) if config else None, sim_config=Path(sim_config) if sim_config else None,
             daemon_args=rt + (tel_args or []), sim_args=sim_rt, telemetry=tel_path) as rig:
        if n_buses > 1:  # one private multicast group per configured bus (the sim's truth maps joints to them)
            rig.bus = ",".join(f"udp_multicast:{multicast_group(f'bench{k}')}" for k in range(n_buses))
        rig.start_sim()
        rig.start_daemon()
        if priority:  # measure what was asked for, or say why not (never SCHED_OTHER figures labelled FIFO)
            got = {"daemon": rig.must("status").get("scheduler"), "simulator": rig.sim_call("state").get("scheduler")}
            bad = {k: v for k, v in got.items() if not str(v).startswith("SCHED_FIFO")}
            if bad:
                raise BenchError(f"loop benchmark: SCHED_FIFO {priority} was asked for but not applied ("
                                 + "; ".join(f"{k}: {v}" for k, v in bad.items()) + "): run as root or with "
                                 f"RLIMIT_RTPRIO >= {priority} (ulimit -r), or pass --realtime-priority 0 to measure "
                                 "SCHED_OTHER")
        rig.must("start")
        time.sleep(0.5)
        try:
            rig.must("mode", mode="drag")
        except ProcessError:  # (#28: refused after a communication deadline passed: said below with the figures)
            faults = rig.must("status").get("faults") or []
            if not faults or not all(timing_fault(f) for f in faults):
                raise
        rig.sim_call("operator", scenario="flange_drag")
        viewer = _viewer(rig.socket, tmp / "view.rrd", seconds, config) if telemetry == "view" else None
        probe = StallProbe(min(99, max(PROBE_PRIORITY, priority + 10)))
        try:
            try:  # the machine's own stalls in the same window (dragd/lab/bench/stalls.py)
                probe.__enter__()
            except OSError as e:
                probe.errors.append(str(e))
            if rig.daemon is None or rig.sim is None:
                raise BenchError("loop benchmark: the simulator and the daemon did not start")
            pids = (rig.daemon.proc.pid, rig.sim.proc.pid)
            before = rig.must("status")
            sim0, w0 = rig.sim_call("state"), time.monotonic()
            spies = _py_spy(profile, seconds, {"daemon": pids[0], "sim": pids[1]})
            cpu0, c0 = [process_cpu_s(p) for p in pids], time.monotonic()
            time.sleep(seconds)
            cpu1, c1 = [process_cpu_s(p) for p in pids], time.monotonic()
            after = rig.must("status")
            if viewer is not None:
                _viewer_done(viewer, tmp / "view.rrd")
            missed_log = rig.must("missed_ticks", since=before["missed_episodes"])  # the window's episodes:
            n_new = after["missed_episodes"] - before["missed_episodes"]
            missed_log["episodes"] = missed_log["episodes"][:max(0, n_new - missed_log["lost"])]
        finally:  # (whatever failed above: neither the probes nor the viewer outlive the session)
            try:
                probe.__exit__(None, None, None)
            finally:
                if viewer is not None and viewer.poll() is None:
                    _stop(viewer)
        for spy in spies:
            spy.wait(60)
        sim1, w1 = rig.sim_call("state"), time.monotonic()
        rig.must("stop")
    # a fault, a guard trip or a hold by request mid-session: the figures would not be of the drag loop. A feedback
    # hold (stale TPDOs on an overloaded host) is the daemon's own pause: it resumes drag by itself — counted, said
    paused = (after.get("mode") == "hold" and after.get("feedback_hold") and after.get("requested_mode") == "drag"
              and after.get("fault_count") == before.get("fault_count")
              and (after.get("guard") or {}).get("trips") == (before.get("guard") or {}).get("trips"))
    # (#28) a communication deadline that passed (the drives' RPDO deadline, heartbeats, lost feedback) is what the
    # machine did to the real-time path on the wall clock: a figure, said with the machine's stalls below, not a failure
    # (the session's daemon is its own: every fault it has is of this run, also one between `mode drag` and the window)
    faults = after.get("faults") or []
    timed_out = bool(faults) and all(timing_fault(f) for f in faults)
    if timed_out:
        print(f"bench: the daemon faulted on a communication deadline ({faults[-1].get('text')}); the figures below "
              "are the session's, the machine's stalls with them", file=sys.stderr)
    if after.get("mode") != "drag" and not paused and not timed_out:
        guard = after.get("guard") or {}
        raise BenchError(f"loop benchmark: the daemon left drag during the session (mode {after.get('mode')!r}, "
                         f"requested {after.get('requested_mode')!r}, feedback hold {after.get('feedback_hold')}, "
                         f"guard trips {guard.get('trips')} (last {guard.get('last_trip')}), last fault: "
                         f"{(after.get('faults') or ['none'])[-1]}); is the machine overloaded? "
                         f"daemon log: {rig.daemon.log_path if rig.daemon else '?'}")
    holds = int(after.get("feedback_holds", 0)) - int(before.get("feedback_holds", 0))
    if holds:
        print(f"bench: {holds} feedback hold(s) during the session (stale drive feedback: an overloaded host); the "
              "daemon resumed drag by itself", file=sys.stderr)
    shutil.rmtree(tmp, ignore_errors=True)
    tel0, tel1 = before.get("telemetry") or {}, after.get("telemetry") or {}  # the writer's counters
    qos = after.get("cpu_latency") or {}
    print(f"bench: loop session {seconds:.0f} s, telemetry {telemetry}, daemon cycle thread {after.get('scheduler')}, "
          "CPU wake-up latency " + (f"held to {qos.get('effective_us')} µs" if qos.get("applied")
                                    else f"not held ({qos.get('reason')})"), file=sys.stderr)
    if profile:
        for name in ("daemon", "sim"):
            stacks = Path(profile) / f"{name}.txt"
            if stacks.exists():
                summary = profile_summary(stacks)
                stacks.with_name(f"{name}-top.txt").write_text(summary + "\n")
                print(summary, file=sys.stderr)
    cycles = after["cycles"] - before["cycles"]
    missed = after["missed_cycles"] - before["missed_cycles"]
    host, own = _missed_by_cause(missed, missed_log, probe, 1.0 / cfg.loop.rate_Hz)
    if probe.complete:
        st = probe.summary()
        print(f"bench: the machine's stalls (probes at SCHED_FIFO {probe.priority} on CPUs {probe.cpus}): "
              f"{st['late_wakeups']} wake-ups over {probe.threshold_us} µs late, the longest "
              f"{st['late_max_ms']:.1f} ms, "
              f"{st['machine_wide_stalls']} on every CPU at once; the daemon's {missed} missed ticks: {host} during "
              f"them, {own} its own", file=sys.stderr)
    else:
        print(f"bench: the machine's stalls not measured ({'; '.join(probe.errors)})", file=sys.stderr)
    wall = c1 - c0  # the window the CPU times were read over
    d_cpu, s_cpu = cpu1[0] - cpu0[0], cpu1[1] - cpu0[1]
    ticks = max(1, cycles + missed)
    return {
        "daemon_cpu_pct": 100.0 * d_cpu / wall,  # share of one core (the sim's and the daemon's own CPU time)
        "sim_cpu_pct": 100.0 * s_cpu / wall,
        "daemon_cpu_us_per_cycle": 1e6 * d_cpu / ticks,
        "sim_cpu_us_per_cycle": 1e6 * s_cpu / ticks,
        "period_p99_us": after["period_p99_us"],
        "missed_ratio": missed / max(1, cycles + missed),
        # the ticks missed while no probe saw the machine stalled (None: the probes could not run)
        "missed_ratio_own": own / max(1, cycles + missed) if probe.complete else None,
        "host_stall_max_ms": probe.summary()["late_max_ms"] if probe.complete else None,
        "probe_errors": probe.errors,
        "compute_p50_us": after["compute_p50_us"],
        "rtf": (sim1["t"] - sim0["t"]) / (w1 - w0),  # sim time over wall time, this session only
        "telemetry_dropped": tel1.get("dropped", 0) - tel0.get("dropped", 0) if tel1 else 0,
    }


def _missed_by_cause(missed: int, log: dict, probe: StallProbe, dt_s: float) -> tuple[int, int]:
    """The session's ``missed`` ticks: (while a probe saw the machine stalled, the daemon's own), from the daemon's
    episodes of the session (`missed_ticks`). Episodes it no longer keeps (``lost``) count as its own."""
    if log.get("lost"):
        print(f"bench: {log['lost']} missed-tick episodes of the session were no longer kept by the daemon: counted "
              "as its own", file=sys.stderr)
    host, _ = attribute(log.get("episodes") or [], probe.stalls, dt_s) if probe.complete else (0, 0)
    host = min(host, missed)
    return host, missed - host


def _viewer(socket: str, rrd: Path, seconds: float, config: str | None) -> subprocess.Popen:
    """`dragd view` beside the daemon for the session (a Rerun recording to ``rrd``: no viewer window here)."""
    try:
        import rerun  # noqa: F401
    except ImportError:
        raise BenchError("loop_period_p99_us_view needs the optional extra dragd[rerun] (rerun-sdk)") from None
    err = rrd.with_suffix(".err")  # (a file, not a pipe nobody reads while the session runs)
    with err.open("w") as f:
        proc = subprocess.Popen([sys.executable, "-m", "dragd", "view", "--socket", socket, "--save", str(rrd),
                                 "--seconds", f"{seconds + 30:.0f}", *(["--config", config] if config else [])],
                                stdout=subprocess.DEVNULL, stderr=f)
    # its start-up (imports, the URDF) before the measured window: until its recording is open (#28: a fixed 3 s was
    # not enough on a loaded machine, SIGINT then found it still importing and nothing was recorded), hang guard 120 s
    end = time.monotonic() + 120.0
    while proc.poll() is None and not rrd.exists() and time.monotonic() < end:
        time.sleep(0.1)
    if proc.poll() is not None:
        raise BenchError(f"dragd view exited at start (exit {proc.returncode}): {err.read_text()[-500:]}")
    if not rrd.exists():
        _stop(proc)
        raise BenchError(f"dragd view did not open its recording {rrd} within 120 s: {err.read_text()[-500:]}")
    return proc


def _viewer_done(proc: subprocess.Popen, rrd: Path) -> None:
    """Stop the viewer and check that it recorded throughout."""
    alive = proc.poll() is None
    _stop(proc)
    if not alive or not rrd.exists() or rrd.stat().st_size == 0:
        err = rrd.with_suffix(".err")
        raise BenchError(f"dragd view did not record through the session (exit {proc.returncode}, "
                         f"{rrd} {'missing' if not rrd.exists() else 'empty'}): "
                         f"{err.read_text()[-500:] if err.exists() else ''}")


def _stop(proc: subprocess.Popen) -> None:
    """SIGINT (the view closes its recording), then SIGKILL after 30 s."""
    import signal

    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(30)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def _opts(opts: dict) -> tuple[float, str | None, int, str | None, str | None]:
    prio = opts.get("realtime_priority")
    return (float(opts.get("seconds", 60.0)), str(opts["config"]) if opts.get("config") else None,
            REALTIME_PRIORITY if prio is None else int(prio), str(opts["profile"]) if opts.get("profile") else None,
            str(opts["sim_config"]) if opts.get("sim_config") else None)


@benchmark("loop_period_p99_us", "us")
def loop_period_p99_us(opts: dict) -> float:
    """99th percentile of the cycle period with the simulated robot beside the daemon (drag, operator pushing)."""
    return float(_session(*_opts(opts))["period_p99_us"])


@benchmark("loop_missed_ratio", "ratio")
def loop_missed_ratio(opts: dict) -> float:
    """Missed ticks / ticks over the session (timerfd expirations > 1)."""
    return float(_session(*_opts(opts))["missed_ratio"])


def _probed(opts: dict, key: str) -> float:
    out = _session(*_opts(opts))
    if out[key] is None:
        raise BenchError(f"{key}: the machine's stalls were not measured ({'; '.join(out['probe_errors'])})")
    return float(out[key])


@benchmark("loop_missed_ratio_own", "ratio")
def loop_missed_ratio_own(opts: dict) -> float:
    """loop_missed_ratio without the ticks missed while the machine itself stalled (a probe per CPU, SCHED_FIFO 80)."""
    return _probed(opts, "missed_ratio_own")


@benchmark("host_stall_max_ms", "ms")
def host_stall_max_ms(opts: dict) -> float:
    """The machine's longest stall in the loop session: the latest wake-up of a probe that does nothing else."""
    return _probed(opts, "host_stall_max_ms")


@benchmark("loop_compute_us", "us")
def loop_compute_us(opts: dict) -> float:
    """Median time from the last TPDO (or the deadline) to the RPDOs written (sent; on a batching udp_multicast bus
    queued to leave with the next SYNC): estimate + compute + write."""
    return float(_session(*_opts(opts))["compute_p50_us"])


@benchmark("sim_rtf", "ratio")
def sim_rtf(opts: dict) -> float:
    """Real-time factor of the simulated robot (sim time / wall time) while the daemon runs beside it."""
    return float(_session(*_opts(opts))["rtf"])


@benchmark("daemon_cpu_pct", "%")
def daemon_cpu_pct(opts: dict) -> float:
    """The daemon's CPU time over the loop session as a share of one core (drag at the configured rate)."""
    return float(_session(*_opts(opts))["daemon_cpu_pct"])


@benchmark("sim_cpu_pct", "%")
def sim_cpu_pct(opts: dict) -> float:
    """The simulator's CPU time over the loop session as a share of one core (physics + drives + bus)."""
    return float(_session(*_opts(opts))["sim_cpu_pct"])


def _in_yardsticks(us: float) -> tuple[float, dict[str, float]]:
    y = yardstick_us_once()
    return us, {"yardstick_us": round(y, 3), "yardsticks": round(us / y, 4)}


@benchmark("daemon_cpu_us_per_cycle", "us")
def daemon_cpu_us_per_cycle(opts: dict) -> tuple[float, dict[str, float]]:
    """The daemon's CPU time per cycle over the loop session (all threads; less load-sensitive than latency)."""
    return _in_yardsticks(float(_session(*_opts(opts))["daemon_cpu_us_per_cycle"]))


@benchmark("sim_cpu_us_per_cycle", "us")
def sim_cpu_us_per_cycle(opts: dict) -> tuple[float, dict[str, float]]:
    """The simulator's CPU time per daemon cycle over the loop session (4 physics steps + SYNC answers each)."""
    return _in_yardsticks(float(_session(*_opts(opts))["sim_cpu_us_per_cycle"]))


@lru_cache(maxsize=4)
def _lockstep_session(seconds: float, config: str | None, sim_config: str | None) -> dict:
    """The drag session on the lockstep clock: ``seconds`` of simulated time granted at once."""
    from dragd.config import load_config
    from dragd.lab.rig import Rig, multicast_group

    yardstick_us_once()
    cfg = load_config(config)
    with Rig("bench-lockstep", config=Path(config) if config else None,
             sim_config=Path(sim_config) if sim_config else None, lockstep=True) as rig:
        if len(cfg.buses) > 1:
            rig.bus = ",".join(f"udp_multicast:{multicast_group(f'bench{k}')}" for k in range(len(cfg.buses)))
        rig.start_sim()
        rig.start_daemon()
        rig.must("start")
        rig.sleep(0.5)
        rig.must("mode", mode="drag")
        rig.sim_call("operator", scenario="flange_drag")
        rig.sleep(0.2)
        assert rig.daemon is not None and rig.sim is not None
        pids = (rig.daemon.proc.pid, rig.sim.proc.pid)
        before = rig.must("status")
        cpu0, w0 = [process_cpu_s(p) for p in pids], time.monotonic()
        rig.sleep(seconds)
        cpu1, w1 = [process_cpu_s(p) for p in pids], time.monotonic()
        after = rig.must("status")
        rig.must("stop")
    if after.get("mode") != "drag":
        raise BenchError(f"lockstep loop benchmark: the daemon left drag (mode {after.get('mode')!r}, last fault "
                         f"{(after.get('faults') or ['none'])[-1]})")
    cycles = max(1, after["cycles"] - before["cycles"])
    wall = w1 - w0
    print(f"bench: lockstep session {seconds:g} s of simulated time in {wall:.2f} s of wall time ({cycles} cycles)",
          file=sys.stderr)
    return {"rtf": seconds / wall, "daemon_cpu_us_per_cycle": 1e6 * (cpu1[0] - cpu0[0]) / cycles,
            "sim_cpu_us_per_cycle": 1e6 * (cpu1[1] - cpu0[1]) / cycles}


def _lockstep_opts(opts: dict) -> tuple[float, str | None, str | None]:
    seconds, config, _prio, _profile, sim_config = _opts(opts)
    return seconds, config, sim_config


@benchmark("lockstep_rtf", "ratio")
def lockstep_rtf(opts: dict) -> float:
    """Simulated time over wall time of the drag session on the lockstep clock (as fast as both processes go)."""
    return float(_lockstep_session(*_lockstep_opts(opts))["rtf"])


@benchmark("lockstep_daemon_cpu_us_per_cycle", "us")
def lockstep_daemon_cpu_us_per_cycle(opts: dict) -> tuple[float, dict[str, float]]:
    """The daemon's CPU time per cycle on the lockstep clock (all threads; the clock's bookkeeping included)."""
    return _in_yardsticks(float(_lockstep_session(*_lockstep_opts(opts))["daemon_cpu_us_per_cycle"]))


@benchmark("lockstep_sim_cpu_us_per_cycle", "us")
def lockstep_sim_cpu_us_per_cycle(opts: dict) -> tuple[float, dict[str, float]]:
    """The simulator's CPU time per cycle on the lockstep clock (a period's physics, the SYNC answer, TIME)."""
    return _in_yardsticks(float(_lockstep_session(*_lockstep_opts(opts))["sim_cpu_us_per_cycle"]))


@benchmark("bus_load", "%")
def bus_load(opts: dict) -> float:
    """Worst-case bus load (bit stuffing included) of the configured PDO layout, highest over the buses."""
    from dragd.config import load_config
    from dragd.daemon.core import bus_layouts

    cfg = load_config(opts.get("config"))
    layouts = bus_layouts(cfg)
    heartbeat_Hz = 1000.0 / cfg.master.heartbeat_ms
    return max(layouts[b.name].budget(cfg.loop.rate_Hz, b.bitrate, b.data_bitrate, heartbeat_Hz).percent
               for b in cfg.buses)


def _telemetry(opts: dict, variant: str) -> dict:
    out = _session(*_opts(opts), telemetry=variant)
    if out["telemetry_dropped"]:
        raise BenchError(f"telemetry ({variant}): the writer dropped {out['telemetry_dropped']} rows")
    return out


@benchmark("loop_period_p99_us_foxglove", "us")
def loop_period_p99_us_foxglove(opts: dict) -> float:
    """loop_period_p99_us with the telemetry MCAP written (every cycle + Foxglove channels at 30 Hz, default)."""
    return float(_telemetry(opts, "foxglove")["period_p99_us"])


@benchmark("loop_period_p99_us_view", "us")
def loop_period_p99_us_view(opts: dict) -> float:
    """loop_period_p99_us with `dragd view` beside the daemon (polling its status at 50 Hz, a Rerun recording)."""
    return float(_telemetry(opts, "view")["period_p99_us"])


@benchmark("loop_missed_ratio_view", "ratio")
def loop_missed_ratio_view(opts: dict) -> float:
    """loop_missed_ratio with `dragd view` beside the daemon."""
    return float(_telemetry(opts, "view")["missed_ratio"])


@benchmark("loop_period_p99_us_telemetry_plain", "us")
def loop_period_p99_us_telemetry_plain(opts: dict) -> float:
    """loop_period_p99_us with the telemetry MCAP written without the Foxglove channels (--no-foxglove)."""
    return float(_telemetry(opts, "plain")["period_p99_us"])
