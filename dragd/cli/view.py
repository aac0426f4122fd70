"""``dragd view`` (the running daemon) and ``dragd log view FILE.mcap`` (a recording) in Rerun (docs/VIEW.md)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from dragd.cli.common import CliError, add_config, add_socket, emit


def _sink(args: argparse.Namespace, joints: Any, cfg: Any) -> Any:
    from dragd.robots import resolve_urdf
    from dragd.telemetry.sinks import RerunSink, RerunUnavailable

    try:
        return RerunSink(url=args.connect, save_path=args.save, spawn=args.save is None and args.connect is None,
                         joint_names=list(joints), urdf=resolve_urdf(cfg.robot.urdf, cfg.base_dir),
                         rate_Hz=args.rate)
    except RerunUnavailable as exc:
        raise CliError(str(exc), status=1) from None


def cmd_log_view(args: argparse.Namespace) -> int:
    from dragd.config import load_config
    from dragd.telemetry.reader import TelemetryFileError
    from dragd.telemetry.view import log_to_rerun

    cfg = load_config(args.config)
    try:
        data = log_to_rerun(args.file, lambda joints: _sink(args, joints, cfg), cfg.joint_names)
    except (TelemetryFileError, ValueError) as exc:
        raise CliError(str(exc)) from None
    data["rrd"] = str(args.save) if args.save else None
    emit(args, data, lambda d: f"{args.file}: {d['rows']} rows, {d['events']} events -> "
                               f"{d['rrd'] or args.connect or 'a Rerun viewer'}")
    return 0


def cmd_view(args: argparse.Namespace) -> int:
    from dragd.config import load_config
    from dragd.protocol import ControlClient, DaemonUnavailable
    from dragd.telemetry.view import live_to_rerun

    cfg = load_config(args.config)
    client = ControlClient(args.socket, args.timeout)
    try:
        first = client.call("status")
    except DaemonUnavailable as exc:
        raise CliError(str(exc), status=1) from None
    if not first.get("ok"):
        raise CliError(f"status: {first.get('error')}", status=1)
    joints = [d["joint"] for d in first.get("drives", [])] or cfg.joint_names
    sink = _sink(args, joints, cfg)
    lease = None
    if args.drag:  # drag while the view runs: a lease renewed from the poll loop (docs/HAND.md)
        import os

        from dragd.cli.daemon import call_daemon
        from dragd.lease import LeaseError, LeaseHolder

        from dragd.protocol import ControlClient

        def call(cmd: str, timeout_s: float | None = None, **kw: Any) -> dict[str, Any]:
            if timeout_s is None:
                return call_daemon(args, cmd, **kw)
            resp = ControlClient(args.socket, timeout_s=timeout_s).call(cmd, **kw)
            if not resp.get("ok", False):
                raise CliError(f"daemon at {args.socket}: {resp.get('error', 'request failed')}", status=1)
            return resp

        lease = LeaseHolder(call, f"dragd view --drag (pid {os.getpid()})")
        try:
            lease.open()
            lease.drag()
        except LeaseError as exc:
            lease.close()
            raise CliError(f"--drag: {exc}", status=1) from None
        lease.keep()  # renewed paced by the daemon's clock in a thread of its own

    def renew(st: dict[str, Any]) -> None:
        if lease is not None and lease.error is not None:
            raise RuntimeError(f"--drag: the lease ended: {lease.error}")

    if args.seconds is None:
        print("dragd: viewing the daemon" + (" (in drag while it runs)" if lease else "") + "; Ctrl-C ends",
              file=sys.stderr)
    try:
        data = live_to_rerun(lambda: client.call("status"), sink, len(joints), args.poll_rate, args.seconds,
                             on_poll=renew)
    except (DaemonUnavailable, RuntimeError) as exc:
        raise CliError(str(exc), status=1) from None
    finally:
        if lease is not None:
            lease.close()
    data["rrd"] = str(args.save) if args.save else None
    emit(args, data, lambda d: f"{d['polls']} samples -> {d['rrd'] or args.connect or 'a Rerun viewer'}")
    return 0


def _viewer_options(p: argparse.ArgumentParser, rate: float) -> None:
    p.add_argument("--save", type=Path, default=None, metavar="FILE.rrd", help="write a Rerun recording instead of "
                   "showing it")
    p.add_argument("--connect", default=None, metavar="URL", help="a running Rerun viewer (gRPC URL, e.g. "
                   "rerun+http://127.0.0.1:9876/proxy); default: spawn one")
    p.add_argument("--rate", type=float, default=rate, help=f"scalar rate in Hz (default {rate:g}; 3D at 30 Hz)")
    add_config(p, params=False)


def register(sub: Any) -> None:
    v = sub.add_parser("view", help="live view of the running daemon in Rerun: 3D arm, currents, mode, faults")
    _viewer_options(v, 100.0)
    v.add_argument("--poll-rate", type=float, default=50.0, help="status polls per second (default 50)")
    v.add_argument("--seconds", type=float, default=None, help="stop after this long (default: until Ctrl-C)")
    v.add_argument("--drag", action="store_true", help="put the arm in drag while the view runs (a drag lease renewed "
                   "on the daemon's clock; closing the view holds the arm): docs/HAND.md")
    add_socket(v)
    v.set_defaults(func=cmd_view)


def register_log(lsub: Any) -> None:
    lv = lsub.add_parser("view", help="a telemetry MCAP in Rerun (or exported to .rrd with --save)")
    lv.add_argument("file", type=Path)
    _viewer_options(lv, 100.0)
    lv.add_argument("--json", action="store_true", help="print JSON")
    lv.set_defaults(func=cmd_log_view)
