"""In-process tests of the simulated arm's physics, truth loader and virtual operator (fast, no bus)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import yaml

from dragd.model import RobotModel
from sim.axis import AxisIO
from sim.operator import Operator, ScenarioError, load_scenario, validate_scenario
from sim.physics import ArmPhysics
from sim.truth import DEFAULT_TRUTH, Truth, TruthError, load_truth

pytestmark = pytest.mark.unit

FRICTIONLESS = {"coulomb_pos_Nm": 0.0, "coulomb_neg_Nm": 0.0, "static_pos_Nm": 0.0, "static_neg_Nm": 0.0,
                "viscous_pos_Nm_s_per_rad": 0.0, "viscous_neg_Nm_s_per_rad": 0.0}


@pytest.fixture(scope="module")
def truth() -> Truth:
    return load_truth()


@pytest.fixture(scope="module")
def robot(truth: Truth) -> RobotModel:
    return truth.load_model()


def make(truth: Truth, robot: RobotModel, q: np.ndarray | None = None) -> tuple[ArmPhysics, list[AxisIO]]:
    axes = [AxisIO() for _ in robot.joint_names]
    phys = ArmPhysics(truth, robot, axes)
    if q is not None:
        phys.set_state(q)
    return phys, axes


def frictionless(truth: Truth, joints: range | list[int] | None = None) -> Truth:
    idx = range(len(truth.joints)) if joints is None else joints
    return truth.with_updates(joints={i: {"friction": FRICTIONLESS} for i in idx})


def run(phys: ArmPhysics, seconds: float, record: bool = False) -> np.ndarray:
    steps = int(round(seconds / phys.dt_s))
    out = np.empty((steps, phys.n)) if record else np.empty((0, phys.n))
    for i in range(steps):
        phys.step()
        if record:
            out[i] = phys.q_rad
    return out


def hold_gravity(phys: ArmPhysics, axes: list[AxisIO], robot: RobotModel, truth: Truth,
                 scale: float = 1.0) -> np.ndarray:
    """Power on with each joint's current = scale·G(q)/K_t (the true K_t); returns G."""
    g = robot.gravity(phys.q_rad)
    for i, ax in enumerate(axes):
        ax.power_stage_on = True
        ax.current_demand_A = scale * g[i] / truth.joints[i].torque_constant_Nm_per_A
    return g


# ----------------------------------------------------------------------------------------------- truth


def test_bundled_truth_is_realistic(truth: Truth, robot: RobotModel) -> None:
    assert truth.physics_rate_Hz >= 4000 and truth.bus.fd
    assert [j.drive.node_id for j in truth.joints] == [1, 2, 3, 4, 5, 6]
    j2 = truth.joints[1]
    assert 10.0 <= j2.friction.static_pos <= 11.0 and 7.5 <= j2.friction.coulomb_pos_Nm <= 8.5
    for j in truth.joints:
        assert j.friction.static_pos > j.friction.coulomb_pos_Nm > 0
        assert j.friction.static_neg < j.friction.coulomb_neg_Nm < 0
        assert 0.001 <= j.drive.rated_current_A / 1000 <= 0.01  # 1 per mille is a few mA
        km = j.drive.rated_torque_Nm / j.drive.rated_current_A
        assert abs(km * j.gear_ratio - j.torque_constant_Nm_per_A) / j.torque_constant_Nm_per_A < 0.05
    # the drives can hold the arm stretched out
    g = np.abs(robot.gravity(np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0])))
    for j, gj in zip(truth.joints, g, strict=True):
        assert gj < 0.8 * j.drive.max_current_A * j.torque_constant_Nm_per_A


def test_truth_errors_name_file_path_and_expectation(tmp_path: Path) -> None:
    data = yaml.safe_load(DEFAULT_TRUTH.read_text())
    data["joints"][2]["gear_ratio"] = "abc"
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(data))
    with pytest.raises(TruthError) as exc:
        load_truth(bad)
    assert f"{bad}: joints[2].gear_ratio: expected a positive number, got 'abc'" in str(exc.value)

    data = yaml.safe_load(DEFAULT_TRUTH.read_text())
    data["physics_rate_Hz"] = 1000
    data["joints"][1]["friction"]["static_pos_Nm"] = 1.0
    data["joints"][0]["hidden"] = {"ripple": [{"amplitude_Nm": 0.1}], "typo": 1}
    bad.write_text(yaml.safe_dump(data))
    with pytest.raises(TruthError) as exc:
        load_truth(bad)
    msg = str(exc.value)
    assert f"{bad}: physics_rate_Hz: expected an integer rate in [4000, 50000] Hz, got 1000" in msg
    assert f"{bad}: joints[1].friction: expected static_pos_Nm >= coulomb_pos_Nm" in msg
    assert f"{bad}: joints[0].hidden.ripple[0].cycles_per_rev: missing required key" in msg
    assert f"{bad}: joints[0].hidden.typo: unknown key" in msg


def test_truth_must_match_robot(truth: Truth, robot: RobotModel) -> None:
    data = truth.model_dump()
    data["joints"][0]["name"] = "shoulder"
    other = Truth.model_validate(data)
    with pytest.raises(TruthError, match="joints: expected the robot's joints joint1"):
        ArmPhysics(other, robot, [AxisIO() for _ in range(6)])


def test_too_stiff_stop_is_rejected(truth: Truth, robot: RobotModel) -> None:
    stiff = truth.with_updates(joints={"joint6": {"hard_stops": {"damping_Nm_s_per_rad": 5000.0}}})
    with pytest.raises(TruthError, match=r"joints\[5\].hard_stops.damping_Nm_s_per_rad"):
        make(stiff, robot)


# ----------------------------------------------------------------------------------------------- dynamics


def _stable_equilibrium(robot: RobotModel, q: np.ndarray, j: int) -> tuple[np.ndarray, float]:
    """Newton on G_j(q_j) = 0 from q, requiring dG_j/dq_j > 0 (the hanging position); returns q and the stiffness."""
    q = q.copy()
    h = 1e-6
    for _ in range(50):
        g = robot.gravity(q)[j]
        qp = q.copy()
        qp[j] += h
        k = (robot.gravity(qp)[j] - g) / h
        q[j] -= g / k
        if abs(g) < 1e-12:
            break
    qp = q.copy()
    qp[j] += h
    qm = q.copy()
    qm[j] -= h
    k = (robot.gravity(qp)[j] - robot.gravity(qm)[j]) / (2 * h)
    assert k > 0, "not a stable equilibrium"
    return q, k


@pytest.mark.parametrize("j, q_guess", [(1, [0.0, 1.5, 0.0, 0.0, 1.5708, 0.0]),
                                        (2, [0.0, 0.0, 1.5, 0.0, 1.5708, 0.0]),
                                        (3, [0.0, 0.0, 0.0, 0.2, 1.5708, 0.0])])
def test_pendulum_period_matches_model(truth: Truth, robot: RobotModel, j: int, q_guess: list[float]) -> None:
    """One joint released (brake off, no power, no friction), the others braked: small-angle period 2π√(I/k)."""
    q_eq, k = _stable_equilibrium(robot, np.array(q_guess), j)
    data = robot.model.createData()
    inertia = pin.crba(robot.model, data, q_eq)[j, j] + truth.joints[j].armature_kgm2
    expected = 2 * math.pi * math.sqrt(inertia / k)

    phys, axes = make(frictionless(truth, [j]), robot)
    q0 = q_eq.copy()
    q0[j] += 0.01
    phys.set_state(q0)
    axes[j].brake_engaged = False
    trace = run(phys, 3.2 * expected, record=True)[:, j] - q_eq[j]
    others = [i for i in range(6) if i != j]
    assert np.array_equal(phys.q_rad[others], q_eq[others]), "braked joints moved"
    # downward zero crossings, linearly interpolated
    idx = np.flatnonzero((trace[:-1] > 0) & (trace[1:] <= 0))
    times = (idx + trace[idx] / (trace[idx] - trace[idx + 1])) * phys.dt_s
    assert len(times) >= 3
    period = float(np.mean(np.diff(times)))
    assert abs(period - expected) / expected < 0.02, (period, expected)
    # no friction: the amplitude stays
    assert np.max(trace[-int(expected / phys.dt_s):]) > 0.0095


def test_gravity_torque_holds_the_arm(truth: Truth, robot: RobotModel) -> None:
    """Current = G(q)/K_t with zero friction: the arm stays within 0.05° over 2 s (and 2 % less does not)."""
    for scale, should_hold in ((1.0, True), (0.98, False)):
        phys, axes = make(frictionless(truth), robot)
        q0 = phys.q_rad.copy()
        hold_gravity(phys, axes, robot, truth, scale)
        run(phys, 0.02)  # current loop settles with the brakes on
        assert np.array_equal(phys.q_rad, q0)
        for ax in axes:
            ax.brake_engaged = False
        trace = run(phys, 2.0, record=True)
        drift_deg = np.degrees(np.max(np.abs(trace - q0)))
        assert (drift_deg < 0.05) == should_hold, (scale, drift_deg)


def test_current_loop_lag_noise_and_quantisation(truth: Truth, robot: RobotModel) -> None:
    phys, axes = make(truth, robot)
    j = 0
    tau = truth.joints[j].current_loop_time_constant_s
    axes[j].power_stage_on = True
    axes[j].current_demand_A = 1.0
    steps = int(round(tau / phys.dt_s))
    readings = []
    for _ in range(steps):
        phys.step()
    assert abs(phys.current_A[j] - (1 - math.exp(-steps * phys.dt_s / tau))) < 1e-9
    for _ in range(4000):
        phys.step()
        readings.append(phys.current_measured_A[j])
    r = np.array(readings)
    quantum = truth.joints[j].current_quantum_A
    assert np.allclose(r / quantum, np.round(r / quantum), atol=1e-9)
    assert abs(r.mean() - 1.0) < 0.003
    assert 0.8 * truth.joints[j].current_noise_std_A < r.std() < 1.25 * truth.joints[j].current_noise_std_A
    axes[j].power_stage_on = False
    phys.step()
    assert phys.current_A[j] == 0.0 and phys.tau_motor_Nm[j] == 0.0


# ----------------------------------------------------------------------------------------------- stick–slip


def _ramp(phys: ArmPhysics, robot: RobotModel, joint: str, sign: int, threshold: float = 2e-4) -> dict:
    op = Operator({"segments": [{"kind": "ramp", "joint": joint, "rate_per_s": 2.0, "sign": sign,
                                 "threshold_rad": threshold, "timeout_s": 30.0}]}, robot, phys.t_s)
    phys.operator = op
    while not op.done:
        phys.step()
    phys.operator = None
    events = op.breakaways()
    assert len(events) == 1, op.events
    return events[0]


@pytest.mark.parametrize("j", [0, 1, 4])
@pytest.mark.parametrize("sign", [1, -1])
def test_ramp_breaks_away_at_static_friction(truth: Truth, robot: RobotModel, j: int, sign: int) -> None:
    """Gravity held by the drives, the others braked: a 2 N·m/s ramp breaks the joint away at its static level."""
    phys, axes = make(truth, robot)
    hold_gravity(phys, axes, robot, truth)
    run(phys, 0.02)
    axes[j].brake_engaged = False
    q0 = phys.q_rad.copy()
    run(phys, 0.1)
    assert np.array_equal(phys.q_rad, q0), "released joint crept before the ramp"
    fr = truth.joints[j].friction
    static = fr.static_pos if sign > 0 else fr.static_neg
    ev = _ramp(phys, robot, f"joint{j + 1}", sign)
    assert abs(ev["torque_Nm"] - static) / abs(static) < 0.05, (ev, static)
    assert abs(ev["onset_load"] - static) / abs(static) < 0.01, (ev, static)
    assert np.sign(phys.q_rad[j] - q0[j]) == sign


def test_no_chatter_no_drift_below_static(truth: Truth, robot: RobotModel) -> None:
    """Below static friction a joint at rest stays exactly at rest; after sliding it stops and stays stopped."""
    phys, axes = make(truth, robot)
    axes[0].brake_engaged = False
    q0 = phys.q_rad.copy()
    static = truth.joints[0].friction.static_pos
    phys.tau_ext_Nm[0] = 0.97 * static
    for _ in range(4000):
        phys.step()
        assert phys.stuck[0] and phys.q_rad[0] == q0[0]
    phys.tau_ext_Nm[0] = 1.5 * static  # slide ...
    run(phys, 0.5)
    assert phys.dq_rad_s[0] > 0.01
    phys.tau_ext_Nm[0] = 0.5 * truth.joints[0].friction.coulomb_pos_Nm  # ... then friction stops it
    run(phys, 1.0)
    q_stop = phys.q_rad[0]
    assert phys.stuck[0] and phys.dq_rad_s[0] == 0.0
    run(phys, 1.0)
    assert phys.q_rad[0] == q_stop
    assert abs(phys.tau_friction_Nm[0] + 0.5 * truth.joints[0].friction.coulomb_pos_Nm) < 1e-9


def test_coupled_joints_stick_and_slide_together(truth: Truth, robot: RobotModel) -> None:
    """Joints 2 and 3 unbraked, gravity 5 % under-compensated: each holds on friction alone (|ΔG| < static)."""
    phys, axes = make(truth, robot)
    g = hold_gravity(phys, axes, robot, truth, 0.95)
    assert all(0.05 * abs(g[i]) < truth.joints[i].friction.static_pos for i in (1, 2))
    run(phys, 0.02)
    q0 = phys.q_rad.copy()
    axes[1].brake_engaged = axes[2].brake_engaged = False
    run(phys, 1.0)
    assert np.array_equal(phys.q_rad, q0)
    # 70 % under-compensated: more than static friction -> the arm sinks and both joints move
    hold_gravity(phys, axes, robot, truth, 0.3)
    run(phys, 0.3)
    assert abs(phys.q_rad[1] - q0[1]) > 1e-3 and not phys.stuck[1]


# ----------------------------------------------------------------------------------------------- brakes, stops


def test_brakes_hold_gravity_and_slip_above_holding_torque(truth: Truth, robot: RobotModel) -> None:
    phys, axes = make(truth, robot)
    q0 = phys.q_rad.copy()
    assert abs(robot.gravity(q0)[1]) > 30  # the brakes carry a real load
    run(phys, 1.0)
    assert np.array_equal(phys.q_rad, q0)
    limit = truth.joints[0].brake_holding_torque_Nm + truth.joints[0].friction.static_pos
    assert phys.static_friction_Nm(0, +1) == pytest.approx(limit)
    phys.tau_ext_Nm[0] = 0.95 * limit
    run(phys, 0.5)
    assert np.array_equal(phys.q_rad, q0)
    phys.tau_ext_Nm[0] = 1.1 * limit
    run(phys, 0.2)
    assert phys.q_rad[0] - q0[0] > 1e-3  # slips


@pytest.mark.parametrize("side", [+1, -1])
def test_hard_stop_stops_the_joint(truth: Truth, robot: RobotModel, side: int) -> None:
    j = 0
    stops = truth.joints[j].hard_stops
    limit = stops.upper_rad if side > 0 else stops.lower_rad
    q = np.array([jj.initial_position_rad for jj in truth.joints])
    q[j] = limit - side * 0.05
    phys, axes = make(truth, robot, q)
    axes[j].brake_engaged = False
    push = 40.0
    phys.tau_ext_Nm[j] = side * push
    trace = run(phys, 1.5, record=True)[:, j]
    overshoot = np.max(side * (trace - limit))
    # energy bound: at most push·0.05 rad of kinetic energy at contact, stored in the stop's spring
    k = stops.stiffness_Nm_per_rad
    static = truth.joints[j].friction.static_pos if side > 0 else -truth.joints[j].friction.static_neg
    assert (push - static) / k < overshoot < math.sqrt(2 * push * 0.05 / k) + push / k
    # at rest in the stop: spring = push ± what static friction can hold
    settle = side * (trace[-1] - limit)
    assert (push - static) / k - 1e-9 <= settle <= (push + static) / k + 1e-9
    assert phys.dq_rad_s[j] == 0.0 and phys.stuck[j]


# ----------------------------------------------------------------------------------------------- hidden effects


def test_current_offset_and_load_friction(truth: Truth, robot: RobotModel) -> None:
    # current offset: the loop delivers demand − offset but reports ≈ demand
    t_o = truth.with_updates(joints={0: {"hidden": {"current_offset_A": 0.05}, "current_noise_std_A": 0.0,
                                         "current_quantum_A": 0.0}})
    phys, axes = make(t_o, robot)
    axes[0].power_stage_on = True
    axes[0].current_demand_A = 1.0
    run(phys, 0.05)
    assert phys.current_A[0] == pytest.approx(0.95)
    assert phys.current_measured_A[0] == pytest.approx(1.0)

    # load-dependent friction: joint 2's breakaway grows by coefficient·|G2|
    t_l = truth.with_updates(joints={1: {"hidden": {"load_friction_per_Nm": 0.05}}})
    phys, axes = make(t_l, robot)
    g = hold_gravity(phys, axes, robot, t_l)
    run(phys, 0.02)
    axes[1].brake_engaged = False
    phys.step()
    expected = truth.joints[1].friction.static_pos + 0.05 * abs(g[1])
    assert phys.static_friction_Nm(1, +1) == pytest.approx(expected)
    ev = _ramp(phys, robot, "joint2", +1)
    assert abs(ev["onset_load"] - expected) / expected < 0.01


def test_ripple_accelerates_free_joint(truth: Truth, robot: RobotModel) -> None:
    t_r = frictionless(truth, [0]).with_updates(joints={0: {"hidden": {"ripple": [
        {"amplitude_Nm": 0.8, "cycles_per_rev": 2, "reference": "motor", "phase_rad": math.pi / 2}]}}})
    phys, axes = make(t_r, robot, np.zeros(6))
    axes[0].brake_engaged = False
    phys.step()
    # the other joints are braked (stuck): joint 1 alone accelerates with 1/(M⁻¹ restricted) = M_11 (+ armature)
    data = robot.model.createData()
    inertia = pin.crba(robot.model, data, np.zeros(6))[0, 0] + truth.joints[0].armature_kgm2
    accel = phys.dq_rad_s[0] / phys.dt_s
    assert accel == pytest.approx(0.8 / inertia, rel=1e-6)


def test_thermal_drift_lowers_friction_as_the_joint_heats(truth: Truth, robot: RobotModel) -> None:
    t_th = truth.with_updates(joints={0: {"hidden": {"thermal": {"heat_capacity_J_per_K": 5.0,
                                                                 "friction_coefficient_per_K": -0.01}}}})
    phys, axes = make(t_th, robot)
    axes[0].brake_engaged = False
    cold = phys.static_friction_Nm(0, +1)
    phys.tau_ext_Nm[0] = 15.0  # spins up against viscous friction, dissipating heat
    run(phys, 3.0)
    assert phys.temperature_C[0] > 30.0
    hot = phys.static_friction_Nm(0, +1)
    expected = truth.joints[0].friction.static_pos * (1 - 0.01 * (phys.temperature_C[0] - 25.0))
    assert hot == pytest.approx(expected) and hot < cold


def test_friction_drift_changes_the_viscous_slope_by_its_own_factor(truth: Truth, robot: RobotModel) -> None:
    """Warm-up drift: the Coulomb level × (1 + change·g), the viscous slope × (1 + viscous_change·g)."""
    def sliding_friction(viscous_change: float | None) -> float:
        drift = {"change": 0.2, "time_constant_s": 0.01, "viscous_change": viscous_change}
        t = truth.with_updates(joints={0: {"hidden": {"friction_drift": drift}}})
        phys, axes = make(t, robot)
        axes[0].brake_engaged = False
        phys.set_state(phys.q_rad, np.array([0.5, 0, 0, 0, 0, 0.0]))
        run(phys, 0.2)  # g = 1 − e^(−20): warm
        phys.set_state(phys.q_rad, np.array([0.5, 0, 0, 0, 0, 0.0]))
        phys.step()
        return -float(phys.tau_friction_Nm[0])

    f = truth.joints[0].friction
    v = 0.5
    both = sliding_friction(None)
    apart = sliding_friction(-0.5)
    visc = f.viscous_pos_Nm_s_per_rad * v
    assert both - apart == pytest.approx((0.2 + 0.5) * visc, rel=0.02)  # only the viscous part differs
    assert visc > 0.05 * both  # the check means something: the viscous part is not negligible at this speed


def test_backlash_lets_the_output_move_against_a_braked_rotor(truth: Truth, robot: RobotModel) -> None:
    gap = 0.004
    t_b = truth.with_updates(joints={0: {"hidden": {"backlash_rad": gap, "gear_stiffness_Nm_per_rad": 20000.0}}})
    phys, axes = make(t_b, robot)
    q0 = phys.q_rad[0]
    phys.tau_ext_Nm[0] = 20.0  # brake engaged on the rotor; the output crosses the gap, then loads the teeth
    run(phys, 1.0)
    moved = phys.q_rad[0] - q0
    assert moved == pytest.approx(gap / 2 + 20.0 / 20000.0, rel=0.05)
    assert phys.rotor_rad[0] == q0  # the brake holds the rotor
    # without backlash the braked joint does not move at all
    phys, axes = make(truth, robot)
    phys.tau_ext_Nm[0] = 20.0
    run(phys, 1.0)
    assert phys.q_rad[0] == q0


def test_backlash_splits_the_friction_between_rotor_and_output(truth: Truth, robot: RobotModel) -> None:
    gap, share = 0.004, 0.3
    t_b = truth.with_updates(joints={0: {"hidden": {"backlash_rad": gap, "output_friction_fraction": share}}})
    phys, axes = make(t_b, robot)
    static = truth.joints[0].friction.static_pos
    axes[0].brake_engaged = False
    run(phys, 0.01)
    assert phys.static_friction_Nm(0, +1) == pytest.approx(static)  # rotor's and output's shares add up
    q0 = phys.q_rad[0]
    phys.tau_ext_Nm[0] = 0.8 * share * static  # below the output's own breakaway: it stays inside the play
    run(phys, 0.5)
    assert phys.q_rad[0] == q0 and phys.rotor_rad[0] == q0
    phys.tau_ext_Nm[0] = 1.2 * share * static  # above it: the output crosses half the play to the rotor's tooth;
    run(phys, 0.5)  # the rotor (the larger share) takes the impact with a nudge and holds it there
    assert phys.dq_rad_s[0] == 0.0
    assert phys.q_rad[0] - phys.rotor_rad[0] == pytest.approx(gap / 2, abs=3e-4)  # + the tooth's compliance
    assert 0.0 <= phys.rotor_rad[0] - q0 < 0.1 * gap


# ----------------------------------------------------------------------------------------------- operator


def test_flange_force_equals_a_point_mass_at_the_flange(truth: Truth, robot: RobotModel) -> None:
    """Jᵀ·[0, 0, −m·g] from the operator equals the gravity torque a mass m adds at tool0."""
    mass = 2.0
    q = np.array([0.3, -0.7, 1.1, -0.5, 1.2, 0.4])
    op = Operator({"segments": [{"kind": "push", "force_N": [0.0, 0.0, -mass * 9.81], "duration_s": 1.0}]}, robot, 0.0)
    tau = np.zeros(6)
    op.apply(0.0, q, np.zeros(6), tau)
    loaded = pin.Model(robot.model)
    fid = loaded.getFrameId("tool0")
    frame = loaded.frames[fid]
    loaded.appendBodyToJoint(frame.parentJoint, pin.Inertia(mass, frame.placement.translation, np.zeros((3, 3))),
                             pin.SE3.Identity())
    extra = pin.computeGeneralizedGravity(loaded, loaded.createData(), q) - robot.gravity(q)
    assert np.allclose(tau, -extra, atol=1e-9)


def test_scenario_segments_and_events(truth: Truth, robot: RobotModel) -> None:
    phys, axes = make(truth, robot)
    axes[0].brake_engaged = False
    scen = {"name": "t", "segments": [
        {"kind": "push", "joint": "joint1", "torque_Nm": 3.0, "duration_s": 0.5},
        {"kind": "ramp", "joint": "joint1", "start": 3.0, "rate_per_s": 4.0, "threshold_rad": 0.001, "then": "hold"},
        {"kind": "hold", "duration_s": 0.2},
        {"kind": "release", "ramp_down_s": 0.1, "duration_s": 0.1},
    ]}
    op = Operator(scen, robot, phys.t_s)
    phys.operator = op
    seen = []
    while not op.done:
        phys.step()
        seen.append((op.segment_index, phys.tau_ext_Nm[0]))
    kinds = [e["kind"] for e in op.events]
    assert kinds == ["start", "segment", "segment", "breakaway", "segment", "segment", "done"]
    br = op.breakaways()[0]
    assert br["torque_Nm"] > truth.joints[0].friction.static_pos
    holds = [tau for seg, tau in seen if seg == 2]
    assert holds and all(tau == br["torque_Nm"] for tau in holds)
    pushes = [tau for seg, tau in seen if seg == 0]
    assert all(tau == 3.0 for tau in pushes)
    assert abs(phys.tau_ext_Nm[0]) < 0.05 * br["torque_Nm"]
    phys.step()
    assert phys.tau_ext_Nm[0] == 0.0


def test_hand_pulls_the_flange_to_a_target(truth: Truth, robot: RobotModel) -> None:
    phys, axes = make(frictionless(truth), robot)
    hold_gravity(phys, axes, robot, truth)
    run(phys, 0.02)
    for ax in axes:
        ax.brake_engaged = False
    data = robot.model.createData()
    fid = robot.model.getFrameId("tool0")
    pin.framesForwardKinematics(robot.model, data, phys.q_rad)
    start = data.oMf[fid].translation.copy()
    op = Operator({"segments": [{"kind": "hand", "position_m": [0.05, 0.0, -0.03], "relative": True,
                                 "stiffness": 400.0, "damping": 80.0, "duration_s": 4.0}]}, robot, phys.t_s)
    phys.operator = op
    for _ in range(int(4.0 / phys.dt_s)):
        hold_gravity(phys, axes, robot, truth)  # an ideal gravity compensation
        phys.step()
    pin.framesForwardKinematics(robot.model, data, phys.q_rad)
    moved = data.oMf[fid].translation - start
    assert np.linalg.norm(moved - np.array([0.05, 0.0, -0.03])) < 0.01


def test_scenario_validation_errors(robot: RobotModel) -> None:
    with pytest.raises(ScenarioError, match=r"segments\[0\]\.ramp.rate_per_s: expected a positive number, got -1"):
        validate_scenario({"segments": [{"kind": "ramp", "joint": "joint2", "rate_per_s": -1}]}, "x.yaml")
    with pytest.raises(ScenarioError, match="expected exactly one of joint"):
        validate_scenario({"segments": [{"kind": "ramp", "rate_per_s": 1}]}, "x.yaml")
    with pytest.raises(ScenarioError, match=r"segments\[0\]\.push\.joint: expected one of joint1"):
        Operator({"segments": [{"kind": "push", "joint": "elbow", "torque_Nm": 1, "duration_s": 1}]}, robot)


def test_bundled_scenarios_load(robot: RobotModel) -> None:
    files = sorted((Path(__file__).resolve().parents[1] / "sim" / "scenarios").glob("*.yaml"))
    assert files
    for f in files:
        Operator(load_scenario(f), robot)


def test_operator_move_segment_measures_effort(truth: Truth, robot: RobotModel) -> None:
    """The `move` hand drives a joint at a set speed; its torque then equals the friction it overcomes."""
    phys, axes = make(truth, robot)
    axes[0].brake_engaged = False  # joint 1 (vertical axis: no gravity), the others braked
    op = Operator({"name": "m", "segments": [{"kind": "move", "joint": "joint1", "velocity_rad_s": 0.2,
                                              "duration_s": 2.0}]}, robot, phys.t_s)
    phys.operator = op
    while not op.done:
        phys.step()
    (ev,) = [e for e in op.events if e["kind"] == "move"]
    fr = truth.joints[0].friction
    expected = fr.coulomb_pos_Nm + fr.viscous_pos_Nm_s_per_rad * 0.2
    assert ev["velocity_mean_rad_s"] == pytest.approx(0.2, rel=0.02)
    assert ev["torque_Nm_mean"] == pytest.approx(expected, rel=0.05)
