"""``python -m sim run``: the simulated robot as its own process (drives on a CAN bus + real-time physics)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from dragd.realtime import single_threaded_blas

if "numpy" not in sys.modules:  # one BLAS thread before numpy loads: the sim's threads may run SCHED_FIFO
    single_threaded_blas()

import can  # noqa: E402

from dragd.config import ConfigError  # noqa: E402


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
    run_p.add_argument("--model", help="dragd params file (identify fit / gap --out): simulate that model (K_t, "
                                       "friction, model-gap effects) on top of the truth file")
    run_p.add_argument("--eds", metavar="FILE",
                       help="build every joint's drive from this EDS: its objects, access and mapping flags, PDOs, "
                            "COB-IDs, dummy usage and 6502h; vendor objects from sim/config/drives/ (matched by the "
                            "EDS's [DeviceInfo]); per joint: drive.eds in the truth file (docs/SIM_DRIVES.md)")
    run_p.add_argument("--bus", help="INTERFACE:CHANNEL, e.g. udp_multicast:239.74.163.2 (default: "
                                     "the truth's bus.channel); "
                                     "A,B,C: several buses (a truth that puts every joint on bus 0 is spread: joint i "
                                     "of n on bus i*k//n of the k buses, as dragd config init splits them)")
    run_p.add_argument("--scenario", help="operator scenario file (or a name in sim/scenarios) started at t = 0")
    run_p.add_argument("--control", help="Unix socket path for the JSON-lines control protocol")
    run_p.add_argument("--seconds", type=float, help="stop after this much simulated time")
    run_p.add_argument("--json", action="store_true", help="print the exit summary as one JSON object")
    run_p.add_argument("--realtime-priority", type=int, metavar="N",
                       help="SCHED_FIFO priority for the physics and bus threads (needs CAP_SYS_NICE or RLIMIT_RTPRIO)")
    run_p.add_argument("--batch-frames", action="store_true",
                       help="udp_multicast: answer each SYNC with one datagram carrying every drive's TPDOs (dragd's "
                            "buses read it; python-can's own udp_multicast tools do not: leave it off for them); "
                            "no effect on other buses (SocketCAN, virtual: one frame per send)")
    run_p.add_argument("--cpus", help="pin the physics and bus threads to these CPUs, e.g. 1 or 0,1")
    run_p.add_argument("--physics-rate-Hz", type=int, metavar="HZ", dest="physics_rate_Hz",
                       help="override the truth's physics_rate_Hz: a multiple of 1000 in [1000, 50000]; below the "
                            "truth's 4000 Hz minimum only for machines too slow for it (the vcan test guest)")
    run_p.add_argument("--lockstep", action="store_true",
                       help="the lockstep clock: one period of simulated time per SYNC (answered, then run, then ended "
                            "with a TIME frame), no real time; for 'dragd run --lockstep' (docs/LOCKSTEP.md)")
    run_p.add_argument("--period-ms", type=float, default=1.0, metavar="MS",
                       help="--lockstep: simulated time per SYNC (the daemon's 1000 / loop.rate_Hz; default 1)")
    truth_p = sub.add_parser("truth", help="print the truth per joint in dragd's units (K_t, friction in A, noise)")
    truth_p.add_argument("--config", help="truth file (default: sim/config/seed_cobot.yaml)")
    truth_p.add_argument("--json", action="store_true", help="print one JSON object")
    drives_p = sub.add_parser("drives", help="print each joint's simulated drive: EDS, where its firmware keeps each "
                                             "quantity, commissioned values, assumptions")
    drives_p.add_argument("--config", help="truth file (default: sim/config/seed_cobot.yaml)")
    drives_p.add_argument("--eds", metavar="FILE", help="every joint's drive from this EDS (as run --eds)")
    drives_p.add_argument("--json", action="store_true", help="print one JSON object")
    log_p = sub.add_parser("log", help="offline, faster than real time: follow a plan with drive-like CSP loops, "
                                       "write a daemon-format MCAP or a CSV log")
    log_p.add_argument("--plan", required=True, help="plan file (.npz with t_s, q_rad; from 'dragd identify plan')")
    log_p.add_argument("--out", required=True, help="log file: .mcap (daemon telemetry) or .csv (t,q1..,i1..,dq1..)")
    log_p.add_argument("--config", help="truth file (default: sim/config/seed_cobot.yaml)")
    log_p.add_argument("--model", help="dragd params file: simulate that model on top of the truth file")
    log_p.add_argument("--dragd-config", help="dragd configuration whose beliefs feed the TRACK feed-forward "
                                              "(default: config/default.yaml)")
    log_p.add_argument("--seconds", type=float, help="only the first SECONDS of the plan")
    log_p.add_argument("--seed", type=int, help="Hall-noise seed (default: the truth's noise_seed)")
    log_p.add_argument("--csp-interpolate", action="store_true",
                       help="interpolate CSP targets over each SYNC period (a drive with 60C2h; sim/drive.py does not)")
    log_p.add_argument("--json", action="store_true", help="print a JSON summary")
    args = parser.parse_args(argv)
    if args.command == "truth":
        return _cmd_truth(args)
    if args.command == "log":
        return _cmd_log(args)
    if args.command == "drives":
        return _cmd_drives(args)

    from sim.runner import run
    from sim.truth import drive_profiles, load_truth, spread_over_buses, with_eds

    if args.eds and not Path(args.eds).is_file():
        print(f"sim: --eds: {args.eds}: file not found; expected a drive's EDS (.eds)", file=sys.stderr)
        return 2
    try:
        truth = _truth_with_model(load_truth(args.config), args.model)
        if args.eds:
            truth = with_eds(truth, args.eds)
        truth = spread_over_buses(truth, args.bus)
        profiles = drive_profiles(truth)  # every joint's EDS and profile checked before any frame
    except ConfigError as exc:
        print(f"sim: {exc}", file=sys.stderr)
        return 2
    for profile in profiles:
        if not profile.bundled:
            print(f"sim: drive {profile.describe()}", file=sys.stderr, flush=True)
    if args.physics_rate_Hz is not None:
        if not 1000 <= args.physics_rate_Hz <= 50000 or args.physics_rate_Hz % 1000:
            print(f"sim: --physics-rate-Hz: expected a multiple of 1000 in [1000, 50000], got {args.physics_rate_Hz}",
                  file=sys.stderr)
            return 2
        truth = truth.model_copy(update={"physics_rate_Hz": args.physics_rate_Hz})  # the stability check still applies
    if not 0 < args.period_ms <= 1000:
        print(f"sim: --period-ms: expected a period in (0, 1000] ms, got {args.period_ms}", file=sys.stderr)
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
        clock = (f"lockstep, {args.period_ms:g} ms per SYNC" if args.lockstep else "real time")
        print(f"sim: running {truth.robot} ({len(proc.drives)} drives, {truth.physics_rate_Hz} Hz physics, {clock}) "
              f"on {','.join(map(str, proc.specs))}{where}", file=sys.stderr, flush=True)
        for what, item in (proc.realtime or {}).items():
            if item.get("requested") is not None or item.get("requested_priority") is not None:
                if not item.get("applied"):
                    print(f"sim: warning: {what}: {item.get('reason')}", file=sys.stderr, flush=True)

    try:
        summary = run(truth, args.bus, scenario=args.scenario, control_path=args.control, seconds=args.seconds,
                      realtime_priority=args.realtime_priority, cpus=cpus, batch_frames=args.batch_frames,
                      ready=ready, lockstep=args.lockstep, period_s=args.period_ms * 1e-3)
    except (ConfigError, ValueError, OSError, can.CanError) as exc:
        print(f"sim: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(summary), flush=True)
    else:
        print(_text_summary(summary), flush=True)
    return 0


def _truth_with_model(truth: Any, model: str | None) -> Any:
    """``--model params.yaml``: the truth that params file describes (sim.truth.truth_from_params)."""
    if not model:
        return truth
    from dragd.config import load_params
    from sim.truth import truth_from_params

    return truth_from_params(load_params(model), truth)


def _cmd_truth(args: argparse.Namespace) -> int:
    from sim.offline import truth_summary
    from sim.truth import load_truth

    try:
        summary = truth_summary(load_truth(args.config))
    except ConfigError as exc:
        print(f"sim: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(summary))
    else:
        for name, j in summary["joints"].items():
            f = j["friction"]
            print(f"{name}: K_t {j['torque_constant_Nm_per_A']:.4f} N·m/A, Coulomb {f['coulomb_pos_A']:+.4f}/"
                  f"{f['coulomb_neg_A']:+.4f} A, static {f['static_pos_A']:+.4f}/{f['static_neg_A']:+.4f} A, "
                  f"viscous {f['viscous_pos_A_s_per_rad']:.4f}/{f['viscous_neg_A_s_per_rad']:.4f} A·s/rad, "
                  f"v_s {f['stribeck_velocity_rad_s']:.3f} rad/s, noise {j['current_noise_std_A'] * 1e3:.0f} mA")
    return 0


def _cmd_drives(args: argparse.Namespace) -> int:
    from sim.truth import drive_profiles, load_truth, with_eds

    if args.eds and not Path(args.eds).is_file():
        print(f"sim: --eds: {args.eds}: file not found; expected a drive's EDS (.eds)", file=sys.stderr)
        return 2
    try:
        truth = load_truth(args.config)
        if args.eds:
            truth = with_eds(truth, args.eds)
        profiles = drive_profiles(truth)
    except ConfigError as exc:
        print(f"sim: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps({j.name: p.summary() for j, p in zip(truth.joints, profiles, strict=True)}))
    else:
        for j, p in zip(truth.joints, profiles, strict=True):
            print(f"{j.name}: {p.describe()}")
    return 0


def _cmd_log(args: argparse.Namespace) -> int:
    import time

    from sim.offline import generate, load_plan, write_log
    from sim.truth import load_truth

    if args.seconds is not None and not args.seconds > 0:
        print(f"sim: --seconds: expected a positive number, got {args.seconds}", file=sys.stderr)
        return 2
    if not str(args.out).endswith((".mcap", ".csv")):
        print(f"sim: --out: expected a .mcap or .csv file name, got {args.out}", file=sys.stderr)
        return 2
    t0 = time.monotonic()
    try:
        truth = _truth_with_model(load_truth(args.config), args.model)
        plan_t, plan_q = load_plan(args.plan)
        data = generate(plan_t, plan_q, truth, config=args.dragd_config, seconds=args.seconds, seed=args.seed,
                        csp_interpolation=args.csp_interpolate)
        write_log(args.out, data, {"plan": str(args.plan), "truth": truth.source,
                                   "seed": str(args.seed if args.seed is not None else truth.noise_seed)})
    except (ConfigError, ValueError, OSError) as exc:
        print(f"sim: {exc}", file=sys.stderr)
        return 2
    wall = time.monotonic() - t0
    summary = {"out": str(args.out), "rows": int(data["t_s"].shape[0]), "sim_time_s": float(data["t_s"][-1]),
               "wall_time_s": round(wall, 3), "rtf": round(float(data["t_s"][-1]) / wall, 3) if wall > 0 else None}
    print(json.dumps(summary) if args.json else
          f"sim: {summary['rows']} rows ({summary['sim_time_s']:.1f} s) -> {args.out} in {wall:.1f} s "
          f"(rtf {summary['rtf']})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
