"""Issue #13 item 6: ``identify fit --method auto`` recognises seed 000's experiment (one joint, one constant
speed each way) and applies seed 000's model — Coulomb = the current level at the test speed, gravity removed.

The log comes from an independent generator written here from the equations (not the simulator): a trapezoid
velocity profile on one joint, i = G(q)/K_t + F_c,d + F_v·q̇ + noise, the other joints still."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dragd.model import RobotModel

from conftest import run_cli

pytestmark = pytest.mark.unit

KT = 0.12  # A per N·m⁻¹: joint-side N·m/A
FC = (0.45, -0.38)  # A, Coulomb per direction
FV = 0.8  # A·s/rad
SPEED = 0.03  # rad/s, the test speed (≈ 1.7°/s, seed 000's "low speed")


def seed000_log(path, joint: int = 1, half_s: float = 20.0, ramp_s: float = 0.2, cycles: int = 2,
                rate: float = 500.0, noise_A: float = 0.02, seed: int = 0) -> None:
    t = np.arange(0.0, 2.0 * half_s * cycles + 2.0, 1.0 / rate)
    tau = t - 1.0  # 1 s at rest at each end
    g = half_s / 2 - np.abs(np.mod(tau + half_s / 2, 2 * half_s) - half_s)  # triangle wave, slope ±1, zeros at k·half
    v = np.where((tau >= 0) & (tau <= 2 * half_s * cycles), SPEED * np.clip(g / (ramp_s / 2), -1.0, 1.0), 0.0)
    q = np.tile([0.0, -0.6, 1.0, 0.0, 0.5, 0.0], (t.size, 1))
    q[:, joint] += np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) / rate)])
    m = RobotModel.from_urdf("seed_cobot")
    i = np.array([m.gravity(x) for x in q]) / KT
    i[:, joint] += np.where(v > 0, FC[0], np.where(v < 0, FC[1], 0.0)) + FV * v
    i += np.random.default_rng(seed).normal(0.0, noise_A, i.shape)
    cols = ["t"] + [f"q{k}" for k in range(1, 7)] + [f"i{k}" for k in range(1, 7)]
    np.savetxt(path, np.column_stack([t, q, i]), delimiter=",", header=",".join(cols), comments="")


def test_auto_recognises_seed000_experiment_and_gives_both_coulomb_levels(tmp_path):
    log = tmp_path / "seed000.csv"
    seed000_log(log)
    out = json.loads(run_cli("identify", "fit", "--robot", "seed_cobot", "--log", str(log), "--out",
                             str(tmp_path / "p.yaml"), "--json").stdout)
    assert out["method"] == "auto"
    j2 = out["joints"]["joint2"]
    level = {"pos": FC[0] + FV * SPEED, "neg": FC[1] - FV * SPEED}  # seed 000: the level at the test speed
    for d in ("pos", "neg"):
        got = j2["friction"][f"coulomb_{d}_A"]
        assert got is not None and abs(got - level[d]) < 0.03 * abs(level[d]), (d, got, level[d])
    assert abs(j2["torque_constant_Nm_per_A"] - KT) < 0.02 * KT
    assert j2["friction"]["viscous_A_s_per_rad"] is None and "seed 000's model" in j2["reasons"]["viscous_A_s_per_rad"]
    note = out["notes"]["auto"]
    assert "seed-000 experiment recognised: one joint (joint2), one speed each way; Coulomb = level at 0.03 rad/s" \
        in note, note
    text = run_cli("identify", "fit", "--robot", "seed_cobot", "--log", str(log), "--out", str(tmp_path / "q.yaml"))
    assert "auto: seed-000 experiment recognised" in text.stdout


def test_auto_keeps_coulomb_and_viscous_apart_with_two_speeds(tmp_path):
    """Not seed 000's experiment (two joints move): the quasi-static model, no seed-000 note."""
    log = tmp_path / "two.csv"
    seed000_log(log)
    data = np.loadtxt(log, delimiter=",", skiprows=1)
    data[:, 1 + 4] += 0.2 * np.sin(2 * np.pi * 0.05 * data[:, 0])  # joint 5 moves too
    np.savetxt(log, data, delimiter=",", header=open(log).readline().strip(), comments="")
    out = json.loads(run_cli("identify", "fit", "--robot", "seed_cobot", "--log", str(log), "--out",
                             str(tmp_path / "p.yaml"), "--json").stdout)
    assert "seed-000" not in out["notes"].get("auto", "")
