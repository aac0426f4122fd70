"""``dragd`` command line: one subcommand per job; ``--help`` everywhere; ``--json`` where a command reports."""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

EXIT_USAGE = 2
EXIT_FAIL = 1


class CliError(Exception):
    """A user-facing error: printed as ``dragd: <message>`` with exit status 2 (bad input) or 1."""

    def __init__(self, message: str, status: int = EXIT_USAGE) -> None:
        super().__init__(message)
        self.status = status


def _floats(text: str, what: str) -> list[float]:
    try:
        values = [float(x) for x in text.split(",") if x.strip() != ""]
    except ValueError:
        raise CliError(f"{what}: expected comma-separated numbers, got '{text}'") from None
    if any(v != v or v in (float("inf"), float("-inf")) for v in values):
        raise CliError(f"{what}: expected finite numbers, got '{text}'")
    return values


def _emit(args: argparse.Namespace, data: dict[str, Any], text: Callable[[dict[str, Any]], str]) -> None:
    if getattr(args, "json", False):
        print(json.dumps(data))
    else:
        print(text(data))


def _table(headers: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    cells = [list(map(str, headers))] + [[f"{c:.4f}" if isinstance(c, float) else str(c) for c in r] for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(headers))]
    lines = ["  ".join(c.rjust(w) for c, w in zip(r, widths)) for r in cells]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------- model


def _robot_model(args: argparse.Namespace):  # noqa: ANN202
    from dragd.config import load_config
    from dragd.model import RobotModel

    if getattr(args, "robot", None):
        return RobotModel.from_urdf(args.robot), None
    cfg = load_config(args.config)
    return RobotModel.from_urdf(cfg.robot.urdf, cfg.base_dir, cfg.robot.gravity_m_s2), cfg


def cmd_model_gravity(args: argparse.Namespace) -> int:
    import numpy as np

    model, _ = _robot_model(args)
    q = np.array(_floats(args.q, "--q"))
    try:
        q = model.check_q(q, "--q")
    except ValueError as exc:
        raise CliError(str(exc)) from None
    g = model.gravity(q)
    data = {"joints": list(model.joint_names), "gravity_Nm": [float(x) for x in g]}
    _emit(args, data, lambda d: _table(["joint", "gravity_Nm"], list(zip(d["joints"], d["gravity_Nm"]))))
    return 0


def cmd_model_current(args: argparse.Namespace) -> int:
    import numpy as np

    from dragd.config import load_config
    from dragd.control.law import LawParams, compensate
    from dragd.model import RobotModel

    cfg = load_config(args.config, args.params)
    model = RobotModel.from_config(cfg)  # with the params' payload (docs/GAP.md)
    if model.nq != len(cfg.joints):
        raise CliError(f"{cfg.source}: joints: the robot has {model.nq} joints, the configuration {len(cfg.joints)}")
    try:
        q = model.check_q(np.array(_floats(args.q, "--q")), "--q")
        dq = model.check_q(np.array(_floats(args.dq, "--dq")), "--dq")
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
        "effects_A": out.effects_A.tolist(),
        "clamped": out.clamped.tolist(),
    }
    _emit(args, data, lambda d: _table(
        ["joint", "current_A", "gravity_A", "friction_A", "startup_A", "back_emf_A", "damping_A", "clamped"],
        list(zip(d["joints"], d["current_A"], d["gravity_A"], d["friction_A"], d["startup_A"], d["back_emf_A"],
                 d["damping_A"], d["clamped"]))))
    return 0


def cmd_config_check(args: argparse.Namespace) -> int:
    from dragd.config import load_config
    from dragd.model import RobotModel

    cfg = load_config(args.config, args.params)
    model = RobotModel.from_urdf(cfg.robot.urdf, cfg.base_dir, cfg.robot.gravity_m_s2)
    if list(model.joint_names) != cfg.joint_names:
        raise CliError(f"{cfg.source}: joints: expected the robot's joints {', '.join(model.joint_names)}, "
                       f"got {', '.join(cfg.joint_names)}")
    data = {"config": cfg.source, "robot": str(model.urdf_path), "joints": cfg.joint_names,
            "buses": [b.name for b in cfg.buses], "ok": True}
    _emit(args, data, lambda d: f"{d['config']}: ok ({len(d['joints'])} joints, robot {d['robot']})")
    return 0


# --------------------------------------------------------------------------------------------- bench


def cmd_bench(args: argparse.Namespace) -> int:
    from dragd.lab import bench

    if args.list:
        for name in bench.names():
            b = bench.REGISTRY[name]
            print(f"{name:24s} [{b.unit}] {b.doc}")
        return 0
    if args.realtime_priority is not None and not 0 <= args.realtime_priority <= 99:
        raise CliError(f"--realtime-priority: expected 0..99, got {args.realtime_priority}")
    opts = {"config": args.config, "seconds": args.seconds, "realtime_priority": args.realtime_priority}
    try:
        result = bench.run(args.names, {k: v for k, v in opts.items() if v is not None})
    except KeyError as exc:
        raise CliError(str(exc.args[0])) from None
    except bench.BenchError as exc:
        raise CliError(str(exc), status=1) from None
    _emit(args, result, lambda d: _table(["benchmark", "value", "unit"], [(k, v["value"], v["unit"]) for k, v in d.items()]))
    return 0


# --------------------------------------------------------------------------------------------- sim


def cmd_sim(args: argparse.Namespace) -> int:
    """Run the simulated robot in its own process (``python -m sim run``); dragd never imports sim/."""
    argv = [sys.executable, "-m", "sim", "run", *args.sim_args]
    os.execv(sys.executable, argv)
    return 0  # pragma: no cover


# --------------------------------------------------------------------------------------------- parser


def _add_config(p: argparse.ArgumentParser, params: bool = True) -> None:
    p.add_argument("--config", type=Path, default=None, help="configuration YAML (default: $DRAGD_CONFIG, "
                   "/etc/dragd/dragd.yaml, else the repository's config/default.yaml)")
    if params:
        p.add_argument("--params", type=Path, default=None, help="identified-parameters file overriding the config's")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="dragd", description="Sensorless hand-guiding daemon for CiA 402 cobot arms.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    model = sub.add_parser("model", help="evaluate the robot model and the compensation law")
    msub = model.add_subparsers(dest="model_command", metavar="WHAT")
    msub.required = True
    g = msub.add_parser("gravity", help="G(q) in N·m")
    g.add_argument("--q", required=True, help="joint positions Q1,...,QN [rad]")
    g.add_argument("--robot", help="bundled robot name or URDF path (default: the config's robot)")
    _add_config(g, params=False)
    g.add_argument("--json", action="store_true", help="print JSON")
    g.set_defaults(func=cmd_model_gravity)
    c = msub.add_parser("current", help="the law's current command and its components in A")
    c.add_argument("--q", required=True, help="joint positions [rad], comma-separated")
    c.add_argument("--dq", required=True, help="joint velocities [rad/s], comma-separated")
    c.add_argument("--t", default=0.0, type=float, help="time [s] for the start-up sine (default 0)")
    _add_config(c)
    c.add_argument("--json", action="store_true", help="print JSON")
    c.set_defaults(func=cmd_model_current)

    cfgp = sub.add_parser("config", help="configuration tools")
    csub = cfgp.add_subparsers(dest="config_command", metavar="WHAT")
    csub.required = True
    chk = csub.add_parser("check", help="validate a configuration (and params) file and its robot")
    _add_config(chk)
    chk.add_argument("--json", action="store_true", help="print JSON")
    chk.set_defaults(func=cmd_config_check)

    b = sub.add_parser("bench", help="run benchmarks (see docs/PERFORMANCE.md)")
    b.add_argument("names", nargs="*", metavar="NAME", help="benchmarks to run (default: all); --list shows them")
    b.add_argument("--list", action="store_true", help="list benchmarks")
    b.add_argument("--seconds", type=float, default=None, help="duration of timed benchmarks")
    b.add_argument("--realtime-priority", type=int, default=None, metavar="N",
                   help="loop benchmarks: SCHED_FIFO priority of the daemon's cycle thread as deployed (default 70, "
                        "the sim's 10 below; applied when permitted), 0 for none")
    _add_config(b, params=False)
    b.add_argument("--json", action="store_true", help="print JSON")
    b.set_defaults(func=cmd_bench)

    s = sub.add_parser("sim", help="run the simulated robot (its own process); arguments go to 'python -m sim run'",
                       add_help=False)
    s.add_argument("sim_args", nargs=argparse.REMAINDER)
    s.set_defaults(func=cmd_sim)

    for register in _EXTRA_COMMANDS:
        register(sub)
    return parser


# Further subcommands (daemon, demo, log, ...) register here from their modules.
_EXTRA_COMMANDS: list[Callable[[Any], None]] = []


def _load_extra_commands() -> None:
    import importlib

    for mod in ("dragd.cli.daemon", "dragd.cli.identify", "dragd.cli.teach", "dragd.cli.gap", "dragd.cli.experiment"):
        try:
            m = importlib.import_module(mod)
        except ModuleNotFoundError as exc:
            if exc.name != mod:
                raise
            continue
        _EXTRA_COMMANDS.append(m.register)


def main(argv: Sequence[str] | None = None) -> int:
    from dragd.config import ConfigError

    _load_extra_commands()
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except CliError as exc:
        print(f"dragd: {exc}", file=sys.stderr)
        return exc.status
    except ConfigError as exc:
        print(f"dragd: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except FileNotFoundError as exc:
        print(f"dragd: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
