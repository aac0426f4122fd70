"""Issue 13 items 1-3: identified base parameters → a physically consistent arm (log-Cholesky least squares), the
params file's ``inertials`` applied by RobotModel, ``identify fit --torque-constants``, K_t reported only where its
relative std is below KT_MAX_REL_STD, and ``identify check`` predicting every joint with the identified model."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import yaml

from dragd.config import ConfigError, LinkInertial, load_config, load_params
from dragd.identify.inertials import (
    RowTarget,
    body_inertial,
    consistent_inertials,
    is_consistent,
    logchol_from_params,
    params_from_logchol,
    triangle_ok,
)
from dragd.identify.methods import KT_MAX_REL_STD
from dragd.identify.regressors import RegressorModel
from dragd.model import RobotModel
from dragd.robots import resolve_urdf

from conftest import run_cli

pytestmark = pytest.mark.unit


@pytest.fixture(scope="module")
def rm() -> RegressorModel:
    return RegressorModel(RobotModel.from_urdf("seed_cobot"))


def _targets(rm: RegressorModel, pi: np.ndarray) -> list[RowTarget]:
    full = np.concatenate([pi, np.zeros(rm.n)])
    return [RowTarget(b.E, b.E @ full, rm.row_scale[j]) for j, b in enumerate(rm.row_full)]


def _torque_error(rm: RegressorModel, pi_a: np.ndarray, pi_b: np.ndarray, seed: int = 3) -> float:
    """Largest |τ_a − τ_b| [N·m] over random states (|q̇|, |q̈| ~ 1): the base parameters' observable effect."""
    rng = np.random.default_rng(seed)
    q = rng.uniform(-np.pi, np.pi, (200, rm.n))
    v, a = rng.normal(0, 1, (200, rm.n)), rng.normal(0, 1, (200, rm.n))
    Y = rm.torque_regressor(q, v, a)
    z = np.zeros(rm.n)
    return float(np.abs(Y @ np.concatenate([pi_a, z]) - Y @ np.concatenate([pi_b, z])).max())


def test_log_cholesky_round_trip_and_every_vector_is_consistent():
    rng = np.random.default_rng(0)
    pi_u = RegressorModel(RobotModel.from_urdf("seed_cobot")).pi_urdf
    for i in range(6):
        p = pi_u[10 * i:10 * i + 10]
        assert np.allclose(params_from_logchol(logchol_from_params(p)), p, atol=1e-9)
    for _ in range(200):  # any real vector is a consistent body
        pi = params_from_logchol(rng.normal(0, 1.5, 10))
        assert is_consistent(pi)
        import pinocchio as pin
        assert triangle_ok(pin.Inertia.FromDynamicParameters(pi).inertia)


def test_random_consistent_arm_is_reproduced_by_consistent_inertials(rm):
    rng = np.random.default_rng(1)
    n = rm.n
    pi_u = rm.pi_urdf[:10 * n]
    x = np.concatenate([logchol_from_params(pi_u[10 * i:10 * i + 10]) + rng.normal(0, 0.15, 10) for i in range(n)])
    pi_t = np.concatenate([params_from_logchol(x[10 * i:10 * i + 10]) for i in range(n)])
    assert _torque_error(rm, pi_t, pi_u) > 0.5  # the target arm is really another arm
    m = consistent_inertials(_targets(rm, pi_t), pi_u)
    assert m.consistent and all(is_consistent(m.pi[10 * i:10 * i + 10]) for i in range(n))
    # reproduces the base parameters: ≤ 10 mN·m of torque anywhere (Hall noise alone is ~0.2 N·m on these joints)
    assert m.max_residual_Nm < 0.01, m.residual_Nm
    assert _torque_error(rm, m.pi, pi_t) < 0.02


def test_inconsistent_target_gets_the_nearest_consistent_arm(rm):
    n = rm.n
    pi_u = rm.pi_urdf[:10 * n]
    pi_b = pi_u.copy()
    pi_b[40] = -0.3  # link 5 with a negative mass: no real arm has these base parameters
    m = consistent_inertials(_targets(rm, pi_b), pi_u)
    assert m.consistent and m.pi[40] > 0
    # nearer to the target than the URDF is, in the torque the base parameters make
    assert _torque_error(rm, m.pi, pi_b) < 0.5 * _torque_error(rm, pi_u, pi_b)
    assert "log-Cholesky" in " ".join(m.notes["solve"])


def _modified_urdf(tmp_path, link: str, mass_scale: float, com_shift: float):
    src = resolve_urdf("seed_cobot")
    tree = ET.parse(src)
    for ln in tree.getroot().iter("link"):
        if ln.get("name") == link:
            inert = ln.find("inertial")
            m = inert.find("mass")
            m.set("value", str(float(m.get("value")) * mass_scale))
            o = inert.find("origin")
            xyz = [float(v) for v in o.get("xyz").split()]
            xyz[0] += com_shift
            o.set("xyz", " ".join(str(v) for v in xyz))
    out = tmp_path / "modified.urdf"
    tree.write(out)
    return out


def test_robot_model_with_inertials_equals_pinocchio_on_the_modified_urdf(tmp_path):
    mod = RobotModel.from_urdf(_modified_urdf(tmp_path, "link3", 1.2, 0.05))
    base = RobotModel.from_urdf("seed_cobot")
    ins = {name: body_inertial(mod.model.inertias[i + 1].toDynamicParameters())
           for i, name in enumerate(mod.link_names())}
    base.apply_inertials(ins)
    rng = np.random.default_rng(2)
    for q in rng.uniform(-2, 2, (20, 6)):
        assert np.allclose(base.gravity(q), mod.gravity(q), atol=1e-9)
        assert not np.allclose(RobotModel.from_urdf("seed_cobot").gravity(q), mod.gravity(q), atol=1e-3)
    with pytest.raises(ValueError, match="inertials: expected link names among link1"):
        base.apply_inertials({"tool0x": ins["link3"]})


def test_params_inertials_reach_the_configured_model_and_are_checked(tmp_path):
    p = tmp_path / "p.yaml"
    ins = body_inertial(RobotModel.from_urdf("seed_cobot").model.inertias[3].toDynamicParameters())
    ins["mass_kg"] *= 1.2
    p.write_text(yaml.safe_dump({"version": 1, "inertials": {"link3": ins}}))
    cfg = load_config(None, p)
    q = np.array([0.0, -0.6, 1.2, -0.6, 1.5708, 0.0])
    g1 = RobotModel.from_config(cfg).gravity(q)
    g0 = RobotModel.from_urdf("seed_cobot").gravity(q)
    assert abs(g1[2] - g0[2]) > 1.0  # link 3 is 20 % heavier in the law's G(q)
    out = json.loads(run_cli("model", "gravity", "--q", ",".join(map(str, q)), "--params", str(p), "--json").stdout)
    assert np.allclose(out["gravity_Nm"], g1, atol=1e-9)
    bad = dict(ins, inertia_kgm2=[1.0, 0.0, 0.0, 0.1, 0.0, 0.1])  # 1 > 0.1 + 0.1: no such body
    p.write_text(yaml.safe_dump({"version": 1, "inertials": {"link3": bad}}))
    with pytest.raises(ConfigError, match="inertials.link3.*triangle inequality"):
        load_params(p)
    with pytest.raises(ValueError):
        LinkInertial(mass_kg=-1.0, com_m=(0, 0, 0), inertia_kgm2=(1, 0, 0, 1, 0, 1))


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    from identify_helpers import fourier_log

    tmp = tmp_path_factory.mktemp("inertials")
    log = fourier_log()
    out = tmp / "full.yaml"
    fit = json.loads(run_cli("identify", "fit", "--log", str(log), "--robot", "seed_cobot", "--method", "full",
                             "--out", str(out), "--json", timeout=600).stdout)
    return log, out, fit, tmp


@pytest.mark.slow
def test_full_fit_writes_a_consistent_arm_reproducing_its_base_parameters(fitted):
    _, out, fit, _ = fitted
    params = load_params(out)
    assert set(params.inertials) == {f"link{i}" for i in range(1, 7)}
    mp = fit["inertials_mapping"]
    assert mp["consistent"]
    # every joint's identified base parameters within 5 of their own standard deviations
    assert max(mp["base_residual_over_std"].values()) < 5.0, mp["base_residual_over_std"]
    # K_t: reported where the relative std is below the bound, else null with the reason (joints 1 and 6 have no
    # gravity torque at all on this arm)
    for j in fit["joints"].values():
        kt = j["torque_constant_Nm_per_A"]
        if kt is not None:
            assert j["std"]["torque_constant_Nm_per_A"] / kt <= KT_MAX_REL_STD
        else:
            assert j["reasons"]["torque_constant_Nm_per_A"]
    assert fit["joints"]["joint1"]["torque_constant_Nm_per_A"] is None
    assert fit["joints"]["joint2"]["torque_constant_Nm_per_A"] == pytest.approx(9.05, rel=0.03)


@pytest.mark.slow
def test_check_predicts_every_joint_with_the_identified_model(fitted):
    log, out, _, _ = fitted
    for dyn in ("base", "inertials"):
        res = json.loads(run_cli("identify", "check", "--params", str(out), "--log", str(log), "--robot", "seed_cobot",
                                 "--mask", "moving", "--dynamics", dyn, "--json", timeout=600).stdout)
        for name, j in res["joints"].items():  # no --config: K_t of joints 1 and 6 unknown, still predicted
            assert j["rmse_A"] is not None, (dyn, name, j)
            assert j["rmse_A"] < 1.5 * j["noise_estimate_A"], (dyn, name, j)
        assert res["joints"]["joint1"]["model"] == "identified base parameters (current space)"


@pytest.mark.slow
def test_torque_constants_given_are_used_and_checked(fitted):
    log, _, _, tmp = fitted
    kt = [9.0, 9.1, 8.9, 4.5, 4.2, 4.6]
    out = tmp / "kt.yaml"
    fit = json.loads(run_cli("identify", "fit", "--log", str(log), "--robot", "seed_cobot", "--method", "full",
                             "--torque-constants", ",".join(map(str, kt)), "--out", str(out), "--json",
                             timeout=600).stdout)
    assert [fit["joints"][f"joint{i}"]["torque_constant_Nm_per_A"] for i in range(1, 7)] == pytest.approx(kt)
    assert load_params(out).joints["joint1"].torque_constant_Nm_per_A == pytest.approx(9.0)
    bad = run_cli("identify", "fit", "--log", str(log), "--robot", "seed_cobot", "--method", "full",
                  "--torque-constants", "9,9", "--out", str(tmp / "x.yaml"), check=False)
    assert bad.returncode == 2 and "--torque-constants: expected 6 positive" in bad.stderr, bad.stderr


@pytest.mark.slow
def test_urdf_masses_20_percent_wrong_identified_arm_gives_the_true_gravity_current(fitted, tmp_path):
    """The law's gravity current G(q)/K_t with a URDF whose links are all 20 % heavier than the simulated arm's:
    before, the URDF's (config K_t); after ``identify fit --method full`` on that URDF, the params' inertials and K_t
    (RobotModel.from_config of the configuration with the params overlaid, what the daemon builds)."""
    from sim.truth import load_truth

    log, _, _, _ = fitted
    src = resolve_urdf("seed_cobot")
    tree = ET.parse(src)
    for ln in tree.getroot().iter("link"):
        inert = ln.find("inertial")
        if inert is not None:
            m = inert.find("mass")
            m.set("value", str(float(m.get("value")) * 1.2))
            ii = inert.find("inertia")
            for k in ii.attrib:
                ii.set(k, str(float(ii.get(k)) * 1.2))
    wrong = tmp_path / "wrong.urdf"
    tree.write(wrong)
    cfg_file = tmp_path / "wrong.yaml"
    from dragd.config import default_config_path

    data = yaml.safe_load(default_config_path().read_text())
    data.setdefault("robot", {})["urdf"] = str(wrong)
    data.pop("params", None)
    cfg_file.write_text(yaml.safe_dump(data))
    out = tmp_path / "p.yaml"
    run_cli("identify", "fit", "--log", str(log), "--config", str(cfg_file), "--method", "full", "--out", str(out),
            timeout=600)
    before = RobotModel.from_config(load_config(cfg_file))
    cfg_after = load_config(cfg_file, out)
    after = RobotModel.from_config(cfg_after)
    kt_before = np.array([j.kt_Nm_per_A for j in load_config(cfg_file).joints])
    kt_after = np.array([j.kt_Nm_per_A for j in cfg_after.joints])
    tr = load_truth()
    kt_true = np.array([j.torque_constant_Nm_per_A for j in tr.joints])
    truth = RobotModel.from_urdf("seed_cobot")
    rng = np.random.default_rng(0)
    lo, hi = truth.position_limits_rad
    Q = rng.uniform(np.maximum(lo, -2.5), np.minimum(hi, 2.5), (300, 6))
    e0 = np.array([before.gravity(q) / kt_before - truth.gravity(q) / kt_true for q in Q])
    e1 = np.array([after.gravity(q) / kt_after - truth.gravity(q) / kt_true for q in Q])
    rms0, rms1 = np.sqrt((e0 ** 2).mean(axis=0)), np.sqrt((e1 ** 2).mean(axis=0))
    # before: joint 2 is ~0.7 A off (20 % of its gravity current); after: within the Hall noise (20 mA) on every
    # joint — the bound 40 mA is 2× the noise, far below what holds a released arm against friction (~0.3-0.9 A)
    assert rms0[1] > 0.4, rms0
    assert np.all(rms1 < 0.04), rms1
    assert np.all(rms1[1:4] < 0.1 * rms0[1:4]), (rms0, rms1)


def test_sim_model_params_carry_the_inertials_into_the_truth(tmp_path):
    """``python -m sim run|log --model params.yaml``: the simulated arm is the identified one."""
    from dragd.config import ParamsFile
    from sim.truth import load_truth, truth_from_params

    ins = body_inertial(RobotModel.from_urdf("seed_cobot").model.inertias[2].toDynamicParameters())
    ins["mass_kg"] *= 0.8
    params = ParamsFile.model_validate({"version": 1, "inertials": {"link2": ins}})
    sim_model = truth_from_params(params, load_truth()).load_model()
    ours = RobotModel.from_urdf("seed_cobot")
    ours.apply_inertials(params.inertials)
    q = np.array([0.0, -0.6, 1.2, -0.6, 1.5708, 0.0])
    assert np.allclose(sim_model.gravity(q), ours.gravity(q), atol=1e-12)
    assert abs(sim_model.gravity(q)[1] - RobotModel.from_urdf("seed_cobot").gravity(q)[1]) > 1.0


def _drag_drift_deg_s(cfg_path, params=None, seconds: float = 3.0) -> np.ndarray:
    """Released arm in drag on the simulated truth arm (sim/physics.py, 4 kHz), the law at 1 kHz with the model
    the daemon builds (RobotModel.from_config of the configuration + params): mean speed |q(T) − q0|/T [deg/s]."""
    from dragd.control.law import compensate
    from dragd.control.params import LawParams
    from sim.axis import AxisIO
    from sim.physics import ArmPhysics
    from sim.truth import load_truth

    cfg = load_config(cfg_path, params)
    model = RobotModel.from_config(cfg)
    law = LawParams.from_config(cfg).replace(use_breakout=False)  # the latch needs the daemon's estimate step
    truth = load_truth()
    axes = [AxisIO() for _ in range(6)]
    phys = ArmPhysics(truth, truth.load_model(), axes)
    q0 = np.array([0.0, -0.6, 1.2, -0.6, 1.5708, 0.0])
    phys.set_state(q0)
    for ax in axes:
        ax.power_stage_on, ax.brake_engaged = True, False
    per = int(round(1e-3 / phys.dt_s))
    for k in range(int(seconds / phys.dt_s)):
        if k % per == 0:
            q = phys.q_rad.copy()
            out = compensate(model.gravity(q), phys.dq_rad_s.copy(), k * phys.dt_s, law, q_rad=q)
            for i, ax in enumerate(axes):
                ax.current_demand_A = float(out.current_A[i])
        phys.step()
    return np.degrees(np.abs(phys.q_rad - q0)) / seconds


@pytest.mark.slow
def test_drag_with_20_percent_wrong_urdf_masses_stops_drifting_after_identify(fitted, tmp_path):
    """Item 1's proof: the daemon's URDF has every link 20 % heavier than the simulated arm. Released in drag, the
    arm drifts (the law over-compensates gravity by ~1 A on joint 2); after identify fit → params (inertials, K_t)
    → the daemon's model, it drifts no more than after the same identification on the correct URDF."""
    from dragd.config import default_config_path

    log, true_fit, _, _ = fitted
    src = resolve_urdf("seed_cobot")
    tree = ET.parse(src)
    for ln in tree.getroot().iter("link"):
        inert = ln.find("inertial")
        if inert is not None:
            m = inert.find("mass")
            m.set("value", str(float(m.get("value")) * 1.2))
            ii = inert.find("inertia")
            for k in ii.attrib:
                ii.set(k, str(float(ii.get(k)) * 1.2))
    wrong = tmp_path / "wrong.urdf"
    tree.write(wrong)
    data = yaml.safe_load(default_config_path().read_text())
    data.setdefault("robot", {})["urdf"] = str(wrong)
    data.pop("params", None)
    cfg_file = tmp_path / "wrong.yaml"
    cfg_file.write_text(yaml.safe_dump(data))
    out = tmp_path / "identified.yaml"
    run_cli("identify", "fit", "--log", str(log), "--config", str(cfg_file), "--method", "full", "--out", str(out),
            timeout=600)
    before = _drag_drift_deg_s(cfg_file)
    after = _drag_drift_deg_s(cfg_file, out)
    reference = _drag_drift_deg_s(default_config_path(), true_fit)  # same fit, correct URDF
    # measured: before 25.7/30.0/15.7 deg/s on joints 2/3/4 (the arm runs to its stops); after 0.001/0.60/2.29,
    # reference 0.000/0.60/2.28 (the residual on joints 3, 4 and 6 is the fitted friction's, not gravity's).
    assert before[1] > 5.0, before
    assert after[1] < 0.05, after  # joint 2: 20 % gravity error (~1 A) gone
    assert np.all(after <= reference + 0.1), (after, reference)  # gravity adds nothing beyond the friction fit
    assert np.all(after[1:4] < 0.2 * before[1:4]), (before, after)
