"""Drag quality: effort to move each joint at 10°/s (compensated vs gravity-only), drift after release."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from dragd.lab.experiment.bench import Bench, move_effort, wait_rest

SPEED_RAD_S = math.radians(10.0)


def _efforts(bench: Bench, rig: Any, joints: list[int], seconds: float) -> dict[int, float]:
    out = {}
    for j in joints:
        name = bench.cfg.joints[j].name
        ev_pos = move_effort(rig, name, SPEED_RAD_S, seconds)
        wait_rest(rig)
        ev_neg = move_effort(rig, name, -SPEED_RAD_S, seconds)
        wait_rest(rig)
        out[j] = 0.5 * (abs(ev_pos["torque_Nm_mean"]) + abs(ev_neg["torque_Nm_mean"]))
    return out


def run_quality(bench: Bench, joints: list[int], move_s: float = 2.0, observe_s: float = 5.0) -> dict[str, Any]:
    """Per joint: effort at 10°/s as % of the uncompensated (gravity-only) case; drift within 5 s of release."""
    gravity_only = {("law", "friction"): False, ("law", "startup"): False, ("law", "damping"): False}
    bench.say("uncompensated (gravity only): moving each joint at ±10°/s ...")
    with bench.rig("effort-gravity-only", gravity_only) as rig:
        base = _efforts(bench, rig, joints, move_s)
    bench.say("drag mode: moving each joint at ±10°/s, then release and watch ...")
    drift: dict[int, float] = {}
    with bench.rig("effort-drag") as rig:
        comp = _efforts(bench, rig, joints, move_s)
        for j in joints:  # move at 10°/s, stop the arm by hand, let go, watch 5 s
            name = bench.cfg.joints[j].name
            rig.sim_call("operator", scenario={"name": f"place_{name}", "segments": [
                {"kind": "move", "joint": name, "velocity_rad_s": SPEED_RAD_S, "duration_s": 1.0},
                {"kind": "move", "joint": name, "velocity_rad_s": 0.0, "duration_s": 0.6},
                {"kind": "release", "duration_s": 0.0}]})
            rig.wait_for(lambda: rig.sim_call("operator_events").get("done", False), 10.0, f"{name} placed")
            q0 = np.array(rig.must("status")["q_rad"])
            rig.sleep(observe_s)
            q1 = np.array(rig.must("status")["q_rad"])
            drift[j] = float(np.degrees(np.abs(q1 - q0)).max())
        guard_trips = int(rig.must("status")["guard"]["trips"])  # the hand's moves are not runaways: 0 expected
    result: dict[str, Any] = {"joints": {}, "guard_trips": guard_trips}
    for j in joints:
        result["joints"][bench.cfg.joints[j].name] = {
            "effort_uncompensated_Nm": round(base[j], 4),
            "effort_compensated_Nm": round(comp[j], 4),
            "effort_pct": round(100.0 * comp[j] / base[j], 2) if base[j] > 0 else None,
            "drift_after_release_deg": round(drift[j], 4),
        }
    result["max_effort_pct"] = max(v["effort_pct"] for v in result["joints"].values())
    result["max_drift_after_release_deg"] = max(v["drift_after_release_deg"] for v in result["joints"].values())
    return result
