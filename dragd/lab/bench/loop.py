"""Loop benchmarks: the daemon's 1 kHz cycle with the simulated robot beside it (separate processes).

One session (default 60 s of drag, `--seconds`) yields ``loop_period_p99_us``, ``loop_missed_ratio``,
``loop_compute_us`` and ``sim_rtf``; running several of them in one ``dragd bench`` call shares the session.
``bus_load`` is the worst-case load of the configured PDO layout (no session needed).

The session runs as deployed (docs/SYSTEMD.md): the daemon's cycle thread SCHED_FIFO 70 and the simulator's
threads 60, where the system permits it (`--realtime-priority 0`: both SCHED_OTHER). The policy in force is
printed on stderr (``dragd status`` → ``scheduler``).
"""

from __future__ import annotations

import sys
import time
from functools import lru_cache
from pathlib import Path

from dragd.lab.bench import BenchError, benchmark


REALTIME_PRIORITY = 70  # the cycle thread's SCHED_FIFO priority as deployed (docs/SYSTEMD.md); the sim's is 10 below
# (at least 1: with --realtime-priority 1..10 both run at the same priority)


TELEMETRY = {  # session variant -> `dragd run` telemetry options (None: no telemetry file)
    "off": None,
    "foxglove": [],  # as configured by default: every cycle + Foxglove channels at 30 Hz
    "plain": ["--no-foxglove"],
}


@lru_cache(maxsize=8)
def _session(seconds: float, config: str | None, priority: int, telemetry: str = "off") -> dict:
    from dragd.lab.rig import Rig

    rt = ["--realtime-priority", str(priority)] if priority else []
    sim_rt = ["--realtime-priority", str(max(1, priority - 10))] if priority else []
    tel_args = TELEMETRY[telemetry]
    import tempfile

    tmp = Path(tempfile.mkdtemp(prefix="dragd-bench-tel-"))
    tel_path = tmp / "telemetry.mcap" if tel_args is not None else None
    with Rig("bench", config=Path(config) if config else None, daemon_args=rt + (tel_args or []), sim_args=sim_rt,
             telemetry=tel_path) as rig:
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
        rig.must("mode", mode="drag")
        rig.sim_call("operator", scenario="flange_drag")
        before = rig.must("status")
        sim0, w0 = rig.sim_call("state"), time.monotonic()
        time.sleep(seconds)
        sim1, w1 = rig.sim_call("state"), time.monotonic()
        after = rig.must("status")
        tel0, tel1 = before.get("telemetry") or {}, after.get("telemetry") or {}  # the writer's counters
        rig.must("stop")
    print(f"bench: loop session {seconds:.0f} s, telemetry {telemetry}, daemon cycle thread {after.get('scheduler')}",
          file=sys.stderr)
    import shutil

    shutil.rmtree(tmp, ignore_errors=True)
    cycles = after["cycles"] - before["cycles"]
    missed = after["missed_cycles"] - before["missed_cycles"]
    return {
        "period_p99_us": after["period_p99_us"],
        "missed_ratio": missed / max(1, cycles + missed),
        "compute_p50_us": after["compute_p50_us"],
        "rtf": (sim1["t"] - sim0["t"]) / (w1 - w0),  # sim time over wall time, this session only
        "telemetry_dropped": tel1.get("dropped", 0) - tel0.get("dropped", 0) if tel1 else 0,
    }


def _opts(opts: dict) -> tuple[float, str | None, int]:
    prio = opts.get("realtime_priority")
    return (float(opts.get("seconds", 60.0)), str(opts["config"]) if opts.get("config") else None,
            REALTIME_PRIORITY if prio is None else int(prio))


@benchmark("loop_period_p99_us", "us")
def loop_period_p99_us(opts: dict) -> float:
    """99th percentile of the cycle period with the simulated robot beside the daemon (drag, operator pushing)."""
    return float(_session(*_opts(opts))["period_p99_us"])


@benchmark("loop_missed_ratio", "ratio")
def loop_missed_ratio(opts: dict) -> float:
    """Missed ticks / ticks over the session (timerfd expirations > 1)."""
    return float(_session(*_opts(opts))["missed_ratio"])


@benchmark("loop_compute_us", "us")
def loop_compute_us(opts: dict) -> float:
    """Median time from the last TPDO (or the deadline) to the RPDOs sent: estimate + compute + write."""
    return float(_session(*_opts(opts))["compute_p50_us"])


@benchmark("sim_rtf", "ratio")
def sim_rtf(opts: dict) -> float:
    """Real-time factor of the simulated robot (sim time / wall time) while the daemon runs beside it."""
    return float(_session(*_opts(opts))["rtf"])


@benchmark("bus_load", "%")
def bus_load(opts: dict) -> float:
    """Worst-case bus load (bit stuffing included) of the configured PDO layout, highest over the buses."""
    from dragd.config import load_config
    from dragd.daemon.core import bus_layouts

    cfg = load_config(opts.get("config"))
    layouts = bus_layouts(cfg)
    return max(layouts[b.name].budget(cfg.loop.rate_Hz, b.bitrate, b.data_bitrate, 1000.0 / cfg.master.heartbeat_ms).percent
               for b in cfg.buses)


def _telemetry(opts: dict, variant: str) -> dict:
    seconds, config, prio = _opts(opts)
    out = _session(seconds, config, prio, variant)
    if out["telemetry_dropped"]:
        raise BenchError(f"telemetry ({variant}): the writer dropped {out['telemetry_dropped']} rows")
    return out


@benchmark("loop_period_p99_us_foxglove", "us")
def loop_period_p99_us_foxglove(opts: dict) -> float:
    """loop_period_p99_us with the telemetry MCAP written (every cycle + Foxglove channels at 30 Hz, default)."""
    return float(_telemetry(opts, "foxglove")["period_p99_us"])


@benchmark("loop_period_p99_us_telemetry_plain", "us")
def loop_period_p99_us_telemetry_plain(opts: dict) -> float:
    """loop_period_p99_us with the telemetry MCAP written without the Foxglove channels (--no-foxglove)."""
    return float(_telemetry(opts, "plain")["period_p99_us"])
