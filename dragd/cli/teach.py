"""CLI of teach and replay: ``dragd teach start|mark|stop|list|show|keyframes``, ``dragd replay ...``.

The daemon records and replays (control socket); ``teach show``, ``teach keyframes`` and ``replay --dry-run`` work
on program files offline.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path
from typing import Any

from dragd.cli.common import CliError, add_config, add_socket, emit, table
from dragd.cli.daemon import call_daemon

REPLAY_ACTIONS = ("pause", "resume", "stop", "speed", "status")


def _program_arg(text: str) -> str:
    """A bare name goes to the daemon as is (its program_dir); a path is made absolute (the daemon's cwd differs)."""
    if "/" in text or text.endswith((".yaml", ".yml")):
        return str(Path(text).expanduser().resolve())
    return text


def _deg(q: list[float]) -> str:
    return ", ".join(f"{math.degrees(x):.3f}" for x in q)


# --------------------------------------------------------------------------------------------- teach


def cmd_teach_start(args: argparse.Namespace) -> int:
    kw: dict[str, Any] = {"action": "start", "name": _program_arg(args.name), "overwrite": args.overwrite}
    if args.rate is not None:
        kw["rate_Hz"] = args.rate
    resp = call_daemon(args, "teach", **kw)
    resp.pop("ok", None)
    emit(args, resp, lambda d: f"teaching '{d['name']}' → {d['program']} (positions at {d['rate_Hz']:g} Hz, raw MCAP "
                                f"{d['mcap']}); mode {d['mode']}: guide the arm, 'dragd teach mark' at each waypoint")
    return 0


def cmd_teach_mark(args: argparse.Namespace) -> int:
    kw: dict[str, Any] = {"action": "mark"}
    if args.name:
        kw["name"] = args.name
    resp = call_daemon(args, "teach", **kw)
    resp.pop("ok", None)
    emit(args, resp,
         lambda d: f"{d['name']} (waypoint {d['index']}) at t = {d['t_s']:.3f} s: q = [{_deg(d['q_rad'])}]°")
    return 0


def cmd_teach_stop(args: argparse.Namespace) -> int:
    resp = call_daemon(args, "teach", action="stop")
    resp.pop("ok", None)
    emit(args, resp, lambda d: f"program '{d['name']}' written: {d['program']} ({d['waypoints']} waypoints, "
                                f"{d['samples']} samples over {d['duration_s']:.1f} s; raw MCAP {d['mcap']})")
    return 0


def _programs_text(d: dict[str, Any]) -> str:
    rows = []
    for p in d["programs"]:
        if p.get("interrupted"):
            stem = Path(p["path"]).stem
            rows.append((stem, "-", "-", "-", f"interrupted: dragd teach recover {stem}"))
        elif "error" in p:
            rows.append((Path(p["path"]).stem, "-", "-", "-", p["error"][:60]))
        else:
            rows.append((p["name"], p["waypoints"], p["samples"], f"{p['duration_s']:.1f}", p["created"]))
    if not rows:
        return f"no programs in {d['program_dir']}"
    return f"{d['program_dir']}:\n" + table(["program", "waypoints", "samples", "duration_s", "created"], rows)


def cmd_teach_list(args: argparse.Namespace) -> int:
    if args.dir is not None:
        from dragd.teach.program import list_programs

        data = {"program_dir": str(args.dir), "programs": list_programs(args.dir)}
    else:
        data = call_daemon(args, "teach", action="list")
        data.pop("ok", None)
    emit(args, data, _programs_text)
    return 0


def cmd_teach_recover(args: argparse.Namespace) -> int:
    from dragd.config import load_config
    from dragd.teach.program import ProgramError, check_name
    from dragd.teach.recover import recover

    src = Path(args.session)
    if src.suffix != ".mcap" and "/" not in args.session:  # a bare name: the configured program folder
        try:
            check_name(args.session)
        except ProgramError as exc:
            raise CliError(str(exc)) from None
        folder = args.dir if args.dir is not None else load_config(args.config).program_dir
        src = Path(folder) / f"{args.session}.mcap"
    try:
        res = recover(src, args.out, overwrite=args.overwrite)
    except ProgramError as exc:
        raise CliError(str(exc)) from None
    emit(args, res, lambda d: f"program '{d['name']}' recovered: {d['program']} ({d['waypoints']} waypoints, "
                              f"{d['samples']} samples over {d['duration_s']:.1f} s"
                              + ("; the recording was cut at its last complete chunk" if d["truncated"] else "") + ")")
    return 0


def _load(path: Path):  # noqa: ANN202
    from dragd.teach.program import ProgramError, load_program

    try:
        return load_program(path)
    except ProgramError as exc:
        raise CliError(str(exc)) from None


def cmd_teach_show(args: argparse.Namespace) -> int:
    prog = _load(args.program)
    data = {"path": str(args.program), **prog.summary(),
            "waypoints_q_rad": {w.name: w.q_rad for w in prog.waypoints}}

    def text(d: dict[str, Any]) -> str:
        lines = [f"{d['path']}: program '{d['name']}' (v{d['version']}, {d['created']}), {d['samples']} samples over "
                 f"{d['duration_s']:.1f} s, keyframes: {d['keyframes']}"]
        for name, q in d["waypoints_q_rad"].items():
            lines.append(f"  {name}: [{_deg(q)}]°")
        return "\n".join(lines)

    emit(args, data, text)
    return 0


def cmd_teach_keyframes(args: argparse.Namespace) -> int:
    from dragd.teach.keyframes import extract_keyframes
    from dragd.teach.program import Keyframe, save_program

    prog = _load(args.program)
    t, q = prog.path_arrays()
    if len(t) < 2:
        raise CliError(f"{args.program}: no continuous recording (path) to reduce")
    if not args.tolerance_deg > 0:
        raise CliError(f"--tolerance-deg: expected a positive angle, got {args.tolerance_deg}")
    try:
        kf = extract_keyframes(t, q, math.radians(args.tolerance_deg), marks_t=[w.t_s for w in prog.waypoints],
                               pause_min_s=args.pause_s)
    except ValueError as exc:
        raise CliError(f"{args.program}: keyframes: {exc}", status=1) from None
    data = {"program": str(args.program), "samples": len(t), "keyframes": len(kf.index),
            "kinds": {k: kf.kind.count(k) for k in sorted(set(kf.kind))},
            "max_deviation_deg": round(math.degrees(kf.max_deviation_rad), 4), "tolerance_deg": args.tolerance_deg,
            "written": False}
    if args.write:
        prog.keyframes = [Keyframe(t_s=float(t[i]), q_rad=q[i].tolist(), kind=k)
                          for i, k in zip(kf.index, kf.kind, strict=True)]
        prog.notes = {**prog.notes, "keyframe_tolerance_deg": args.tolerance_deg}
        save_program(prog, args.program)
        data["written"] = True
    emit(args, data, lambda d: f"{d['keyframes']} keyframes from {d['samples']} samples ({d['kinds']}); the spline "
                                f"through them stays within {d['max_deviation_deg']:.3f}° of the recording"
                                + (" — written to the program" if d["written"] else ""))
    return 0


# --------------------------------------------------------------------------------------------- replay


def _replay_text(d: dict[str, Any]) -> str:
    r = d.get("replay") or d
    if r is None:
        return "no replay"
    parts = [f"replay '{r.get('name', r.get('program'))}' ({r.get('interp')}): {r.get('state', d.get('mode'))}"]
    if "t_s" in r:
        parts.append(f"t = {r['t_s']:.2f} s of {r.get('duration_s', 0):.2f} s, cycle {r.get('cycle')}/"
                     f"{r.get('cycles') or '∞'}, speed {r.get('speed_override', r.get('speed'))}")
    if r.get("next_waypoint"):
        parts.append(f"next {r['next_waypoint']}")
    return ", ".join(parts)


def cmd_replay(args: argparse.Namespace) -> int:
    target = args.target
    if target in REPLAY_ACTIONS:
        return _replay_action(args, target)
    if args.value is not None:
        raise CliError(f"replay {target}: unexpected argument '{args.value}' (replay PROGRAM [options])")
    if not 0.1 <= args.speed <= 1.0:
        raise CliError(f"--speed: expected a fraction 0.1..1, got {args.speed}")
    if args.cycles < 0:
        raise CliError(f"--cycles: expected 0 (until stopped) or more, got {args.cycles}")
    if args.dry_run:
        return _dry_run(args)
    kw: dict[str, Any] = {"program": _program_arg(target), "interp": args.interp, "speed": args.speed,
                          "cycles": args.cycles}
    if args.source:
        kw["source"] = args.source
    resp = call_daemon(args, "replay", **kw)
    resp.pop("ok", None)
    if args.wait:
        end = time.monotonic() + args.wait_timeout
        while time.monotonic() < end:
            st = call_daemon(args, "status")
            r = st.get("replay") or {}
            if r.get("outcome"):
                resp["outcome"] = r["outcome"]
                resp["mode"] = st["mode"]
                break
            time.sleep(0.1)
        else:
            raise CliError(f"replay: still running after {args.wait_timeout:.0f} s (--wait-timeout)", status=1)
        if resp["outcome"] != "done":
            emit(args, resp, lambda d: f"replay ended: {d['outcome']}")
            return 1
    emit(args, resp, lambda d: f"replaying {d['program']} ({d['interp']}, {d['source']}): move to start "
                                f"{d['move_to_start_s']:.1f} s, cycle {d['cycle_s']:.1f} s"
                                + (f" → {d['outcome']}" if "outcome" in d else ""))
    return 0


def _replay_action(args: argparse.Namespace, action: str) -> int:
    if action == "status":
        st = call_daemon(args, "status")
        data = {"replay": st.get("replay"), "mode": st["mode"]}
        emit(args, data, _replay_text)
        return 0
    if action == "speed":
        if args.value is None:
            raise CliError("replay speed: expected a fraction 0.1..1, e.g. 'dragd replay speed 0.5'")
        try:
            v = float(args.value)
        except ValueError:
            raise CliError(f"replay speed: expected a fraction 0.1..1, got '{args.value}'") from None
        if not 0.1 <= v <= 1.0:
            raise CliError(f"replay speed: expected a fraction 0.1..1, got {v}")
        resp = call_daemon(args, "replay_speed", speed=v)
        resp.pop("ok", None)
        emit(args, resp, lambda d: f"speed override {d['speed_override']:g} ({d['state']})")
        return 0
    if args.value is not None:
        raise CliError(f"replay {action}: unexpected argument '{args.value}'")
    resp = call_daemon(args, f"replay_{action}")
    resp.pop("ok", None)
    emit(args, resp, lambda d: f"replay {action}: {d['state']} (mode {d['mode']})")
    return 0


def _dry_run(args: argparse.Namespace) -> int:
    """Plan offline with the configuration, from the first waypoint (or the path's start)."""
    import numpy as np

    from dragd.config import load_config
    from dragd.teach.plan import PlanError, plan_replay, request_from_config

    cfg = load_config(args.config)
    from dragd.teach.program import ProgramError, resolve_program

    try:
        path = resolve_program(args.target, cfg.program_dir)
    except ProgramError as exc:
        raise CliError(str(exc)) from None
    prog = _load(path)
    if prog.waypoints:
        q0 = prog.waypoints[0].q_rad
    elif prog.path:
        q0 = prog.path[0][1:]
    else:
        raise CliError(f"{path}: no waypoints and no recording")
    req = request_from_config(cfg, path, q0, interp=args.interp, source=args.source)
    try:
        res = plan_replay(req)
    except (PlanError, ValueError) as exc:
        raise CliError(str(exc), status=1) from None
    s = res["summary"]
    s["max_velocity_rad_s"] = np.abs(res["dq"]).max(axis=0).round(4).tolist()
    s["program"] = str(path)
    emit(args, s, lambda d: f"{d['program']} ({d['interp']}, {d['source']}): cycle {d['cycle_s']:.2f} s in "
                             f"{len(d['segments']) - 2} segment(s); waypoints "
                             + ", ".join(f"{m['name']} at {m['t_s']:.2f} s ({m['kind']})" for m in d["marks"]))
    return 0


# --------------------------------------------------------------------------------------------- parser


def register(sub: Any) -> None:
    t = sub.add_parser("teach", help="teach by hand: record a drag, mark waypoints (start | mark | stop | list | "
                                     "show | keyframes)")
    tsub = t.add_subparsers(dest="teach_command", metavar="ACTION")
    tsub.required = True
    s = tsub.add_parser("start", help="start teaching NAME: arm to drag, record positions and the raw MCAP")
    s.add_argument("name", help="program name (stored in the daemon's replay.program_dir) or a .yaml path")
    s.add_argument("--rate", type=float, default=None, help="recording rate in Hz (default: replay.record_rate_Hz)")
    s.add_argument("--overwrite", action="store_true", help="replace an existing program of that name")
    add_socket(s)
    s.set_defaults(func=cmd_teach_start)
    m = tsub.add_parser("mark", help="mark the present pose as the next waypoint (p1, p2, ...)")
    m.add_argument("name", nargs="?", default=None, help="waypoint name (default p<N>)")
    add_socket(m)
    m.set_defaults(func=cmd_teach_mark)
    st = tsub.add_parser("stop", help="stop teaching and write the program file")
    add_socket(st, timeout=30.0)
    st.set_defaults(func=cmd_teach_stop)
    ls = tsub.add_parser("list", help="taught programs (the daemon's program_dir, or --dir)")
    ls.add_argument("--dir", type=Path, default=None, help="list this folder instead of asking the daemon")
    add_socket(ls, timeout=30.0)
    ls.set_defaults(func=cmd_teach_list)
    rc = tsub.add_parser("recover", help="write the program of a teach session that never reached 'stop' (daemon "
                         "killed, power lost) from its recording")
    rc.add_argument("session", help="program name (in replay.program_dir, or --dir) or the session's .mcap file")
    rc.add_argument("--dir", type=Path, default=None, help="the program folder (default: the configuration's)")
    rc.add_argument("--out", type=Path, default=None, help="program file to write (default: NAME.yaml beside the "
                    "recording)")
    rc.add_argument("--overwrite", action="store_true", help="replace an existing program file")
    add_config(rc, params=False)
    rc.add_argument("--json", action="store_true", help="print JSON")
    rc.set_defaults(func=cmd_teach_recover)
    sh = tsub.add_parser("show", help="summary and waypoints of a program file")
    sh.add_argument("program", type=Path)
    sh.add_argument("--json", action="store_true", help="print JSON")
    sh.set_defaults(func=cmd_teach_show)
    kf = tsub.add_parser("keyframes", help="reduce a program's continuous recording to keyframes (post-processing)")
    kf.add_argument("program", type=Path)
    kf.add_argument("--tolerance-deg", type=float, default=0.5,
                    help="max deviation of the replayed path (default 0.5°)")
    kf.add_argument("--pause-s", type=float, default=0.3, help="a hand still this long marks a stop (default 0.3 s)")
    kf.add_argument("--write", action="store_true", help="store the keyframes in the program (replay uses them)")
    kf.add_argument("--json", action="store_true", help="print JSON")
    kf.set_defaults(func=cmd_teach_keyframes)

    r = sub.add_parser("replay", help="replay a taught program in CSP (or: replay pause | resume | stop | speed X | "
                                      "status)")
    r.add_argument("target", metavar="PROGRAM",
                   help="program name or .yaml path; or pause, resume, stop, speed, status")
    r.add_argument("value", nargs="?", default=None, help=argparse.SUPPRESS)
    r.add_argument("--interp", choices=["linear", "circular", "spline"], default="linear",
                   help="linear: point-to-point joint moves; circular: Cartesian circle through p1, p2, p3; "
                        "spline: smooth through the waypoints (default linear)")
    r.add_argument("--speed", type=float, default=1.0, help="speed override 0.1..1 (default 1)")
    r.add_argument("--cycles", type=int, default=1, help="repetitions, 0 = until 'replay stop' (default 1)")
    r.add_argument("--source", choices=["waypoints", "path"], default=None,
                   help="replay the marked waypoints or the continuous recording (default: waypoints if ≥ 2)")
    r.add_argument("--wait", action="store_true", help="return when the replay has ended (exit 1 unless done)")
    r.add_argument("--wait-timeout", type=float, default=600.0, help="seconds --wait waits at most (default 600)")
    r.add_argument("--dry-run", action="store_true", help="plan offline with --config and print the plan, no daemon")
    add_config(r, params=False)
    add_socket(r, timeout=60.0)
    r.set_defaults(func=cmd_replay)
