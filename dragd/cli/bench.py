"""``dragd bench [NAME ...]``: the benchmarks of docs/PERFORMANCE.md."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from dragd.cli.common import CliError, absolute, add_config, emit, table


def cmd_bench(args: argparse.Namespace) -> int:
    from dragd.lab import bench

    if args.list:
        for name in bench.names():
            b = bench.REGISTRY[name]
            print(f"{name:24s} [{b.unit}] {b.doc}")
        return 0
    if args.realtime_priority is not None and not 0 <= args.realtime_priority <= 99:
        raise CliError(f"--realtime-priority: expected 0..99, got {args.realtime_priority}")
    if args.seconds is not None and not args.seconds > 0:  # (a negative or NaN duration would fail mid-session)
        raise CliError(f"--seconds: expected a duration > 0 s, got {args.seconds:g}")
    if args.jobs is not None and args.jobs < 1:
        raise CliError(f"--jobs: expected ≥ 1, got {args.jobs}")
    opts = {"config": absolute(args.config), "seconds": args.seconds, "realtime_priority": args.realtime_priority,
            "jobs": args.jobs, "cases": args.cases, "out": absolute(args.out), "profile": absolute(args.profile),
            "sim_config": absolute(args.sim_config), "data": absolute(args.data), "train": args.train,
            "valid": args.valid, "eds_dir": absolute(args.eds_dir), "robot": args.robot, "clock": args.clock}
    try:
        result = bench.run(args.names, {k: v for k, v in opts.items() if v is not None})
    except KeyError as exc:
        raise CliError(str(exc.args[0])) from None
    except bench.BenchError as exc:
        raise CliError(str(exc), status=1) from None
    def text(d: dict[str, Any]) -> str:
        rows = [(k, v["value"], v["unit"]) for k, v in d.items() if "value" in v]
        out = [table(["benchmark", "value", "unit"], rows)] if rows else []
        for k, v in d.items():
            if "faults" in v:
                out.append(table([k, "detected_ms", "reaction", "max_speed_rad_s", "max_drift_deg", "recovered",
                                  "rows_lost"],
                                 [(f, r["detected_ms"], r["reaction"], r["max_joint_speed_rad_s"], r["max_drift_deg"],
                                   r["recovered"], r["rows_lost"]) for f, r in v["faults"].items()]))
            if "files" in v:
                def short(x: Any) -> str:
                    if x is None or isinstance(x, (int, float)):
                        return "-" if x is None else str(x)
                    if isinstance(x, list):
                        return f"{len(x)} error(s)"
                    return x if len(x) <= 40 else x[:37] + "..."

                out.append(table([k, "config_check", "boot", "drag_drift_deg", "identify", "refused_reason"],
                                 [(f, short(r["config_check"]), short(r["boot"]), short(r["drag_drift_deg"]),
                                   short(r["identify"]), short(r["refused_reason"])) for f, r in v["files"].items()]))
        out += [f"{k}: details with --json" for k, v in d.items() if "detail" in v]
        return "\n".join(out)

    emit(args, result, text)
    return 0


def register(sub: Any) -> None:
    b = sub.add_parser("bench", help="run benchmarks (see docs/PERFORMANCE.md)")
    b.add_argument("names", nargs="*", metavar="NAME", help="benchmarks to run (default: all); --list shows them")
    b.add_argument("--list", action="store_true", help="list benchmarks")
    b.add_argument("--seconds", type=float, default=None, help="duration of timed benchmarks")
    b.add_argument("--clock", choices=("lockstep", "wall"), default=None,
                   help="the sim + daemon benchmarks of behaviour (fault_matrix, drive_profiles): lockstep (default: "
                        "simulated time, the same figures on any machine) or wall (real time, as deployed)")
    b.add_argument("--realtime-priority", type=int, default=None, metavar="N",
                   help="loop benchmarks: SCHED_FIFO priority of the daemon's cycle thread as deployed (default 70, "
                        "the sim's 10 below; applied when permitted), 0 for none")
    b.add_argument("--jobs", type=int, default=None, metavar="N",
                   help="gap_confusion: cases run at once in worker processes (default 2)")
    b.add_argument("--cases", default=None, metavar="PATTERNS",
                   help="gap_confusion: comma-separated shell patterns of case ids (default: the whole matrix)")
    b.add_argument("--out", type=Path, default=None, metavar="DIR",
                   help="gap_confusion: keep the generated cases and results.json here (default: a temporary directory)")
    b.add_argument("--profile", type=Path, default=None, metavar="DIR",
                   help="loop benchmarks: also sample the daemon and the simulator with py-spy over the session and "
                        "write DIR/daemon.svg, DIR/sim.svg (flame graphs) and DIR/*.txt (collapsed stacks)")
    b.add_argument("--sim-config", type=Path, default=None, metavar="FILE",
                   help="loop benchmarks: the simulator's truth file (default: the bundled seed cobot's); with a "
                        "daemon configuration of several buses its joints' bus_index must match")
    b.add_argument("--data", type=Path, default=None, metavar="DIR",
                   help="ident_real, contact_real: the UR10e dataset, a git checkout of "
                        "github:shamilmamedov/dynamic_calibration (default: $DRAGD_UR10E_DATA)")
    b.add_argument("--train", action="append", default=None, metavar="LOG[+LOG]",
                   help="ident_real: a training set of the dataset's logs by name, '+' joining several (repeat: "
                        "several sets; default: the 50 s 12-harmonic run, and the 50 s 14-harmonic run)")
    b.add_argument("--valid", action="append", default=None, metavar="LOG[,LOG]",
                   help="ident_real: validation logs by name, each validated against every training set it is not "
                        "part of (default: the 20 s 5/7/8/10-, 50 s 12/14/15-harmonic runs)")
    b.add_argument("--eds-dir", type=Path, default=None, metavar="DIR",
                   help="drive_profiles: the vendors' EDS files (docs/DRIVES.md)")
    b.add_argument("--robot", default=None, metavar="URDF",
                   help="drive_profiles: the robot (default: the seed cobot's URDF file)")
    add_config(b, params=False)
    b.add_argument("--json", action="store_true", help="print JSON")
    b.set_defaults(func=cmd_bench)
