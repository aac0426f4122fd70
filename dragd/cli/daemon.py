"""CLI of the daemon: ``run`` (foreground daemon), ``start|stop|mode|status`` (control socket), ``demo``, ``log``."""

from __future__ import annotations

import argparse
import asyncio
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

from dragd.cli.app import CliError, _add_config, _emit, _table

if TYPE_CHECKING:
    from dragd.config import Config

DEFAULT_SOCKET = "/run/dragd/dragd.sock"


def _client(args: argparse.Namespace):  # noqa: ANN202
    from dragd.protocol import ControlClient

    return ControlClient(args.socket, timeout_s=args.timeout)


def _call(args: argparse.Namespace, cmd: str, **kw: Any) -> dict[str, Any]:
    from dragd.protocol import DaemonUnavailable

    try:
        resp = _client(args).call(cmd, **kw)
    except DaemonUnavailable as exc:
        raise CliError(str(exc), status=1) from None
    if not resp.get("ok", False):
        raise CliError(f"daemon at {args.socket}: {resp.get('error', 'request failed')}", status=1)
    return resp


def with_realtime_priority(cfg: Config, priority: int) -> Config:
    """``cfg`` with ``loop.realtime_priority`` = ``priority`` (0: none), validated by the config schema."""
    if not 0 <= priority <= 99:
        raise CliError(f"--realtime-priority: expected 1..99 (SCHED_FIFO priority of the cycle thread) or 0 (none), "
                       f"got {priority}")
    loop = type(cfg.loop).model_validate({**cfg.loop.model_dump(), "realtime_priority": priority or None})
    return cfg.model_copy(update={"loop": loop})


def cmd_run(args: argparse.Namespace) -> int:
    from dragd.config import load_config
    from dragd.daemon.core import BusBudgetError, Daemon
    from dragd.hardware.master import DriveError

    cfg = load_config(args.config, args.params)
    if args.realtime_priority is not None:
        cfg = with_realtime_priority(cfg, args.realtime_priority)
    try:
        daemon = Daemon(cfg, bus_override=args.bus, socket_path=args.socket, telemetry_path=args.telemetry,
                        rerun=args.rerun)
    except (BusBudgetError, ValueError) as exc:
        raise CliError(str(exc)) from None
    try:
        return asyncio.run(daemon.run())
    except DriveError as exc:
        raise CliError(str(exc), status=1) from None


def cmd_start(args: argparse.Namespace) -> int:
    resp = _call(args, "start")
    _emit(args, resp, lambda d: f"drives enabled, mode {d['mode']}")
    return 0


def cmd_stop(args: argparse.Namespace) -> int:
    resp = _call(args, "stop")
    _emit(args, resp, lambda d: f"drives disabled, mode {d['mode']}")
    return 0


def cmd_mode(args: argparse.Namespace) -> int:
    resp = _call(args, "mode", mode=args.mode)
    _emit(args, resp, lambda d: f"mode {d['mode']}")
    return 0


def _status_text(d: dict[str, Any]) -> str:
    import math

    lines = [f"mode {d['mode']}, drives {'enabled' if d['drives_enabled'] else 'disabled'}, {d['cycles']} cycles, "
             f"period p99 {d['period_p99_us'] or 0:.0f} µs, missed {d['missed_cycles']}"]
    rows = [(dr["joint"], dr["node_id"], dr["state"], f"{math.degrees(q):.3f}", f"{i:.3f}")
            for dr, q, i in zip(d["drives"], d["q_rad"], d["current_A"])]
    lines.append(_table(["joint", "node", "state", "q_deg", "current_A"], rows))
    for f in d["faults"]:
        lines.append(f"fault at {f['t_s']:.3f} s: {f['text']}")
    return "\n".join(lines)


def cmd_status(args: argparse.Namespace) -> int:
    resp = _call(args, "status")
    resp.pop("ok", None)
    _emit(args, resp, _status_text)
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from dragd.lab.demo import DemoError, run_demo

    try:
        result = run_demo(seconds=args.seconds, config=args.config, out=args.out, scenario=args.scenario,
                          progress=not args.json)
    except DemoError as exc:
        raise CliError(str(exc), status=1) from None
    _emit(args, result, lambda d: "\n".join(f"{k:28s} {v}" for k, v in d.items()))
    return 0


def cmd_log_summary(args: argparse.Namespace) -> int:
    from dragd.telemetry.writer import TelemetryFileError, summarize

    try:
        data = summarize(args.file)
    except TelemetryFileError as exc:
        raise CliError(str(exc)) from None
    if args.json:
        print(json.dumps(data, default=str))
    else:
        print(json.dumps(data, indent=2, default=str))
    return 0


def _add_socket(p: argparse.ArgumentParser) -> None:
    p.add_argument("--socket", default=DEFAULT_SOCKET, help=f"daemon control socket (default {DEFAULT_SOCKET})")
    p.add_argument("--timeout", type=float, default=10.0, help="seconds to wait for the daemon's answer")


def register(sub: Any) -> None:
    r = sub.add_parser("run", help="run the daemon in the foreground (what systemd starts)")
    _add_config(r)
    r.add_argument("--bus", help="INTERFACE:CHANNEL overriding the config's bus (comma-separated for several buses), "
                   "e.g. socketcan:can0, udp_multicast:239.74.163.2, virtual:arm")
    r.add_argument("--socket", default=None, help=f"control socket path (default: config control.socket, {DEFAULT_SOCKET})")
    r.add_argument("--telemetry", default=None, help="write every cycle to this MCAP file")
    r.add_argument("--realtime-priority", type=int, default=None, metavar="N",
                   help="SCHED_FIFO priority 1..99 of the cycle thread, when permitted (0: none); overrides loop.realtime_priority")
    r.add_argument("--rerun", action="store_true", help="live view in rerun (needs the optional extra dragd[rerun])")
    r.set_defaults(func=cmd_run)

    for name, fn, helptext in (("start", cmd_start, "enable the drives and hold the pose"),
                               ("stop", cmd_stop, "ramp down to hold, disable the drives (brakes on)")):
        p = sub.add_parser(name, help=helptext)
        _add_socket(p)
        p.add_argument("--json", action="store_true", help="print JSON")
        p.set_defaults(func=fn)
    m = sub.add_parser("mode", help="switch mode without a jump in current: idle | hold | drag")
    m.add_argument("mode", choices=["idle", "hold", "drag"])
    _add_socket(m)
    m.add_argument("--json", action="store_true", help="print JSON")
    m.set_defaults(func=cmd_mode)
    s = sub.add_parser("status", help="the daemon's state, timing and faults")
    _add_socket(s)
    s.add_argument("--json", action="store_true", help="print JSON")
    s.set_defaults(func=cmd_status)

    d = sub.add_parser("demo", help="the main job: sim + daemon as separate processes, a scripted drag, MCAP written")
    d.add_argument("--seconds", type=float, default=20.0, help="length of the drag session (default 20)")
    d.add_argument("--scenario", default="drag", help="demo scenario (default: drag)")
    d.add_argument("--out", type=Path, default=None, help="output folder for the MCAP log (default ./out)")
    _add_config(d, params=False)
    d.add_argument("--json", action="store_true", help="print the summary as JSON")
    d.set_defaults(func=cmd_demo)

    lg = sub.add_parser("log", help="telemetry logs")
    lsub = lg.add_subparsers(dest="log_command", metavar="WHAT")
    lsub.required = True
    su = lsub.add_parser("summary", help="what an MCAP log holds")
    su.add_argument("file", type=Path)
    su.add_argument("--json", action="store_true", help="print compact JSON")
    su.set_defaults(func=cmd_log_summary)
