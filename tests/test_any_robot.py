"""Any robot: the UR5 and UR10 of example-robot-data, their URDFs unchanged (joint names shoulder_pan_joint, ...),
through ``dragd config init``/``check``, ``dragd model gravity``, an offline identification (``identify plan`` →
``python -m sim log`` on a truth generated from the URDF → ``identify fit``), ``dragd gap``, and (UR5) the
simulator and daemon processes on the lockstep clock: start, drag, a push, stop."""

from __future__ import annotations

import importlib.metadata
import json
import math
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import yaml

from dragd.config import ConfigError, load_config
from dragd.model import RobotModel

from conftest import run_cli, run_sim

ROBOTS = ("ur5", "ur10")
START = "0,-0.5,0.8,-1.57,-1.57,0"  # elbow up, wrist down: every joint's identification range is reachable


def erd_urdf(name: str) -> Path:
    """The URDF of an example-robot-data robot (a test dependency, pyproject.toml [test])."""
    dist = importlib.metadata.distribution("example-robot-data")
    hits = [f for f in dist.files or () if f.name == f"{name}_robot.urdf"]
    assert hits, f"example-robot-data {dist.version} has no {name}_robot.urdf"
    return Path(dist.locate_file(hits[0]))


@pytest.fixture(scope="module")
def configs(tmp_path_factory) -> dict[str, Path]:
    """``dragd config init`` for each robot, written by the real CLI."""
    d = tmp_path_factory.mktemp("any-robot")
    out = {}
    for name in ROBOTS:
        out[name] = d / f"{name}.yaml"
        out[name].write_text(run_cli("config", "init", "--robot", str(erd_urdf(name))).stdout)
    return out


@pytest.mark.unit
@pytest.mark.parametrize("name", ROBOTS)
def test_config_init_names_joints_as_the_urdf_and_checks(configs, name):
    urdf = pin.buildModelFromUrdf(str(erd_urdf(name)))
    cfg = load_config(configs[name])
    assert cfg.joint_names == list(urdf.names[1:]) == ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint",
                                                       "wrist_1_joint", "wrist_2_joint", "wrist_3_joint"]
    assert [j.node_id for j in cfg.joints] == [1, 2, 3, 4, 5, 6]
    for j, effort in zip(cfg.joints, urdf.effortLimit, strict=True):  # the URDF's effort at the current limit
        assert j.kt_Nm_per_A * j.current_limit_A == pytest.approx(effort, rel=1e-4)
    d = json.loads(run_cli("config", "check", "--config", str(configs[name]), "--json").stdout)
    assert d["ok"] and d["joints"] == cfg.joint_names
    lift = d["gravity"][1]
    assert lift["joint"] == "shoulder_lift_joint" and not lift["exceeds"]
    assert lift["gravity_Nm"] == pytest.approx({"ur5": 59.4, "ur10": 121.0}[name], rel=0.01)


@pytest.mark.unit
@pytest.mark.parametrize("name", ROBOTS)
def test_model_gravity_is_pinocchios(configs, name):
    urdf = pin.buildModelFromUrdf(str(erd_urdf(name)))
    q = np.array([0.3, -1.1, 1.4, -0.9, 0.7, 0.2])
    d = json.loads(run_cli("model", "gravity", "--config", str(configs[name]), "--q", ",".join(map(str, q)),
                           "--json").stdout)
    assert d["joints"] == list(urdf.names[1:])
    np.testing.assert_allclose(d["gravity_Nm"], pin.computeGeneralizedGravity(urdf, urdf.createData(), q), atol=1e-9)


@pytest.mark.unit
def test_wrong_joint_names_are_one_error_with_the_urdfs_names(configs, tmp_path):
    data = yaml.safe_load(configs["ur5"].read_text())
    data["joints"][0]["name"], data["joints"][1]["name"] = data["joints"][1]["name"], data["joints"][0]["name"]
    swapped = tmp_path / "swapped.yaml"
    swapped.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError) as e:
        load_config(swapped)
    assert str(e.value).startswith(f"{swapped}: joints[].name: expected the robot's joints shoulder_pan_joint, "
                                   "shoulder_lift_joint, elbow_joint, wrist_1_joint, wrist_2_joint, wrist_3_joint in "
                                   "this order (from ")
    assert str(e.value).endswith("(out of order)")
    for i, j in enumerate(data["joints"]):
        j["name"] = f"joint{i + 1}"
    seed_names = tmp_path / "seed_names.yaml"
    seed_names.write_text(yaml.safe_dump(data))
    proc = run_cli("config", "check", "--config", str(seed_names), check=False)
    assert proc.returncode == 2 and "ur5_robot.urdf), got joint1, joint2" in proc.stderr
    assert "unknown joint1, joint2, joint3, joint4, joint5, joint6; missing shoulder_pan_joint" in proc.stderr


@pytest.mark.unit
def test_gravity_current_above_the_limit_is_an_error(configs, tmp_path):
    data = yaml.safe_load(configs["ur10"].read_text())
    data["joints"][1]["current_limit_A"] = 4.0  # the UR10's shoulder needs 4.4 A at K_t 27.5 N·m/A
    p = tmp_path / "weak.yaml"
    p.write_text(yaml.safe_dump(data))
    proc = run_cli("config", "check", "--config", str(p), check=False)
    assert proc.returncode == 2, proc.stdout
    msg = proc.stderr
    assert f"{p}: joints[1] (shoulder_lift_joint): gravity needs 4.40 A over its range at q = [" in msg
    assert "(|G| 121.0" in msg and "above its current_limit_A 4 A" in msg and "elbow_joint" not in msg
    # a payload counts: the UR5's elbow holds its own arm at 4 A (1.3 A needed), not with 10 kg at the flange
    data = yaml.safe_load(configs["ur5"].read_text())
    data["joints"][2]["current_limit_A"] = 4.0
    data["payload"] = {"mass_kg": 10.0}
    p = tmp_path / "payload.yaml"
    p.write_text(yaml.safe_dump(data))
    msg = run_cli("config", "check", "--config", str(p), check=False).stderr
    assert "joints[2] (elbow_joint): gravity needs" in msg and "with the 10 kg payload" in msg


@pytest.mark.unit
def test_gravity_excess_at_a_pose(configs):
    from dragd.robots.gravity import gravity_excess_at

    cfg = load_config(configs["ur10"])
    weak = cfg.model_copy(update={"joints": [cfg.joints[0], cfg.joints[1].model_copy(update={"current_limit_A": 4.0}),
                                             *cfg.joints[2:]]})
    model = RobotModel.from_config(cfg)
    folded = np.array([0.0, -math.pi / 2, 0.0, 0.0, 0.0, 0.0])  # the arm straight up: no shoulder load
    assert gravity_excess_at(weak, model, folded) is None
    msg = gravity_excess_at(weak, model, np.zeros(6))  # stretched out horizontally
    assert msg is not None and "joints[1] (shoulder_lift_joint): gravity needs 4.39 A here at q = [0.000" in msg


@pytest.mark.unit
def test_generated_truth_round_trips_and_holds_gravity(tmp_path):
    from sim.truth import load_truth, truth_for_robot, truth_yaml

    truth = truth_for_robot(erd_urdf("ur10"))
    p = tmp_path / "ur10_truth.yaml"
    p.write_text(truth_yaml(truth))
    again = load_truth(p)
    assert again.model_dump() == truth.model_dump()
    model = again.load_model()
    assert [j.name for j in again.joints] == list(model.joint_names)
    g = np.abs(model.gravity(np.zeros(6)))
    limit = np.array([j.torque_constant_Nm_per_A * j.drive.max_current_A for j in again.joints])
    assert np.all(g < 0.7 * limit)  # the drives hold the outstretched arm with headroom
    assert load_truth(str(erd_urdf("ur10"))).model_dump() == truth.model_dump()  # a .urdf "truth file"


@pytest.fixture(scope="module", params=ROBOTS)
def identified(request, configs, tmp_path_factory):
    """One pose of the gap plan on a truth made from the URDF, fitted, then dragd gap against the fit."""
    name = request.param
    d = tmp_path_factory.mktemp(f"identify-{name}")
    cfg = str(configs[name])
    run_cli("identify", "plan", "--kind", "gap", "--scale", "0.34", "--config", cfg, "--start", START,
            "--out", str(d / "plan.npz"))
    run_sim("log", "--plan", str(d / "plan.npz"), "--out", str(d / "log.mcap"), "--config", str(erd_urdf(name)),
            "--dragd-config", cfg, timeout=300)
    fit = json.loads(run_cli("identify", "fit", "--log", str(d / "log.mcap"), "--config", cfg, "--out",
                             str(d / "params.yaml"), "--json").stdout)
    gap = json.loads(run_cli("gap", "--measured", str(d / "log.mcap"), "--config", cfg, "--model",
                             str(d / "params.yaml"), "--json", timeout=300).stdout)
    return name, fit, gap, d, configs[name]


@pytest.mark.unit
@pytest.mark.slow
def test_identification_finds_the_truth(identified):
    from sim.truth import truth_for_robot

    name, fit, _, d, cfg_path = identified
    truth = {j.name: j for j in truth_for_robot(erd_urdf(name)).joints}
    assert list(fit["joints"]) == list(truth)
    for jn in ("shoulder_lift_joint", "elbow_joint"):  # the joints gravity loads: K_t within 1 %
        kt = fit["joints"][jn]["torque_constant_Nm_per_A"]
        assert kt == pytest.approx(truth[jn].torque_constant_Nm_per_A, rel=0.01), jn
    for jn, j in fit["joints"].items():  # Coulomb levels within 5 % of the truth's (N·m / K_t)
        kt = truth[jn].torque_constant_Nm_per_A
        assert j["friction"]["coulomb_pos_A"] == pytest.approx(truth[jn].friction.coulomb_pos_Nm / kt, rel=0.05), jn
    assert set(yaml.safe_load((d / "params.yaml").read_text())["joints"]) == set(truth)  # keyed by the URDF's names
    cfg = load_config(cfg_path, d / "params.yaml")  # the config with the identified params overlaid
    assert cfg.joints[1].kt_Nm_per_A == pytest.approx(fit["joints"]["shoulder_lift_joint"]["torque_constant_Nm_per_A"])


@pytest.mark.unit
@pytest.mark.slow
def test_gap_names_the_missing_rotor_inertia(identified):
    _, _, gap, _, _ = identified
    assert set(gap["baseline"]["joints"]) == {"shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint",
                                              "wrist_1_joint", "wrist_2_joint", "wrist_3_joint"}
    # the truth's rotors (× gear²) are not in the URDF: inertia is the effect, and it closes the gap to the noise
    assert [e["effect"] for e in gap["effects"]] == ["inertia"], gap["effects"]
    assert gap["final"]["rmse_A"] < 0.3 * gap["baseline"]["rmse_A"] and gap["final"]["rmse_A"] < 0.03


@pytest.mark.lockstep
@pytest.mark.slow
def test_ur5_drag_on_the_simulator(configs, tmp_path):
    """The UR5 on the simulated robot (its truth generated from the URDF), the daemon on the generated config:
    start holds the arm, drag lets a push move the base joint, the arm stays where it comes to rest, stop."""
    from dragd.lab.rig import Rig
    from sim.truth import truth_for_robot, truth_yaml

    truth = tmp_path / "ur5_truth.yaml"
    truth.write_text(truth_yaml(truth_for_robot(erd_urdf("ur5"), initial_q_rad=[0.0, -0.5, 0.8, -1.57, -1.57, 0.0])))
    rig = Rig("ur5", workdir=tmp_path, config=configs["ur5"], sim_config=truth)
    try:
        rig.start_sim()
        rig.start_daemon()
        p = rig.cli("start", "--json")
        assert p.returncode == 0, (p.stderr, rig.daemon.tail())
        rig.sleep(0.3)  # (start answers once the drives are enabled; the hold current builds up after the brakes)
        st = rig.must("status")
        assert st["mode"] == "hold" and abs(st["current_A"][1]) > 1.0  # the shoulder holds the arm
        assert rig.cli("mode", "drag").returncode == 0, rig.daemon.tail()
        rig.sleep(0.5)
        before = np.array(rig.sim_call("state")["q_rad"])
        rig.sim_call("operator", scenario={"name": "push_pan", "segments": [
            {"kind": "push", "joint": "shoulder_pan_joint", "torque_Nm": 15.0, "duration_s": 0.6},
            {"kind": "release", "duration_s": 0.0}]})
        rig.sleep(0.7)
        rig.wait_for(lambda: max(abs(v) for v in rig.sim_call("state")["dq_rad_s"]) <= 1e-4, 8.0,
                     "the arm to come to rest")
        rest = np.array(rig.sim_call("state")["q_rad"])
        rig.sleep(1.5)
        later = np.array(rig.sim_call("state")["q_rad"])
        drag = rig.must("status")
        p = rig.cli("stop", "--json")
        assert p.returncode == 0, p.stderr
        rig.sleep(0.2)
        after = rig.sim_call("state")
    finally:
        rig.close()
    assert math.degrees(rest[0] - before[0]) > 2.0  # the push turned the base
    assert np.degrees(np.abs(rest[1:] - before[1:])).max() < 1.0  # ... and nothing else sagged
    assert np.degrees(np.abs(later - rest)).max() < 0.1  # it stays where it came to rest
    assert drag["mode"] == "drag" and drag["faults"] == []
    assert all(after["brakes"])
