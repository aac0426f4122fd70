"""CLI of contact detection: ``dragd contact detect|calibrate`` (see docs/CONTACT.md).

- ``calibrate``  the detector's per-joint bands from free-motion logs of the arm → a params file with ``contact``
- ``detect``     the detector (the cycle's code) over a log → contact events, the bands, how close free motion came
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

from dragd.cli.common import CliError, Stages, emit, floats, table


def _model(args: argparse.Namespace) -> tuple[Any, Any]:
    """The identified model: ``--robot`` + ``--params`` (+ ``--torque-constants``) → (ContactModel, params)."""
    from dragd.config import load_params
    from dragd.contact.model import ContactModel, ContactModelError

    params = load_params(args.params)
    kt = floats(args.torque_constants, "--torque-constants") if args.torque_constants else None
    try:
        return ContactModel.from_files(args.robot, params, str(args.params), kt), params
    except ContactModelError as exc:
        raise CliError(str(exc)) from None
    except (FileNotFoundError, ValueError) as exc:  # the URDF
        raise CliError(str(exc)) from None


def _logs(args: argparse.Namespace, model: Any, paths: list[str]) -> list[Any]:
    from dragd.identify.data import LogError, load_log, parse_layout

    try:
        layout = parse_layout(args.columns) if args.columns else None
        return [load_log(p, joints=model.names, robot=str(args.robot), drop_bad_rows=args.drop_bad_rows,
                         layout=layout) for p in paths]
    except LogError as exc:
        raise CliError(str(exc)) from None


def _settings(gain: float) -> Any:
    from dragd.control.contact import ContactSettings

    return ContactSettings(observer_gain_per_s=gain)


# --------------------------------------------------------------------------------------------- calibrate


def cmd_calibrate(args: argparse.Namespace) -> int:
    from dragd.config import save_params
    from dragd.contact.calibrate import CalibrationError, calibrate, to_params
    from dragd.contact.detect import run_log
    from dragd.control.contact import ContactBands

    if not args.margin > 1.0:
        raise CliError(f"--margin: expected a factor > 1 (the band over the largest free-motion deviation), got "
                       f"{args.margin:g}")
    if not args.observer_gain > 0:
        raise CliError(f"--observer-gain: expected a positive gain [1/s], got {args.observer_gain:g}")
    with Stages(args, "contact calibrate") as st:
        st.stage("loading the model")
        model, params = _model(args)
        st.stage(f"reading {', '.join(args.log)}")
        logs = _logs(args, model, args.log)
        settings = _settings(args.observer_gain)
        unbounded = ContactBands.uniform(len(model.names), math.inf, 0.0, 0.0, 0.0, 0.1, math.inf, math.inf, 0.0)
        st.stage("running the observer over the logs")
        runs = [(log.path, run_log(model, unbounded, settings, log)) for log in logs]
        st.stage("fitting the bands")
        try:
            cal = calibrate(model, runs, settings, margin=args.margin)
        except CalibrationError as exc:
            raise CliError(str(exc)) from None
        out = Path(args.out)
        st.stage(f"writing {out}")
        block = to_params(cal, model.names, settings)
        save_params(params.model_copy(update={"contact": block}), out)
    data = {"out": str(out), "observer_gain_per_s": settings.observer_gain_per_s, "margin": args.margin,
            "kt_source": model.kt_source, "joints": block.model_dump(mode="json")["joints"],
            "report": cal.report, "warnings": [w for _, r in runs for w in r.warnings]}

    def text(d: dict[str, Any]) -> str:
        rows = []
        for nm, b in d["joints"].items():
            r = d["report"]["joints"][nm]
            rows.append((nm, b["base_A"], b["slow_A"], b["speed_A_s_per_rad"], b["accel_A_s2_per_rad"],
                         b["settling_A"], b["held_A"], b["held_moving_A"], r["moving_band_A"]["median"]))
        lines = [f"contact bands from {len(args.log)} free-motion log(s) → {d['out']} (margin {d['margin']:g}: every "
                 f"calibration sample at ≤ {1 / d['margin']:.2f} of its band; observer {d['observer_gain_per_s']:g}/s)",
                 table(["joint", "base A", "slow A", "speed A·s", "accel A·s²", "settling A", "held A", "held+arm A",
                        "moving median A"], rows)]
        lines += [f"warning: {w}" for w in d["warnings"]]
        return "\n".join(lines)

    emit(args, data, text)
    return 0


# --------------------------------------------------------------------------------------------- detect


def detect(model: Any, params: Any, params_name: str, log: Any, sensitivity: float = 1.0,
           compiled: bool = True) -> tuple[Any, dict[str, Any]]:
    """``contact detect``'s pipeline on a loaded log: (the run, its JSON)."""
    import numpy as np

    from dragd.contact.calibrate import from_params
    from dragd.contact.detect import run_log
    from dragd.control.contact import ContactSettings

    bands, gain = from_params(params, model.names, params_name)
    settings = ContactSettings(observer_gain_per_s=gain, scale=1.0 / sensitivity)
    run = run_log(model, bands, settings, log, compiled=compiled)
    ratio = run.ratio()
    moving = run.state == 0
    with np.errstate(invalid="ignore"):
        free = {nm: (None if not np.isfinite(ratio[:, j]).any() else round(float(np.nanmax(ratio[:, j])), 3))
                for j, nm in enumerate(model.names)}
    data = {"events": [e.to_json(model.names) for e in run.events],
            "thresholds_A": [round(float(x) / sensitivity, 4) for x in bands.base_A],
            "thresholds": "the moving band at steady speed (base_A / sensitivity); the band of each sample depends on "
                          "the joint's state, speed and acceleration (docs/CONTACT.md)",
            "bands": {f: [round(float(v), 4) for v in getattr(bands, f)] for f in bands.__dataclass_fields__},
            "joints": model.names, "sensitivity": sensitivity, "observer_gain_per_s": gain,
            "kt_source": model.kt_source, "samples": int(run.t.shape[0]),
            "duration_s": round(float(run.t[-1] - run.t[0]), 3), "max_ratio": free,
            "moving_share": round(float(moving.mean()), 3), "warnings": list(log.warnings) + run.warnings}
    return run, data


def cmd_detect(args: argparse.Namespace) -> int:
    from dragd.contact.calibrate import CalibrationError

    if not 0 < args.sensitivity <= 4:
        raise CliError("--sensitivity: expected a factor in (0, 4] (1: the calibrated bands), "
                       f"got {args.sensitivity:g}")
    model, params = _model(args)
    log = _logs(args, model, [args.log])[0]
    try:
        run, data = detect(model, params, str(args.params), log, args.sensitivity)
    except CalibrationError as exc:
        raise CliError(str(exc)) from None
    if args.plots:
        data["plots"] = plot(run, model.names, args.plots, args.log)

    def text(d: dict[str, Any]) -> str:
        rows = [(f"{e['t_start_s'] - run.t[0]:.2f}", "—" if e["t_end_s"] is None else f"{e['t_end_s'] - run.t[0]:.2f}",
                 ", ".join(e["joints"]), ", ".join(f"{x:.1f}" for x in e["peak_Nm"])) for e in d["events"]]
        lines = [f"{args.log}: {len(d['events'])} contact event(s) in {d['duration_s']:.1f} s "
                 f"(sensitivity {d['sensitivity']:g})"]
        if rows:
            lines.append(table(["from s", "to s", "joints", "peak N·m"], rows))
        lines.append("largest |deviation|/band: " + ", ".join(f"{nm} {'—' if v is None else f'{v:.2f}'}"
                                                              for nm, v in d["max_ratio"].items()))
        lines += [f"warning: {w}" for w in d["warnings"]]
        lines += [f"plot: {p}" for p in d.get("plots", [])]
        return "\n".join(lines)

    emit(args, data, text)
    return 0


def plot(run: Any, names: list[str], out_dir: str | Path, title: str) -> list[str]:
    """PNG per joint: the deviation judged, its band (±), the residual, and the events."""
    import matplotlib
    import numpy as np

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t = run.t - run.t[0]
    files = []
    for j, nm in enumerate(names):
        fig, ax = plt.subplots(figsize=(12, 4))
        ax.plot(t, run.e_A[:, j], color="0.7", lw=0.5, label="residual r/K_t")
        ax.plot(t, run.d_A[:, j], color="C0", lw=0.7, label="deviation judged")
        band = np.where(np.isfinite(run.band_A[:, j]), run.band_A[:, j], np.nan)
        ax.plot(t, band, color="C3", lw=0.6, label="band")
        ax.plot(t, -band, color="C3", lw=0.6)
        for e in run.events:
            ax.axvspan(e.t_start_s - run.t[0], (e.t_end_s if e.t_end_s is not None else run.t[-1]) - run.t[0],
                       color="C1", alpha=0.2)
        ax.set_title(f"{title}: {nm}")
        ax.set_xlabel("t [s]")
        ax.set_ylabel("[A]")
        ax.legend(loc="upper right", fontsize=8)
        fig.tight_layout()
        f = out / f"{nm}.png"
        fig.savefig(f, dpi=90)
        plt.close(fig)
        files.append(str(f))
    return files


# --------------------------------------------------------------------------------------------- parser


def register(sub: Any) -> None:
    p = sub.add_parser("contact", help="contact detection offline: calibrate its bands, run it over a log "
                                       "(docs/CONTACT.md)")
    csub = p.add_subparsers(dest="contact_command", metavar="COMMAND")
    csub.required = True

    def common(q: argparse.ArgumentParser) -> None:
        q.add_argument("--robot", required=True, help="bundled robot name or URDF path")
        q.add_argument("--params", required=True, type=Path,
                       help="identified params file (dragd identify fit --method full): inertials, rotor inertias, "
                            "friction, K_t")
        q.add_argument("--torque-constants", metavar="K1,..,KN",
                       help="joint-side torque constants [N·m/A] (default: the params file's)")
        q.add_argument("--columns", metavar="BLOCKS",
                       help="a headerless CSV's blocks of one column per joint after t, e.g. q,dq,i,- ('-': not read; "
                            "default: from the column count)")
        q.add_argument("--drop-bad-rows", action="store_true",
                       help="skip log rows with NaN/inf values, malformed or out-of-sequence rows "
                            "(warned, lines named)")
        q.add_argument("--json", action="store_true", help="print JSON")

    c = csub.add_parser("calibrate", help="the detector's per-joint bands from free-motion logs → params file")
    common(c)
    c.add_argument("--log", required=True, action="append",
                   help="a free-motion log of this arm (repeat: several logs); not the fit's own logs, no contact")
    c.add_argument("--out", required=True, help="params file to write: --params with the contact bands")
    c.add_argument("--margin", type=float, default=1.5,
                   help="band / the largest free-motion deviation (default 1.5: calibration samples at ≤ 0.67 of it)")
    c.add_argument("--observer-gain", type=float, default=25.0, help="momentum observer gain K_o [1/s] (default 25)")
    c.set_defaults(func=cmd_calibrate)

    d = csub.add_parser("detect", help="run the contact detector over a log: events, bands")
    common(d)
    d.add_argument("--log", required=True, help="MCAP or CSV log (t, q, i; q̇ when the log has it)")
    d.add_argument("--sensitivity", type=float, default=1.0,
                   help="the calibrated bands / sensitivity (default 1; the configuration's contact.<mode>.sensitivity "
                        "in the daemon)")
    d.add_argument("--plots", help="directory for a PNG per joint: deviation, band, events")
    d.set_defaults(func=cmd_detect)
