"""Any N-joint arm: a 3-joint URDF and a synthetic CSV (current = RNEA/K_t + friction + Hall noise) through the CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dragd.model import RobotModel

from conftest import run_cli

pytestmark = pytest.mark.unit

URDF = """<?xml version="1.0"?>
<robot name="three">
  <link name="base"/>
  <joint name="a1" type="revolute"><parent link="base"/><child link="l1"/><origin xyz="0 0 0.2"/>
    <axis xyz="0 1 0"/><limit lower="-3" upper="3" effort="100" velocity="2"/></joint>
  <link name="l1"><inertial><origin xyz="0.2 0 0"/><mass value="4"/>
    <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.06" iyz="0" izz="0.06"/></inertial></link>
  <joint name="a2" type="revolute"><parent link="l1"/><child link="l2"/><origin xyz="0.4 0 0"/>
    <axis xyz="0 1 0"/><limit lower="-3" upper="3" effort="100" velocity="2"/></joint>
  <link name="l2"><inertial><origin xyz="0.15 0 0.01"/><mass value="2"/>
    <inertia ixx="0.005" ixy="0" ixz="0" iyy="0.02" iyz="0" izz="0.02"/></inertial></link>
  <joint name="a3" type="revolute"><parent link="l2"/><child link="l3"/><origin xyz="0.3 0 0"/>
    <axis xyz="1 0 0"/><limit lower="-3" upper="3" effort="50" velocity="2"/></joint>
  <link name="l3"><inertial><origin xyz="0 0 0"/><mass value="0.5"/>
    <inertia ixx="0.001" ixy="0" ixz="0" iyy="0.001" iyz="0" izz="0.001"/></inertial></link>
</robot>
"""

KT = np.array([6.0, 5.0, 3.0])
FC_POS, FC_NEG = np.array([0.40, 0.30, 0.20]), np.array([-0.35, -0.28, -0.18])
FV = np.array([0.30, 0.25, 0.10])


def _trapezoid(t, lo, hi, v, a, phase):
    """Back-and-forth at constant speed v between lo and hi with accelerations a (period from the geometry)."""
    d = hi - lo
    tb = v / a
    T = d / v + tb
    u = np.mod(t + phase, 2 * T)
    s = np.where(u < T, u, 2 * T - u)
    pos = np.where(s < tb, 0.5 * a * s**2, np.where(s > T - tb, d - 0.5 * a * (T - s) ** 2, v * (s - tb / 2)))
    return lo + pos


def test_three_joint_arm_from_csv(tmp_path):
    urdf = tmp_path / "three.urdf"
    urdf.write_text(URDF)
    robot = RobotModel.from_urdf(urdf)
    rng = np.random.default_rng(1)
    t = np.arange(0.0, 240.0, 0.002)
    q = np.column_stack([_trapezoid(t, -1.2, 0.8, 0.25, 1.0, 0.0), _trapezoid(t, -0.5, 1.5, 0.4, 1.0, 3.0),
                         _trapezoid(t, -1.0, 1.0, 0.3, 1.0, 1.0)])
    # speed changes every 60 s (several speed levels: viscous separable from Coulomb)
    for k, f in enumerate((1.0, 0.5, 1.5, 0.8)):
        m = (t >= 60 * k) & (t < 60 * (k + 1))
        q[m] = np.column_stack([_trapezoid(t[m] * f, -1.2, 0.8, 0.25, 1.0, 0.0),
                                _trapezoid(t[m] * f, -0.5, 1.5, 0.4, 1.0, 3.0),
                                _trapezoid(t[m] * f, -1.0, 1.0, 0.3, 1.0, 1.0)])
    dq = np.gradient(q, t, axis=0)
    ddq = np.gradient(dq, t, axis=0)
    tau = np.array([robot.inverse_dynamics(q[k], dq[k], ddq[k]) for k in range(t.size)])
    fr = np.where(dq > 1e-6, FC_POS + FV * dq, np.where(dq < -1e-6, FC_NEG + FV * dq, 0.0))
    i = tau / KT + fr + rng.normal(0.0, 0.02, tau.shape)
    cols = ["t", "q1", "q2", "q3", "i1", "i2", "i3"]
    np.savetxt(tmp_path / "log.csv", np.column_stack([t, q, i]), delimiter=",", header=",".join(cols), comments="")
    out = tmp_path / "p.yaml"
    d = json.loads(run_cli("identify", "fit", "--log", str(tmp_path / "log.csv"), "--robot", str(urdf),
                           "--method", "synchronous", "--out", str(out), "--json").stdout)
    assert list(d["joints"]) == ["a1", "a2", "a3"]
    for k, name in enumerate(("a1", "a2")):
        j = d["joints"][name]
        assert abs(j["torque_constant_Nm_per_A"] - KT[k]) / KT[k] < 0.01
        assert abs(j["friction"]["coulomb_pos_A"] - FC_POS[k]) < 0.01
        assert abs(j["friction"]["coulomb_neg_A"] - FC_NEG[k]) < 0.01
        assert abs(j["friction"]["viscous_A_s_per_rad"] - FV[k]) / FV[k] < 0.1
    # joint a3 rolls about the link's own axis with its mass on it: no gravity torque, K_t null with the reason
    a3 = d["joints"]["a3"]
    assert a3["torque_constant_Nm_per_A"] is None and a3["reasons"]["torque_constant_Nm_per_A"]
    assert abs(a3["friction"]["coulomb_pos_A"] - FC_POS[2]) < 0.01
    chk = json.loads(run_cli("identify", "check", "--params", str(out), "--log", str(tmp_path / "log.csv"),
                             "--robot", str(urdf), "--json").stdout)
    assert chk["joints"]["a1"]["rmse_A"] < 0.025 and chk["joints"]["a3"]["rmse_A"] is None  # K_t unknown, no config
