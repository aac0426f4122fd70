"""``dragd payload estimate|set|clear|show`` and ``dragd check model`` through the daemon (docs/PAYLOAD.md)."""

from __future__ import annotations

import argparse
from typing import Any

from dragd.cli.common import CliError, add_socket, emit, floats, table
from dragd.cli.daemon import call_daemon


def _applied(d: dict[str, Any]) -> str:
    where = f"written to {d['params']}" if d.get("params") else (d.get("note") or "")
    return (f"payload {d['mass_kg']:g} kg at ({', '.join(f'{x:g}' for x in d['com_m'])}) m in the last joint's frame; "
            f"the law takes it over {d['ramp_s']:g} s; {where}")


def _estimate_text(d: dict[str, Any]) -> str:
    lines = [f"payload estimate from {d['samples']} rests at {d['poses']} poses:",
             f"  mass {d['mass_kg']:.3f} kg (std {d['mass_std_kg']:.3f} kg)",
             "  centre of mass " + ", ".join(f"{a} {v * 1000:+.0f} mm (std {s * 1000:.0f})"
                                             for a, v, s in zip("xyz", d["com_m"], d["com_std_m"], strict=True)),
             f"  rms residual {d['rms_residual_Nm']:.2f} N·m", f"  {d['observability']}"]
    if d.get("applied"):
        lines.append("  applied: " + _applied(d["applied"]))
    else:
        lines.append("  not applied (--apply to use it)")
    return "\n".join(lines)


def cmd_payload(args: argparse.Namespace) -> int:
    if args.action == "estimate":
        resp = call_daemon(args, "payload", action="estimate", poses=args.poses, apply=args.apply)
        emit(args, resp, _estimate_text)
    elif args.action == "set":
        if args.mass_kg is None:
            raise CliError("payload set: expected --mass-kg M (and --com-m X,Y,Z)")
        com = floats(args.com_m, "--com-m") if args.com_m else [0.0, 0.0, 0.0]
        if len(com) != 3:
            raise CliError(f"--com-m: expected X,Y,Z (3 numbers, m), got {len(com)}")
        emit(args, call_daemon(args, "payload", action="set", mass_kg=args.mass_kg, com_m=com), _applied)
    elif args.action == "clear":
        emit(args, call_daemon(args, "payload", action="clear"), _applied)
    else:
        emit(args, call_daemon(args, "payload", action="show"),
             lambda d: f"payload {d['mass_kg']:g} kg at ({', '.join(f'{x:g}' for x in d['com_m'])}) m")
    return 0


def _check_text(d: dict[str, Any]) -> str:
    rows = [[r["joint"], r["verdict"], "" if r["slope_ratio"] is None else f"{r['slope_ratio']:+.2f}",
             f"{r['delta_model_A']:+.2f}", "" if r["delta_measured_A"] is None else f"{r['delta_measured_A']:+.2f}"]
            for r in d["joints"]]
    head = "model check passed" if d["ok"] else "model check FAILED: drag is refused until it passes"
    return head + f" (tolerance ±{d['tolerance'] * 100:.0f} % on K_t's scale)\n" + table(
        ["joint", "verdict", "measured/model", "ΔI model A", "ΔI measured A"], rows) + \
        "".join(f"\n{r['joint']}: {r['text']}" for r in d["joints"] if r["text"])


def cmd_check(args: argparse.Namespace) -> int:
    resp = call_daemon(args, "check_model", step_rad=args.step_rad)
    emit(args, resp, _check_text)
    return 0 if resp.get("ok") else 1


def register(sub: Any) -> None:
    p = sub.add_parser("payload", help="the flange payload: estimate it from hold currents, set a known one, clear it")
    p.add_argument("action", choices=["estimate", "set", "clear", "show"])
    p.add_argument("--poses", type=int, default=6, help="estimate: poses to rest at (3..8, default 6)")
    p.add_argument("--apply", action="store_true", help="estimate: apply it to the running law and the params file")
    p.add_argument("--mass-kg", type=float, default=None, help="set: the tool's mass [kg]")
    p.add_argument("--com-m", default=None, help="set: its centre of mass X,Y,Z [m] in the last joint's frame")
    add_socket(p, timeout=180.0)
    p.set_defaults(func=cmd_payload)
    c = sub.add_parser("check", help="start-up checks: 'check model' moves each joint a little in HOLD and confirms "
                       "encoder direction, current sign and K_t's scale against the gravity model")
    c.add_argument("what", choices=["model"])
    c.add_argument("--step-rad", type=float, default=0.25, help="each joint's move either side of the pose (rad)")
    add_socket(c, timeout=180.0)
    c.set_defaults(func=cmd_check)
