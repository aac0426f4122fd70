"""``dragd demo --scenario contact``: the contact detector in the daemon, proven on the simulated arm.

Two sessions of the simulated robot and the daemon (separate processes, as ``dragd demo``):

1. **Calibration** (the detector not yet calibrated): the arm moves by itself through free motion — each joint
   alone, out and back at two speeds with rests (the held-while-others-move band needs it), two multi-joint moves,
   then a Fourier excitation (the coupled dynamics of every joint moving) — recorded to MCAP; ``dragd contact calibrate`` on that recording with the daemon's
   own model (the configuration's K_t and friction as a params file) writes the bands.
2. **Detection** (the daemon restarted with those bands, reaction ``stop`` in every mode): held 2 s; the teach demo
   (three waypoints by hand in drag, replayed linearly and circularly); an identification run of another plan
   (a Fourier excitation); every contact alarm there is a false alarm. Then the contacts, each by the simulator's
   operator whose force is the truth: a 60 N impact on the forearm (link 3) against its motion during a replay and
   during an identification run, a push on the forearm of the held arm; and in drag, hands pushing at the grip
   point (the flange) whose force the daemon estimates from the same residual.

Figures: per contact the detection delay (the daemon's event start − the contact force's start, both in the arm's
time), the peak contact force, the time from the detection until the arm stopped (every joint below
``STOPPED_RAD_S`` from then on) and how far the struck point travelled from the detection; false alarms per free run; in drag the
hand-force error against the truth where the truth is above 10 N.
"""

from __future__ import annotations

import json
import math
import sys
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

from dragd.lab.rig import ProcessError, Rig

STRIKE_LINK = "link3"  # the forearm
STRIKE_POINT_M = (0.0, 0.0, 0.15)  # on it (the link's frame)
IMPACT_N = 60.0
IMPACT = {"profile": "half_sine", "duration_s": 0.1}  # a 60 N impact: 100 ms half-sine
STOPPED_RAD_S = 0.01  # the arm counts as stopped once every joint is slower than this ...
STAYS_S = 0.2  # ... and stays so (for at least this long, within STOP_WINDOW_S of the detection)
STOP_WINDOW_S = 0.5  # (the demo starts nothing else within it)
HAND_PUSHES_N = ([18.0, 0.0, 0.0], [0.0, -22.0, 0.0], [0.0, 12.0, 16.0], [-15.0, 10.0, -10.0])  # drag: at the grip
HAND_FORCE_MIN_N = 10.0
CALIBRATION_SEED = 3  # the calibration's Fourier excitation; the detection session's identification runs use others  # the hand-force error is judged where the true force is above this


class ContactDemoError(RuntimeError):
    """The contact demo could not run; the message names the step and carries the process output."""


def _say(progress: bool, text: str) -> None:
    if progress:
        print(f"demo contact: {text}", file=sys.stderr, flush=True)


# ----------------------------------------------------------------------------------------------- calibration


def model_params(cfg: Any) -> Any:
    """The daemon's own model of the arm as a params file (K_t and friction of the configuration): what the
    residual is computed with in the cycle when the configuration names no identified params."""
    from dragd.config import FrictionParams, JointParams, ParamsFile

    joints = {}
    for j in cfg.joints:
        f = j.friction
        fr = FrictionParams(**{k: getattr(f, k) for k in FrictionParams.model_fields if getattr(f, k, None) is not None})
        joints[j.name] = JointParams(torque_constant_Nm_per_A=j.torque_constant_Nm_per_A, friction=fr,
                                     effects=j.effects)
    return ParamsFile(method="config", robot=cfg.robot.urdf, joints=joints,
                      notes={"source": f"{cfg.source}: the configuration's model (dragd demo --scenario contact)"})


def calibration_plan(q0: np.ndarray, cfg: Any) -> Any:
    """Free motion that visits every state the bands describe: each joint alone out and back (0.25 and 0.6 of its
    speed cap) with rests between, then two synchronised multi-joint passes."""
    from dragd.identify import excitation as E
    from dragd.model import RobotModel

    model = RobotModel.from_urdf(cfg.robot.urdf)
    limits = E.Limits.from_model(model, cfg)
    b = E.PlanBuilder(q0, limits)
    amp = np.array([0.35, 0.25, 0.3, 0.4, 0.4, 0.5])[:limits.n]
    for j in range(limits.n):
        for frac in (0.25, 0.6):
            tgt = q0.copy()
            tgt[j] += amp[j] if j % 2 == 0 else -amp[j]
            v = frac * float(limits.velocity_rad_s[j])
            b.move(tgt, speed=v, kind="synchronous", joint=j)
            b.hold(0.6)
            b.move(q0, speed=v, kind="synchronous", joint=j)
            b.hold(0.8)
    for sign, frac in ((1.0, 0.3), (-1.0, 0.6)):
        tgt = q0 + sign * np.array([0.3, -0.2, 0.25, 0.3, -0.3, 0.4])[:limits.n]
        b.move(tgt, speed=frac * float(limits.velocity_rad_s.min()))
        b.hold(0.8)
        b.move(q0, speed=frac * float(limits.velocity_rad_s.min()))
        b.hold(1.0)
    return b.build("contact-calibration")


def fourier_plan(q0: np.ndarray, cfg: Any, seed: int) -> Any:
    """An identification run's excitation (a short Fourier plan) from ``q0``."""
    from dragd.identify import excitation as E
    from dragd.model import RobotModel

    model = RobotModel.from_urdf(cfg.robot.urdf)
    return E.build_plan("fourier", model, q0, E.Limits.from_model(model, cfg), scale=0.2, seed=seed,
                        fourier_iterations=10)


def run_motion(rig: Rig, t: np.ndarray, q: np.ndarray, label: str, work: Path, timeout_s: float | None = None,
               during: Any = None) -> dict[str, Any]:
    """One ``track`` motion (a ``label`` starting with "identify" is an identification run's) until the daemon
    holds again; ``during(rig, t_motion_s)`` is called once as the motion runs (a contact). Its last status."""
    path = work / f"{label.replace(' ', '_')}.npz"
    np.savez(path, t_s=t, q_rad=q)
    resp = rig.must("track", file=str(path), label=label)
    got: dict[str, Any] = {}

    def back() -> bool:
        got["st"] = rig.must("status")
        st = got["st"]
        return st["mode"] in ("hold", "fault") and st.get("trajectory") is None and st.get("drive_mode") == "cst"

    if during is not None:
        during(rig)
    rig.wait_for(back, timeout_s or float(resp["duration_s"]) + 20.0, f"the end of '{label}'")
    return got["st"]


def approach(rig: Rig, q1: np.ndarray, work: Path, label: str) -> None:
    from dragd.identify.runner import _approach

    q0 = np.array(rig.must("status")["q_rad"])
    if float(np.max(np.abs(q1 - q0))) < 1e-3:
        return
    t, q = _approach(q0, q1)
    run_motion(rig, t, q, label, work)


def calibrate_session(config: Path | None, work: Path, lockstep: bool, progress: bool = False) -> tuple[Path, dict]:
    """Session 1: the free-motion run recorded, then ``dragd contact calibrate`` → the params file with bands."""
    from dragd.config import load_config, save_params

    cfg = load_config(config)
    rig = Rig("contact-cal", workdir=work / "calibration", config=config, lockstep=lockstep, allow_dirs=[work])
    try:
        rig.start_sim()
        rig.start_daemon()
        rig.must("start")
        rig.sleep(0.5)
        q0 = np.array(rig.must("status")["q_rad"])
        plan = calibration_plan(q0, cfg)
        rich = fourier_plan(q0, cfg, seed=CALIBRATION_SEED)
        _say(progress, f"calibration: free motion {plan.duration_s + rich.duration_s:.0f} s (each joint alone, then "
                       "all; a Fourier excitation)")
        rec = work / "calibration.mcap"
        rig.must("record", action="start", path=str(rec), label="contact calibration")
        rig.sleep(1.0)  # held first
        run_motion(rig, plan.t_s, plan.q_rad, "identify contact-calibration", work)
        rig.sleep(1.0)
        run_motion(rig, rich.t_s, rich.q_rad, "identify contact-calibration-fourier", work)
        rig.sleep(1.0)
        rig.must("record", action="stop")
        rig.must("stop")
    except ProcessError as exc:
        raise ContactDemoError(f"calibration session: {exc}") from None
    finally:
        rig.close()
    p1 = work / "model.yaml"
    save_params(model_params(cfg), p1)
    p2 = work / "contact.yaml"
    import subprocess

    proc = subprocess.run([sys.executable, "-m", "dragd", "contact", "calibrate", "--robot", cfg.robot.urdf, "--params",
                           str(p1), "--log", str(rec), "--out", str(p2), "--json"], capture_output=True, text=True,
                          timeout=600.0)
    if proc.returncode != 0:
        raise ContactDemoError(f"dragd contact calibrate failed:\n{proc.stderr}{proc.stdout}")
    return p2, json.loads(proc.stdout)


def identify_session(config: Path | None, work: Path) -> Path:
    """The identified model (``dragd identify fit --method full --torque-constants config``) on session 1's
    recording: rigid-body base parameters, friction and the rotor inertias the data separate."""
    import subprocess

    out = work / "identified.yaml"
    cmd = [sys.executable, "-m", "dragd", "identify", "fit", "--log", str(work / "calibration.mcap"), "--method",
           "full", "--torque-constants", "config", "--out", str(out)]
    if config is not None:
        cmd += ["--config", str(config)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=1800.0)
    if proc.returncode != 0:
        raise ContactDemoError(f"dragd identify fit failed:\n{proc.stderr}{proc.stdout}")
    return out


def hand_force_offline(params: Path, cfg: Any, rows: dict[str, np.ndarray], t_from: float,
                       t_to: float) -> dict[str, np.ndarray]:
    """The hand's force over the drag window from the daemon's telemetry (q, q̇, measured current) with the model of
    ``params``: the cycle's arithmetic (``ContactModel.log_terms``: p = M̄q̇ and τ_in by the compiled kernel; the
    observer step; the weighted grip force; the low-pass) — what the daemon shows with that model."""
    from dragd.config import load_params
    from dragd.contact.model import ContactModel
    from dragd.control.contact_watch import grip_force
    from dragd.control.observer import observer_step

    t = rows["t_s"]
    k = (t >= t_from - 0.5) & (t <= t_to)
    t, q, dq, i = t[k], rows["q_rad"][k], rows["dq_rad_s"][k], rows["current_measured_A"][k]
    cm = ContactModel.from_files(cfg.robot.urdf, load_params(params), str(params))
    cm.robot.add_grip(cfg.contact.grip.frame, cfg.contact.grip.offset_m, cfg.source)
    P, T = cm.log_terms(q, dq, i)
    pc = load_params(params).contact
    k_o = float(pc.observer_gain_per_s) if pc is not None else 25.0  # (the detector's default without bands)
    rest = cm.law.rest_threshold_rad_s + cm.law.fade_width_rad_s
    w2 = cfg.contact.grip.rest_weight ** 2
    dt0 = float(np.median(np.diff(t))) if len(t) > 1 else 1e-3
    alpha = 1.0 - math.exp(-2.0 * math.pi * cfg.contact.wrench_Hz * dt0)
    r, integ, p0 = np.zeros(len(cm.names)), np.zeros(len(cm.names)), P[0].copy()
    raw, f, out = np.zeros(3), np.zeros(3), np.zeros((len(t), 3))
    for n in range(len(t)):
        observer_step(float(t[n] - t[n - 1]) if n else 0.0, k_o, T[n], P[n], p0, integ, r)
        w = np.where(np.abs(dq[n]) >= rest, 1.0, w2)
        if grip_force(cm.robot.grip_jacobian(q[n]), r, w, raw):
            f += (raw - f) * alpha
        out[n] = f
    return {"t_s": t, "hand_force_N": out}


def detection_config(config: Path | None, params: Path, work: Path, reactions: dict[str, str] | None = None) -> Path:
    """The configuration with ``params`` (the bands) and the reactions per mode (default: stop)."""
    import yaml

    from dragd.config import default_config_path

    src = Path(config) if config is not None else default_config_path()
    data = yaml.safe_load(src.read_text()) or {}
    data["params"] = str(Path(params).absolute())
    urdf = (data.get("robot") or {}).get("urdf")
    if urdf and (src.parent / urdf).is_file():
        data["robot"]["urdf"] = str((src.parent / urdf).absolute())
    contact = data.setdefault("contact", {}) or {}
    for m, r in (reactions or {}).items():
        contact.setdefault(m, {})["reaction"] = r
    data["contact"] = contact
    out = work / "contact-config.yaml"
    out.write_text(yaml.safe_dump(data, sort_keys=False))
    return out


# ----------------------------------------------------------------------------------------------- measuring


class Clocks:
    """The simulator's time ↔ the daemon's controller time (both stand still between the rig's grants)."""

    def __init__(self, rig: Rig) -> None:
        st = rig.must("status")
        sim = rig.sim_call("state")
        self.offset_s = float(sim["t"]) - float(st["t_s"])

    def to_daemon(self, sim_t_s: float) -> float:
        return sim_t_s - self.offset_s


def head_on(rig: Rig, model: Any, link: str = STRIKE_LINK, point: tuple[float, float, float] = STRIKE_POINT_M) -> list[float]:
    """The direction of a head-on impact on ``link``'s point: against its present velocity (world); straight down
    where it is (nearly) at rest."""
    import pinocchio as pin

    st = rig.must("status")
    q, dq = np.array(st["q_rad"]), np.array(st["dq_rad_s"])
    m, d = model.model, model.data
    fid = m.getFrameId(link)
    J = pin.computeFrameJacobian(m, d, q, fid, pin.LOCAL_WORLD_ALIGNED)
    r = d.oMf[fid].rotation @ np.asarray(point)
    v = (J[:3] - np.cross(r, J[3:].T).T) @ dq
    n = float(np.linalg.norm(v))
    return (-v / n).tolist() if n > 0.02 else [0.0, 0.0, -1.0]


def point_position(model: Any, q: np.ndarray, link: str = STRIKE_LINK,
                   point: tuple[float, float, float] = STRIKE_POINT_M) -> np.ndarray:
    import pinocchio as pin

    m, d = model.model, model.data
    pin.framesForwardKinematics(m, d, q)
    M = d.oMf[m.getFrameId(link)]
    return M.translation + M.rotation @ np.asarray(point)


def contact_faults(status: dict[str, Any], since_t_s: float = -math.inf) -> list[dict[str, Any]]:
    return [f for f in status["faults"] if f.get("kind") == "contact" and f["t_s"] >= since_t_s]


def strike_info(rig: Rig, clocks: Clocks, before_onsets: int, what: str) -> dict[str, Any]:
    """The contact just applied, as the run knows it: the operator's events (the truth) and the daemon's first
    contact fault entry since (figures from the telemetry follow in :func:`strike_figures`)."""
    ev = rig.sim_call("operator_events")["events"]
    start = next(e for e in ev if e["kind"] == "strike")
    end = next((e for e in ev if e["kind"] == "strike_end"), None)
    t_contact = clocks.to_daemon(float(start["t"]))
    st = rig.must("status")
    faults = contact_faults(st, t_contact - 1.0)
    res: dict[str, Any] = {"what": what, "link": start["link"], "peak_N": end["peak_N"] if end else None,
                           "direction": [round(x, 3) for x in start["direction"]],
                           "alarms": st["contact"]["onsets"] - before_onsets, "t_contact_s": round(t_contact, 4),
                           "t_contact_end_s": round(clocks.to_daemon(float(end["t"])), 4) if end else None}
    if not faults:
        res["detected"] = False
        return res
    f = faults[0]
    t_det = float(f.get("t_start_s") or f["t_s"])
    res.update(detected=True, delay_ms=round(1000.0 * (t_det - t_contact), 1), t_detect_s=round(t_det, 4),
               joints=f["joints"], residual_A=f["residual_A"], contact_Nm=f["contact_Nm"], reaction=f.get("reaction"))
    return res


def strike_figures(res: dict[str, Any], rows: dict[str, np.ndarray], model: Any) -> dict[str, Any]:
    """From the daemon's telemetry: how long after the detection (and after the contact's force ended) every joint
    was below ``STOPPED_RAD_S``, and how far the struck point travelled from the detection until then."""
    if not res.get("detected"):
        return res
    t = rows["t_s"]
    t_det = res["t_detect_s"]
    k0 = int(np.searchsorted(t, t_det))
    speed = np.abs(rows["dq_rad_s"]).max(axis=1)
    res["speed_at_detection_rad_s"] = round(float(speed[min(k0, len(t) - 1)]), 4)
    # stopped: from the first sample after which every joint stays slower than STOPPED_RAD_S for STAYS_S (a
    # rebound's turning point is not a stop)
    k_end = int(np.searchsorted(t, t_det + STOP_WINDOW_S))
    moving = np.nonzero(speed[k0:k_end] >= STOPPED_RAD_S)[0]
    k1 = k0 + (int(moving[-1]) + 1 if moving.size else 0)
    if k1 >= len(t) or t[min(k_end, len(t) - 1)] - t[k1] < STAYS_S:
        res["stopped_after_ms"] = None
        return res
    res["stopped_after_ms"] = round(1000.0 * (t[k1] - t_det), 1)
    if res.get("t_contact_end_s") is not None:  # (the contact's force may push the arm after the detection)
        res["stopped_after_contact_end_ms"] = round(1000.0 * (t[k1] - res["t_contact_end_s"]), 1)
    res["stop_distance_mm"] = round(1000.0 * float(np.linalg.norm(point_position(model, rows["q_rad"][k1])
                                                                   - point_position(model, rows["q_rad"][k0]))), 2)
    res["stop_distance_deg"] = round(math.degrees(float(np.max(np.abs(rows["q_rad"][k1] - rows["q_rad"][k0])))), 3)
    return res


def hand_force_error(trace: dict[str, Any], offset_s: float, rows: dict[str, np.ndarray], t_from: float,
                     t_to: float) -> dict[str, Any]:
    """The daemon's hand-force estimate against the operator's true force (sampled every ms) where the truth is
    above ``HAND_FORCE_MIN_N``: |f̂ − f| / |f| (median, 95th percentile, largest) and the same once each push
    has settled (0.3 s after it starts: the residual's and the estimate's low-passes)."""
    ts = np.array(trace["t_s"]) - offset_s
    f_true = np.array(trace["force_N"], dtype=float).reshape(-1, 3)
    t = rows["t_s"]
    keep = (t >= t_from) & (t <= t_to)
    t, f_est = t[keep], rows["hand_force_N"][keep]
    truth = np.column_stack([np.interp(t, ts, np.nan_to_num(f_true[:, k])) for k in range(3)])
    known = np.interp(t, ts, np.isfinite(f_true[:, 0]).astype(float)) > 0.999
    norm = np.linalg.norm(truth, axis=1)
    sel = known & (norm > HAND_FORCE_MIN_N)
    err = np.linalg.norm(f_est - truth, axis=1)[sel] / norm[sel]
    # settled: the truth unchanged (within 1 %) over the last 0.3 s
    lag = 300
    steady = np.zeros_like(sel)
    if len(t) > lag:
        steady[lag:] = np.linalg.norm(truth[lag:] - truth[:-lag], axis=1) < 0.01 * np.maximum(norm[lag:], 1.0)
    sel2 = sel & steady
    err2 = np.linalg.norm(f_est - truth, axis=1)[sel2] / norm[sel2]

    def q(x: np.ndarray, p: float) -> float | None:
        return round(float(np.percentile(x, p)), 4) if x.size else None

    # the estimate along the truth: its cosine and its projection's gain (1: the right size)
    n2 = np.maximum(norm[sel2], 1e-9)
    cos = np.sum(f_est[sel2] * truth[sel2], axis=1) / (n2 * np.maximum(np.linalg.norm(f_est[sel2], axis=1), 1e-9))
    gain = np.sum(f_est[sel2] * truth[sel2], axis=1) / (n2 * n2)

    return {"samples": int(sel.sum()), "error_rel_median": q(err, 50), "error_rel_p95": q(err, 95),
            "error_rel_max": q(err, 100), "settled_samples": int(sel2.sum()), "settled_error_rel_median": q(err2, 50),
            "settled_error_rel_p95": q(err2, 95), "settled_error_rel_max": q(err2, 100),
            "settled_cos_median": q(cos, 50), "settled_gain_median": q(gain, 50),
            "true_force_max_N": round(float(norm.max()), 2) if norm.size else 0.0}


# ----------------------------------------------------------------------------------------------- the demo


def _strike(rig: Rig, model: Any, name: str, profile: dict[str, Any] | None = None, peak_N: float = IMPACT_N,
            direction: list[float] | None = None) -> None:
    seg = {"kind": "strike", "link": STRIKE_LINK, "point_m": list(STRIKE_POINT_M),
           "direction": direction or head_on(rig, model), "peak_N": peak_N, **(profile or IMPACT)}
    rig.sim_call("operator", scenario={"name": name, "segments": [seg, {"kind": "release", "duration_s": 0.0}]})


def run_contact_demo(config: Path | None = None, out: Path | None = None, progress: bool = True,
                     lockstep: bool = False, calibrated: Path | None = None) -> dict[str, Any]:
    """Both sessions (``calibrated``: a params file with bands from an earlier calibration session: the second
    alone)."""
    from dragd.config import load_config
    from dragd.lab.demo import TEACH_STEPS_RAD, guide_and_settle
    from dragd.model import RobotModel

    out = Path(out) if out is not None else Path.cwd() / "out"
    out.mkdir(parents=True, exist_ok=True)
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    work = (out / f"contact-{stamp}").absolute()
    work.mkdir(parents=True, exist_ok=True)
    from dragd.config import load_params

    if calibrated is None:
        _say(progress, f"session 1: calibration{' (lockstep clock)' if lockstep else ''} ...")
        params, _ = calibrate_session(config, work, lockstep, progress)
        _say(progress, "the identified model (identify fit --method full) on the calibration's recording ...")
        identified: Path | None = identify_session(config, work)
    else:
        params = Path(calibrated)
        identified = params.parent / "identified.yaml" if (params.parent / "identified.yaml").is_file() else None
    pc = load_params(params).contact
    cal = pc.calibration if pc is not None else {}
    margins = {nm: j.get("moving_max_ratio") for nm, j in (cal.get("joints") or {}).items()}
    cfg2 = detection_config(config, params, work)
    cfg = load_config(cfg2)
    model = RobotModel.from_urdf(cfg.robot.urdf)
    mcap = work / "detection.mcap"
    rig = Rig("contact-demo", workdir=work / "detection", config=cfg2, telemetry=mcap, lockstep=lockstep,
              allow_dirs=[work])
    result: dict[str, Any] = {"calibration": {"params": str(params), "log": str(work / "calibration.mcap"),
                                              "max_ratio": margins}}
    try:
        _say(progress, "session 2: the daemon with the bands ...")
        rig.start_sim()
        rig.start_daemon()
        rig.must("start")
        clocks = Clocks(rig)
        st = rig.must("status")
        if not st["contact"]["calibrated"]:
            raise ContactDemoError(f"the daemon did not take the bands: {st['contact']['reason']}")
        false: dict[str, int] = {}

        def onsets() -> int:
            return int(rig.must("status")["contact"]["onsets"])

        n0 = onsets()
        rig.sleep(2.0)
        false["hold_2s"] = onsets() - n0
        # the teach demo: three waypoints by hand (drag), replayed linearly and circularly
        _say(progress, "teach demo: three waypoints by hand, replayed linearly and circularly ...")
        program = work / "teach.yaml"
        n0 = onsets()
        rig.must("teach", action="start", name=str(program))
        for i, step in enumerate(TEACH_STEPS_RAD):
            guide_and_settle(rig, step, 2.0, f"teach_p{i + 1}")
            rig.must("teach", action="mark")
        rig.must("teach", action="stop")
        rig.must("mode", mode="hold")
        rig.sleep(0.5)
        for interp in ("linear", "circular"):
            resp = rig.must("replay", program=str(program), interp=interp, timeout_s=60.0)
            rig.wait_for(lambda: bool((rig.must("status").get("replay") or {}).get("outcome")),
                         resp["duration_s"] + 30.0, f"the {interp} replay")
            outcome = rig.must("status")["replay"]["outcome"]
            if outcome != "done":
                raise ContactDemoError(f"the {interp} replay ended with: {outcome}")
            rig.sleep(0.3)
        false["teach_demo"] = onsets() - n0
        # an identification run (a plan the calibration never ran)
        q_home = np.array(rig.must("status")["q_rad"])
        plan = fourier_plan(q_home, cfg, seed=11)
        _say(progress, f"identification run: Fourier excitation {plan.duration_s:.0f} s ...")
        n0 = onsets()
        run_motion(rig, plan.t_s, plan.q_rad, "identify fourier", work)
        false["identify_run"] = onsets() - n0
        result["false_alarms"] = false
        result["free_motion_s"] = {"hold": 2.0, "identify_run": round(plan.duration_s, 1)}
        contacts = []
        # 1. a 60 N impact on the forearm during a replay (head-on)
        _say(progress, "a 60 N impact on the forearm during a replay ...")
        n0 = onsets()
        resp = rig.must("replay", program=str(program), interp="linear", timeout_s=60.0)
        rig.sleep(float(resp["move_to_start_s"]) + 0.6 * (float(resp["duration_s"]) - float(resp["move_to_start_s"])))
        _strike(rig, model, "impact_replay")
        rig.wait_for(lambda: bool((rig.must("status").get("replay") or {}).get("outcome")), 60.0, "the replay's end")
        rig.sleep(0.5)
        contacts.append(strike_info(rig, clocks, n0, "impact during replay"))
        # 2. the same during an identification run
        _say(progress, "a 60 N impact on the forearm during an identification run ...")
        approach(rig, plan.q_rad[0], work, "identify approach")
        n0 = onsets()
        def impact(r: Rig) -> None:
            r.sleep(0.45 * plan.duration_s)
            _strike(r, model, "impact_identify")

        run_motion(rig, plan.t_s, plan.q_rad, "identify fourier-2", work, during=impact)
        rig.sleep(0.5)
        contacts.append(strike_info(rig, clocks, n0, "impact during identify run"))
        # 3. a push on the held arm's forearm (40 N, rising over 0.2 s, held 0.5 s)
        _say(progress, "a push on the held arm's forearm ...")
        rig.sleep(1.5)
        n0 = onsets()
        _strike(rig, model, "push_hold", {"profile": "trapezoid", "rise_s": 0.2, "hold_s": 0.5, "fall_s": 0.2},
                peak_N=40.0, direction=[0.0, 0.0, -1.0])
        rig.sleep(1.5)
        contacts.append(strike_info(rig, clocks, n0, "push on the held arm"))
        # the hand's force in drag
        _say(progress, "drag: hands pushing at the grip point ...")
        rig.must("mode", mode="drag")
        rig.sleep(1.0)
        t_from = rig.must("status")["t_s"]
        segs: list[dict[str, Any]] = []
        for f in HAND_PUSHES_N:
            segs += [{"kind": "push", "force_N": list(f), "duration_s": 1.0}, {"kind": "release", "duration_s": 0.8}]
        rig.sim_call("operator", scenario={"name": "hands", "segments": segs})
        rig.sleep(1.8 * len(HAND_PUSHES_N) + 0.2)
        t_to = rig.must("status")["t_s"]
        trace = rig.sim_call("operator_trace", timeout_s=30.0, since_t_s=clocks.offset_s + t_from)
        (work / "hand_truth.json").write_text(json.dumps({"offset_s": clocks.offset_s, "t_from_s": t_from,
                                                         "t_to_s": t_to, "trace": trace}))
        status = rig.must("status")
        rig.must("stop")
        codes = rig.close()
        if codes.get("dragd") != 0:
            raise ContactDemoError(f"the daemon exited with {codes.get('dragd')} on SIGTERM (expected 0)")
    except ProcessError as exc:
        raise ContactDemoError(str(exc)) from None
    finally:
        rig.close()
    from dragd.telemetry.reader import read_rows

    rows = read_rows(mcap, ["t_s", "q_rad", "dq_rad_s", "hand_force_N", "current_measured_A"])
    result["contacts"] = [strike_figures(c, rows, model) for c in contacts]
    result["hand_force"] = {**hand_force_error(trace, clocks.offset_s, rows, t_from, t_to),
                            "pushes_N": [list(f) for f in HAND_PUSHES_N], "grip": cfg.contact.grip.frame,
                            "model": "the configuration's (the daemon's, in the cycle)"}
    if identified is not None:  # the same drag through the identified model (the cycle's arithmetic, offline)
        est = hand_force_offline(identified, cfg, rows, t_from, t_to)
        result["hand_force_identified"] = {**hand_force_error(trace, clocks.offset_s, est, t_from, t_to),
                                           "params": str(identified)}
    result["contact_status"] = {k: status["contact"][k] for k in ("modes", "thresholds_A", "observer_gain_per_s")}
    result["false_alarms_total"] = sum(false.values())
    result["mcap"] = str(mcap)
    return result
