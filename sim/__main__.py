"""``python -m sim run``: the simulated robot as its own process (drives on a CAN bus + real-time physics)."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

import can

from dragd.config import ConfigError


def _text_summary(s: dict[str, Any]) -> str:
    lines = [
        f"sim: {s['robot']} on {s['bus']}: {s['sim_time_s']:.3f} s simulated in {s['wall_time_s']:.3f} s "
        f"(rtf {s['rtf']:.4f}), {s['steps']} steps at {s['physics_rate_Hz']} Hz",
        f"  late ticks {s['late_ticks']}, late steps {s['late_steps']}, dropped steps {s['dropped_steps']}; "
        f"wake latency p50 {s['wake_latency_us']['p50']:.0f} us, p99 {s['wake_latency_us']['p99']:.0f} us, "
        f"max {s['wake_latency_us']['max']:.0f} us; tick busy mean {s['tick_busy_us']['mean']:.0f} us, "
        f"max {s['tick_busy_us']['max']:.0f} us; CPU {s['cpu_pct']:.1f} %",
    ]
    for node, d in s["drives"].items():
        lines.append(f"  node {node}: {d['state']} / {d['nmt']}, syncs {d['syncs']}, tpdos {d['tpdos_sent']}, "
                     f"rpdos {d['rpdos_received']}")
    for e in s.get("operator_events", []):
        lines.append(f"  event {e}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m sim", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    run_p = sub.add_parser("run", help="run the simulated robot until SIGTERM/SIGINT, a 'stop' command or --seconds")
    run_p.add_argument("--config", help="truth file (default: sim/config/seed_cobot.yaml)")
    run_p.add_argument("--bus", help="INTERFACE:CHANNEL, e.g. udp_multicast:239.74.163.2 (default: the truth's bus.channel)")
    run_p.add_argument("--scenario", help="operator scenario file (or a name in sim/scenarios) started at t = 0")
    run_p.add_argument("--control", help="Unix socket path for the JSON-lines control protocol")
    run_p.add_argument("--seconds", type=float, help="stop after this much simulated time")
    run_p.add_argument("--json", action="store_true", help="print the exit summary as one JSON object")
    run_p.add_argument("--realtime-priority", type=int, metavar="N",
                       help="SCHED_FIFO priority for the physics and bus threads (needs CAP_SYS_NICE or RLIMIT_RTPRIO)")
    run_p.add_argument("--cpus", help="pin the physics and bus threads to these CPUs, e.g. 1 or 0,1")
    args = parser.parse_args(argv)

    from sim.runner import run
    from sim.truth import load_truth

    try:
        truth = load_truth(args.config)
    except ConfigError as exc:
        print(f"sim: {exc}", file=sys.stderr)
        return 2
    if args.seconds is not None and not args.seconds > 0:
        print(f"sim: --seconds: expected a positive number, got {args.seconds}", file=sys.stderr)
        return 2

    cpus = None
    if args.cpus:
        try:
            cpus = {int(c) for c in args.cpus.split(",") if c.strip()}
        except ValueError:
            print(f"sim: --cpus: expected CPU numbers like 1 or 0,1, got {args.cpus!r}", file=sys.stderr)
            return 2

    def ready(proc: Any) -> None:
        where = f", control at {proc.control_path}" if proc.control_path else ""
        print(f"sim: running {truth.robot} ({len(proc.drives)} drives, {truth.physics_rate_Hz} Hz physics) "
              f"on {','.join(map(str, proc.specs))}{where}", file=sys.stderr, flush=True)
        for what, item in (proc.realtime or {}).items():
            if item.get("requested") is not None or item.get("requested_priority") is not None:
                if not item.get("applied"):
                    print(f"sim: warning: {what}: {item.get('reason')}", file=sys.stderr, flush=True)

    try:
        summary = run(truth, args.bus, scenario=args.scenario, control_path=args.control, seconds=args.seconds,
                      realtime_priority=args.realtime_priority, cpus=cpus, ready=ready)
    except (ConfigError, ValueError, OSError, can.CanError) as exc:
        print(f"sim: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(summary), flush=True)
    else:
        print(_text_summary(summary), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
