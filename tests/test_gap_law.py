"""The law's model-gap term (dragd/control/law.py ``effects_current``, back-EMF knee) against its formulas, and the
payload in the robot model: what ``dragd gap --out`` adds is what the daemon compensates."""

from __future__ import annotations

import numpy as np
import pytest

from dragd.config import ParamsFile, apply_params, load_config
from dragd.control.law import LawOutput, Workspace, compensate, effects_current, friction_current
from dragd.control.params import LawParams
from dragd.model import RobotModel

pytestmark = pytest.mark.unit

PARAMS = {
    "joints": {
        "joint2": {"effects": {"position_periodic": [{"cycles_per_rev": 24.0, "sin_A": 0.03, "cos_A": -0.02},
                                                     {"cycles_per_rev": 7.5, "sin_A": 0.01, "cos_A": 0.0}],
                               "load_friction_per_Nm": 0.04, "current_offset_A": -0.05,
                               "temperature_drift": {"friction_change": -0.1, "time_constant_s": 30.0}}},
        "joint3": {"effects": {"back_emf": {"A_s_per_rad": 0.4, "knee_rad_s": 0.2}}},
    },
    "payload": {"mass_kg": 1.5, "com_m": [0.0, 0.0, 0.05]},
}


@pytest.fixture(scope="module")
def law_cfg():
    cfg = apply_params(load_config(), ParamsFile.model_validate(PARAMS), "test")
    return LawParams.from_config(cfg), cfg


def test_effects_current_matches_its_formula(law_cfg):
    p, cfg = law_cfg
    rng = np.random.default_rng(3)
    kt2 = cfg.joints[1].kt_Nm_per_A
    for _ in range(20):
        q = rng.uniform(-2, 2, 6)
        dq = rng.uniform(-0.6, 0.6, 6)
        tau = rng.uniform(-60, 60, 6)
        t = float(rng.uniform(0, 200))
        fr = friction_current(dq, p)
        out = effects_current(q, dq, tau, t, p, fr, ws=Workspace(6))
        w = np.tanh(abs(dq[1]) / p.smoothing_rad_s)
        want = (0.03 * np.sin(24 * q[1]) - 0.02 * np.cos(24 * q[1]) + 0.01 * np.sin(7.5 * q[1]) - 0.05
                + p.friction_scale * w * np.sign(dq[1]) * 0.04 * abs(tau[1]) / kt2
                - 0.1 * fr[1])  # friction falls as it warms (Δ < 0): the warm level at once (the safe side)
        assert out[1] == pytest.approx(want, abs=1e-12)
        assert np.allclose(np.delete(out, 1), 0.0)


def test_drift_with_its_own_viscous_change_matches_its_formula():
    """A warm-up whose viscous part changes by its own factor (grease viscosity): Δ·g·(I_f − I_visc) + Δ_v·g·I_visc,
    each part at its warm level at once where it falls (the safe side), else rising with g = 1 − e^(−t/τ)."""
    data = {"joints": {"joint2": {"friction": {"viscous_pos_A_s_per_rad": 0.5, "viscous_neg_A_s_per_rad": 0.4},
                                  "effects": {"temperature_drift": {"friction_change": 0.2, "viscous_change": -0.3,
                                                                    "time_constant_s": 40.0}}}}}
    p = LawParams.from_config(apply_params(load_config(), ParamsFile.model_validate(data), "test"))
    rng = np.random.default_rng(5)
    for _ in range(20):
        dq = rng.uniform(-0.6, 0.6, 6)
        t = float(rng.uniform(0, 200))
        fr = friction_current(dq, p)
        out = effects_current(np.zeros(6), dq, np.zeros(6), t, p, fr, ws=Workspace(6))
        visc = p.friction_scale * (0.5 if dq[1] >= 0 else 0.4) * dq[1]
        g = 1.0 - np.exp(-t / 40.0)
        assert out[1] == pytest.approx(0.2 * g * (fr[1] - visc) - 0.3 * visc, abs=1e-12)
        assert np.allclose(np.delete(out, 1), 0.0)


def test_back_emf_knee_and_switch(law_cfg):
    p, _ = law_cfg
    assert p.use_back_emf and p.back_emf_A_s_per_rad[2] == pytest.approx(0.4)
    dq = np.array([0, 0, 0.5, 0, 0, 0.0])
    out = compensate(np.zeros(6), dq, 0.0, p, LawOutput.zeros(6), Workspace(6), q_rad=np.zeros(6))
    assert out.back_emf_A[2] == pytest.approx(0.4 * 0.3)
    dq[2] = -0.15  # below the knee: nothing
    out = compensate(np.zeros(6), dq, 0.0, p, LawOutput.zeros(6), Workspace(6), q_rad=np.zeros(6))
    assert out.back_emf_A[2] == 0.0


def test_no_effects_leaves_the_law_as_it_was():
    p = LawParams.from_config(load_config())
    assert p.effects is None
    out = compensate(np.zeros(6), np.full(6, 0.3), 0.0, p, LawOutput.zeros(6), Workspace(6))
    assert np.all(out.effects_A == 0.0)


def test_payload_in_the_model_changes_gravity(law_cfg):
    _, cfg = law_cfg
    plain = RobotModel.from_urdf("seed_cobot")
    loaded = RobotModel.from_config(cfg)
    q = np.array([0.0, -0.3, 0.8, -0.4, 1.2, 0.0])
    dg = loaded.gravity(q) - plain.gravity(q)
    assert dg[0] == pytest.approx(0.0, abs=1e-9) and abs(dg[1]) > 1.0  # 1.5 kg at ~0.8 m on the shoulder


def test_compensate_is_allocation_free_with_effects(law_cfg):
    import tracemalloc

    p, _ = law_cfg
    out, ws = LawOutput.zeros(6), Workspace(6)
    q, dq, g = np.full(6, 0.3), np.full(6, 0.2), np.ones(6)
    compensate(g, dq, 0.1, p, out, ws, q_rad=q)
    tracemalloc.start()
    before = tracemalloc.take_snapshot()
    for k in range(200):
        compensate(g, dq, 0.1 + k * 1e-3, p, out, ws, q_rad=q)
    after = tracemalloc.take_snapshot()
    tracemalloc.stop()
    grown = sum(s.size_diff for s in after.compare_to(before, "filename") if "law.py" in str(s.traceback))
    assert grown < 2048
