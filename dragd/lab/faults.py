"""The fault matrix: every fault the simulator injects, run against the sim + daemon, measured (docs/SAFETY.md).

For each fault: the arm in drag at rest, the sim's ``inject``, then the daemon's status and the sim's truth polled
until the policy's reaction and recovery are seen (or a time limit). Every wait is on the rig's clock (``Rig.now``,
``Rig.sleep``): on the lockstep clock the injection lands between two cycles and the status is looked at after every
cycle until the fault shows, so ``detected_ms`` is exact to the cycle and the run is the same on any machine; on the
wall clock (``lockstep=False``, as deployed) it is polled as fast as the requests return. Per fault::

    detected_ms             injection → the daemon's status shows it (fault, hold, or the counter that names it)
    reaction                what the daemon did: fault | hold | dropped | tolerated
    max_joint_speed_rad_s   fastest joint (the sim's truth) from the injection until recovered
    max_drift_deg           largest joint excursion from the pose at the injection (truth) until recovered
    recovered               the policy's recovery happened (auto rejoin in HOLD; or 'dragd start' → HOLD; or drag
                            went on / resumed)
    rows_lost               telemetry rows dropped by the writer meanwhile (a cycle without feedback still logs a row)
"""

from __future__ import annotations

import math
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dragd.hardware.cia402 import EMCY_OVER_CURRENT, EMCY_TEMPERATURE_DEVICE
from dragd.lab.rig import Rig


@dataclass(frozen=True)
class FaultCase:
    kind: str
    args: dict[str, Any]
    reaction: str  # the documented reaction
    recover: str  # auto (rejoin in hold) | start (operator) | continue (drag goes on or resumes by itself)
    detect: str  # the status field that detects it when no fault is raised
    settle_s: float = 0.0  # wait after the injection before recovering (the fault's own duration)
    expect_fault: tuple[str, ...] = field(default_factory=tuple)  # words in the first fault's text
    rig: str = "default"  # default | hand (the guiding device wired, drag by its enabling switch: hand_rig_kwargs)


CASES: dict[str, FaultCase] = {
    "drive_silent": FaultCase("drive_silent", {"node_id": 3, "seconds": 1.0}, "fault", "start", "faults", 1.3,
                              ("node 3",)),
    "burst_loss": FaultCase("burst_loss", {"frames": 150}, "hold", "continue", "feedback_holds"),
    "burst_loss_short": FaultCase("burst_loss", {"frames": 18}, "tolerated", "continue", "late_tpdo_cycles"),
    "duplicates": FaultCase("duplicates", {"frames": 60}, "tolerated", "continue", "duplicate_tpdos"),
    "late_tpdo": FaultCase("late_tpdo", {"delay_ms": 15.0, "seconds": 0.3}, "hold", "continue",
                           "late_tpdo_cycles", 0.4),
    "emcy": FaultCase("emcy", {"node_id": 2, "code": EMCY_TEMPERATURE_DEVICE}, "fault", "start", "faults", 0.2,
                      (f"EMCY 0x{EMCY_TEMPERATURE_DEVICE:04X}",)),
    "drive_fault": FaultCase("drive_fault", {"node_id": 3, "code": EMCY_OVER_CURRENT}, "fault", "start", "faults", 0.2,
                             ("node 3",)),
    "switched_on": FaultCase("switched_on", {"node_id": 5}, "fault", "start", "faults", 0.3,
                             ("node 5", "left operation enabled")),
    "node_reboot": FaultCase("node_reboot", {"node_id": 4}, "fault", "auto", "faults", 0.0, ("node 4",)),
    "bus_off": FaultCase("bus_off", {"seconds": 1.0}, "fault", "auto", "faults", 1.0),
    "encoder_jump": FaultCase("encoder_jump", {"node_id": 2, "rad": 0.3, "seconds": 0.5}, "fault", "start",
                              "faults", 0.8, ("encoder jump", "node 2")),
    "garbage": FaultCase("garbage", {"node_id": 2}, "dropped", "continue", "rejected_frames"),
}

# --- the guiding device's input faults (#30; docs/HAND.md, docs/SAFETY.md) ---------------------------------------
# Their own rig (hand_rig_kwargs): the enabling switch, mark, stop and teach wired to joint6's 60FDh, drag only while
# the switch is held; a classic CAN bus (per-node layout, 250 Hz: what one classic bus carries), where the inputs
# ride in an event TPDO beside the statusword (TPDO2), so losing it loses the inputs, not the feedback (TPDO1).
HAND_CASES: dict[str, FaultCase] = {
    # the operator lets go of the switch and one channel stays closed (a welded contact)
    "stuck_enable": FaultCase("stuck_enable", {"channel": 1, "seconds": 1.0}, "hold", "start", "faults", 1.0,
                              ("channels disagree", "joint6 60FDh bits 16, 17, 18"), rig="hand"),
    # the switch's contact opens and closes by itself while the operator holds it
    "chattering_contact": FaultCase("chattering", {"button": "enable", "period_ms": 8.0, "seconds": 0.4}, "hold",
                                    "start", "faults", 0.4, ("chattering contact",), rig="hand"),
    # the event TPDO carrying joint6's inputs is lost (the feedback goes on)
    "inputs_lost": FaultCase("inputs_lost", {"node_id": 6, "seconds": 0.3}, "hold", "press", "faults", 0.3,
                             ("lost", "60FDh"), rig="hand"),
}
CASES.update(HAND_CASES)
HAND_WIRING = [{"function": "enable", "joint": "joint6", "bit": 16, "second_bit": 17, "panic_bit": 18},
               {"function": "mark", "joint": "joint6", "bit": 19},
               {"function": "stop", "joint": "joint6", "bit": 20, "active": "low"},
               {"function": "teach", "joint": "joint6", "bit": 21}]  # (the simulated arm's device: sim/truth.py hand)


def hand_config(path: Path) -> Path:
    """config/default.yaml with the guiding device wired and required, on one classic CAN bus at 250 Hz."""
    import yaml

    from dragd.resources import config_path

    data = yaml.safe_load(config_path("default.yaml").read_text())
    data["robot"]["urdf"] = "seed_cobot"
    data["hand"] = {"inputs": HAND_WIRING}
    data["drag"] = {"require": "enable_input"}
    data["loop"]["rate_Hz"] = 250
    data["buses"][0].update(fd=False, layout="per_node")
    data["buses"][0].pop("data_bitrate", None)
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def hand_rig_kwargs(workdir: Path) -> dict[str, Any]:
    """Rig arguments for the hand's cases: its configuration, drag as configured (no lab flag)."""
    workdir.mkdir(parents=True, exist_ok=True)
    return {"config": hand_config(workdir / "hand.yaml"), "drag_guard": "config"}


def hand_drag(rig: Rig, timeout_s: float = 5.0) -> None:
    """Enabled, the switch released and pressed again (a latched fault cleared by 'start' first), in drag."""
    end = rig.now() + timeout_s
    while rig.now() < end:
        st = rig.must("status")
        if st["mode"] in ("idle", "fault") or any(i.get("fault") for i in st["drag"]["inputs"]):
            rig.call("start")
            rig.sleep(0.3)
            continue
        rig.sim_call("hand", action="let_go", button="enable")
        rig.sleep(0.05)
        rig.sim_call("hand", action="press", button="enable")
        rig.sleep(0.05)
        if rig.must("status")["mode"] == "drag":
            rig.sleep(0.3)
            return
    st = rig.must("status")
    raise RuntimeError(f"the enabling switch did not bring the arm into drag within {timeout_s:g} s: {st['mode']}, "
                       f"{st['drag']['refusal']}")


def run_hand_fault(rig: Rig, name: str) -> dict[str, Any]:
    """One input fault of the guiding device (a ``hand`` rig, in drag by the switch): detect → react → recover.
    Adds ``out_of_drag_ms`` (injection → drag ended) to ``run_fault``'s keys."""
    case = CASES[name]
    hand_drag(rig)
    before = rig.must("status")
    telemetry0 = (before.get("telemetry") or {}).get("dropped", 0)
    sim0 = rig.sim_call("state")
    q0 = sim0["q_rad"]
    max_speed = max_drift = 0.0
    texts: list[str] = []

    def truth() -> None:
        nonlocal max_speed, max_drift
        s = rig.sim_call("state")
        max_speed = max(max_speed, max(abs(v) for v in s["dq_rad_s"]))
        max_drift = max(max_drift, max(abs(a - b) for a, b in zip(s["q_rad"], q0, strict=True)))

    def saw(st: dict[str, Any]) -> dict[str, Any]:
        for f in st["faults"][len(st["faults"]) - (st["fault_count"] - before["fault_count"]):]:
            if f["text"] not in texts:
                texts.append(f["text"])
        return st

    t_inj = rig.now()
    injected = rig.sim_call("inject", kind=case.kind, **case.args)
    if not injected.get("ok"):
        raise RuntimeError(f"inject {name}: {injected.get('error')}")
    if case.kind == "stuck_enable":
        rig.sim_call("hand", action="let_go", button="enable")  # the operator lets go; the welded channel stays
    detected_ms = out_ms = None
    period = rig.must("clock")["clock"]["period_s"] if rig.lockstep else 0.001
    while rig.now() < t_inj + DETECT_TIMEOUT_S:
        st = saw(rig.must("status"))
        if out_ms is None and st["mode"] != "drag":
            out_ms = (rig.now() - t_inj) * 1e3
        if st["fault_count"] > before["fault_count"] and any(w in t for t in texts for w in case.expect_fault[:1]):
            detected_ms = (rig.now() - t_inj) * 1e3
            break
        truth()
        _poll(rig, period)
    while rig.now() < t_inj + case.settle_s + 0.3:  # the fault's own duration
        truth()
        saw(rig.must("status"))
        _poll(rig, WATCH_POLL_S)
    status = saw(rig.must("status"))
    reaction = "hold" if out_ms is not None and status["mode"] == "hold" else status["mode"]
    # recovery: 'start' clears a latched input fault whose cause is gone; then the operator releases the switch and
    # presses it again (a switch held through a fault or a loss never drags by itself)
    recovered = False
    if case.recover == "start":
        rig.must("start")
        rig.sleep(0.3)
    end = rig.now() + RECOVER_TIMEOUT_S
    while rig.now() < end and not recovered:
        truth()
        rig.sim_call("hand", action="let_go", button="enable")
        rig.sleep(0.05)
        rig.sim_call("hand", action="press", button="enable")
        rig.sleep(0.1)
        recovered = rig.must("status")["mode"] == "drag"
    after = rig.must("status")
    sim1 = rig.sim_call("state")
    rate = sim1["steps"] / sim1["t"] if sim1["t"] > 0 else 1000.0
    behind = (sim1["late_steps"] + sim1["dropped_steps"] - sim0["late_steps"] - sim0["dropped_steps"]) / rate
    return {
        "detected_ms": None if detected_ms is None else round(detected_ms, 1),
        "out_of_drag_ms": None if out_ms is None else round(out_ms, 1),
        "reaction": reaction,
        "max_joint_speed_rad_s": round(max_speed, 4),
        "max_drift_deg": round(math.degrees(max_drift), 3),
        "recovered": recovered,
        "rows_lost": int((after.get("telemetry") or {}).get("dropped", 0) - telemetry0),
        "feedback_holds": after["feedback_holds"] - before["feedback_holds"],
        "sim_behind_ms": round(behind * 1e3, 1),
        "expected": {"reaction": case.reaction, "recover": case.recover},
        "faults": texts[:4],
    }

# --- end of the guiding device's input faults --------------------------------------------------------------------

RECOVER_TIMEOUT_S = 15.0  # of the rig's clock
DETECT_TIMEOUT_S = 5.0
DETECT_POLL_S = 0.001  # the status after every cycle until the fault shows (lockstep: detected_ms to the cycle)
WATCH_POLL_S = 0.01  # then every 10 ms: the truth (speed, drift) and the recovery


def _counter(status: dict[str, Any], name: str) -> int:
    if name == "faults":
        return int(status["fault_count"])
    return int(status.get(name) or 0)


def _poll(rig: Rig, seconds: float) -> None:
    """Between two looks: ``seconds`` of arm time on the lockstep clock; on the wall clock the requests' own pace."""
    if rig.lockstep:
        rig.sleep(seconds)


def drag_at_rest(rig: Rig, timeout_s: float = 20.0) -> None:
    """Enabled, in drag, no fault (restarting the arm where needed: the previous fault's state)."""
    end = rig.now() + timeout_s
    while rig.now() < end:
        st = rig.must("status")
        if st["mode"] == "drag" and not st["feedback_hold"]:
            rig.sleep(0.5)
            return
        if st["mode"] in ("idle", "fault"):
            rig.call("start")
            rig.sleep(0.4)
        elif st["mode"] == "hold" and not st["feedback_hold"] and st["drives_enabled"]:
            rig.call("mode", mode="drag")
            rig.sleep(0.3)
        else:
            rig.sleep(0.1)
    st = rig.must('status')
    raise RuntimeError(f"the arm did not reach drag within {timeout_s:.0f} s: {st['mode']}, "
                       f"faults {[f['text'] for f in st['faults']][-4:]}")


def run_fault(rig: Rig, name: str) -> dict[str, Any]:
    """Inject one fault into a running rig (arm in drag) and measure the daemon's reaction and recovery."""
    case = CASES[name]
    if case.rig == "hand":
        return run_hand_fault(rig, name)
    drag_at_rest(rig)
    before = rig.must("status")
    telemetry0 = (before.get("telemetry") or {}).get("dropped", 0)
    sim0 = rig.sim_call("state")
    q0 = sim0["q_rad"]
    max_speed, max_drift = 0.0, 0.0
    texts: list[str] = []
    old_texts = {f["text"] for f in before["faults"]}

    def saw(st: dict[str, Any]) -> dict[str, Any]:
        for f in st["faults"]:
            if f["text"] not in old_texts and f["text"] not in texts:
                texts.append(f["text"])
        return st

    def truth() -> None:
        nonlocal max_speed, max_drift
        s = rig.sim_call("state")
        max_speed = max(max_speed, max(abs(v) for v in s["dq_rad_s"]))
        max_drift = max(max_drift, max(abs(a - b) for a, b in zip(s["q_rad"], q0, strict=True)))

    t_now = rig.now()  # (lockstep: the arm's time stands still until the next grant: the injection lands now)
    injected = rig.sim_call("inject", kind=case.kind, **case.args)
    if not injected.get("ok"):
        raise RuntimeError(f"inject {name}: {injected.get('error')}")
    t_inj = t_now if rig.lockstep else float(injected["t_mono"])  # (wall: the sim's CLOCK_MONOTONIC, as rig.now)
    detected_ms = None
    status = before
    end_detect = t_inj + DETECT_TIMEOUT_S
    while (now := rig.now()) < end_detect:
        status = saw(rig.must("status"))
        if _counter(status, case.detect) > _counter(before, case.detect) or \
                status["fault_count"] > before["fault_count"]:
            detected_ms = (now - t_inj) * 1e3
            break
        truth()
        _poll(rig, DETECT_POLL_S)
    # the fault's own duration, watching the truth
    end_settle = t_inj + case.settle_s + 0.3
    while rig.now() < end_settle:
        truth()
        saw(rig.must("status"))  # (a rejoin's 'start' clears the daemon's fault list: texts are collected here)
        _poll(rig, WATCH_POLL_S)
    status = saw(rig.must("status"))
    new_count = status["fault_count"] - before["fault_count"]
    holds = status["feedback_holds"] - before["feedback_holds"]
    if new_count > 0:
        reaction = "fault"
    elif case.reaction == "hold":
        reaction = "hold" if holds > 0 else "tolerated"
    elif case.detect == "rejected_frames" and detected_ms is not None:
        reaction = "dropped"
    else:
        # (a feedback hold here is the loaded host's own multicast loss, the documented reaction to stale
        # feedback, not this fault's: reported as feedback_holds, not as the reaction)
        reaction = "tolerated"
    recovered = False
    end = rig.now() + RECOVER_TIMEOUT_S
    started = False
    while rig.now() < end:
        truth()
        st = saw(rig.must("status"))
        if case.recover == "auto":
            if st["mode"] == "hold" and st["drives_enabled"] and st["comms"]["rejoins"] > before["comms"]["rejoins"]:
                recovered = True
                break
        elif case.recover == "start":
            if st["mode"] == "hold" and st["drives_enabled"] and started:
                recovered = True
                break
            if st["mode"] == "fault" and not started:
                if rig.call("start").get("ok"):
                    started = True
            elif st["mode"] == "fault":
                rig.sleep(0.2)
                if rig.must("status")["mode"] == "fault":
                    rig.call("start")
        else:
            if st["mode"] == "drag" and not st["feedback_hold"] and st["fault_count"] == before["fault_count"]:
                recovered = True
                break
            if st["mode"] == "fault":
                break
        rig.sleep(WATCH_POLL_S)
    after = rig.must("status")
    sim1 = rig.sim_call("state")
    rate = sim1["steps"] / sim1["t"] if sim1["t"] > 0 else 1000.0
    behind = (sim1["late_steps"] + sim1["dropped_steps"] - sim0["late_steps"] - sim0["dropped_steps"]) / rate
    telemetry1 = (after.get("telemetry") or {}).get("dropped", 0)
    return {
        "detected_ms": None if detected_ms is None else round(detected_ms, 1),
        "reaction": reaction,
        "max_joint_speed_rad_s": round(max_speed, 4),
        "max_drift_deg": round(math.degrees(max_drift), 3),
        "recovered": recovered,
        "rows_lost": int(telemetry1 - telemetry0),
        "feedback_holds": holds,
        # how far the host left the simulated robot behind real time meanwhile (its bus thread starved alike)
        "sim_behind_ms": round(behind * 1e3, 1),
        "expected": {"reaction": case.reaction, "recover": case.recover},
        "faults": texts[:4],
    }


def fault_matrix(names: list[str] | None = None, workdir: Path | None = None,
                 daemon_args: list[str] | None = None, sim_args: list[str] | None = None,
                 lockstep: bool = True) -> dict[str, Any]:
    """Every fault (or ``names``) against one sim + daemon rig, in turn; on the lockstep clock unless told not to."""
    out: dict[str, Any] = {}
    # wall clock as deployed: the daemon's cycle SCHED_FIFO 70, the sim 60 (where permitted; a loaded host otherwise
    # stalls the master heartbeat past the drives' consumer time, a fault of its own)
    rt = not lockstep
    rig_kw: dict[str, Any] = {"lockstep": lockstep,
                              "daemon_args": daemon_args if daemon_args is not None else
                              (["--realtime-priority", "70"] if rt else []),
                              "sim_args": sim_args if sim_args is not None else
                              (["--realtime-priority", "60"] if rt else [])}
    if workdir is not None:
        rig_kw["workdir"] = workdir
    todo = names or list(CASES)
    for group in ("default", "hand"):  # (the hand's cases on a rig of their own: hand_rig_kwargs)
        group_names = [n for n in todo if CASES[n].rig == group]
        if not group_names:
            continue
        kw = dict(rig_kw)
        if group == "hand":
            kw["workdir"] = Path(kw.get("workdir") or tempfile.mkdtemp(prefix="dragd-faults-")) / "hand"
            kw.update(hand_rig_kwargs(kw["workdir"]))
        with Rig(f"faults-{group}", **kw) as rig:
            rig.telemetry = rig.workdir / "faults.mcap"
            rig.start_sim()
            rig.start_daemon()
            for name in group_names:
                out[name] = run_fault(rig, name)
    return {n: out[n] for n in todo}
