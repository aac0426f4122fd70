"""``dragd log summary FILE``: what a telemetry (MCAP) log holds; ``dragd log view FILE`` (dragd/cli/view.py)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from dragd.cli.common import CliError


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


def register(sub: Any) -> None:
    lg = sub.add_parser("log", help="telemetry logs")
    lsub = lg.add_subparsers(dest="log_command", metavar="WHAT")
    lsub.required = True
    su = lsub.add_parser("summary", help="what an MCAP log holds")
    su.add_argument("file", type=Path)
    su.add_argument("--json", action="store_true", help="print compact JSON")
    su.set_defaults(func=cmd_log_summary)
    from dragd.cli.view import register_log

    register_log(lsub)
