"""The bridge's translations without ROS (dragd/ros2/convert.py): joint order, trajectories, names, diagnostics."""

from __future__ import annotations

import math

import pytest

from dragd.ros2 import convert

pytestmark = pytest.mark.unit

J = ["joint1", "joint2", "joint3"]


def test_order_by_name_and_every_mistake_named_at_once():
    assert convert.order(["joint3", "joint1", "joint2"], [3.0, 1.0, 2.0], J, "x") == [1.0, 2.0, 3.0]
    with pytest.raises(ValueError) as e:
        convert.order(["joint1", "joint1", "wrist"], [0.0, 0.0, 0.0], J, "cmd")
    text = str(e.value)
    assert "unknown joint(s) wrist" in text and "named twice joint1" in text and "missing joint(s) joint2, joint3" \
        in text and text.startswith("cmd:")
    with pytest.raises(ValueError, match="2 names but 3 positions"):
        convert.order(["joint1", "joint2"], [0, 0, 0], J, "cmd")
    with pytest.raises(ValueError, match="positions of joint2 are not finite"):
        convert.order(J, [0.0, math.nan, 0.0], J, "cmd")


def test_trajectory_samples_as_joint_trajectory_controller_reads_them():
    pts = [(1.0, [0.1, 0.2, 0.3]), (2.0, [0.2, 0.3, 0.4])]
    t, q = convert.trajectory_samples(J, pts, J, [0.0, 0.0, 0.0])
    assert t == [0.0, 1.0, 2.0] and q[0] == [0.0, 0.0, 0.0]  # reached from where the arm is
    t, q = convert.trajectory_samples(list(reversed(J)), [(0.0, [3, 2, 1]), (1.0, [3, 2, 0])], J, None)
    assert t == [0.0, 1.0] and q == [[1, 2, 3], [0, 2, 3]]
    for pts, match in [([], "no points"), ([(1.0, [0, 0, 0]), (1.0, [0, 0, 0])], "increase strictly"),
                       ([(-1.0, [0, 0, 0])], ">= 0"), ([(0.0, [0, 0, 0])], "single point")]:
        with pytest.raises(ValueError, match=match):
            convert.trajectory_samples(J, pts, J, [0, 0, 0])
    with pytest.raises(ValueError, match="not known yet"):
        convert.trajectory_samples(J, [(1.0, [0, 0, 0])], J, None)


def test_service_names():
    assert convert.service_name("pick-and-place v2") == "pick_and_place_v2"
    assert convert.service_name("2nd") == "p_2nd" and convert.service_name("---") == "program"


def test_diagnostics_levels():
    status = {"mode": "fault", "cycles": 10, "missed_cycles": 0, "period_p99_us": 1010.0,
              "faults": [{"t_s": 1.0, "joint": "joint2", "text": "EMCY 0x8130"}], "fault_count": 1,
              "bus_load_pct": {"arm": 52.2}, "comms": {"outage": False}, "drives": [
                  {"joint": "joint1", "node_id": 1, "state": "FAULT", "stale_cycles": 0}]}
    got = {name: (lv, msg, dict(kv)) for lv, name, msg, kv in convert.diagnostics(status, {"daemon": True})}
    assert got["dragd: faults"][0] == convert.ERROR and got["dragd: faults"][1] == "EMCY 0x8130"
    assert got["dragd: drives"][0] == convert.ERROR and got["dragd: bus arm"][0] == convert.OK
    assert got["dragd: ros2 bridge"][0] == convert.OK
    gone = {name: lv for lv, name, _m, _kv in convert.diagnostics({"mode": None}, {"daemon": False})}
    assert gone["dragd: ros2 bridge"] == convert.ERROR
