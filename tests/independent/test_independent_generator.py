"""Checks of the independent log generator itself (no dragd run): determinism, file formats, trajectories inside
their envelope and consistent (q, q̇, q̈), and the physics against hand-computed values (gravity at rest, a payload's
static torque via the Jacobian, an offset, a belief error that must leave the log alone)."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))

import generator as g  # noqa: E402

pytestmark = pytest.mark.unit


def _load(path: Path) -> tuple[list[str], np.ndarray]:
    header = path.read_text().splitlines()[0].split(",")
    return header, np.loadtxt(path, delimiter=",", skiprows=1)


def _resting(d: np.ndarray, k: int = 3) -> np.ndarray:
    """Rows where every joint's (quantised) position is the same for ± k samples: the arm rests."""
    q = d[:, 1:7]
    same = np.all(q[1:] == q[:-1], axis=1)
    out = np.zeros(q.shape[0], bool)
    for r in range(k, q.shape[0] - k):
        out[r] = same[r - k:r + k].all()
    return out


def _spec(**kw) -> g.CaseSpec:
    base = dict(case_id="t", excitation="ptp", rate_Hz=100, duration_s=12.0, noise_A=0.0, seed=4)
    base.update(kw)
    return g.CaseSpec(**base)


def test_deterministic_by_seed(tmp_path: Path) -> None:
    s = _spec(noise_A=0.02)
    g.generate(s, tmp_path / "a")
    g.generate(s, tmp_path / "b")
    g.generate(_spec(noise_A=0.02, seed=5), tmp_path / "c")
    assert (tmp_path / "a/log.csv").read_bytes() == (tmp_path / "b/log.csv").read_bytes()
    assert (tmp_path / "a/log.csv").read_bytes() != (tmp_path / "c/log.csv").read_bytes()


@pytest.mark.parametrize("with_dq", [True, False])
def test_csv_format_and_rate(tmp_path: Path, with_dq: bool) -> None:
    g.generate(_spec(rate_Hz=250, with_dq=with_dq), tmp_path)
    header, d = _load(tmp_path / "log.csv")
    want = ["t"] + [f"q{k}" for k in range(1, 7)] + [f"i{k}" for k in range(1, 7)]
    assert header == want + ([f"dq{k}" for k in range(1, 7)] if with_dq else [])
    assert np.allclose(np.diff(d[:, 0]), 1 / 250)
    pf = yaml.safe_load((tmp_path / "belief.yaml").read_text())
    assert pf["version"] == 1 and set(pf["joints"]) == {f"joint{k}" for k in range(1, 7)}


@pytest.mark.parametrize("kind", g.EXCITATIONS)
def test_trajectories_in_envelope_and_consistent(kind: str) -> None:
    r = g.seed_cobot()
    m = g.build_motion(kind, r, 40.0, np.random.default_rng(1), (1, 2))
    home, exc = np.array(r.home_rad), np.array(r.excursion_rad)
    assert np.all(m.q >= home - exc - 0.1) and np.all(m.q <= home + exc + 0.1)
    assert np.all(np.abs(m.dq) <= np.array(r.speed_rad_s) + 1e-9)
    dt = 1.0 / g.GRID_HZ
    assert np.abs(np.gradient(m.q, dt, axis=0) - m.dq)[2:-2].max() < 2e-3
    assert np.abs(np.gradient(m.dq, dt, axis=0) - m.ddq)[2:-2].max() < 2e-2


def test_rest_current_is_gravity_over_kt(tmp_path: Path) -> None:
    """At rest the friction current is 0 and the current is G(q)/K_t (noise off; per-mille quantum 4/2 mA)."""
    info = g.generate(_spec(), tmp_path)
    _, d = _load(tmp_path / "log.csv")
    q, i = d[:, 1:7], d[:, 7:13]
    rest = _resting(d)
    assert rest.sum() > 50
    model = pin.buildModelFromUrdf(str(g.SEED_COBOT_URDF))
    data = model.createData()
    kt = np.array([info["truth_joints"][f"joint{k}"]["kt_Nm_per_A"] for k in range(1, 7)])
    for k in np.nonzero(rest)[0][::10]:
        G = pin.computeGeneralizedGravity(model, data, q[k])
        assert np.allclose(i[k], G / kt, atol=2.5e-3)


def test_payload_static_torque_matches_jacobian(tmp_path: Path) -> None:
    """The payload's extra current at rest equals −Jᵀ·m·g at its centre / K_t (computed here independently)."""
    eff = g.Payload(mass_kg=2.0, com_flange_m=(0.0, 0.0, 0.06), radius_m=0.04)
    g.generate(_spec(), tmp_path / "clean")
    g.generate(_spec(effects=(eff,)), tmp_path / "payload")
    _, a = _load(tmp_path / "clean/log.csv")
    _, b = _load(tmp_path / "payload/log.csv")
    model = pin.buildModelFromUrdf(str(g.SEED_COBOT_URDF))
    data = model.createData()
    fid = model.getFrameId("flange")
    kt = np.array([jt.kt_Nm_per_A for jt in g.seed_cobot().joints])
    rest = np.nonzero(_resting(a))[0][::25]
    assert rest.size > 5
    for k in rest:
        q = a[k, 1:7]
        pin.framesForwardKinematics(model, data, q)
        p_flange = data.oMf[fid]
        pt = p_flange.act(np.array(eff.com_flange_m))
        # point Jacobian (world frame) of the payload centre: column c = J_lin,c + J_ang,c × r
        J = pin.computeFrameJacobian(model, data, q, fid, pin.LOCAL_WORLD_ALIGNED)
        r = pt - p_flange.translation
        Jv = J[:3] + np.array([np.cross(J[3:, c], r) for c in range(6)]).T
        tau = -Jv.T @ (eff.mass_kg * np.array([0, 0, -9.81]))
        assert np.allclose(b[k, 7:13] - a[k, 7:13], tau / kt, atol=5e-3)


def test_offset_and_belief_error_leave_the_truth(tmp_path: Path) -> None:
    g.generate(_spec(noise_A=0.02), tmp_path / "clean")
    g.generate(_spec(noise_A=0.02, effects=(g.CurrentOffset(joints=(3,), offset_A=0.08),)), tmp_path / "off")
    g.generate(_spec(noise_A=0.02, effects=(g.TorqueConstantError(joints=(1,), relative=0.3),)), tmp_path / "kt")
    _, a = _load(tmp_path / "clean/log.csv")
    _, b = _load(tmp_path / "off/log.csv")
    _, c = _load(tmp_path / "kt/log.csv")
    diff = b[:, 7:13] - a[:, 7:13]
    assert abs(diff[:, 3].mean() - 0.08) < 2e-3 and np.abs(diff[:, [0, 1, 2, 4, 5]]).max() < 1e-9
    assert np.array_equal(a, c)  # a belief error changes the params file, not the log
    belief = yaml.safe_load((tmp_path / "clean/belief.yaml").read_text())
    kt_clean = belief["joints"]["joint2"]["torque_constant_Nm_per_A"]
    kt_bad = yaml.safe_load((tmp_path / "kt/belief.yaml").read_text())["joints"]["joint2"]["torque_constant_Nm_per_A"]
    assert math.isclose(kt_bad, kt_clean * 1.3)


def test_expected_answer_names_the_effect(tmp_path: Path) -> None:
    info = g.generate(_spec(excitation="trapezoid", duration_s=20.0, noise_A=0.02,
                            effects=(g.ViscousFriction(joints=(1,)),)), tmp_path)
    exp = info["expected"]["viscous_friction"]
    assert exp["required"] == ["joint2"] and exp["allowed"] == ["joint2"]


def test_ur5_runs(tmp_path: Path) -> None:
    info = g.generate(_spec(robot="ur5"), tmp_path)
    assert Path(info["urdf"]).is_file() and 'name="joint1"' in Path(info["urdf"]).read_text()
