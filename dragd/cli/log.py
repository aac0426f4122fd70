"""``dragd log summary FILE``: what a telemetry (MCAP) log holds; ``dragd log view FILE`` (dragd/cli/view.py)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from dragd.cli.common import CliError, add_config


def cmd_log_summary(args: argparse.Namespace) -> int:
    from dragd.telemetry.reader import TelemetryFileError, summarize

    try:
        data = summarize(args.file)
    except TelemetryFileError as exc:
        raise CliError(str(exc)) from None
    if args.json:
        print(json.dumps(data, default=str))
    else:
        print(json.dumps(data, indent=2, default=str))
    return 0


def cmd_log_ros2(args: argparse.Namespace) -> int:
    from dragd.config import load_config
    from dragd.control.params import LawParams
    from dragd.robots import resolve_urdf
    from dragd.telemetry.foxglove import FoxgloveSpec
    from dragd.telemetry.reader import TelemetryFileError
    from dragd.telemetry.ros2 import export

    if not 0 < args.rate <= 1000:
        raise CliError(f"--rate: expected a rate in (0, 1000] Hz, got {args.rate:g}")
    if args.output.resolve() == args.file.resolve():
        raise CliError(f"{args.output}: the output would overwrite the input")
    cfg = load_config(args.config)
    spec = FoxgloveSpec(cfg.joint_names, resolve_urdf(cfg.robot.urdf, cfg.base_dir), rate_Hz=args.rate,
                        encoding="ros2", kt_Nm_per_A=LawParams.from_config(cfg).kt_Nm_per_A.tolist())
    try:
        data = export(args.file, args.output, spec)
    except (TelemetryFileError, ValueError) as exc:
        raise CliError(str(exc)) from None
    if args.json:
        print(json.dumps(data))
    else:
        print(f"{args.output}: {data['joint_states']} joint states (+ /tf, /robot_description) from {data['rows']} "
              f"rows, {data['events']} events on /rosout: ros2 bag play {args.output}")
    return 0


def register(sub: Any) -> None:
    lg = sub.add_parser("log", help="telemetry logs")
    lsub = lg.add_subparsers(dest="log_command", metavar="WHAT")
    lsub.required = True
    su = lsub.add_parser("summary", help="what an MCAP log holds")
    su.add_argument("file", type=Path)
    su.add_argument("--json", action="store_true", help="print compact JSON")
    su.set_defaults(func=cmd_log_summary)
    ro = lsub.add_parser("ros2", help="a ROS 2 bag (MCAP, CDR) from a telemetry log: /joint_states, /tf, "
                                      "/robot_description, events on /rosout (ros2 bag play, Foxglove)")
    ro.add_argument("file", type=Path)
    ro.add_argument("output", type=Path)
    ro.add_argument("--rate", type=float, default=100.0, help="joint states per second (default 100)")
    add_config(ro, params=False)
    ro.add_argument("--json", action="store_true", help="print JSON")
    ro.set_defaults(func=cmd_log_ros2)
    from dragd.cli.view import register_log

    register_log(lsub)
