"""The compensation law: each term's sign, continuity, the faded hand-over, clamps, the velocity estimator."""

from __future__ import annotations

import numpy as np
import pytest

from dragd.config import load_config
from dragd.control.estimate import VelocityEstimator
from dragd.control.law import (
    LawOutput,
    Workspace,
    back_emf_current,
    clamp_current,
    compensate,
    friction_current,
    gravity_current,
    startup_current,
    startup_weight,
)
from dragd.control.params import LawParams
from dragd.model import RobotModel

from conftest import DEFAULT_CONFIG, cli_json

pytestmark = pytest.mark.unit


@pytest.fixture(scope="module")
def cfg():
    return load_config(DEFAULT_CONFIG)


@pytest.fixture(scope="module")
def params(cfg):
    """The configured law with friction_scale 1, so the friction model's values can be checked exactly."""
    return LawParams.from_config(cfg).replace(friction_scale=1.0)


def test_friction_scale_under_compensates(cfg):
    p = LawParams.from_config(cfg)
    assert p.friction_scale == 0.95
    v = np.full(6, 0.3)
    assert np.allclose(friction_current(v, p), 0.95 * friction_current(v, p.replace(friction_scale=1.0)))


def test_gravity_current_is_g_over_kt(cfg, params):
    model = RobotModel.from_urdf(cfg.robot.urdf)
    q = np.array([0.1, -0.5, 0.8, 0.2, 0.3, 0.0])
    g = model.gravity(q)
    assert np.allclose(gravity_current(g, params.kt_Nm_per_A), g / np.array([j.kt_Nm_per_A for j in cfg.joints]))


def test_friction_signs_and_direction_dependent_levels(params):
    fast = np.full(6, 0.5)
    f_pos = friction_current(fast, params)
    f_neg = friction_current(-fast, params)
    assert np.all(f_pos > 0) and np.all(f_neg < 0)
    # well above the Stribeck velocity: Coulomb level + viscous slope of that direction
    assert f_pos[1] == pytest.approx(params.coulomb_pos_A[1] + 0.5 * params.viscous_pos_A_s_per_rad[1], rel=1e-6)
    assert f_neg[1] == pytest.approx(params.coulomb_neg_A[1] - 0.5 * params.viscous_neg_A_s_per_rad[1], rel=1e-6)
    assert f_pos[0] > abs(f_neg[0])  # joint 1's levels are asymmetric in the default config (0.55 / -0.52 A)
    assert f_pos[0] - 0.5 * params.viscous_pos_A_s_per_rad[0] == pytest.approx(params.coulomb_pos_A[0], rel=1e-6)


def test_friction_stribeck_hump_and_switch(params):
    v = np.full(6, 0.02)  # at the Stribeck velocity, past the tanh crossing
    with_s = friction_current(v, params)
    without = friction_current(v, params.replace(use_stribeck=False))
    assert np.all(with_s > without)
    expected = params.coulomb_pos_A + (params.static_pos_A - params.coulomb_pos_A) * np.exp(
        -((0.02 / params.stribeck_velocity_rad_s) ** params.stribeck_exponent))
    w = np.tanh(0.02 / params.smoothing_rad_s)
    assert np.allclose(with_s, w * expected + 0.02 * params.viscous_pos_A_s_per_rad)


def test_friction_continuous_at_zero_and_zero_at_rest(params):
    assert np.allclose(friction_current(np.zeros(6), params), 0.0)
    eps = 1e-7
    assert np.allclose(friction_current(np.full(6, eps), params), 0.0, atol=1e-4)
    assert np.allclose(friction_current(np.full(6, -eps), params), 0.0, atol=1e-4)
    v = np.linspace(-0.05, 0.05, 2001)
    f = np.array([friction_current(np.full(6, x), params) for x in v])
    assert np.max(np.abs(np.diff(f, axis=0))) < 0.02  # no jump anywhere on a 50 µrad/s grid


def test_seed000_velocity_band(params):
    p = params.replace(deadband_rad_s=0.05)
    assert np.allclose(friction_current(np.full(6, 0.04), p)[:1], 0.04 * p.viscous_pos_A_s_per_rad[:1])
    assert friction_current(np.full(6, 0.2), p)[0] > 0.9 * p.coulomb_pos_A[0]


def test_startup_term_at_rest_and_faded_when_moving(params):
    t = 1.0 / (4 * 16.0)  # quarter period of joint 1's 16 Hz: sin = 1
    s = startup_current(t, np.zeros(6), params)
    assert s[0] == pytest.approx(params.startup_amp_pos_A[0])
    s_neg = startup_current(3 * t, np.zeros(6), params)
    assert s_neg[0] == pytest.approx(-params.startup_amp_neg_A[0])
    moving = params.rest_threshold_rad_s + params.fade_width_rad_s + 1e-3
    assert np.allclose(startup_current(t, moving, params), 0.0)
    phi, w = params.rest_threshold_rad_s[0], params.fade_width_rad_s[0]
    assert np.all(params.rest_threshold_rad_s == phi) and np.all(params.fade_width_rad_s == w)
    r = startup_weight(np.array([0.0, phi, phi + w / 2, phi + w, phi + 2 * w, -(phi + w / 2)]), params)
    assert r[0] == 1.0 and r[1] == 1.0 and 0 < r[2] < 1 and r[3] == 0.0 and r[4] == 0.0 and r[5] == r[2]


def test_handover_has_no_current_step(cfg, params):
    """Sweep |q̇| through Φ..Φ+width at fixed t: total current changes smoothly (seed 001 eq. 28 would step)."""
    model = RobotModel.from_urdf(cfg.robot.urdf)
    g = model.gravity(np.zeros(6))
    t = 1.0 / 64.0
    v = np.linspace(0.0, 0.1, 4001)
    totals = np.array([compensate(g, np.full(6, x), t, params).current_A for x in v])
    steps = np.max(np.abs(np.diff(totals, axis=0)), axis=0)
    assert np.all(steps < 0.01), steps
    # the seed's abrupt switch steps by up to the static level at Φ (worst when the sine is at zero)
    phi = params.rest_threshold_rad_s[0]
    abrupt_before = params.startup_amp_pos_A[0] * np.sin(2 * np.pi * 16 * 0.0)
    abrupt_after = friction_current(np.full(6, phi), params.replace(smoothing_rad_s=1e-9))[0]
    assert abs(abrupt_after - abrupt_before) > 0.05


def test_clamp_reports_joints(params):
    i = np.array([20.0, -20.0, 1.0, 7.0, -7.0, 0.0])
    out, mask = clamp_current(i, params.current_limit_A)
    assert np.allclose(out, [12, -12, 1, 6, -6, 0])
    assert mask.tolist() == [True, True, False, True, True, False]
    o = compensate(np.array([0, 500.0, 0, 0, 0, 0]), np.zeros(6), 0.0, params)
    assert o.clamped[1] and o.current_A[1] == pytest.approx(12.0)


def test_back_emf_term_switch(params):
    p = params.replace(back_emf_A_s_per_rad=np.full(6, 0.5), use_back_emf=True)
    assert np.allclose(back_emf_current(np.full(6, 2.0), p), 1.0)
    o = compensate(np.zeros(6), np.full(6, 2.0), 0.0, p)
    assert np.allclose(o.back_emf_A, 1.0)
    o = compensate(np.zeros(6), np.full(6, 2.0), 0.0, params)
    assert np.allclose(o.back_emf_A, 0.0)


def test_damping_opposes_motion(params):
    o = compensate(np.zeros(6), np.full(6, 0.2), 0.0, params)
    assert np.all(o.damping_A < 0)
    assert np.allclose(o.damping_A, -0.2 * params.damping_A_s_per_rad)


def test_every_term_switchable(params):
    g = np.full(6, 5.0)
    dq = np.full(6, 0.005)
    base = compensate(g, dq, 0.01, params)
    for flag, field in [("use_gravity", "gravity_A"), ("use_friction", "friction_A"), ("use_startup", "startup_A"),
                        ("use_damping", "damping_A")]:
        assert np.any(getattr(base, field) != 0)
        off = compensate(g, dq, 0.01, params.replace(**{flag: False}))
        assert np.all(getattr(off, field) == 0)


def test_in_place_evaluation_matches_allocating(params):
    out, ws = LawOutput.zeros(6), Workspace(6)
    rng = np.random.default_rng(3)
    for _ in range(50):
        g, dq, t = rng.normal(0, 10, 6), rng.normal(0, 0.05, 6), rng.uniform(0, 10)
        a = compensate(g, dq, t, params)
        b = compensate(g, dq, t, params, out, ws)
        assert np.array_equal(a.current_A, b.current_A) and np.array_equal(a.friction_A, b.friction_A)
        assert np.allclose(a.current_A, np.clip(a.gravity_A + a.friction_A + a.startup_A + a.back_emf_A + a.damping_A,
                                                -params.current_limit_A, params.current_limit_A))


def test_cli_current_is_sum_of_parts():
    out = cli_json("model", "current", "--q", "0,0.3,0.2,0.1,0.5,0", "--dq", "0,0.1,-0.1,0,0.012,0", "--t", "0.013")
    parts = sum(np.array(out[k]) for k in ("gravity_A", "friction_A", "startup_A", "back_emf_A", "damping_A"))
    assert np.allclose(out["current_A"], parts)
    assert out["friction_A"][1] > 0 and out["friction_A"][2] < 0


def test_velocity_estimator_tracks_ramp_with_documented_delay():
    cpr = np.full(2, 2**19)
    est = VelocityEstimator(cpr, cutoff_Hz=40.0)
    dt, v = 1e-3, np.array([0.3, -0.2])
    for k in range(400):
        counts = np.round(v * k * dt * cpr / (2 * np.pi)).astype(np.int64)
        out = est.update(counts, dt)
    assert np.allclose(out, v, rtol=0.02)
    assert est.delay_s(dt) == pytest.approx(1 / (2 * np.pi * 40) + 0.5e-3)


def test_velocity_estimator_ignores_sampling_jitter_and_stale_samples():
    """A late SYNC samples later and a lost TPDO brings no new counts: neither may show up as velocity."""
    cpr = np.full(2, 2**19)
    v = np.array([0.02, -0.5])  # rad/s: a joint starting to move (Φ ≈ 0.01) and a fast one
    rng = np.random.default_rng(3)
    est = VelocityEstimator(cpr, cutoff_Hz=40.0)
    t, out = 0.0, []
    est.update(np.zeros(2, dtype=np.int64), 1e-3)
    for k in range(1500):
        dt = 1e-3 * (2.0 if k % 97 == 0 else rng.uniform(0.6, 1.4))  # jitter and the odd missed tick
        t += dt
        fresh = np.array([k % 50 != 7, k % 31 != 3])  # lost TPDOs
        counts = np.floor(v * t * cpr / (2 * np.pi)).astype(np.int64)
        out.append(est.update(counts, dt, fresh).copy())
    out = np.array(out)[500:]
    # one count per sample is 0.012 rad/s of raw noise, which the 40 Hz filter averages down; jitter adds nothing
    assert np.abs(out - v).max(axis=0)[0] < 0.006 and np.abs(out - v).max(axis=0)[1] < 0.01


def test_velocity_estimator_int32_wrap():
    est = VelocityEstimator(np.array([1000]), cutoff_Hz=400.0)
    est.update(np.array([2**31 - 5]), 1e-3)
    for k in range(1, 50):
        val = ((2**31 - 5 + 10 * k + 2**31) % 2**32) - 2**31  # int32 wrap
        out = est.update(np.array([val]), 1e-3)
    assert out[0] == pytest.approx(10 * 2 * np.pi / 1000 / 1e-3, rel=1e-3)


def test_velocity_estimator_int32_wrap_downwards_and_integer_counts_only():
    est = VelocityEstimator(np.array([1000]), cutoff_Hz=400.0)
    est.update(np.array([-2**31 + 5]), 1e-3)
    for k in range(1, 50):
        val = ((-2**31 + 5 - 10 * k + 2**31) % 2**32) - 2**31  # int32 wrap from −2^31 to +2^31 − 1
        out = est.update(np.array([val]), 1e-3)
    assert out[0] == pytest.approx(-10 * 2 * np.pi / 1000 / 1e-3, rel=1e-3)
    with pytest.raises(TypeError, match="integer"):
        VelocityEstimator(np.array([1000]), cutoff_Hz=400.0).update(np.array([1.5]), 1e-3)


def test_square_wave_and_abrupt_switch_options(params):
    t = 1.0 / (8 * 16.0)  # sin(2π·16·t) = 0.707 on joint 1
    sq = startup_current(t, np.zeros(6), params.replace(startup_square=True))
    assert sq[0] == pytest.approx(params.startup_amp_pos_A[0])
    phi = params.rest_threshold_rad_s[0]
    abrupt = params.replace(startup_abrupt=True)
    below = startup_current(t, np.full(6, 0.99 * phi), abrupt)
    above = startup_current(t, np.full(6, 1.01 * phi), abrupt)
    assert below[0] == pytest.approx(params.startup_amp_pos_A[0] * np.sin(2 * np.pi * 16 * t))
    assert np.all(above == 0.0)
    # the abrupt switch steps the total current at Φ; the fade does not
    g = np.zeros(6)
    step_abrupt = compensate(g, np.full(6, 1.01 * phi), 0.0, abrupt).current_A - compensate(
        g, np.full(6, 0.99 * phi), 0.0, abrupt).current_A
    step_fade = compensate(g, np.full(6, 1.01 * phi), 0.0, params).current_A - compensate(
        g, np.full(6, 0.99 * phi), 0.0, params).current_A
    assert np.abs(step_abrupt).max() > 0.3 and np.abs(step_fade).max() < 0.01


def _latch_run(params, q_of_t, seconds: float, dq_of_t=None):
    """Drive the break-out latch and the start-up term along q(t) at 1 kHz; the per-cycle start-up current."""
    from dragd.control.breakout import BreakoutState, breakout_update

    st = BreakoutState(6).configure(params)
    st.reset(0.0)
    out = []
    for k in range(int(seconds * 1000)):
        t = k * 1e-3
        q = q_of_t(t)
        dq = dq_of_t(t) if dq_of_t else np.zeros(6)
        breakout_update(q, dq, t, params, st)
        out.append(startup_current(t, dq, params, None, None, None, st).copy())
    return np.array(out), st


def _sine_term(params, j, t):
    sine = np.sin(2 * np.pi * params.startup_freq_Hz[j] * t)
    return np.where(sine >= 0, params.startup_amp_pos_A[j], params.startup_amp_neg_A[j]) * sine


def test_breakout_latch_holds_the_peak_of_a_creeping_joint(params):
    from dragd.control.breakout import BREAKOUT_RAMP_S

    slip = params.breakout_slip_rad[0]
    amp = params.startup_amp_pos_A[0]

    def q(t):  # joint 1 creeps forward by micro-slips from t = 0.5 s until past the slip distance; the others stay
        x = np.zeros(6)
        x[0] = 0.0 if t < 0.5 else min(0.4 * slip * np.floor((t - 0.5) / 0.0625 + 1), 1.2 * slip)
        return x

    s, st = _latch_run(params, q, 1.0)
    t = np.arange(1000) * 1e-3
    assert st.latches[0] == 1 and st.latches[1:].sum() == 0
    k = int(np.flatnonzero(np.array([q(x)[0] for x in t]) > slip)[0])  # the cycle it crept past the slip distance
    assert np.allclose(s[:k, 0], _sine_term(params, 0, t[:k]))  # the plain sine before
    hold = int(round(params.breakout_hold_s[0] * 1000))
    ramp = int(round(BREAKOUT_RAMP_S * 1000))
    # the sine blends into the held peak in the creep's direction and stays there for the hold time ...
    assert np.allclose(s[k + ramp:k + hold, 0], amp)
    # ... then blends back (no further creep: the arm did not follow) and stays the sine
    assert np.allclose(s[k + hold + ramp + 1:, 0], _sine_term(params, 0, t[k + hold + ramp + 1:]))
    # never a step: at most the sine's own slope plus the blend's 2·A per ramp time
    assert np.abs(np.diff(s[:, 0])).max() <= 2 * np.pi * 16 * amp * 1e-3 + 2 * amp * 1e-3 / BREAKOUT_RAMP_S + 1e-9
    for j in range(1, 6):  # the other joints never left the sine
        assert np.allclose(s[:, j], _sine_term(params, j, t))


def test_breakout_latch_ignores_a_joint_coasting_to_rest_and_can_be_switched_off(params):
    slip = params.breakout_slip_rad[0]

    def q(t):  # decelerating from 0.05 rad/s to rest over 0.2 s (well beyond the slip distance), then still
        x = np.zeros(6)
        x[0] = 0.05 * min(t, 0.2) - 0.125 * min(t, 0.2) ** 2
        return x

    def dq(t):
        v = np.zeros(6)
        v[0] = max(0.05 - 0.25 * t, 0.0)
        return v

    assert q(1.0)[0] > 100 * slip
    _, st = _latch_run(params, q, 1.0, dq)
    assert st.latches.sum() == 0  # it moved while disarmed, then settled: armed at the new place
    assert st.armed.all() and st.anchor_rad[0] == pytest.approx(q(1.0)[0])
    off = params.replace(use_breakout=False)

    def creep(t):
        x = np.zeros(6)
        x[0] = 10 * slip * t
        return x

    s, _ = _latch_run(off, creep, 0.6)
    assert np.allclose(s[:, 0], _sine_term(params, 0, np.arange(600) * 1e-3))


def test_hand_over_is_slew_limited_against_velocity_noise(params):
    """A velocity estimate that jumps across the fade band (a late TPDO, a stalled loop) must not step the current."""
    from dragd.control.breakout import REST_WEIGHT_STEP, BreakoutState, breakout_update

    st = BreakoutState(6).configure(params)
    st.reset(0.0)
    g, q = np.zeros(6), np.zeros(6)
    phi, w = params.rest_threshold_rad_s, params.fade_width_rad_s
    fast, slow = phi + 2 * w, 0.5 * phi
    outs = []
    for k in range(60):
        dq = np.where((k // 15) % 2 == 0, fast, slow)  # jumps across the whole band every 15 cycles
        breakout_update(q, dq, k * 1e-3, params, st)
        o = compensate(g, dq, k * 1e-3, params, breakout=st)
        outs.append((st.rest.copy(), o.friction_A + o.startup_A))
    r = np.array([x[0] for x in outs])
    assert np.abs(np.diff(r, axis=0)).max() <= REST_WEIGHT_STEP + 1e-12
    assert r[14].max() == 0.0 and r[29].min() == 1.0  # it still hands over fully, within 10 cycles
    unslewed = np.abs(compensate(g, np.full(6, fast), 0.0, params).friction_A
                      - compensate(g, np.full(6, slow), 0.0, params).friction_A)
    steps = np.abs(np.diff([x[1] for x in outs], axis=0)).max(axis=0)
    assert np.all(steps < 0.5 * unslewed + 2 * np.pi * params.startup_freq_Hz * params.startup_amp_pos_A * 1e-3)


def test_breakout_latch_stays_off_where_gravity_errors_could_explain_the_creep(params):
    """Where 2 % of the gravity current exceeds the sine's margin below static friction, a creep may be the model's
    error rather than a hand: the latch must not fire there (seed 001's hand-over stays)."""
    from dragd.control.breakout import BreakoutState, breakout_update

    slip = params.breakout_slip_rad[0]
    margin = params.static_pos_A - params.startup_amp_pos_A
    tau_g = np.zeros(6)
    tau_g[0] = 1.5 * margin[0] / params.gravity_uncertainty * params.kt_Nm_per_A[0]  # joint 1: gravity-loaded
    tau_g[1] = 0.5 * margin[1] / params.gravity_uncertainty * params.kt_Nm_per_A[1]  # joint 2: lightly loaded
    st = BreakoutState(6).configure(params)
    st.reset(0.0)
    for k in range(600):
        t = k * 1e-3
        q = np.zeros(6)
        q[:2] = 0.0 if t < 0.3 else 3 * slip  # both creep past the slip distance after settling
        breakout_update(q, np.zeros(6), t, params, st, tau_g)
    assert st.latches[0] == 0 and st.suppressed[0] > 0
    assert st.latches[1] == 1 and st.suppressed[1] == 0
