"""The robot model: the seed cobot equals the seeds' closed form; any URDF loads; G(q) = RNEA at rest."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from dragd.model import RobotModel

from conftest import cli_json, run_cli

pytestmark = pytest.mark.unit


def seed_closed_form(q: np.ndarray) -> np.ndarray:
    """Seed 000's gravity (N·m), with G5 the gradient of the same potential (see docs/MODEL.md)."""
    _, q2, q3, q4, q5, _ = q
    q23, q234 = q2 + q3, q2 + q3 + q4
    g4 = 1.69 * np.sin(q234) - 0.35 * np.cos(q234) * np.sin(q5)
    g3 = -18.64 * np.cos(q23) + g4
    g2 = -40.87 * np.cos(q2) + g3
    g5 = -0.35 * np.sin(q234) * np.cos(q5)
    return np.array([0.0, g2, g3, g4, g5, 0.0])


def test_seed_cobot_matches_closed_form():
    model = RobotModel.from_urdf("seed_cobot")
    assert model.joint_names == tuple(f"joint{i}" for i in range(1, 7))
    masses = [model.model.inertias[i].mass for i in range(1, 7)]
    assert masses == pytest.approx([3.75, 8.24, 2.4, 1.46, 1.46, 0.2])
    rng = np.random.default_rng(42)
    for _ in range(500):
        q = rng.uniform(-np.pi, np.pi, 6)
        assert np.max(np.abs(model.gravity(q) - seed_closed_form(q))) < 1e-3


def test_printed_g5_is_not_a_gradient():
    """The seed's printed G5 = -0.35 cos q234 sin q5 breaks ∂G4/∂q5 = ∂G5/∂q4; ours satisfies it."""
    q = np.array([0.0, 0.3, -0.7, 0.4, 0.9, 0.0])
    h = 1e-6

    def grad(f, i, j):
        e = np.zeros(6)
        e[j] = h
        return (f(q + e)[i] - f(q - e)[i]) / (2 * h)

    model = RobotModel.from_urdf("seed_cobot")
    assert grad(model.gravity, 3, 4) == pytest.approx(grad(model.gravity, 4, 3), abs=1e-6)

    def printed(qq):
        g = seed_closed_form(qq)
        g[4] = -0.35 * np.cos(qq[1] + qq[2] + qq[3]) * np.sin(qq[4])
        return g

    assert abs(grad(printed, 3, 4) - grad(printed, 4, 3)) > 0.05


def _ur5_urdf() -> Path:
    import cmeel  # noqa: F401  (installed with example-robot-data)

    roots = [Path(p) for p in __import__("sys").path if p]
    for r in roots:
        cand = r / "cmeel.prefix/share/example-robot-data/robots/ur_description/urdf/ur5_robot.urdf"
        if cand.is_file():
            return cand
    pytest.skip("example-robot-data's UR5 URDF is not installed (pip install '.[test]')")


def test_second_robot_loads_unchanged_and_matches_rnea():
    path = _ur5_urdf()
    model = RobotModel.from_urdf(path)
    ref = pin.buildModelFromUrdf(str(path))
    data = ref.createData()
    rng = np.random.default_rng(7)
    for _ in range(100):
        q = rng.uniform(-np.pi, np.pi, model.nq)
        expect = pin.rnea(ref, data, q, np.zeros(ref.nv), np.zeros(ref.nv))
        assert np.allclose(model.gravity(q), expect, atol=1e-9)
    out = cli_json("model", "gravity", "--q", ",".join(["0.1"] * model.nq), "--robot", str(path))
    assert out["joints"] == list(model.joint_names)
    assert np.allclose(out["gravity_Nm"], model.gravity(np.full(model.nq, 0.1)), atol=1e-9)


def test_cli_gravity_seed_convention():
    q = [0.2, -0.4, 1.1, 0.3, -0.8, 2.0]
    out = cli_json("model", "gravity", "--q", ",".join(map(str, q)))
    assert out["joints"] == [f"joint{i}" for i in range(1, 7)]
    assert np.allclose(out["gravity_Nm"], seed_closed_form(np.array(q)), atol=1e-3)


def test_cli_gravity_bad_input():
    p = run_cli("model", "gravity", "--q", "1,2,3", "--json", check=False)
    assert p.returncode == 2 and "--q: expected 6 values" in p.stderr
    p = run_cli("model", "gravity", "--q", "1,a,3", check=False)
    assert p.returncode == 2 and "expected comma-separated numbers" in p.stderr
    p = run_cli("model", "gravity", "--q", "0,0,0,0,0,0", "--robot", "/nonexistent.urdf", check=False)
    assert p.returncode == 2 and "/nonexistent.urdf" in p.stderr


def test_bad_urdf_named(tmp_path):
    bad = tmp_path / "bad.urdf"
    bad.write_text("<robot name='x'><link name='a'/><joint name='j' type='revolute'></robot>")
    with pytest.raises(ValueError, match="bad.urdf"):
        RobotModel.from_urdf(bad)
