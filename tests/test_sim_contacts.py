"""The simulator's contacts (sim/operator.py ``strike`` and ``obstacle``): the joint torques are Jᵀ of the force at
the struck point, the profile is the one asked for, the operator's Cartesian force (its truth) is recorded every ms.
The daemon's detector against them: tests/test_contact_daemon.py."""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import pytest

from dragd.model import RobotModel
from sim.operator import Operator, ScenarioError

pytestmark = pytest.mark.unit

Q = np.array([0.1, -0.6, 1.2, -0.6, 1.5708, 0.0])


def _point(rm: RobotModel, q: np.ndarray, link: str, p: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    m, d = rm.model, rm.data
    fid = m.getFrameId(link)
    pin.computeJointJacobians(m, d, q)
    pin.framesForwardKinematics(m, d, q)
    M = d.oMf[fid]
    at = M.translation + M.rotation @ np.asarray(p)
    placed = pin.SE3(np.eye(3), M.rotation.T @ (at - M.translation))
    m2 = m.copy()
    f2 = m2.addFrame(pin.Frame("pt", m.frames[fid].parentJoint, fid, m.frames[fid].placement * placed,
                               pin.FrameType.OP_FRAME))
    d2 = m2.createData()
    J = pin.computeFrameJacobian(m2, d2, q, f2, pin.LOCAL_WORLD_ALIGNED)
    return J[:3], at


def test_a_strike_is_the_jacobian_transpose_of_its_force_profile_and_its_truth_is_recorded():
    rm = RobotModel.from_urdf("seed_cobot")
    seg = {"kind": "strike", "link": "link3", "point_m": [0.0, 0.0, 0.15], "direction": [0.0, 3.0, 4.0], "peak_N": 60.0,
           "profile": "half_sine", "duration_s": 0.1}
    op = Operator({"segments": [seg]}, rm, 0.0)
    Jp, at = _point(rm, Q, "link3", (0.0, 0.0, 0.15))
    out = np.zeros(6)
    peak = 0.0
    for k in range(0, 121):
        t = k * 1e-3
        op.apply(t, Q, np.zeros(6), out)
        f = 60.0 * math.sin(math.pi * t / 0.1) if t < 0.1 else 0.0
        want = Jp.T @ (f * np.array([0.0, 0.6, 0.8]))
        np.testing.assert_allclose(out, want, atol=1e-9)
        peak = max(peak, f)
    ev = [e for e in op.events if e["kind"] in ("strike", "strike_end")]
    assert [e["kind"] for e in ev] == ["strike", "strike_end"] and ev[0]["t"] == 0.0
    end = ev[1]
    assert end["peak_N"] == pytest.approx(60.0, abs=0.01) and end["t"] == pytest.approx(0.1, abs=1e-3)
    tr = op.trace()
    t = np.array(tr["t_s"])
    f = np.array(tr["force_N"], dtype=float)
    assert np.allclose(np.diff(t), 1e-3) and len(t) == 121
    np.testing.assert_allclose(f[50], 60.0 * np.array([0.0, 0.6, 0.8]), atol=1e-9)  # the peak at 50 ms
    np.testing.assert_allclose(np.array(tr["at_m"], dtype=float)[50], at, atol=1e-9)
    assert np.isnan(f[-1]).all()  # after the last segment: no load known


def test_a_trapezoid_rises_holds_and_falls():
    rm = RobotModel.from_urdf("seed_cobot")
    op = Operator({"segments": [{"kind": "strike", "link": "link2", "direction": [1.0, 0.0, 0.0], "peak_N": 40.0,
                                 "profile": "trapezoid", "rise_s": 0.2, "hold_s": 0.5, "fall_s": 0.2}]}, rm, 0.0)
    out = np.zeros(6)
    got = []
    for k in range(0, 1000, 50):
        op.apply(k * 1e-3, Q, np.zeros(6), out)
        got.append(op.force_N[0] if op._force_known else 0.0)
    assert got[2] == pytest.approx(20.0) and got[4] == pytest.approx(40.0) and got[10] == pytest.approx(40.0)
    assert got[16] == pytest.approx(20.0) and got[19] == 0.0


def test_an_obstacle_pushes_only_while_a_link_point_is_inside_it():
    rm = RobotModel.from_urdf("seed_cobot")
    _, at = _point(rm, Q, "link3", (0.0, 0.0, 0.15))
    plane = at + np.array([0.0, 0.0, -0.01])  # 1 cm below the point, normal up
    op = Operator({"segments": [{"kind": "obstacle", "link": "link3", "link_point_m": [0.0, 0.0, 0.15],
                                 "point_m": plane.tolist(), "normal": [0.0, 0.0, 1.0], "stiffness_N_m": 20000.0,
                                 "damping_N_s_m": 0.0, "duration_s": 1.0}]}, rm, 0.0)
    out = np.zeros(6)
    op.apply(0.0, Q, np.zeros(6), out)
    assert not out.any() and not any(e["kind"] == "obstacle_contact" for e in op.events)
    # move the arm down into it: joint 2 forward until the point is 5 mm inside
    q = Q.copy()
    for _ in range(200):
        Jp, p = _point(rm, q, "link3", (0.0, 0.0, 0.15))
        if p[2] < plane[2] - 0.005:
            break
        q[1] += 0.002 * np.sign(-Jp[2, 1])
    Jp, p = _point(rm, q, "link3", (0.0, 0.0, 0.15))
    depth = plane[2] - p[2]
    assert depth > 0.004
    op.apply(0.1, q, np.zeros(6), out)
    np.testing.assert_allclose(out, Jp.T @ np.array([0.0, 0.0, 20000.0 * depth]), rtol=1e-9, atol=1e-9)
    assert any(e["kind"] == "obstacle_contact" for e in op.events)
    op.apply(1.1, q, np.zeros(6), out)
    end = [e for e in op.events if e["kind"] == "obstacle_end"][0]
    assert end["touched"] and end["depth_m"] == pytest.approx(depth, abs=1e-5)


def test_a_strike_on_an_unknown_link_is_named():
    rm = RobotModel.from_urdf("seed_cobot")
    with pytest.raises(ScenarioError,
                       match=r"segments\[0\]\.strike\.link: expected a link \(frame\) of the robot, got"):
        Operator({"segments": [{"kind": "strike", "link": "arm9", "direction": [1, 0, 0], "peak_N": 10.0}]}, rm, 0.0)
