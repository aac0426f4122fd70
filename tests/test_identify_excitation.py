"""Excitation plans: within limits, rest-to-rest, the seeds' shapes, loadable by the daemon's Trajectory."""

from __future__ import annotations

import numpy as np
import pytest

from dragd.identify import excitation as E
from dragd.identify.runner import _approach, chunks

from identify_helpers import START, limits, robot

pytestmark = pytest.mark.unit


def _speeds(plan, kind, joint=None):
    dq, _ = plan.derivatives()
    out = []
    for s in plan.segments:
        if s.kind == kind and (joint is None or s.joint == joint):
            m = (plan.t_s > s.t0_s) & (plan.t_s < s.t1_s)
            out.append(np.abs(dq[m]).max(axis=0))
    return np.array(out)


def test_lowspeed_is_slow_reciprocating_single_joint():
    b = E.PlanBuilder(START, limits())
    E.add_lowspeed(b, [1], seconds_per_joint=100.0)
    plan = b.build("low")
    sp = _speeds(plan, "lowspeed", 1)
    assert len(sp) == 4  # two round trips
    assert sp[:, 1].max() <= np.radians(2.0) * 1.001  # ≤ 2°/s (seed 000)
    assert np.all(sp[:, [0, 2, 3, 4, 5]] < 1e-9)  # the other joints are held
    low = [s for s in plan.segments if s.kind == "lowspeed"]
    assert 90.0 < sum(s.t1_s - s.t0_s for s in low) < 110.0  # ~100 s of motion
    assert plan.check(limits()) == []


def test_symmetric_passes_retrace_at_equal_speed():
    b = E.PlanBuilder(START, limits())
    E.add_symmetric(b, passes=3, speed=0.2, rng=np.random.default_rng(1))
    plan = b.build("sym")
    segs = [s for s in plan.segments if s.kind == "symmetric"]
    assert len(segs) == 6
    for fwd, back in zip(segs[::2], segs[1::2], strict=True):
        mf = (plan.t_s >= fwd.t0_s) & (plan.t_s <= fwd.t1_s)
        mb = (plan.t_s >= back.t0_s) & (plan.t_s <= back.t1_s)
        qf, qb = plan.q_rad[mf], plan.q_rad[mb]
        assert np.allclose(qf[0], qb[-1], atol=2e-3) and np.allclose(qf[-1], qb[0], atol=2e-3)  # A→B then B→A
        assert fwd.t1_s - fwd.t0_s == pytest.approx(back.t1_s - back.t0_s, rel=1e-3)  # same speeds
    assert plan.check(limits()) == []


def test_friction_speed_ladder_has_fine_low_steps():
    b = E.PlanBuilder(START, limits())
    E.add_friction(b, [0], speeds=(0.004, 0.008, 0.02, 0.1, 0.5))
    plan = b.build("fric")
    segs = [s for s in plan.segments if s.kind == "friction"]
    got = sorted({round(s.speed_rad_s, 4) for s in segs})
    assert got == [0.004, 0.008, 0.02, 0.1, 0.5]
    assert plan.check(limits()) == []


def test_synchronous_45_degrees_two_poses():
    b = E.PlanBuilder(START, limits())
    E.add_synchronous(b, [1], speeds=(0.2, 0.4), cycles=1)
    plan = b.build("sync")
    segs = [s for s in plan.segments if s.kind == "synchronous"]
    notes = {s.note for s in segs}
    assert any(n.startswith("pose 0") for n in notes) and any(n.startswith("pose 1") for n in notes)
    m = np.zeros_like(plan.t_s, dtype=bool)
    for s in segs:
        m |= (plan.t_s >= s.t0_s) & (plan.t_s <= s.t1_s)
    assert np.degrees(np.ptp(plan.q_rad[m, 1])) == pytest.approx(90.0, abs=1.0)  # ±45°


def test_fourier_is_periodic_rest_to_rest_and_well_conditioned(tmp_path):
    lim = limits()
    coef, qc, info = E.optimise_fourier(robot(), lim, START, maxiter=15)
    w = 2 * np.pi / 10.0
    q, dq, ddq = E._fourier_eval(coef, qc, w, np.array([0.0, 10.0]))
    assert np.allclose(q[0], qc) and np.allclose(q[1], qc, atol=1e-9)
    assert np.allclose(dq, 0.0, atol=1e-9) and np.allclose(ddq, 0.0, atol=1e-9)
    t = np.linspace(0, 10, 2001)
    q, dq, ddq = E._fourier_eval(coef, qc, w, t)
    assert np.all(q >= lim.lower_rad - 1e-9) and np.all(q <= lim.upper_rad + 1e-9)
    assert np.all(np.abs(dq) <= lim.velocity_rad_s + 1e-9) and np.all(np.abs(ddq) <= lim.acceleration_rad_s2 + 1e-9)
    assert len(info["condition_numbers"]) == 6


def test_plan_file_round_trip_is_what_the_daemon_loads(tmp_path):
    from dragd.control.trajectory import Trajectory

    plan = E.build_plan("symmetric", robot(), START, limits(), scale=0.25)
    f = tmp_path / "p.npz"
    plan.save(f)
    again = E.Plan.load(f)
    assert np.array_equal(again.q_rad, plan.q_rad)
    assert [s.kind for s in again.segments] == [s.kind for s in plan.segments]
    tr = Trajectory.load(f, 0.001)
    assert tr.duration_s == pytest.approx(plan.duration_s)
    assert np.allclose(tr.start_q, START)


def test_bad_plan_inputs_are_named():
    with pytest.raises(E.PlanError, match="kind: expected one of lowspeed"):
        E.build_plan("sideways", robot(), START, limits())
    bad = START.copy()
    bad[1] = 3.5
    with pytest.raises(E.PlanError, match=r"start pose outside the identification limits .* joint2 = 3\.500 rad"):
        E.PlanBuilder(bad, limits())
    with pytest.raises(E.PlanError, match=r"--joints: expected joint numbers 1\.\.6, got \[7\]"):
        E.build_plan("friction", robot(), START, limits(), joints=[7])


def test_runner_approach_and_chunks():
    t, q = _approach(START, START + 0.3)
    assert np.allclose(q[0], START) and np.allclose(q[-1], START + 0.3)
    v = np.abs(np.diff(q, axis=0) / np.diff(t)[:, None]).max()
    assert v <= 0.21
    plan = E.build_plan("standard", robot(), START, limits(), scale=0.3)
    cuts = chunks(plan, 200.0)
    assert cuts[0][0] == 0.0 and cuts[-1][1] == plan.duration_s and len(cuts) >= 3
    assert all(b - a <= 260.0 for a, b in cuts)
