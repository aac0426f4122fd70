"""Teach and replay, offline: program file, jerk-limited profile, kinematics, replay planning, keyframes (no rig)."""

from __future__ import annotations

import json
import math

import numpy as np
import pinocchio as pin
import pytest
import yaml

from dragd.config import ConfigError, load_config
from dragd.model import RobotModel
from dragd.teach.keyframes import extract_keyframes
from dragd.teach.kinematics import Circle, Kinematics, KinematicsError
from dragd.teach.plan import PlanError, plan_replay, request_from_config
from dragd.teach.profile import SCurve
from dragd.teach.program import FORMAT, Program, ProgramError, Waypoint, load_program, resolve_program, save_program

from conftest import DEFAULT_CONFIG, run_cli
from daemon_helpers import derived_config

pytestmark = pytest.mark.unit

Q0 = np.array([0.0, -0.6, 1.2, -0.6, 1.5708, 0.0])  # the simulated arm's start pose
STEPS = [[0.20, 0.10, -0.10, 0.10, 0.0, 0.0], [0.25, 0.20, -0.35, 0.15, 0.15, 0.25],
         [-0.35, 0.05, 0.25, -0.05, -0.20, -0.15]]  # the teach demo's hand pulls


@pytest.fixture(scope="module")
def cfg():
    return load_config(DEFAULT_CONFIG)


@pytest.fixture(scope="module")
def kin():
    return Kinematics(RobotModel.from_urdf("seed_cobot").model)


def _waypoints() -> list[np.ndarray]:
    out, q = [], Q0.copy()
    for s in STEPS:
        q = q + np.array(s)
        out.append(q.copy())
    return out


def _program(tmp_path, wps, name="prog", path_rows=None):
    prog = Program(name=name, joints=[f"joint{i + 1}" for i in range(6)], created="2025-01-01T00:00:00Z",
                   waypoints=[Waypoint(name=f"p{i + 1}", t_s=float(i), q_rad=list(map(float, w)))
                              for i, w in enumerate(wps)],
                   path=path_rows or [])
    return save_program(prog, tmp_path / f"{name}.yaml")


def _derivatives(q, dt):
    v = np.diff(q, axis=0) / dt
    a = np.diff(v, axis=0) / dt
    j = np.diff(a, axis=0) / dt
    return v, a, j


# ------------------------------------------------------------------------------------------------ profile


@pytest.mark.parametrize("length", [1e-4, 0.02, 0.3, 2.0, 8.0])
def test_scurve_reaches_length_within_limits(length):
    V, A, J = 1.0, 2.0, 20.0
    p = SCurve.plan(length, V, A, J)
    t = np.arange(0.0, p.duration + 1e-4, 1e-4)
    s, v, a, jk = p.evaluate(t)
    assert s[-1] == pytest.approx(length, rel=1e-12) and s[0] == 0.0
    assert abs(v[-1]) < 1e-9 and abs(a[-1]) < 1e-9
    assert v.max() <= V * (1 + 1e-9) and np.abs(a).max() <= A * (1 + 1e-9) and np.abs(jk).max() <= J * (1 + 1e-9)
    assert np.all(np.diff(s) >= -1e-15)  # never backwards
    # numerical derivatives agree with the closed form
    assert np.allclose(np.gradient(s, t), v, atol=1e-3 * max(V, 1e-3))
    # time-optimal within its class: a limit is reached (velocity, or acceleration, or jerk throughout)
    assert v.max() > 0.999 * V or np.abs(a).max() > 0.999 * A or p.tv == 0.0


def test_scurve_stretch_is_a_time_scaling():
    p = SCurve.plan(1.0, 1.0, 2.0, 20.0)
    k = 2.5
    q = SCurve.plan(1.0, 1.0 / k, 2.0 / k ** 2, 20.0 / k ** 3)
    assert q.duration == pytest.approx(k * p.duration, rel=1e-9)
    t = np.linspace(0.0, p.duration, 50)
    assert np.allclose(p.evaluate(t)[0], q.evaluate(k * t)[0], atol=1e-9)


# ------------------------------------------------------------------------------------------------ program


def test_program_file_roundtrip_is_human_readable_and_versioned(tmp_path):
    wps = _waypoints()
    rows = [[0.02 * k] + list(Q0 + 0.001 * k) for k in range(10)]
    path = _program(tmp_path, wps, path_rows=rows)
    text = path.read_text()
    data = yaml.safe_load(text)
    assert data["format"] == FORMAT and data["version"] == 1
    assert data["waypoints"][1]["name"] == "p2" and len(data["waypoints"][1]["q_rad"]) == 6
    assert "- name: p1\n  t_s: 0.0\n  q_rad: [0.2, -0.5, 1.1, -0.5, 1.5708, 0.0]\n" in text  # a vector per line
    assert "\n- [0.02, 0.001, -0.599, 1.201, -0.599, 1.5718, 0.001]\n" in text  # a sample per line
    assert len(data["path"]) == 10 and len(data["path"][0]) == 7
    prog = load_program(path)
    assert np.allclose(prog.waypoint_array(), wps, atol=1e-7)
    t, q = prog.path_arrays()
    assert t.shape == (10,) and q.shape == (10, 6)
    # a newer version, another format, a wrong vector length, an unknown key: clear refusals
    for edit, msg in ((lambda d: d.update(version=2), "version 2"),
                      (lambda d: d.update(format="other"), "format: expected 'dragd.teach.program'"),
                      (lambda d: d["waypoints"][0].update(q_rad=[0.0, 1.0]), "waypoints[0].q_rad: expected 6 values"),
                      (lambda d: d.update(colour="red"), "colour: unknown key")):
        bad = yaml.safe_load(text)
        edit(bad)
        p = tmp_path / "bad.yaml"
        p.write_text(yaml.safe_dump(bad))
        with pytest.raises(ProgramError, match=msg.replace("[", r"\[").replace("]", r"\]")):
            load_program(p)
    assert resolve_program("demo", "/x/progs").as_posix() == "/x/progs/demo.yaml"
    assert resolve_program("./a/b.yaml", "/x").as_posix() == "a/b.yaml"
    with pytest.raises(ProgramError, match="program name"):
        resolve_program("bad name!", "/x")


def test_replay_config_section_defaults_and_errors(tmp_path):
    cfg = load_config(DEFAULT_CONFIG)
    assert cfg.replay.acceleration_limits_rad_s2 == 2.0 and cfg.replay.move_to_start_speed == 0.25
    assert cfg.per_joint(cfg.replay.tracking_error_limit_rad) == [cfg.replay.tracking_error_limit_rad] * 6
    bad = derived_config(tmp_path, "bad", lambda d: d.update(replay={"acceleration_limits_rad_s2": [1.0, 2.0]}))
    with pytest.raises(ConfigError, match=r"replay.acceleration_limits_rad_s2: expected one value or 6"):
        load_config(bad)
    bad = derived_config(tmp_path, "bad2", lambda d: d.update(replay={"move_to_start_speed": 2}))
    with pytest.raises(ConfigError, match=r"replay.move_to_start_speed: expected a fraction in \(0, 1\]"):
        load_config(bad)


# ------------------------------------------------------------------------------------------------ kinematics


def test_ik_reaches_fk_pose_and_circle_through_three_points(kin):
    rng = np.random.default_rng(3)
    for _ in range(5):
        q = Q0 + rng.uniform(-0.3, 0.3, 6)
        target = kin.pose(q)
        sol = kin.ik(target, q + rng.uniform(-0.05, 0.05, 6))
        err = pin.log6(kin.pose(sol).actInv(target)).vector
        assert np.linalg.norm(err) < 1e-9
        assert np.abs(sol - q).max() < 1e-6  # same configuration from a nearby start
    with pytest.raises(KinematicsError, match="out of reach"):
        kin.ik(pin.SE3(np.eye(3), np.array([3.0, 0.0, 0.0])), Q0)
    p = [np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]), np.array([-1.0, 0.0, 0.0])]
    c = Circle.through(*p)
    assert np.allclose(c.center, 0.0, atol=1e-12) and c.radius == pytest.approx(1.0)
    assert c.angles[1] == pytest.approx(math.pi / 2) and c.angles[2] == pytest.approx(math.pi)
    assert np.allclose(c.point(c.angles[1]), p[1])
    with pytest.raises(KinematicsError, match="one line"):
        Circle.through(p[0], 2 * p[0], 3 * p[0])


# ------------------------------------------------------------------------------------------------ planning


def _check_limits(res, req):
    lim = req.limits
    dt = req.dt
    v, a, j = _derivatives(res["q"], dt)
    assert np.all(np.abs(v).max(axis=0) <= np.array(lim["velocity_rad_s"]) * 1.01)
    assert np.all(np.abs(a).max(axis=0) <= np.array(lim["acceleration_rad_s2"]) * 1.02)
    # the jerk of the sampled table (third difference) against the limit, with the sampling's slack
    assert np.all(np.abs(j).max(axis=0) <= np.array(lim["jerk_rad_s3"]) * 1.1)
    assert np.allclose(res["dq"][1:-1], (res["q"][2:] - res["q"][:-2]) / (2 * dt), atol=0.01)
    assert np.all(res["q"] >= np.array(lim["lower_rad"])) and np.all(res["q"] <= np.array(lim["upper_rad"]))


def test_plan_linear_ptp_stops_exactly_at_waypoints_within_limits(tmp_path, cfg, kin):
    wps = _waypoints()
    path = _program(tmp_path, wps)
    start = wps[-1] + 0.05
    req = request_from_config(cfg, path, start, interp="linear")
    res = plan_replay(req)
    _check_limits(res, req)
    q, dt = res["q"], req.dt
    assert np.allclose(q[0], start) and np.allclose(q[-1], wps[0])
    # move to start is slow: velocity at most move_to_start_speed × the limits
    b = res["body_row"]
    assert np.all(np.abs(res["dq"][:b]).max(axis=0) <= np.array(req.limits["velocity_rad_s"]) * req.move_to_start_speed
                  * 1.001)
    marks = res["marks"]
    assert [m["name"] for m in marks] == ["p2", "p3", "p1"] and {m["kind"] for m in marks} == {"stop"}
    for m in marks:
        k = int(round(m["t_s"] / dt))
        seg = q[k - int(req.settle_s / dt) + 1:k + 1]  # the settle dwell before the mark: at the waypoint, still
        assert np.abs(seg - np.array(m["q_rad"])).max() < 1e-12
    # each joint-space move is a straight line: every joint starts and stops together (synchronised)
    s = res["summary"]
    ptp = [g for g in s["segments"] if g["label"].startswith("ptp")]
    assert len(ptp) == 3 and all(max(g["velocity_ratio"], g["acceleration_ratio"], g["jerk_ratio"],
                                     g["tcp_speed_ratio"]) > 0.99 for g in ptp)  # a limit is used fully
    # TCP speed within the Cartesian limit (forward kinematics of the table)
    pos = np.array([kin.position(x) for x in q[::5]])
    assert np.linalg.norm(np.diff(pos, axis=0), axis=1).max() / (5 * dt) <= cfg.replay.cartesian_speed_m_s * 1.02
    assert res["ff_Nm"].shape == q.shape and np.abs(res["ff_Nm"]).max() > 0.1  # inertial feed-forward


def test_plan_circular_follows_the_cartesian_circle_through_p1_p2_p3(tmp_path, cfg, kin):
    wps = _waypoints()
    path = _program(tmp_path, wps)
    req = request_from_config(cfg, path, wps[0], interp="circular")
    res = plan_replay(req)
    _check_limits(res, req)
    circle = res["summary"]["circle"]
    c, r, n = np.array(circle["center_m"]), circle["radius_m"], np.array(circle["normal"])
    assert 0.1 < r < 0.3
    b = res["body_row"]
    body = res["q"][b:]
    pos = np.array([kin.position(x) for x in body[::10]])
    d = pos - c
    assert np.abs(np.linalg.norm(d - np.outer(d @ n, n), axis=1) - r).max() < 1e-4  # on the circle's cylinder...
    assert np.abs(d @ n).max() < 1e-4  # ... and in its plane
    # the whole circle: the angle swept is 2π (back to p1)
    ang = np.unwrap(np.arctan2(d @ np.cross(n, d[0] / np.linalg.norm(d[0])), d @ (d[0] / np.linalg.norm(d[0]))))
    assert abs(ang[-1] - ang[0]) == pytest.approx(2 * math.pi, abs=0.02)
    marks = {m["name"]: m for m in res["marks"]}
    assert marks["p2"]["kind"] == "pass" and marks["p3"]["kind"] == "pass" and marks["p1"]["kind"] == "stop"
    for name, w in (("p2", wps[1]), ("p3", wps[2])):
        k = int(round(marks[name]["t_s"] / req.dt))
        assert np.abs(res["q"][k - 1:k + 2] - w).min(axis=0).max() < math.radians(0.02)  # passes the taught joints
    # constant TCP speed in the cruise at most the Cartesian limit
    speed = np.linalg.norm(np.diff(pos, axis=0), axis=1) / (10 * req.dt)
    assert speed.max() <= cfg.replay.cartesian_speed_m_s * 1.02
    # two waypoints make no circle; collinear poses neither
    with pytest.raises(PlanError, match="exactly 3 waypoints"):
        plan_replay(request_from_config(cfg, _program(tmp_path, wps[:2], "two"), wps[0], interp="circular"))


def test_plan_spline_and_soft_limits(tmp_path, cfg):
    wps = _waypoints()
    path = _program(tmp_path, wps)
    req = request_from_config(cfg, path, wps[0], interp="spline")
    res = plan_replay(req)
    _check_limits(res, req)
    marks = {m["name"]: m for m in res["marks"]}
    for name, w in (("p2", wps[1]), ("p3", wps[2])):
        k = int(round(marks[name]["t_s"] / req.dt))
        assert np.abs(res["q"][k - 1:k + 2] - w).min(axis=0).max() < math.radians(0.05)
        assert np.abs(res["dq"][k]).max() > 0.05  # passes without stopping
    # a waypoint beyond the soft limit (limit - margin) is refused before anything moves
    far = [w.copy() for w in wps]
    far[1][1] = 3.1
    with pytest.raises(PlanError, match="soft limits of joint2"):
        plan_replay(request_from_config(cfg, _program(tmp_path, far, "far"), wps[0], interp="linear"))


def test_keyframes_and_retimed_path_replay(tmp_path, cfg):
    # a recording at 50 Hz: a smooth curve, a 1 s pause in the middle, a second curve
    t = np.arange(0.0, 8.0, 0.02)
    s = np.clip((t - 0.5) / 3.0, 0, 1)
    s2 = np.clip((t - 4.5) / 3.0, 0, 1)
    q = Q0 + np.outer(0.5 - 0.5 * np.cos(np.pi * s), [0.3, 0.2, -0.2, 0.1, 0.2, 0.3]) \
        + np.outer(np.sin(np.pi * s) * 0.1, [0, 1, 0, 1, 0, 0]) \
        + np.outer(0.5 - 0.5 * np.cos(np.pi * s2), [-0.2, 0.1, 0.1, 0.0, -0.3, 0.1])
    kf = extract_keyframes(t, q, math.radians(0.5))
    assert kf.kind[0] == "start" and kf.kind[-1] == "end" and "pause" in kf.kind
    assert len(kf.index) < len(t) / 8 and kf.max_deviation_rad <= math.radians(0.5)
    rows = [[float(a)] + list(map(float, b)) for a, b in zip(t, q, strict=True)]
    path = _program(tmp_path, [], name="rec", path_rows=rows)
    # post-processing from the CLI: keyframes written into the program, then a re-timed replay plan
    out = json.loads(run_cli("teach", "keyframes", str(path), "--tolerance-deg", "0.5", "--write", "--json").stdout)
    assert out["written"] and out["keyframes"] == len(kf.index) and out["max_deviation_deg"] <= 0.5
    assert load_program(path).keyframes is not None
    req = request_from_config(cfg, path, q[0], interp="spline")
    res = plan_replay(req)
    _check_limits(res, req)
    assert res["summary"]["source"] == "path"
    # the replayed path (not the move back to the start) stays within the tolerance of the recording
    segs = [g for g in res["summary"]["segments"] if g["label"] == "path"]
    assert len(segs) == 2  # two sections: the pause is a stop
    rows_path = np.concatenate([np.arange(int(g["t0_s"] / req.dt), int(g["t1_s"] / req.dt)) for g in segs])
    d = np.abs(res["q"][rows_path[::10], None, :] - q[None, :, :]).max(axis=2).min(axis=1)
    assert d.max() < math.radians(0.6)
    # re-timed under the limits: faster than the hand (8 s) but not faster than the limits allow
    assert res["summary"]["cycle_s"] < 8.0
    dry = json.loads(run_cli("replay", str(path), "--dry-run", "--interp", "spline", "--json").stdout)
    assert dry["source"] == "path" and dry["cycle_s"] == pytest.approx(res["summary"]["cycle_s"], abs=0.01)


def test_keyframes_of_a_hand_recording_with_still_periods_and_marks(tmp_path, cfg):
    # as a hand teaches: still at the start, a pull, still while p1 is marked, a pull, still at the end (marked)
    t = np.arange(0.0, 9.0, 0.02)
    s1 = np.clip((t - 1.0) / 2.0, 0, 1)
    s2 = np.clip((t - 5.0) / 2.0, 0, 1)
    q = Q0 + np.outer(0.5 - 0.5 * np.cos(np.pi * s1), STEPS[0]) + np.outer(0.5 - 0.5 * np.cos(np.pi * s2), STEPS[1])
    kf = extract_keyframes(t, q, math.radians(0.5), marks_t=[4.0, 8.5])
    kq = q[kf.index]
    assert np.linalg.norm(np.diff(kq, axis=0), axis=1).min() > 1e-4  # no two keyframes at one place
    assert kf.kind[0] == "start" and kf.kind[-1] == "end" and kf.kind.count("pause") + kf.kind.count("mark") >= 1
    rows = [[float(a)] + list(map(float, b)) for a, b in zip(t, q, strict=True)]
    path = _program(tmp_path, [], name="hand", path_rows=rows)
    res = plan_replay(request_from_config(cfg, path, q[0], interp="spline"))
    labels = [g["label"] for g in res["summary"]["segments"]]
    assert labels.count("path") == 2  # one stop where the hand held still in the middle
    still = _program(tmp_path, [], name="still", path_rows=[[0.02 * k] + list(Q0) for k in range(50)])
    with pytest.raises(PlanError, match="no motion"):
        plan_replay(request_from_config(cfg, still, Q0, interp="spline"))
