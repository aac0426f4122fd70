"""The daemon: ``dragd run`` (the foreground daemon), ``dragd start|stop|mode|status|clock`` (its control socket)."""

from __future__ import annotations

import argparse
import os
import sys
from typing import TYPE_CHECKING, Any

from dragd.cli.common import DEFAULT_SOCKET, CliError, add_config, add_socket, emit, table

LOCKSTEP_GUARD_S = 10.0  # dragd.clock.GUARD_S (not imported here: socket commands load no asyncio)

if TYPE_CHECKING:
    from dragd.config import Config


def call_daemon(args: argparse.Namespace, cmd: str, **kw: Any) -> dict[str, Any]:
    """Send ``cmd`` to the daemon at ``args.socket``; an unreachable daemon or a refusal is a CliError (exit 1)."""
    from dragd.protocol import ControlClient, DaemonUnavailable

    try:
        resp = ControlClient(args.socket, timeout_s=args.timeout).call(cmd, **kw)
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


def with_telemetry_options(cfg: Any, args: argparse.Namespace) -> Any:
    """``cfg`` with ``--telemetry-decimation`` / ``--foxglove-rate`` / ``--no-foxglove`` applied (validated)."""
    update: dict[str, Any] = {}
    if getattr(args, "telemetry_decimation", None) is not None:
        update["cycle_decimation"] = args.telemetry_decimation
    if getattr(args, "foxglove_rate", None) is not None:
        update["foxglove_rate_Hz"] = args.foxglove_rate
    if getattr(args, "no_foxglove", False):
        update["foxglove"] = False
    if getattr(args, "foxglove_encoding", None) is not None:
        update["foxglove_encoding"] = args.foxglove_encoding
    if not update:
        return cfg
    from pydantic import ValidationError

    try:
        tel = type(cfg.telemetry).model_validate({**cfg.telemetry.model_dump(), **update})
    except ValidationError as exc:
        err = exc.errors()[0]
        raise CliError(f"telemetry.{err['loc'][0]}: {err['msg']} (got {err.get('input')!r})") from None
    return cfg.model_copy(update={"telemetry": tel})


def cmd_run(args: argparse.Namespace) -> int:
    from dragd.realtime import single_threaded_blas

    if "numpy" not in sys.modules:  # (in a test's process it may be: the BLAS threads are then left as they are)
        single_threaded_blas()
    import can

    from dragd.clock import LockstepError
    from dragd.config import load_config
    from dragd.daemon.core import BusBudgetError, Daemon
    from dragd.hardware.master import DriveError

    cfg = load_config(args.config, args.params)
    if args.realtime_priority is not None:
        cfg = with_realtime_priority(cfg, args.realtime_priority)
    cfg = with_telemetry_options(cfg, args)
    try:
        daemon = Daemon(cfg, bus_override=args.bus, socket_path=args.socket, telemetry_path=args.telemetry,
                        rerun=args.rerun, allow_dirs=args.allow_dir, batch_frames=args.batch_frames,
                        lockstep=args.lockstep, lockstep_guard_s=args.lockstep_guard_s,
                        lab_unguarded_drag=args.lab_unguarded_drag)
    except (BusBudgetError, ValueError) as exc:
        raise CliError(str(exc)) from None
    try:
        import asyncio

        from dragd.daemon.commands import command_table

        return asyncio.run(daemon.run(command_table))
    except DriveError as exc:
        raise CliError(str(exc), status=1) from None
    except can.CanError as exc:  # e.g. socketcan:can0 on a machine without that interface
        raise CliError(str(exc), status=1) from None
    except ValueError as exc:  # e.g. another dragd holds the run lock
        raise CliError(str(exc), status=1) from None
    except LockstepError as exc:  # the simulator stopped answering, or runs another period
        raise CliError(str(exc), status=1) from None


def cmd_start(args: argparse.Namespace) -> int:
    resp = call_daemon(args, "start")
    emit(args, resp, lambda d: f"drives enabled, mode {d['mode']}")
    return 0


def cmd_stop(args: argparse.Namespace) -> int:
    resp = call_daemon(args, "stop")
    emit(args, resp, lambda d: f"drives disabled, mode {d['mode']}")
    return 0


def cmd_mode(args: argparse.Namespace) -> int:
    kw = {"accept": True} if getattr(args, "accept", False) else {}
    if args.hold:
        if args.mode != "drag":
            raise CliError(f"--hold: only with 'mode drag' (the lease keeps the arm in drag), got 'mode {args.mode}'")
        return _drag_held(args, kw)
    if args.seconds is not None:
        raise CliError("--seconds: only with --hold")
    resp = call_daemon(args, "mode", mode=args.mode, **kw)
    emit(args, resp, lambda d: f"mode {d['mode']}")
    return 0


def _drag_held(args: argparse.Namespace, kw: dict[str, Any]) -> int:
    """``dragd mode drag --hold``: a drag lease, renewed while this command runs (docs/HAND.md); Ctrl-C, SIGTERM or
    ``--seconds`` (of the daemon's clock: simulated time on the lockstep clock) end it (the lease is closed: the arm
    holds). Exit status 1 when the lease lapsed or drag ended without it (the reason is printed). The renewals are
    paced by the daemon (this process reads no clock)."""
    import signal

    from dragd.lease import LeaseError, LeaseHolder
    from dragd.protocol import ControlClient, DaemonUnavailable

    if args.seconds is not None and not args.seconds > 0:
        raise CliError(f"--seconds: expected a positive number of seconds, got {args.seconds}")

    class Stopped(BaseException):  # (not an Exception: it passes through the lease's error handling)
        pass

    def call(cmd: str, timeout_s: float | None = None, **kw_: Any) -> dict[str, Any]:
        try:
            resp = ControlClient(args.socket, timeout_s=timeout_s or args.timeout).call(cmd, **kw_)
        except DaemonUnavailable as exc:
            raise CliError(str(exc), status=1) from None
        if not resp.get("ok", False):
            raise CliError(f"daemon at {args.socket}: {resp.get('error', 'request failed')}", status=1)
        return resp

    holder = LeaseHolder(call, f"dragd mode drag --hold (pid {os.getpid()})", args.lease_s)
    stop: dict[str, Any] = {"why": None, "waiting": False}

    def on_signal(signum: int, _frame: Any) -> None:
        stop["why"] = signal.Signals(signum).name
        if stop["waiting"]:
            raise Stopped  # (out of the wait for a paced answer)

    old = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    status, outcome = 0, ""
    t0: float | None = None
    try:
        holder.open()
        resp = holder.drag(**kw)
        if not args.json:
            print(f"mode {resp['mode']}: drag lease {holder.lease} (renewed every {holder.every_s * 1e3:.0f} ms of the "
                  f"daemon's clock, lapses after {holder.period_s:g} s without); Ctrl-C ends drag", file=sys.stderr,
                  flush=True)
        while stop["why"] is None:
            try:
                stop["waiting"] = True
                ans = holder.renew_paced()
            except Stopped:
                break
            finally:
                stop["waiting"] = False
            t0 = holder.t_s if t0 is None else t0
            if not ans.get("drag") and not holder.drag_can_return(ans):
                ended = (call("status").get("drag") or {}).get("last_drag_end") or {}
                outcome, status = f"drag ended: {ended.get('reason', 'the arm left drag (' + ans['mode'] + ')')}", 1
                break
            if args.seconds is not None and holder.t_s is not None and t0 is not None and \
                    holder.t_s - t0 >= args.seconds - 1e-9:
                stop["why"] = f"{args.seconds:g} s"
        if not outcome:
            outcome = f"ended by {stop['why']}"
    except LeaseError as exc:
        outcome, status = str(exc), 1
    finally:
        for sig, h in old.items():
            signal.signal(sig, h)
        closed = holder.close()
    mode = (closed or {}).get("mode") or "unknown"
    held = round(holder.t_s - t0, 3) if holder.t_s is not None and t0 is not None else 0.0
    data = {"lease": holder.lease, "renewals": holder.renewals, "held_s": held, "outcome": outcome, "mode": mode}
    emit(args, data, lambda d: f"drag lease {d['lease']} closed after {d['held_s']:g} s ({d['renewals']} renewals): "
                               f"{d['outcome']}; mode {d['mode']}")
    return status


def _status_text(d: dict[str, Any]) -> str:
    import math

    lines = [f"mode {d['mode']}, drives {'enabled' if d['drives_enabled'] else 'disabled'}, {d['cycles']} cycles, "
             f"period p99 {d['period_p99_us'] or 0:.0f} µs, missed {d['missed_cycles']}"]
    rows = [(dr["joint"], dr["node_id"], dr["state"], f"{math.degrees(q):.3f}", f"{i:.3f}")
            for dr, q, i in zip(d["drives"], d["q_rad"], d["current_A"], strict=True)]
    lines.append(table(["joint", "node", "state", "q_deg", "current_A"], rows))
    g, p = d.get("guard"), d.get("payload")
    if p is not None and p.get("mass_kg"):
        lines.append(f"payload {p['mass_kg']:g} kg at ({', '.join(f'{x:g}' for x in p['com_m'])}) m")
    if g is not None and (g.get("trips") or any(g.get("gravity_offset_A") or [])):
        lines.append(f"runaway guard: {g['trips']} trip(s); gravity offset "
                     f"{', '.join(f'{x:+.2f}' for x in g['gravity_offset_A'])} A")
    for f in d["faults"]:
        lines.append(f"fault at {f['t_s']:.3f} s: {f['text']}")
    return "\n".join(lines)


def cmd_clock(args: argparse.Namespace) -> int:
    kw: dict[str, Any] = {"action": args.action}
    if args.action == "advance":
        if args.seconds is None:
            raise CliError("clock advance: expected SECONDS (simulated time to let the arm run)")
        kw["seconds"] = args.seconds
        args.timeout = max(args.timeout, 60.0 + 10.0 * args.seconds)  # (a slow machine runs below real time)
    resp = call_daemon(args, "clock", **kw)
    c = resp["clock"]
    emit(args, resp, lambda d: (f"lockstep clock at {c['t_s']:.3f} s ({c['ticks']} periods of {c['period_s'] * 1e3:g} "
                                f"ms), real-time factor {c['rtf']}{', running' if c['free_run'] else ''}"
                                if c["lockstep"] else f"wall clock (CLOCK_MONOTONIC {c['t_s']:.3f} s)"))
    return 0


def cmd_status(args: argparse.Namespace) -> int:
    resp = call_daemon(args, "status")
    resp.pop("ok", None)
    emit(args, resp, _status_text)
    return 0


def register(sub: Any) -> None:
    r = sub.add_parser("run", help="run the daemon in the foreground (what systemd starts)")
    add_config(r)
    r.add_argument("--bus", help="INTERFACE:CHANNEL overriding the config's bus (comma-separated for several buses), "
                   "e.g. socketcan:can0, udp_multicast:239.74.163.2, virtual:arm")
    r.add_argument("--allow-dir", action="append", default=None, metavar="DIR",
                   help="a folder control requests may read/write files in, beside control.allowed_dirs (repeatable)")
    r.add_argument("--socket", default=os.environ.get("DRAGD_SOCKET") or None,
                   help="control socket path (default: $DRAGD_SOCKET, else the config's "
                        f"control.socket, {DEFAULT_SOCKET})")
    r.add_argument("--telemetry", default=None, help="write every cycle to this MCAP file")
    r.add_argument("--telemetry-decimation", type=int, default=None, metavar="N",
                   help="write every N-th cycle to the MCAP's /dragd/cycle (size option; overrides "
                        "telemetry.cycle_decimation; docs/TELEMETRY.md gives MB per hour)")
    r.add_argument("--foxglove-rate", type=float, default=None, metavar="HZ",
                   help="rate of the MCAP's Foxglove channels (joint states, transforms; telemetry.foxglove_rate_Hz)")
    r.add_argument("--no-foxglove", action="store_true",
                   help="no Foxglove channels in the MCAP (telemetry.foxglove: false)")
    r.add_argument("--foxglove-encoding", choices=("json", "ros2"), default=None,
                   help="those channels as Foxglove's JSON or ROS 2's CDR (sensor_msgs/JointState, tf2_msgs, /rosout; "
                        "telemetry.foxglove_encoding; docs/ROS2.md)")
    r.add_argument("--realtime-priority", type=int, default=None, metavar="N",
                   help="SCHED_FIFO priority 1..99 of the cycle thread, when permitted (0: none); "
                        "overrides loop.realtime_priority")
    r.add_argument("--rerun", action="store_true", help="live view in rerun (needs the optional extra dragd[rerun])")
    r.add_argument("--batch-frames", action="store_true",
                   help="udp_multicast: send each cycle's command frames with the next SYNC in one datagram (the "
                        "simulator with --batch-frames reads it; python-can's own udp_multicast tools do not: leave it "
                        "off for them); no effect on other buses")
    r.add_argument("--lockstep", action="store_true",
                   help="run on the lockstep clock against 'dragd sim --lockstep': simulated time, one period per "
                        "SYNC, advanced only when granted ('dragd clock advance|run') or waited for by a command; "
                        "for tests, demos and experiments (docs/LOCKSTEP.md)")
    r.add_argument("--lab-unguarded-drag", action="store_true",
                   help="a lab's flag: drag needs no lease (and no enabling switch where none is wired), whatever "
                        "drag.require says; 'dragd status' reports it (drag.lab_unguarded). Never on a robot people "
                        "work beside (docs/HAND.md)")
    r.add_argument("--lockstep-guard-s", type=float, default=LOCKSTEP_GUARD_S, metavar="S",
                   help="lockstep: wall seconds without the simulator's answer before it is an error (default "
                        f"{LOCKSTEP_GUARD_S:g})")
    r.set_defaults(func=cmd_run)

    for name, fn, helptext in (("start", cmd_start, "enable the drives and hold the pose"),
                               ("stop", cmd_stop, "ramp down to hold, disable the drives (brakes on)")):
        p = sub.add_parser(name, help=helptext)
        add_socket(p)
        p.set_defaults(func=fn)
    m = sub.add_parser("mode", help="switch mode without a jump in current: idle | hold | drag")
    m.add_argument("mode", choices=["idle", "hold", "drag"])
    m.add_argument("--accept", action="store_true",
                   help="drag even where the hold current disagrees with the gravity model: the measured hold currents "
                   "become the gravity offset around this pose (docs/PAYLOAD.md)")
    m.add_argument("--hold", action="store_true",
                   help="drag: hold a drag lease while this command runs (renewed in the background; Ctrl-C, SIGTERM "
                        "or --seconds close it and the arm holds; a killed command lets it lapse): what drag.require: "
                        "lease asks for (docs/HAND.md)")
    m.add_argument("--seconds", type=float, default=None,
                   help="with --hold: end after this long (of the daemon's clock: simulated time on the lockstep "
                        "clock)")
    m.add_argument("--lease-s", type=float, default=None, metavar="S",
                   help="with --hold: the lease period (default and at most the daemon's drag.lease_s)")
    add_socket(m)
    m.set_defaults(func=cmd_mode)
    k = sub.add_parser("clock", help="the cycle's clock: status; on a --lockstep daemon advance SECONDS, run, pause")
    k.add_argument("action", nargs="?", default="status", choices=["status", "advance", "run", "pause"])
    k.add_argument("seconds", nargs="?", type=float, help="advance: simulated seconds to let the arm run")
    add_socket(k)
    k.set_defaults(func=cmd_clock)
    s = sub.add_parser("status", help="the daemon's state, timing and faults")
    add_socket(s)
    s.set_defaults(func=cmd_status)
