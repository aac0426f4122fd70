"""``contact_real``: dragd's contact detector on a real UR10e that was struck and pushed, against the textbook
reference.

Data: the public UR10e dataset github:shamilmamedov/dynamic_calibration (no licence: never in this repository; the
benchmark takes its path, ``dragd bench contact_real --data DIR --json``, DIR = a *git checkout* of that repository,
or ``$DRAGD_UR10E_DATA``). Contact logs: ``dataset_ur10e/collision/ur-20_01_22-push_pose_1/2.csv`` (the arm holds a
pose, a person pushes it) and ``data_ur10/collision_detection_data/collision_2link.csv`` read from the checkout's
commit ed20311 (``git show``: a periodic motion, link 2 struck). That folder's other logs are a held-out check and
are never read. ``data_ur10`` is the same arm as ``dataset_ur10e`` (the identification and validation logs of both
folders are byte-identical); collision_2link.csv has 25 columns, t, q, q̇, i and six columns that are not the
target current (uncorrelated with i, no gravity level) — read with ``--columns q,dq,i,-``.

1. **Identification**: ``dragd identify fit --method full --torque-constants <drvGains> --load-friction`` on the two
   12-harmonic runs (ident_real's training logs).
2. **Calibration**: ``dragd contact calibrate`` (margin 1.5) on free-motion logs of the same arm that are neither
   the fit's nor contact logs: the 20 s 5/7/8/10-harmonic runs, the 40 s 12-harmonic run, the 50 s 14/15-harmonic
   runs, the 19-12-23 free run, the 20-01-31 unloaded run, the six jointwise runs and the ten held poses p1..p10.
3. **Detection**: ``dragd contact detect`` on the three contact logs, scored against labels made without any model
   (dragd/contact/labels.py): hits, misses, false alarms, delays (dragd/contact/score.py).
4. **Held-out free motion**: each free-motion log in turn left out of the calibration and detected with the bands of
   the others: the largest |deviation|/band and the events (false alarms) on a run the bands never saw.
5. **Reference** (in the same run, same files): OLS rigid-body + Coulomb/viscous/offset (ident_real's), a
   momentum observer with gain 25/s, thresholds 1.2 × the largest free-motion residual of the same calibration logs
   (same samples: the observer's first 0.2 s and each log's final stop left out for both).

Value: dragd's median detection delay on impacts (contacts of ≥ 1 A on the struck moving arm). Targets: every
contact of ≥ 1 A found, no false alarm on the contact logs, free motion of the struck run below 0.8 of the bands,
median impact delay ≤ 65 ms.
"""

from __future__ import annotations

import math
import os
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from dragd.lab.bench import BenchError, benchmark

COLLISION_COMMIT = "ed20311ca9a853731d2d2a90629d90ba01162125"
COLLISION_PATH = "data_ur10/collision_detection_data/collision_2link.csv"
COLLISION_COLUMNS = "q,dq,i,-"
PUSH = ("ur-20_01_22-push_pose_1", "ur-20_01_22-push_pose_2")
CALIBRATION = (
    *(f"identification_data/{n}" for n in (
        "ur-20_02_06-20sec_5harm", "ur-20_02_10-20sec_7harm", "ur-20_02_05-20sec_8harm", "ur-20_02_06-20sec_10harm",
        "ur-20_02_12-40sec_12harm", "ur-20_02_19_14harm50sec", "ur-20_02_19_15harm50sec", "ur-19_12_23_free",
        "ur-20_01_31-unload")),
    *(f"jointwise_motion/ur-20_01_22-joint_{k}" for k in range(1, 7)),
    *(f"validation_data/ur-20_01_17-p{k}" for k in range(1, 11)))
MARGIN = 1.5
TARGET_DELAY_MS = 65.0
TARGET_FREE_RATIO = 0.8


def _collision_log(root: Path, tmp: Path) -> Path:
    """collision_2link.csv from the checkout's commit ed20311 (only that file of its folder)."""
    out = tmp / "collision_2link.csv"
    try:
        blob = subprocess.run(["git", "-C", str(root), "show", f"{COLLISION_COMMIT}:{COLLISION_PATH}"],
                              capture_output=True, check=True, timeout=60).stdout
    except (OSError, subprocess.CalledProcessError, subprocess.TimeoutExpired) as exc:
        why = getattr(exc, "stderr", b"") or b""
        raise BenchError(f"contact_real: --data {root}: cannot read {COLLISION_PATH} at commit {COLLISION_COMMIT[:7]} "
                         f"(git show: {why.decode(errors='replace').strip() or exc}); expected a git checkout of "
                         "github:shamilmamedov/dynamic_calibration with its history") from None
    out.write_bytes(blob)
    return out


def _load(path: Path, names: list[str], urdf: Path, layout: str | None = None) -> Any:
    from dragd.identify.data import LogError, load_log, parse_layout

    try:
        return load_log(path, joints=names, robot=str(urdf), drop_bad_rows=True,
                        layout=parse_layout(layout) if layout else None)
    except LogError as exc:
        raise BenchError(f"contact_real: {exc}") from None


def _events(run: Any, names: list[str]) -> list[tuple[float, float, list[str]]]:
    t0 = float(run.t[0])
    return [(e.t_start_s - t0, (e.t_end_s if e.t_end_s is not None else float(run.t[-1])) - t0,
             [names[j] for j in e.joints]) for e in run.events]


@benchmark("contact_real", "ms")
def contact_real(opts: dict) -> tuple[float, dict[str, Any]] | dict[str, Any]:
    """Median contact-detection delay on a real UR10e's impacts; hits, false alarms vs the textbook one (--data DIR).

    Every contact, false alarm and band in ``detail``, the reference's beside them (see the module docstring)."""
    from dragd.lab.bench.ident_real import EXPECTED, TRAIN, Reference, filter_data, find_dataset

    data = opts.get("data") or os.environ.get("DRAGD_UR10E_DATA")
    if not data and "contact_real" not in opts.get("selected", ["contact_real"]):
        return {"skipped": "the UR10e dataset is not here (--data DIR or $DRAGD_UR10E_DATA); DIR = " + EXPECTED}
    ds = find_dataset(data)
    root = ds.root / "dataset_ur10e"
    missing = [f"dataset_ur10e/{n}.csv" for n in (*CALIBRATION, *(f"collision/{p}" for p in PUSH))
               if not (root / f"{n}.csv").is_file()]
    if missing:
        raise BenchError(f"contact_real: --data {ds.root}: missing {', '.join(missing[:3])}"
                         f"{f' (+{len(missing) - 3} more)' if len(missing) > 3 else ''}; expected {EXPECTED}")
    t_all = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="dragd-contact-real-") as tmpd:
        tmp = Path(tmpd)
        return _run(ds, root, tmp, TRAIN, Reference, filter_data, t_all)


def _run(ds: Any, root: Path, tmp: Path, train_spec: Any, Reference: Any, filter_data: Any,
         t_all: float) -> tuple[float, dict[str, Any]]:
    from dragd.cli.contact import detect
    from dragd.config import load_params, save_params
    from dragd.contact.calibrate import CalibrationError, calibrate, to_params, usable
    from dragd.contact.detect import log_terms, run_log
    from dragd.contact.labels import HELD_WINDOWS, held_labels, periodic_labels
    from dragd.contact.model import ContactModel
    from dragd.contact.reference import TextbookDetector
    from dragd.contact.score import combine, max_ratio_outside, score
    from dragd.control.contact import ContactBands, ContactSettings
    from dragd.identify.data import stack_logs
    from dragd.identify.fit import fit_params
    from dragd.identify.methods import Options
    from dragd.model import RobotModel

    names = list(RobotModel.from_urdf(ds.urdf).joint_names)
    timing: dict[str, float] = {}
    t0 = time.perf_counter()
    train = {p: _load(p, names, ds.urdf) for p in ds.train}
    cal_logs = {n: _load(root / f"{n}.csv", names, ds.urdf) for n in CALIBRATION}
    coll_path = _collision_log(ds.root, tmp)
    contact_logs = {"collision_2link": _load(coll_path, names, ds.urdf, COLLISION_COLUMNS),
                    **{p: _load(root / "collision" / f"{p}.csv", names, ds.urdf) for p in PUSH}}
    timing["load_s"] = time.perf_counter() - t0

    # 1. identification: dragd identify fit --method full --torque-constants drvGains (through YAML as the CLI does)
    t0 = time.perf_counter()
    o = Options()
    o.torque_constants = [float(g) for g in ds.gains]
    o.load_friction = True  # --load-friction
    _, params, _ = fit_params(stack_logs(list(train.values())), RobotModel.from_urdf(ds.urdf), "full", o)
    pfile = tmp / "fitted.yaml"
    save_params(params, pfile)
    params = load_params(pfile)
    model = ContactModel.from_files(ds.urdf, params, str(pfile))
    timing["fit_s"] = time.perf_counter() - t0

    # 2. calibration: dragd contact calibrate --margin 1.5 on the free-motion logs
    t0 = time.perf_counter()
    settings = ContactSettings()
    unbounded = ContactBands.uniform(len(names), math.inf, 0.0, 0.0, 0.0, 0.1, math.inf, math.inf, 0.0)
    terms = {n: log_terms(model, lg) for n, lg in cal_logs.items()}
    runs = [(n, run_log(model, unbounded, settings, cal_logs[n], terms=terms[n])) for n in CALIBRATION]
    try:
        cal = calibrate(model, runs, settings, margin=MARGIN)
    except CalibrationError as exc:
        raise BenchError(f"contact_real: {exc}") from None
    p2 = tmp / "contact.yaml"
    save_params(params.model_copy(update={"contact": to_params(cal, names, settings)}), p2)
    params2 = load_params(p2)
    timing["calibrate_s"] = time.perf_counter() - t0

    # 3. detection on the contact logs, scored against the labels
    t0 = time.perf_counter()
    per_log: dict[str, Any] = {}
    scores = []
    free_ratio = None
    for name, lg in contact_logs.items():
        if name == "collision_2link":
            labels = periodic_labels(lg.t, lg.q, lg.dq, lg.i)
        else:
            labels = held_labels(lg.t, lg.i, HELD_WINDOWS[name])
        run, out = detect(model, params2, str(p2), lg)
        sc = score(labels.contacts, _events(run, names))
        scores.append(sc)
        ratio = max_ratio_outside(run.t, run.ratio(), labels.contacts)
        per_log[name] = {"labels": {"method": labels.method, "contacts": len(labels.contacts)},
                         "score": sc, "events": out["events"], "max_ratio_outside_contacts": ratio,
                         "duration_s": out["duration_s"]}
        if name == "collision_2link":
            free_ratio = ratio
    timing["detect_s"] = time.perf_counter() - t0

    # 4. held-out free motion: each moving log left out of the calibration
    t0 = time.perf_counter()
    held_out: dict[str, Any] = {}
    for name in CALIBRATION:
        if name.startswith("validation_data"):
            continue  # the held poses alone hold no motion (they stay in every calibration)
        others = [(n, r) for n, r in runs if n != name]
        try:
            b = calibrate(model, others, settings, margin=MARGIN).bands
        except CalibrationError as exc:
            held_out[name] = {"skipped": str(exc)}
            continue
        held = run_log(model, b, settings, cal_logs[name], terms=terms[name])
        ok, cut = usable(held, settings)
        ho_ratio = np.where(ok[:, None], held.ratio(), np.nan)
        starts = [(e.t_start_s - held.t[0]) for e in held.events]
        fa = [round(a, 2) for a in starts if not (cut and cut[0] <= a <= cut[1])]
        held_out[name] = {"max_ratio": [round(float(x), 3) for x in np.nanmax(ho_ratio, axis=0)],
                          "false_alarms_s": fa, "left_out_final_stop_s": [round(x, 2) for x in cut]}
    timing["held_out_s"] = time.perf_counter() - t0

    # 5. the textbook reference, same files
    t0 = time.perf_counter()
    ref = Reference(ds.urdf, ds.gains)
    ref.fit([filter_data(p.stem, train[p], rows) for p, (_, rows) in zip(ds.train, train_spec, strict=True)])
    tb = TextbookDetector(ref)
    ref_res = []
    for n, r in runs:
        lg = cal_logs[n]
        pp, tau = tb.terms(lg.q, lg.dq, lg.i)
        ref_res.append((tb.residual(lg.t, pp, tau), usable(r, settings)[0]))
    tb.calibrate(ref_res)
    thresholds = tb.thresholds_A
    if thresholds is None:
        raise BenchError("contact_real: the textbook detector set no thresholds from the free-motion logs")
    set_by = {nm: {"log": runs[i][0], "t_s": round(float(cal_logs[runs[i][0]].t[k] - cal_logs[runs[i][0]].t[0]), 2),
                   "speed_rad_s": round(float(abs(cal_logs[runs[i][0]].dq[k, j])), 3)}
              for j, (nm, (i, k)) in enumerate(zip(names, tb.set_by, strict=True))}
    ref_scores = []
    ref_logs: dict[str, Any] = {}
    for name, lg in contact_logs.items():
        labels = (periodic_labels(lg.t, lg.q, lg.dq, lg.i) if name == "collision_2link"
                  else held_labels(lg.t, lg.i, HELD_WINDOWS[name]))
        pp, tau = tb.terms(lg.q, lg.dq, lg.i)
        rr = tb.detect(lg.t, tb.residual(lg.t, pp, tau))
        evs = [(e.t_start_s - lg.t[0], e.t_end_s - lg.t[0], [names[j] for j in e.joints]) for e in rr.events]
        sc = score(labels.contacts, evs)
        ref_scores.append(sc)
        with np.errstate(invalid="ignore", divide="ignore"):
            rat = np.abs(rr.r_A) / thresholds
        ref_logs[name] = {"score": sc, "max_ratio_outside_contacts": max_ratio_outside(lg.t, rat, labels.contacts)}
    timing["reference_s"] = time.perf_counter() - t0

    total, ref_total = combine(scores), combine(ref_scores)
    targets = {
        "every_contact_of_1A_found": total["required_found"] == total["required"],
        "no_false_alarm": total["false_alarms"] == 0,
        "free_motion_below_0.8_of_band": bool(free_ratio is not None and np.nanmax(free_ratio) < TARGET_FREE_RATIO),
        "median_impact_delay_ms_max_65": bool(total["median_impact_delay_ms"] is not None
                                              and total["median_impact_delay_ms"] <= TARGET_DELAY_MS)}
    detail = {
        "data": str(ds.root), "drive_gains_Nm_per_A": ds.gains.tolist(),
        "files": {"fit": [str(p.relative_to(ds.root)) for p in ds.train],
                  "calibration": [f"dataset_ur10e/{n}.csv" for n in CALIBRATION],
                  "contact": [f"git show {COLLISION_COMMIT[:7]}:{COLLISION_PATH} (--columns {COLLISION_COLUMNS})",
                              *(f"dataset_ur10e/collision/{p}.csv" for p in PUSH)]},
        "dragd": {"total": total, "logs": per_log, "bands": cal.report,
                  "free_motion_max_ratio_collision_2link": free_ratio, "held_out_free_motion": held_out,
                  "commands": ["dragd identify fit --robot URDF --log TRAIN1 --log TRAIN2 --method full "
                               "--torque-constants GAINS --load-friction --out fitted.yaml",
                               "dragd contact calibrate --robot URDF --params fitted.yaml --log FREE1 ... --log FREEn "
                               "--margin 1.5 --out contact.yaml",
                               "dragd contact detect --robot URDF --params contact.yaml --log LOG [--columns "
                               "q,dq,i,-] --json"]},
        "reference": {"total": ref_total, "logs": ref_logs,
                      "thresholds_A": [round(float(x), 4) for x in thresholds], "thresholds_set_by": set_by,
                      "model": "OLS base rigid-body + viscous/Coulomb/offset (ident_real's reference, scripts' rows)",
                      "observer_gain_per_s": tb.gain, "threshold": "1.2 × the largest free-motion |residual|"},
        "targets": {"every_contact_of_1A_found": True, "false_alarms": 0, "free_motion_ratio_max": TARGET_FREE_RATIO,
                    "median_impact_delay_ms_max": TARGET_DELAY_MS},
        "targets_met": bool(all(targets.values())), "targets_met_by_item": targets,
        "timing_s": {k: round(v, 1) for k, v in {**timing, "total_s": time.perf_counter() - t_all}.items()},
    }
    value = total["median_impact_delay_ms"]
    return (math.nan if value is None else float(value)), detail
