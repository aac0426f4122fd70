"""CLI of the model-gap workflow: ``dragd gap --measured FILE [--robot R] [--model params.yaml] [--out params.yaml]
[--report DIR] [--json]`` (docs/GAP.md)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from dragd.cli.common import CliError, Stages, add_config, emit, table


def cmd_gap(args: argparse.Namespace) -> int:
    from dragd.config import check_joint_names, load_config, load_params, save_params
    from dragd.gap.effects import NAMES
    from dragd.gap.run import analyse
    from dragd.identify.data import LogError, load_log
    from dragd.model import RobotModel

    cfg = load_config(args.config)
    try:
        model = RobotModel.from_urdf(args.robot) if args.robot else RobotModel.from_urdf(cfg.robot.urdf, cfg.base_dir,
                                                                                        cfg.robot.gravity_m_s2)
    except (FileNotFoundError, ValueError) as exc:
        raise CliError(f"--robot: {exc}") from None
    check_joint_names(cfg, (model.joint_names, model.urdf_path or cfg.robot.urdf))  # (else: give --config for it)
    params = load_params(args.model) if args.model else None
    if params is not None and params.inertials:  # the identified arm is the baseline's model (docs/MODEL.md)
        try:
            model.apply_inertials(params.inertials, str(args.model))
        except ValueError as exc:
            raise CliError(str(exc)) from None
    effects = None
    if args.effects:
        effects = tuple(e.strip() for e in args.effects.split(",") if e.strip())
        bad = [e for e in effects if e not in NAMES]
        if bad:
            raise CliError(f"--effects: unknown {', '.join(bad)}; expected some of {', '.join(NAMES)}")
    with Stages(args, "gap") as st:
        try:
            st.stage(f"reading {args.measured}")
            log = load_log(args.measured, joints=list(model.joint_names), robot=str(model.urdf_path or "robot"),
                           drop_bad_rows=args.drop_bad_rows)
            st.stage("analysing (baseline, effects, fit, validation)")
            res = analyse(log, model, cfg, params, effects)
        except LogError as exc:
            raise CliError(str(exc)) from None
        data = res.to_json()
        extra: dict[str, Any] = {}
        if args.out:
            st.stage(f"writing {args.out}")
            save_params(res.params, Path(args.out))
            extra["out"] = str(args.out)
        if args.report:
            from dragd.gap.report import write

            st.stage(f"writing the report {args.report}")
            extra.update(write(res, args.report, str(args.measured), str(args.model) if args.model else None,
                               str(args.out) if args.out else None))

    def ma(x: Any) -> str:
        return "—" if x is None else f"{x * 1e3:.1f}"

    def text(d: dict[str, Any]) -> str:
        det = res.details()
        lines = [f"{args.measured}: baseline ({det['baseline_kind']}) RMSE {ma(d['baseline']['rmse_A'])} mA → "
                 f"{ma(d['final']['rmse_A'])} mA (noise {ma(det['noise_A'])} mA)"]
        if d["effects"]:
            lines.append(table(["effect", "joints", "RMSE after mA"],
                                [(e["effect"], ",".join(e["joints"]), ma(e["rmse_A"])) for e in d["effects"]]))
            for e in d["effects"]:
                for a in e["ambiguous_with"]:
                    lines.append(f"ambiguous: {e['effect']} and {a['effect']} explain {','.join(a['joints'])} equally "
                                 f"well (held-out difference within the noise); {e['effect']} was added — the data "
                                 f"do not tell them apart")
        else:
            lines.append("nothing missing: no effect improves the held-out error")
        rows = [(nm, ma(v["rmse_A"]), ma(det["final_joints"][nm]["rmse_A"]), ma(v["noise_A"]))
                for nm, v in d["baseline"]["joints"].items()]
        lines.append(table(["joint", "before mA", "after mA", "noise mA"], rows))
        if extra.get("out"):
            lines.append(f"extended model: {extra['out']}")
        if extra.get("report"):
            lines.append(f"report: {extra['report']}")
        lines += [f"warning: {w}" for w in det["warnings"]]
        return "\n".join(lines)

    emit(args, data, text)  # --json: exactly baseline, effects, final (details: the report's gap.json)
    if args.json:  # the warnings still reach the user: on stderr, the JSON on stdout stays exactly the result
        for w in res.details()["warnings"]:
            print(f"warning: {w}", file=sys.stderr)
    return 0


def register(sub: Any) -> None:
    from dragd.gap import EFFECT_NAMES as NAMES

    p = sub.add_parser("gap", help="model gap: where model and measurement disagree, the missing effect named, added, "
                                   "the gap shown shrinking (docs/GAP.md)")
    p.add_argument("--measured", required=True, help="measured log: MCAP (dragd telemetry, TRACK rows) or CSV "
                                                     "t,q1..qN,i1..iN[,dq1..dqN]")
    p.add_argument("--robot", help="bundled robot name or URDF path (default: the configuration's robot)")
    p.add_argument("--drop-bad-rows", action="store_true",
                   help="skip log rows with NaN/inf values, malformed or out-of-sequence rows (warned, lines named) "
                        "instead of stopping with an error")
    p.add_argument("--model", help="params file of the model to check (default: seed 000's G/K_t + Coulomb levels "
                                   "fitted on the log)")
    p.add_argument("--out",
                   help="write the extended model (params YAML: the daemon, `dragd model` and the sim load it)")
    p.add_argument("--report", help="directory for the report (report.md, PNG residual plots before/after)")
    p.add_argument("--effects", help=f"candidates to consider (default all): {','.join(NAMES)}")
    add_config(p, params=False)
    p.add_argument("--json", action="store_true", help="print JSON: baseline, effects, final (+ details)")
    p.set_defaults(func=cmd_gap)
