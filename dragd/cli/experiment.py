"""``dragd experiment startup | sine-sweep | drag-quality``: seed 001's experiments on the simulated robot."""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path
from typing import Any

from dragd.cli.common import CliError, absolute, add_config, emit, table


def _joints(text: str | None, n: int) -> list[int]:
    if not text:
        return list(range(n))
    try:
        idx = [int(x.strip().removeprefix("joint")) - 1 for x in text.split(",") if x.strip()]
    except ValueError:
        raise CliError(f"--joints: expected joint numbers or names like 1,2 or joint1,joint2, got '{text}'") from None
    bad = [i + 1 for i in idx if not 0 <= i < n]
    if bad:
        raise CliError(f"--joints: expected joints 1..{n}, got {bad}")
    return idx


def _bench(args: argparse.Namespace, joints_arg: str | None):  # noqa: ANN202
    from dragd.lab.experiment.bench import Bench

    if args.ramp_s is not None and not 1.0 <= args.ramp_s <= 120.0:
        raise CliError(f"--ramp-s: expected seconds in [1, 120], got {args.ramp_s}")
    work = Path(args.work_dir) if args.work_dir else Path(tempfile.mkdtemp(prefix="dragd-experiment-"))
    bench = Bench(work, config=absolute(args.config), params=absolute(args.params), progress=not args.json,
                  lockstep=args.lockstep or None)
    joints = _joints(joints_arg, len(bench.cfg.joints))
    if args.params is None:  # the compensation runs on identified parameters only (never the sim's truth)
        bench.identify_on_sim(joints)
    return bench, joints


def cmd_startup(args: argparse.Namespace) -> int:
    from dragd.lab.experiment import plots
    from dragd.lab.experiment.startup import run_startup
    from dragd.telemetry.reader import read_rows

    bench, joints = _bench(args, args.joints)
    result = run_startup(bench, joints, reps=args.reps, ramp_s=args.ramp_s)
    if args.plots:
        out = Path(args.plots)
        out.mkdir(parents=True, exist_ok=True)
        result["plots"] = [str(plots.startup_bars(result, out / "startup_torque.png"))]
        rows = read_rows(bench.workdir / "ramps_on.mcap")
        result["plots"].append(str(plots.ramp_trace(rows, joints[0], out / "startup_trace.png",
                                                    f"{bench.cfg.joints[joints[0]].name}: ramps "
                                                    "with start-up compensation")))

    def text(d: dict[str, Any]) -> str:
        rows = [(n, v["starting_torque_without_Nm"], v["starting_torque_with_Nm"], f"{v['reduction_pct']:.2f}",
                 f"{v['oscillation_deg']:.4f}") for n, v in d["joints"].items()]
        return (table(["joint", "without_Nm", "with_Nm", "reduction_%", "oscillation_°"], rows)
                + f"\nmean reduction {d['mean_reduction_pct']:.2f} % (seed 001: 60.58 %)")

    emit(args, result, text)
    return 0


def cmd_sweep(args: argparse.Namespace) -> int:
    from dragd.lab.experiment import plots
    from dragd.lab.experiment.startup import run_sweep, write_frequency

    if args.joint is not None and "," in args.joint:
        raise CliError(f"--joint: expected one joint, got '{args.joint}'")
    bench, (joint,) = _bench(args, args.joint)
    freqs = None
    if args.frequencies:
        try:
            freqs = [float(x) for x in args.frequencies.split(",")]
        except ValueError:
            raise CliError(f"--frequencies: expected comma-separated numbers, got '{args.frequencies}'") from None
    result = run_sweep(bench, joint, freqs, reps=args.reps, ramp_s=args.ramp_s)
    if args.out and result["best_frequency_Hz"] is not None:
        write_frequency(bench.params, Path(args.out), result["joint"], result["best_frequency_Hz"])  # identified kept
        result["params"] = str(args.out)
    if args.plots:
        out = Path(args.plots)
        out.mkdir(parents=True, exist_ok=True)
        result["plots"] = [str(plots.sweep_plot(result, out / f"sweep_{result['joint']}.png"))]

    def text(d: dict[str, Any]) -> str:
        rows = [(p["frequency_Hz"], p["starting_torque_Nm"], f"{p['oscillation_deg']:.4f}") for p in d["points"]]
        cmp = [(k, v["starting_torque_Nm"], f"{v['oscillation_deg']:.4f}", v["handover_step_A"])
               for k, v in d["comparisons"].items()]
        return (table(["frequency_Hz", "starting_torque_Nm", "oscillation_°"], rows)
                + f"\nchosen {d['best_frequency_Hz']} Hz\n"
                + table(["variant", "starting_torque_Nm", "oscillation_°", "handover_step_A"], cmp))

    emit(args, result, text)
    return 0


def cmd_quality(args: argparse.Namespace) -> int:
    from dragd.lab.experiment import plots
    from dragd.lab.experiment.quality import run_quality

    bench, joints = _bench(args, args.joints)
    result = run_quality(bench, joints)
    if args.plots:
        out = Path(args.plots)
        out.mkdir(parents=True, exist_ok=True)
        result["plots"] = [str(plots.quality_bars(result, out / "drag_effort.png"))]

    def text(d: dict[str, Any]) -> str:
        rows = [(n, v["effort_uncompensated_Nm"], v["effort_compensated_Nm"], v["effort_pct"],
                 v["drift_after_release_deg"])
                for n, v in d["joints"].items()]
        return table(["joint", "uncompensated_Nm", "drag_Nm", "effort_%", "drift_°"], rows)

    emit(args, result, text)
    return 0


def register(sub: Any) -> None:
    e = sub.add_parser("experiment", help="seed 001's start-up experiments and drag quality on the simulated robot",
                       description="Seed 001's experiments on the simulated robot. The compensation uses identified "
                                   "parameters only: --params FILE, or (without it) a friction identification run "
                                   "on the simulated arm first (plan, log, fit: about a minute).")
    esub = e.add_subparsers(dest="experiment_command", metavar="WHAT")
    esub.required = True

    def common(p: argparse.ArgumentParser) -> None:
        add_config(p)
        p.add_argument("--reps", type=int, default=2, help="repetitions per joint (alternating direction; default 2)")
        p.add_argument("--plots", help="write PNG figures to this folder")
        p.add_argument("--work-dir", help="keep the rigs' logs and MCAP recordings here (default: a temp folder)")
        p.add_argument("--ramp-s", type=float, default=None,
                       help="seconds the load ramp takes to the believed static friction (default 10)")
        p.add_argument("--lockstep", action="store_true",
                       help="run the simulated robot and the daemon on the lockstep clock: simulated time, so a loaded "
                            "machine cannot disturb (or void) a repetition, and the same run gives the same figures")
        p.add_argument("--json", action="store_true", help="print JSON")

    s = esub.add_parser("startup", help="starting torque without/with start-up compensation (seed 001 Table XI)")
    s.add_argument("--joints", help="joints to test, e.g. 1,2,3 (default: all)")
    common(s)
    s.set_defaults(func=cmd_startup)
    w = esub.add_parser("sine-sweep", help="sweep the start-up frequency of one joint (seed 001 Fig. 13)")
    w.add_argument("--joint", required=True, help="the joint, e.g. 1 or joint1")
    w.add_argument("--frequencies", help="comma-separated Hz (default 2,4,8,12,16,20,25,30,40)")
    w.add_argument("--out", type=Path, help="write the chosen frequency into this params file")
    common(w)
    w.set_defaults(func=cmd_sweep)
    q = esub.add_parser("drag-quality", help="effort at 10°/s vs uncompensated, drift after release")
    q.add_argument("--joints", help="joints to test (default: all)")
    common(q)
    q.set_defaults(func=cmd_quality)
