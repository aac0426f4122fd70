"""``dragd model gravity|current`` (the robot model and the compensation law) and ``dragd config check|init``."""

from __future__ import annotations

import argparse
from typing import Any

from dragd.cli.common import CliError, add_config, emit, floats, table


def _robot_model(args: argparse.Namespace) -> Any:
    """``--robot`` (URDF) or the configuration's robot, with a params file's identified arm (``inertials``, payload):
    ``--params``, else the configuration's ``params``."""
    from dragd.config import load_config, load_params
    from dragd.model import RobotModel

    params = getattr(args, "params", None)
    if getattr(args, "robot", None):
        model = RobotModel.from_urdf(args.robot)
        if params:
            pf = load_params(params)
            try:
                if pf.inertials:
                    model.apply_inertials(pf.inertials, str(params))
            except ValueError as exc:
                raise CliError(str(exc)) from None
            if pf.payload is not None:
                model.add_payload(pf.payload.mass_kg, pf.payload.com_m)
        return model
    cfg = load_config(args.config, params)
    try:
        return RobotModel.from_config(cfg)
    except ValueError as exc:
        raise CliError(str(exc)) from None


def cmd_model_gravity(args: argparse.Namespace) -> int:
    import numpy as np

    model = _robot_model(args)
    q = np.array(floats(args.q, "--q"))
    try:
        q = model.check_q(q, "--q")
    except ValueError as exc:
        raise CliError(str(exc)) from None
    g = model.gravity(q)
    data = {"joints": list(model.joint_names), "gravity_Nm": [float(x) for x in g]}
    emit(args, data, lambda d: table(["joint", "gravity_Nm"], list(zip(d["joints"], d["gravity_Nm"], strict=True))))
    return 0


def cmd_model_current(args: argparse.Namespace) -> int:
    import numpy as np

    from dragd.config import load_config
    from dragd.control.law import compensate
    from dragd.control.params import LawParams
    from dragd.model import RobotModel

    cfg = load_config(args.config, args.params)
    try:
        model = RobotModel.from_config(cfg)  # with the params' identified inertials and payload (docs/MODEL.md)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    if model.nq != len(cfg.joints):
        raise CliError(f"{cfg.source}: joints: the robot has {model.nq} joints, the configuration {len(cfg.joints)}")
    try:
        q = model.check_q(np.array(floats(args.q, "--q")), "--q")
        dq = model.check_q(np.array(floats(args.dq, "--dq")), "--dq")
    except ValueError as exc:
        raise CliError(str(exc)) from None
    out = compensate(model.gravity(q), dq, float(args.t), LawParams.from_config(cfg), q_rad=q)
    data = {
        "joints": list(model.joint_names),
        "current_A": out.current_A.tolist(),
        "gravity_A": out.gravity_A.tolist(),
        "friction_A": out.friction_A.tolist(),
        "startup_A": out.startup_A.tolist(),
        "back_emf_A": out.back_emf_A.tolist(),
        "damping_A": out.damping_A.tolist(),
        "effects_A": (np.zeros_like(out.current_A) if out.effects_A is None else out.effects_A).tolist(),
        "clamped": out.clamped.tolist(),
    }
    emit(args, data, lambda d: table(
        ["joint", "current_A", "gravity_A", "friction_A", "startup_A", "back_emf_A", "damping_A", "clamped"],
        list(zip(d["joints"], d["current_A"], d["gravity_A"], d["friction_A"], d["startup_A"], d["back_emf_A"],
                 d["damping_A"], d["clamped"], strict=True))))
    return 0


def cmd_config_check(args: argparse.Namespace) -> int:
    """Validate the configuration, its robot and its drives (every drive's EDS, offline): every problem at once."""
    from dragd.config import check_joint_names, load_config
    from dragd.hardware.plan import plan_drives
    from dragd.hardware.profile import ProfileError, grouped
    from dragd.model import RobotModel
    from dragd.robots.gravity import check_gravity_currents  # any gravity current above current_limit_A: ConfigError

    cfg = load_config(args.config, args.params)
    model = RobotModel.from_urdf(cfg.robot.urdf, cfg.base_dir, cfg.robot.gravity_m_s2)
    check_joint_names(cfg, (model.joint_names, model.urdf_path or cfg.robot.urdf))
    try:
        plan = plan_drives(cfg)
    except ProfileError as exc:
        raise CliError(str(exc)) from None
    findings = [{"level": f.level, "text": f.body if where else f.text, "at": where, "refusal": f.refusal}
                for f, where in grouped(plan.findings)]
    counts = {lvl: sum(1 for f in findings if f["level"] == lvl) for lvl in ("error", "warning", "note")}
    drives = [{"joint": p.joint.name, "node_id": p.node_id, "bus": p.joint.bus, "drive": p.drive_name,
               "eds": str(p.eds_path), "fd": p.fd,
               "current": None if p.current is None else {"object": f"{p.current.index:04X}h:{p.current.sub}",
                                                          "unit": p.current_unit},
               "torque_command": None if p.command is None else f"{p.command.index:04X}h", "csp": p.csp}
              for p in plan.profiles.profiles]
    buses = [{"name": b.name, "fd": b.fd, "layout": plan.layouts[b.name].kind,
              "position_targets": plan.layouts[b.name].position_targets,
              "load_pct": round(plan.budget[b.name]["load_pct"], 2),
              "load_min_pct": round(plan.budget[b.name]["load_min_pct"], 2), "limit_pct": b.load_limit_pct}
             for b in cfg.buses]
    ok = counts["error"] == 0
    gravity = [g.to_json() for g in check_gravity_currents(cfg)] if ok else []
    data = {"config": cfg.source, "robot": str(model.urdf_path), "joints": cfg.joint_names,
            "buses": [b.name for b in cfg.buses], "bus_load": buses, "drives": drives, "findings": findings,
            "errors": counts["error"], "warnings": counts["warning"], "notes": counts["note"],
            "refused": plan.refusals, "gravity": gravity, "ok": ok}

    def text(d: dict[str, Any]) -> str:
        lines = []
        for f in d["findings"]:
            lines.append(f"{f['level']}: {f['text']}")
            if f["at"]:
                lines.append(f"    at {f['at']}")
        for b in d["bus_load"]:
            lines.append(f"bus '{b['name']}': {'CAN FD' if b['fd'] else 'classic CAN'}, layout {b['layout']}"
                         f"{'' if b['position_targets'] else ' (no position targets)'}, worst-case load "
                         f"{b['load_pct']:.1f} % (no stuff bits {b['load_min_pct']:.1f} %), "
                         f"limit {b['limit_pct']:.0f} %")
        for r in d["refused"]:
            lines.append(f"refused: {r}")
        verdict = "ok" if d["ok"] else "NOT usable"
        lines.append(f"{d['config']}: {verdict}: {d['errors']} error(s), {d['warnings']} warning(s), {d['notes']} "
                     f"note(s) ({len(d['joints'])} joints, robot {d['robot']})")
        return "\n".join(lines)

    emit(args, data, text)
    return 0 if ok else 1


def register(sub: Any) -> None:
    from dragd.cli.robot_config import register_config

    model = sub.add_parser("model", help="evaluate the robot model and the compensation law")
    msub = model.add_subparsers(dest="model_command", metavar="WHAT")
    msub.required = True
    g = msub.add_parser("gravity", help="G(q) in N·m")
    g.add_argument("--q", required=True, help="joint positions Q1,...,QN [rad]")
    g.add_argument("--robot", help="bundled robot name or URDF path (default: the config's robot)")
    add_config(g)
    g.add_argument("--json", action="store_true", help="print JSON")
    g.set_defaults(func=cmd_model_gravity)
    c = msub.add_parser("current", help="the law's current command and its components in A")
    c.add_argument("--q", required=True, help="joint positions [rad], comma-separated")
    c.add_argument("--dq", required=True, help="joint velocities [rad/s], comma-separated")
    c.add_argument("--t", default=0.0, type=float, help="time [s] for the start-up sine (default 0)")
    add_config(c)
    c.add_argument("--json", action="store_true", help="print JSON")
    c.set_defaults(func=cmd_model_current)

    cfgp = sub.add_parser("config", help="configuration tools")
    csub = cfgp.add_subparsers(dest="config_command", metavar="WHAT")
    csub.required = True
    chk = csub.add_parser("check", help="validate a configuration (and params) file, its robot and its drives (each "
                                        "drive's EDS, offline): every problem at once, with the key to change")
    add_config(chk)
    chk.add_argument("--json", action="store_true", help="print JSON")
    chk.set_defaults(func=cmd_config_check)
    register_config(csub)  # dragd config init
