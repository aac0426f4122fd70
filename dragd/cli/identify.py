"""CLI of identification: ``dragd identify plan|run|fit|check`` (see docs/IDENTIFICATION.md).

- ``plan``  write an excitation plan (.npz) within the joint limits
- ``run``   drive a plan on the robot through the daemon (CSP) with a progress bar, recording MCAP
- ``fit``   identify K_t and friction (and more) from an MCAP or CSV log → params file (+ JSON)
- ``check`` predict the current of another log with a params file: RMSE/MAE/max per joint, plots
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from dragd.cli.common import CliError, Stages, add_config, add_socket, emit, floats, table

FIT_METHODS = ("lowspeed", "symmetric", "synchronous", "full", "auto")


def _robot(args: argparse.Namespace):  # noqa: ANN202
    """The robot model: ``--robot`` (bundled name or URDF), else the configuration's robot."""
    from dragd.config import load_config
    from dragd.model import RobotModel

    try:
        if getattr(args, "robot", None):
            return RobotModel.from_urdf(args.robot), None
        cfg = load_config(args.config)
        return RobotModel.from_urdf(cfg.robot.urdf, cfg.base_dir, cfg.robot.gravity_m_s2), cfg
    except (FileNotFoundError, ValueError) as exc:
        if exc.__class__.__name__ == "ConfigError":
            raise
        raise CliError(str(exc)) from None


def _load_log(path: str, model: Any = None, drop_bad_rows: bool = False):  # noqa: ANN202
    from dragd.identify.data import LogError, load_log

    try:
        if model is None:
            return load_log(path, drop_bad_rows=drop_bad_rows)
        return load_log(path, joints=list(model.joint_names), robot=str(model.urdf_path or "robot"),
                        drop_bad_rows=drop_bad_rows)
    except LogError as exc:
        raise CliError(str(exc)) from None


# --------------------------------------------------------------------------------------------- plan


def _build_plan(args: argparse.Namespace, q_start: list[float] | None = None):  # noqa: ANN202
    import numpy as np

    from dragd.identify.excitation import Limits, PlanError, build_plan

    model, cfg = _robot(args)
    limits = Limits.from_model(model, cfg, margin_rad=args.margin, acceleration_rad_s2=args.acceleration)
    if q_start is None:
        if args.start:
            q_start = floats(args.start, "--start")
        else:
            raise CliError("--start: the plan's start pose is needed (the robot's current pose; "
                           "'dragd identify run --plan KIND' takes it from the daemon)")
    q0 = np.array(q_start, dtype=float)
    if q0.shape[0] != model.nq:
        raise CliError(f"--start: expected {model.nq} values ({', '.join(model.joint_names)}), got {q0.shape[0]}")
    joints = [int(x) for x in floats(args.joints, "--joints")] if args.joints else None
    try:
        return build_plan(args.kind, model, q0, limits, joints=joints, scale=args.scale, seed=args.seed)
    except PlanError as exc:
        raise CliError(str(exc)) from None


def cmd_plan(args: argparse.Namespace) -> int:
    plan = _build_plan(args)
    out = Path(args.out)
    if out.suffix != ".npz":
        raise CliError(f"--out {out}: expected an .npz file name")
    plan.save(out)
    kinds: dict[str, int] = {}
    for s in plan.segments:
        kinds[s.kind] = kinds.get(s.kind, 0) + 1
    data = {"out": str(out), "kind": args.kind, "duration_s": round(plan.duration_s, 3),
            "samples": int(plan.t_s.shape[0]),
            "segments": kinds, "info": plan.info}
    emit(args, data, lambda d: f"{d['out']}: {d['kind']} plan, {d['duration_s']:.1f} s "
                                f"({', '.join(f'{v} {k}' for k, v in d['segments'].items())})")
    return 0


# --------------------------------------------------------------------------------------------- run


def cmd_run(args: argparse.Namespace) -> int:
    from dragd.identify.excitation import PLAN_KINDS, Plan, PlanError
    from dragd.identify.runner import RunError, run_plan
    from dragd.protocol import ControlClient, DaemonUnavailable

    client = ControlClient(args.socket, timeout_s=args.timeout)

    def call(cmd: str, **kw: Any) -> dict[str, Any]:
        try:
            return client.call(cmd, **kw)
        except DaemonUnavailable as exc:
            raise CliError(str(exc), status=1) from None

    if args.plan in PLAN_KINDS:
        st = call("status")
        if not st.get("ok", True) or "q_rad" not in st:
            raise CliError(f"daemon at {args.socket}: {st.get('error', 'no status')}", status=1)
        args.kind = args.plan
        plan = _build_plan(args, st["q_rad"])
    else:
        try:
            plan = Plan.load(args.plan)
        except PlanError as exc:
            raise CliError(str(exc)) from None
    try:
        res = run_plan(call, plan, args.out, progress=not args.no_progress and not args.json, chunk_s=args.chunk)
    except RunError as exc:
        raise CliError(str(exc), status=1) from None
    emit(args, res, lambda d: f"{d['log']}: {d['rows']} rows recorded ({d['plan']}, {d['plan_duration_s']:.1f} s plan, "
                               f"{d['chunks']} motion(s), {d['wall_time_s']:.0f} s)"
                               + (" — interrupted" if d.get("interrupted") else "")
                               + (f"; faults: {d['faults']}" if d.get("faults") else ""))
    return 1 if res.get("interrupted") or res.get("faults") else 0


# --------------------------------------------------------------------------------------------- fit


def _fit_text(d: dict[str, Any]) -> str:
    def f(x: Any, s: Any = None, fmt: str = ".4f") -> str:
        if x is None:
            return "null"
        return f"{x:{fmt}}" + (f"±{s:.1g}" if s is not None else "")

    rows = []
    for name, j in d["joints"].items():
        fr, sd = j["friction"], j["std"]
        rows.append((name, f(j["torque_constant_Nm_per_A"], sd.get("torque_constant_Nm_per_A")),
                     f(fr["coulomb_pos_A"], sd.get("coulomb_pos_A")), f(fr["coulomb_neg_A"], sd.get("coulomb_neg_A")),
                     f(fr["viscous_A_s_per_rad"], sd.get("viscous_A_s_per_rad")),
                     f(fr["static_pos_A"]), f(fr["static_neg_A"]), f(fr["stribeck_velocity_rad_s"], fmt=".3f")))
    lines = [f"method {d['method']} on {d['log']} (load {d.get('load_s', 0):.1f} s, fit {d.get('elapsed_s', 0):.1f} s) "
             f"→ {d.get('out')}",
             table(["joint", "K_t N·m/A", "F_c+ A", "F_c- A", "F_v A·s/rad", "F_s+ A", "F_s- A", "v_s rad/s"], rows)]
    if d.get("notes", {}).get("auto"):
        lines.append(f"auto: {d['notes']['auto']}")
    for name, j in d["joints"].items():
        seen = set()
        for why in j["reasons"].values():
            if why in seen:
                continue
            seen.add(why)
            keys = [kk for kk, w in j["reasons"].items() if w == why]
            lines.append(f"  {name}: {', '.join(keys)} null: {why}")
    mp = d.get("inertials_mapping")
    if mp:
        ch = ", ".join(f"{k} {v * 100:+.1f} %" for k, v in mp["mass_change"].items() if v is not None)
        lines.append(f"inertials: {'consistent' if mp['consistent'] else 'NOT consistent'} link set written "
                     f"(base-parameter residual ≤ {mp['max_base_residual_Nm'] * 1e3:.2f} mN·m; masses vs URDF: {ch})")
    for w in d.get("warnings", []):
        lines.append(f"warning: {w}")
    return "\n".join(lines)


def cmd_fit(args: argparse.Namespace) -> int:
    import time

    from dragd.config import save_params
    from dragd.identify.data import LogError, stack_logs
    from dragd.identify.fit import fit_params
    from dragd.identify.methods import Options

    with Stages(args, "identify fit") as st:
        st.stage("loading the robot model")
        model, cfg = _robot(args)
        cfg_kt = None
        if cfg is not None and cfg.joint_names == list(model.joint_names):
            cfg_kt = [float(j.kt_Nm_per_A) for j in cfg.joints]
        opts = Options()
        if args.torque_constants:
            if args.torque_constants == "config":
                if cfg_kt is None:
                    raise CliError("--torque-constants config: needs the configuration's robot (no --robot)")
                opts.torque_constants = list(cfg_kt)
            else:
                kt = floats(args.torque_constants, "--torque-constants")
                if len(kt) != model.nq or not all(k > 0 for k in kt):
                    raise CliError(f"--torque-constants: expected {model.nq} positive joint-side "
                                   "torque constants [N·m/A] "
                                   f"({', '.join(model.joint_names)}) or 'config', got {args.torque_constants!r}")
                opts.torque_constants = list[float | None](kt)
            if args.method not in ("full", "auto"):
                raise CliError(f"--torque-constants: used by --method full (and auto), not {args.method}")
        logs = args.log  # --log is repeatable: a list
        st.stage(f"reading {', '.join(logs)}")
        t0 = time.perf_counter()
        try:
            log = stack_logs([_load_log(p, model, args.drop_bad_rows) for p in logs])
        except LogError as exc:
            raise CliError(str(exc)) from None
        load_s = time.perf_counter() - t0
        if args.cutoff is not None:
            opts.cutoff_Hz = args.cutoff
        if args.load_friction:
            if args.method not in ("full", "auto"):
                raise CliError(f"--load-friction: a term of --method full (and auto), not {args.method}")
            opts.load_friction = True
        st.stage(f"fitting ({args.method})")
        try:
            res, params, mapped = fit_params(log, model, args.method, opts, cfg_kt)
        except LogError as exc:
            raise CliError(str(exc)) from None
        out = Path(args.out)
        st.stage(f"writing {out}")
        save_params(params, out)
    data = res.to_json()
    data["out"] = str(out)
    data["load_s"] = round(load_s, 3)
    if mapped is not None:
        data["inertials"] = mapped["inertials"]
        data["inertials_mapping"] = mapped["mapping"]
    emit(args, data, _fit_text)
    return 0


# --------------------------------------------------------------------------------------------- check


def cmd_check(args: argparse.Namespace) -> int:
    from dragd.config import check_joint_names, load_config, load_params
    from dragd.identify.check import check_params, plot
    from dragd.identify.data import LogError

    model, _ = _robot(args)
    params = load_params(args.params)
    cfg = None
    if args.config is not None:
        cfg = load_config(args.config)
        check_joint_names(cfg, (model.joint_names, model.urdf_path or cfg.robot.urdf))
    elif not args.robot:
        cfg = load_config(None)
    log = _load_log(args.log, model, args.drop_bad_rows)
    try:
        res = check_params(log, model, params, str(args.params), cfg=cfg, terms=args.terms, mask=args.mask,
                           keep_series=bool(args.plots), dynamics=args.dynamics)
    except (LogError, ValueError) as exc:
        raise CliError(str(exc)) from None
    data = res.to_json()
    if args.plots:
        data["plots"] = plot(res, list(model.joint_names), args.plots)

    def text(d: dict[str, Any]) -> str:
        def ma(x: Any) -> str:
            return "—" if x is None else f"{x * 1e3:.1f}"

        rows = [(nm, ma(j.get("rmse_A")), ma(j.get("mae_A")), ma(j.get("max_A")), j.get("samples", 0),
                 j.get("reason") or j.get("model", "")) for nm, j in d["joints"].items()]
        lines = [f"{args.log} predicted with {args.params} ({d['mask']} samples, {d['terms']} model): "
                 f"RMSE {ma(d['rmse_A'])} mA overall",
                 table(["joint", "RMSE mA", "MAE mA", "max mA", "samples", "note"], rows)]
        lines += [f"warning: {w}" for w in d.get("warnings", [])]
        lines += [f"plot: {p}" for p in d.get("plots", [])]
        return "\n".join(lines)

    emit(args, data, text)
    return 0


# --------------------------------------------------------------------------------------------- parser


def register(sub: Any) -> None:
    from dragd.identify import PLAN_KINDS

    p = sub.add_parser("identify", help="identification: excitation plans, runs, fits, checks (docs/IDENTIFICATION.md)")
    isub = p.add_subparsers(dest="identify_command", metavar="WHAT")
    isub.required = True

    def plan_opts(q: argparse.ArgumentParser) -> None:
        q.add_argument("--joints", help="joint numbers for single-joint kinds, e.g. 2,3 (default: all)")
        q.add_argument("--scale", type=float, default=1.0, help="< 1 shortens the plan (fewer passes/speeds)")
        q.add_argument("--margin", type=float, default=0.15, help="distance kept from the soft limits [rad]")
        q.add_argument("--acceleration", type=float, default=1.5, help="joint acceleration limit [rad/s²]")
        q.add_argument("--seed", type=int, default=5, help="random seed of pose choices and the Fourier optimisation")
        q.add_argument("--robot", help="bundled robot name or URDF path (default: the configuration's robot)")
        add_config(q, params=False)

    pl = isub.add_parser("plan", help="write an excitation plan (.npz: t_s, q_rad, segments)")
    pl.add_argument("--kind", required=True, choices=PLAN_KINDS, help="lowspeed (seed 000), symmetric and friction "
                    "(seed 001), synchronous (seed 002), fourier (full dynamics), standard, all")
    pl.add_argument("--start", help="start pose Q1,...,QN [rad] (the robot's current pose)")
    pl.add_argument("--out", required=True, help="plan file (.npz)")
    plan_opts(pl)
    pl.add_argument("--json", action="store_true", help="print JSON")
    pl.set_defaults(func=cmd_plan)

    rn = isub.add_parser("run", help="drive a plan on the robot through the daemon (CSP), recording MCAP")
    rn.add_argument("--plan", required=True, help=f"plan file (.npz) or a kind ({', '.join(PLAN_KINDS)}) built from "
                                                 "the current pose")
    rn.add_argument("--out", required=True, help="MCAP file the daemon records the run to")
    add_socket(rn, timeout=30.0, json_flag=False)
    rn.add_argument("--chunk", type=float, default=600.0, help="longest single motion [s]; longer "
                                                               "plans are cut at rests")
    rn.add_argument("--no-progress", action="store_true", help="no progress bar")
    plan_opts(rn)
    rn.add_argument("--json", action="store_true", help="print JSON")
    rn.set_defaults(func=cmd_run)

    ft = isub.add_parser("fit", help="identify K_t and friction from a log → params file")
    ft.add_argument("--log", required=True, action="append",
                    help="MCAP (dragd telemetry, TRACK rows) or CSV t,q1..qN,i1..iN[,dq1..dqN] (or headerless: UR RTDE "
                         "t,q,qd,i,i_target,tau_target; docs/IDENTIFICATION.md); repeat to fit several logs together "
                         "(each filtered as its own stretch, rows stacked)")
    ft.add_argument("--robot", help="bundled robot name or URDF path (default: the configuration's robot)")
    ft.add_argument("--method", default="auto", choices=FIT_METHODS, help="lowspeed (seed 000), symmetric (seed 001), "
                    "synchronous (seed 002), full (rigid-body base parameters + friction), auto (default)")
    ft.add_argument("--out", required=True, help="params file to write (YAML; the model, daemon and sim load it)")
    ft.add_argument("--drop-bad-rows", action="store_true",
                    help="skip log rows with NaN/inf values, malformed or out-of-sequence rows (warned, lines named) "
                         "instead of stopping with an error")
    ft.add_argument("--cutoff", type=float, default=None, help="regression filter cutoff [Hz] (default 5)")
    ft.add_argument("--torque-constants", metavar="K1,..,KN|config",
                    help="joint-side torque constants [N·m/A] the user knows (or 'config': the configuration's); "
                         "full/auto method. Without: K_t is reported where the data determine it")
    add_config(ft, params=False)
    ft.add_argument("--load-friction", action="store_true",
                    help="full method: also fit load-dependent Coulomb friction sign(q̇)·k_L·|G(q)| per joint (written "
                         "as effects.load_friction_per_Nm; kept where it lowers the residual by 2 %%)")
    ft.add_argument("--json", action="store_true", help="print JSON")
    ft.set_defaults(func=cmd_fit)

    ck = isub.add_parser("check", help="predict another log's current with a params file: RMSE, MAE, max per joint")
    ck.add_argument("--params", required=True, help="params file (from 'dragd identify fit')")
    ck.add_argument("--log", required=True, help="MCAP or CSV log to predict")
    ck.add_argument("--robot", help="bundled robot name or URDF path (default: the configuration's robot)")
    ck.add_argument("--mask", default="steady", choices=("steady", "moving", "all"),
                    help="samples evaluated: steady motion (default, seed 001 Table VIII), any sliding, all")
    ck.add_argument("--terms", default="rigid", choices=("rigid", "gravity"),
                    help="rigid-body torque from the URDF (default) or gravity only (what drag compensates)")
    ck.add_argument("--dynamics", default="base", choices=("base", "inertials"),
                    help="rigid-body model: the fit's identified base parameters where the params file has them "
                         "(default), or the link inertials + K_t the daemon compensates with")
    ck.add_argument("--drop-bad-rows", action="store_true",
                    help="skip log rows with NaN/inf values, malformed or out-of-sequence rows (warned, lines named) "
                         "instead of stopping with an error")
    ck.add_argument("--plots", help="directory for PNG plots of measured vs predicted current per joint")
    add_config(ck, params=False)
    ck.add_argument("--json", action="store_true", help="print JSON")
    ck.set_defaults(func=cmd_check)

