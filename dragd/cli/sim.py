"""The simulated robot: ``dragd sim`` (its own process, ``python -m sim run``) and ``dragd demo`` (sim + daemon)."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Any

from dragd.cli.common import CliError, absolute, add_config, emit


def cmd_sim(args: argparse.Namespace) -> int:
    """Replace this process by ``python -m sim run ARGS``; dragd never imports sim/."""
    argv = [sys.executable, "-m", "sim", "run", *args.sim_args]
    os.execv(sys.executable, argv)
    return 0  # pragma: no cover


def cmd_demo(args: argparse.Namespace) -> int:
    from dragd.lab.demo import DemoError, run_demo

    try:
        result = run_demo(seconds=args.seconds, config=absolute(args.config), out=args.out, scenario=args.scenario,
                          progress=not args.json, lockstep=args.lockstep)
    except DemoError as exc:
        raise CliError(str(exc), status=1) from None
    emit(args, result, lambda d: "\n".join(f"{k:28s} {v}" for k, v in d.items()))
    return 0


def register(sub: Any) -> None:
    # NUL never starts a command-line argument: with it as the only option prefix, every argument (--help
    # included) is a value for the simulator's own parser.
    s = sub.add_parser("sim", help="run the simulated robot (its own process); every argument goes to "
                                   "'python -m sim run' ('dragd sim --help' lists them)",
                       prefix_chars="\0", add_help=False)
    s.add_argument("sim_args", nargs=argparse.REMAINDER)
    s.set_defaults(func=cmd_sim)

    d = sub.add_parser("demo", help="the main job: sim + daemon as separate processes, a scripted drag, MCAP written")
    d.add_argument("--seconds", type=float, default=20.0, help="length of the drag session (default 20)")
    d.add_argument("--scenario", default="drag", help="demo scenario: drag, teach, payload, buttons (a teach session from the hand's buttons) (default: drag)")
    d.add_argument("--out", type=Path, default=None, help="output folder for the MCAP log (default ./out)")
    add_config(d, params=False)
    d.add_argument("--lockstep", action="store_true",
                   help="both processes on the lockstep clock: simulated time, as fast as they go, the same telemetry "
                        "on every run (its digest and the real-time factor are reported); default: the wall clock")
    d.add_argument("--json", action="store_true", help="print the summary as JSON")
    d.set_defaults(func=cmd_demo)
