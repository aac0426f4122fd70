"""The contact detector in the daemon (docs/CONTACT.md), on the lockstep clock: the simulator's operator strikes and
pushes the arm with a force it knows (its truth), the daemon must notice, react as configured and say what happened.

The bands are calibrated the way a user does it (dragd/lab/demo_contact.py, the contact demo's first session): a
free-motion run of the simulated arm recorded, then ``dragd contact calibrate`` on it — once per source tree, shared
with tests/test_contact_daemon_runs.py (tests/contact_helpers.py). Every test then runs the daemon with them. (The
demo itself, with its figures: ``dragd demo --scenario contact``.)
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from contact_helpers import calibration, contact_rig

from dragd.config import load_config
from dragd.lab.demo_contact import (
    IMPACT_N,
    STRIKE_LINK,
    STRIKE_POINT_M,
    Clocks,
    head_on,
    point_position,
    strike_figures,
    strike_info,
)
from dragd.lab.rig import Rig
from dragd.model import RobotModel
from dragd.telemetry.reader import read_rows

# a hang guard: the first test of either contact module may wait for the calibration session (tests/contact_helpers.py:
# a minute and a half of simulated arm, 12 minutes at load 20 on 2 cores), made by the other module's worker, before
# its own run
pytestmark = [pytest.mark.lockstep, pytest.mark.timeout(1800)]

Q_TRACK = np.array([0.5, 0.3, -0.4, 0.4, 0.3, 0.5])  # a motion's excursion from the start pose [rad]


@pytest.fixture(scope="module")
def bands() -> Path:
    return calibration()[0]


@pytest.fixture(scope="module")
def model() -> RobotModel:
    return RobotModel.from_urdf("seed_cobot")


_rig = contact_rig


def _strike(rig: Rig, direction: list[float], peak_N: float = IMPACT_N, **profile: object) -> None:
    seg = {"kind": "strike", "link": STRIKE_LINK, "point_m": list(STRIKE_POINT_M), "direction": direction,
           "peak_N": peak_N, **(profile or {"profile": "half_sine", "duration_s": 0.1})}
    rig.sim_call("operator", scenario={"name": "strike", "segments": [seg, {"kind": "release", "duration_s": 0.0}]})


def _track(rig: Rig, tmp_path: Path, seconds: float = 4.0, label: str = "track") -> float:
    q0 = np.array(rig.must("status")["q_rad"])
    t = np.linspace(0.0, seconds, int(seconds * 50) + 1)
    q = q0 + np.outer((1 - np.cos(2 * np.pi * t / seconds)) / 2, Q_TRACK)
    np.savez(tmp_path / "m.npz", t_s=t, q_rad=q)
    return float(rig.must("track", file=str(tmp_path / "m.npz"), label=label)["duration_s"])


def test_status_shows_the_calibrated_bands_sensitivity_and_reaction_of_every_mode(tmp_path, bands):
    rig = _rig(tmp_path, bands, {"hold": "retract", "track": "stop", "identify": "compliant"},
               hold={"sensitivity": 2.0, "reaction": "retract"})
    with rig:
        rig.sleep(1.0)
        st = rig.must("status")["contact"]
        rig.must("stop")
    assert st["calibrated"] and st["watching"] == "hold" and st["armed"] and st["reason"] is None
    assert st["modes"]["hold"] == {"sensitivity": 2.0, "reaction": "retract"}
    assert st["modes"]["identify"]["reaction"] == "compliant" and st["modes"]["track"]["sensitivity"] == 1.0
    cal = load_config(tmp_path / "contact-config.yaml").contact_calibration
    for nm, b in st["bands_A"].items():
        assert b["held_A"] == pytest.approx(cal.joints[nm].held_A)
    assert st["thresholds_A"]["hold"] == pytest.approx([x / 2.0 for x in st["thresholds_A"]["track"]], abs=1e-4)
    assert len(st["residual_A"]) == 6 and st["ratio_max"] < 1.0 and st["onsets"] == 0
    assert st["states"] == ["held"] * 6  # at rest > 0.3 s, residual still: held against the latched baseline


def test_impact_during_a_motion_is_detected_within_30_ms_and_the_arm_stops_within_100_ms(tmp_path, bands, model):
    with _rig(tmp_path, bands) as rig:
        clocks = Clocks(rig)
        duration = _track(rig, tmp_path)
        rig.sleep(0.45 * duration)
        assert rig.must("status")["contact"]["onsets"] == 0  # the motion itself raised nothing
        _strike(rig, head_on(rig, model))
        rig.wait_for(lambda: rig.must("status")["mode"] == "hold", 2.0, "the protective stop")
        rig.sleep(0.5)
        res = strike_info(rig, clocks, 0, "impact during track")
        st = rig.must("status")
        rig.must("stop")
    assert res["detected"] and res["alarms"] == 1, res
    f = [x for x in st["faults"] if x.get("kind") == "contact"][0]
    # the fault entry: the joints, their residual and the estimated contact torque, what the arm did
    assert f["reaction"] == "hold" and f["mode"] == "track" and set(f["joints"]) <= set(load_config().joint_names)
    assert len(f["residual_A"]) == len(f["joints"]) == len(f["contact_Nm"]) > 0 and max(f["contact_Nm"]) > 0.0
    # the stop ends the motion and with it the event the motion's bands judged; its end and peaks are recorded
    assert f["t_end_s"] is not None and max(f["peak_Nm"]) >= max(f["contact_Nm"]) - 0.01
    assert "contact in track" in f["text"] and "N·m" in f["text"]
    figures = strike_figures(dict(res), read_rows(tmp_path / "t.mcap", ["t_s", "q_rad", "dq_rad_s"]), model)
    assert 0.0 < res["delay_ms"] <= 30.0, res
    # the protective stop: from the arm's state to rest within the stop's bounds, held against the rest of the impact
    # (~70 ms of it after the detection): every joint below 0.01 rad/s, and staying so, within 100 ms
    assert 0.0 < f["stop_s"] <= 0.1, f
    assert figures["stopped_after_ms"] is not None and figures["stopped_after_ms"] <= 100.0, figures
    assert figures["stop_distance_mm"] < 30.0, figures
    # then held where it came to rest (no spring back toward the path)
    after = _rows_between(tmp_path / "t.mcap", res["t_detect_s"] + 0.3, st["t_s"])
    assert (after["mode"] == "hold").all()
    assert np.abs(after["q_rad"] - after["q_rad"][0]).max() < 1e-3


def _rows_between(mcap: Path, t_s: float, until_s: float) -> dict[str, np.ndarray]:
    """Telemetry rows from ``t_s`` to ``until_s`` (before the test's own stop)."""
    rows = read_rows(mcap, ["t_s", "q_rad", "q_ref_rad", "mode"])
    k, m = int(np.searchsorted(rows["t_s"], t_s)), int(np.searchsorted(rows["t_s"], until_s, side="right"))
    return {name: v[k:m] for name, v in rows.items()}


def test_push_on_the_held_arm_stops_it_where_it_is(tmp_path, bands, model):
    with _rig(tmp_path, bands) as rig:
        clocks = Clocks(rig)
        rig.sleep(1.5)
        _strike(rig, [0.0, 0.0, -1.0], 40.0, profile="trapezoid", rise_s=0.2, hold_s=0.5, fall_s=0.2)
        rig.sleep(1.5)
        res = strike_info(rig, clocks, 0, "push on the held arm")
        st = rig.must("status")
        rig.must("stop")
    assert res["detected"] and res["alarms"] == 1 and res["reaction"] == "hold", res
    assert res["delay_ms"] < 200.0, res  # while the push still rises (over 0.2 s)
    assert st["mode"] == "hold" and st["contact"]["last_event"]["mode"] == "hold"
    # the hold's pose is the one the detection found (it no longer springs back into the contact) and stays so
    after = _rows_between(tmp_path / "t.mcap", res["t_detect_s"], st["t_s"])
    assert (after["mode"] == "hold").all()
    np.testing.assert_allclose(after["q_ref_rad"], np.tile(after["q_rad"][0], (len(after["q_rad"]), 1)), atol=1e-9)


def test_retract_backs_off_a_bounded_distance_along_the_contact(tmp_path, bands, model):
    with _rig(tmp_path, bands, {"hold": "retract"}, retract_rad=0.03) as rig:
        clocks = Clocks(rig)
        rig.sleep(1.5)
        down = [0.0, 0.0, -1.0]
        _strike(rig, down, 40.0, profile="trapezoid", rise_s=0.2, hold_s=0.3, fall_s=0.05)
        rig.sleep(2.0)
        res = strike_info(rig, clocks, 0, "push, retract")
        st = rig.must("status")
        rig.must("stop")
    assert res["detected"] and res["reaction"] == "retract", res
    assert st["mode"] == "hold"
    after = _rows_between(tmp_path / "t.mcap", res["t_detect_s"], st["t_s"])
    q_det, target = after["q_rad"][0], after["q_ref_rad"][-1]
    assert np.abs(target - q_det).max() == pytest.approx(0.03, abs=1e-9)  # the hold pose backed off retract_rad ...
    step = np.abs(np.diff(after["q_ref_rad"], axis=0)).max()
    assert step <= 0.15 * 1e-3 + 1e-12  # ... at retract_speed_rad_s (0.15 rad/s)
    moved = point_position(model, target) - point_position(model, q_det)
    assert float(np.dot(moved, down)) > 0.0  # the struck point backs off the way the contact pushed it


def test_compliant_reaction_hands_the_arm_to_drag(tmp_path, bands, model):
    with _rig(tmp_path, bands, {"track": "compliant"}) as rig:
        duration = _track(rig, tmp_path)
        rig.sleep(0.45 * duration)
        _strike(rig, head_on(rig, model))
        rig.wait_for(lambda: rig.must("status")["mode"] == "drag", 2.0, "drag after the contact")
        st = rig.must("status")
        rig.must("stop")
    f = [x for x in st["faults"] if x.get("kind") == "contact"][0]
    assert f["reaction"] == "drag" and st["guard"]["trips"] == 0


def test_an_obstacle_in_the_path_of_a_motion_stops_it_and_the_retract_frees_the_arm(tmp_path, bands, model):
    """The simulator's obstacle (sim/operator.py ``obstacle``): a plane across the forearm's path. The daemon must find
    the contact while the arm presses into it, stop the motion (a protective stop) and, with ``retract``, back the arm
    out of it: the force the obstacle feels stays below ISO/TS 15066's quasi-static limit for the forearm (160 N) and
    ends at zero."""
    seconds = 4.0
    with _rig(tmp_path, bands, {"track": "retract"}, retract_rad=0.03) as rig:
        clocks = Clocks(rig)
        q0 = np.array(rig.must("status")["q_rad"])
        # where the forearm's point will be 0.3 of the way through the motion, and which way it moves there
        x = 0.3
        q1 = q0 + (1 - math.cos(2 * math.pi * x)) / 2 * Q_TRACK
        dq1 = math.pi * math.sin(2 * math.pi * x) / seconds * Q_TRACK
        p1 = point_position(model, q1)
        ahead = point_position(model, q1 + 1e-3 * dq1) - p1
        normal = -ahead / np.linalg.norm(ahead)  # the plane faces the arm coming at it
        rig.sim_call("operator", scenario={"name": "obstacle", "segments": [
            {"kind": "obstacle", "link": STRIKE_LINK, "link_point_m": list(STRIKE_POINT_M), "point_m": p1.tolist(),
             "normal": normal.tolist(), "duration_s": 8.0}, {"kind": "release", "duration_s": 0.0}]})
        t0 = rig.sim_call("state")["t"]
        _track(rig, tmp_path, seconds)
        rig.wait_for(lambda: rig.must("status")["mode"] == "hold", seconds + 2.0, "the protective stop")
        rig.sleep(1.5)  # the retract (0.03 rad at 0.15 rad/s)
        st = rig.must("status")
        trace = rig.sim_call("operator_trace", timeout_s=30.0, since_t_s=t0)
        ev = rig.sim_call("operator_events")["events"]
        rig.must("stop")
    touch = [e for e in ev if e["kind"] == "obstacle_contact"]
    assert touch, ev  # the arm ran into it
    faults = [f for f in st["faults"] if f.get("kind") == "contact"]
    assert faults and faults[0]["mode"] == "track" and faults[0]["reaction"] == "retract", st["faults"]
    delay_ms = 1000.0 * (float(faults[0].get("t_start_s") or faults[0]["t_s"]) - clocks.to_daemon(touch[0]["t"]))
    assert 0.0 < delay_ms <= 100.0, (delay_ms, faults[0])
    assert st["mode"] == "hold" and st["trajectory"] is None
    assert (st.get("replay") or {}).get("outcome") is None  # (a track, not a replay)
    t_tr = np.array(trace["t_s"])
    force = np.linalg.norm(np.nan_to_num(np.array(trace["force_N"], dtype=float)), axis=1)
    assert force.size and float(force.max()) > 0.0  # (the trace covers the contact)
    assert float(force.max()) < 160.0, force.max()
    assert float(force[t_tr >= t_tr[-1] - 0.2].max()) == 0.0  # backed out of the obstacle: no force left
