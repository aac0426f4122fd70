"""The compiled drag law (dragd/control/fused.py) against its numpy reference (breakout_update + compensate).

Long randomised sequences at 1 kHz — rests, creeps that fire the latch (and creeps the gravity uncertainty
suppresses), motions through the fade, late ticks, velocity noise, wall currents — with every switch of
LawParams: every output and every state array must match the reference (to the last few ulp: the kernels use
libm's exp/tanh/sin/pow where numpy uses its own SIMD versions).
"""

from __future__ import annotations

import numpy as np
import pytest

from dragd.config import load_config
from dragd.control import fused
from dragd.control.breakout import BreakoutState, breakout_update
from dragd.control.law import LawOutput, Workspace, compensate
from dragd.control.params import LawParams

from conftest import DEFAULT_CONFIG

pytestmark = [pytest.mark.unit,
              pytest.mark.skipif(not fused.available(), reason="numba is not installed")]

STATE = ("anchor_rad", "still_ref_rad", "armed", "still_since_s", "latch", "latch_t0_s", "held", "weight", "rest",
         "latches", "suppressed")
OUTPUT = ("current_A", "gravity_A", "friction_A", "startup_A", "back_emf_A", "damping_A", "clamped")


@pytest.fixture(scope="module")
def base() -> LawParams:
    return LawParams.from_config(load_config(DEFAULT_CONFIG))


def _motion(rng: np.random.Generator, seconds: float, slip: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Times (with late ticks), positions and velocity estimates of a 6-joint arm: per joint, segments of rest,
    creeps of a few slip distances (the latch's business), motions through the fade, and fast moves."""
    n_steps = int(seconds * 1000)
    dt = np.full(n_steps, 1e-3)
    late = rng.random(n_steps) < 0.01
    dt[late] *= rng.integers(2, 5, late.sum())
    t = np.cumsum(dt)
    dq = np.zeros((n_steps, 6))
    for j in range(6):
        k = 0
        while k < n_steps:
            length = int(rng.integers(50, 1200))
            kind = rng.integers(0, 4)
            sign = rng.choice([-1.0, 1.0])
            if kind == 1:  # creep: slower than Φ, far enough to fire the latch
                dq[k:k + length, j] = sign * rng.uniform(0.001, 0.008)
            elif kind == 2:  # through the fade
                dq[k:k + length, j] = sign * rng.uniform(0.005, 0.06) * np.sin(np.linspace(0, np.pi, length))[:len(
                    dq[k:k + length, j])]
            elif kind == 3:  # moving
                dq[k:k + length, j] = sign * rng.uniform(0.05, 1.2)
            k += length
    q = np.cumsum(dq * dt[:, None], axis=0) + rng.uniform(-1, 1, 6)
    dq_est = dq + rng.normal(0.0, 0.0008, dq.shape)  # the velocity estimate's noise
    dq_est[rng.random(dq.shape) < 0.002] = 0.0  # exact zeros: the sign branches
    return t, q, dq_est


def _variants(base: LawParams) -> list[tuple[str, LawParams]]:
    return [("default", base),
            ("scale 1, deadband", base.replace(friction_scale=1.0, deadband_rad_s=0.003)),
            ("square", base.replace(startup_square=True)),
            ("abrupt", base.replace(startup_abrupt=True)),
            ("no breakout", base.replace(use_breakout=False)),
            ("no stribeck, back-emf", base.replace(use_stribeck=False, use_back_emf=True,
                                                   back_emf_A_s_per_rad=np.full(6, 0.2))),
            ("no startup", base.replace(use_startup=False)),
            ("no friction, no damping, no gravity", base.replace(use_friction=False, use_damping=False,
                                                                 use_gravity=False)),
            ("high gravity uncertainty", base.replace(gravity_uncertainty=0.5)),
            ("no gravity uncertainty, tight limits", base.replace(gravity_uncertainty=0.0,
                                                                  current_limit_A=np.full(6, 0.6)))]


def _same(a: np.ndarray, b: np.ndarray, what: str) -> None:
    """Equal (integers, booleans) or within a few ulp (floats; NaN where NaN), step by step: ``a`` and ``b`` are the
    reference's and the kernels' values stacked over the steps (axis 0); a mismatch names its first step."""
    if a.dtype.kind == "f":
        ok = np.isclose(b, a, rtol=1e-12, atol=1e-12, equal_nan=True)
    else:
        ok = b == a
    bad = np.flatnonzero(~ok.reshape(ok.shape[0], -1).all(axis=1))
    if bad.size:
        k = int(bad[0])
        if a.dtype.kind == "f":
            np.testing.assert_allclose(b[k], a[k], rtol=1e-12, atol=1e-12, err_msg=f"{what} at step {k}")
        np.testing.assert_array_equal(b[k], a[k], err_msg=f"{what} at step {k}")


@pytest.mark.parametrize("variant", range(10))
def test_the_kernels_match_the_numpy_reference(base: LawParams, variant: int) -> None:
    name, p = _variants(base)[variant]
    rng = np.random.default_rng(1000 + variant)
    t, q, dq = _motion(rng, 8.0, p.breakout_slip_rad)
    tau_g = rng.uniform(-40, 40, 6)
    law = fused.DragLaw(p)
    assert law.compiled
    ref_st, ref_out, ws = BreakoutState(6).configure(p), LawOutput.zeros(6), Workspace(6)
    ref_st.reset(t[0])
    law.state.reset(t[0])
    # every step's state and outputs, copied, compared at the end (all steps, each its own ulp check)
    fields = [("state", f) for f in STATE] + [("output", f) for f in OUTPUT]
    ref: dict[tuple[str, str], list[np.ndarray]] = {k: [] for k in fields}
    got: dict[tuple[str, str], list[np.ndarray]] = {k: [] for k in fields}
    scalars_ref, scalars_got = [], []
    for k in range(t.shape[0]):
        g = tau_g + 3 * np.sin(q[k])
        extra = np.zeros(6) if k % 7 else rng.normal(0.0, 0.5, 6)  # wall currents now and then
        breakout_update(q[k], dq[k], t[k], p, ref_st, g)
        law.breakout(q[k], dq[k], t[k], p, g)
        compensate(g, dq[k], t[k], p, ref_out, ws, extra, ref_st, q[k])
        out = law.compensate(g, dq[k], t[k], p, extra, q[k])
        for f in STATE:
            ref["state", f].append(np.array(getattr(ref_st, f)))
            got["state", f].append(np.array(getattr(law.state, f)))
        for f in OUTPUT:
            ref["output", f].append(np.array(getattr(ref_out, f)))
            got["output", f].append(np.array(getattr(out, f)))
        scalars_ref.append((ref_st.active, ref_st.t_prev_s))
        scalars_got.append((law.state.active, law.state.t_prev_s))
    for kind, f in fields:
        a, b = np.stack(ref[kind, f]), np.stack(got[kind, f])
        _same(a, b, f"{name}: {f}")
    bad = [k for k, (x, y) in enumerate(zip(scalars_ref, scalars_got, strict=True)) if x != y]
    assert not bad, f"{name}: active/t_prev_s at step {bad[0]}: {scalars_got[bad[0]]} != {scalars_ref[bad[0]]}"
    worst = 0.0  # the largest float difference (NaN where both are NaN: not a difference)
    for f in OUTPUT:
        if ref["output", f][0].dtype.kind == "f":
            d = np.abs(np.stack(got["output", f]) - np.stack(ref["output", f]))
            worst = max(worst, float(d[~np.isnan(d)].max(initial=0.0)))
    latched, suppressed = int(ref_st.latches.sum()), int(ref_st.suppressed.sum())
    # the sequences exercise the latch (where it is on): fired, and suppressed where the uncertainty is high
    if p.use_breakout and p.use_startup and not p.startup_abrupt and p.gravity_uncertainty < 0.5:
        assert latched > 0, f"{name}: no latch fired: the sequence does not test the latch"
    if p.gravity_uncertainty >= 0.5:
        assert suppressed > 0, f"{name}: no creep suppressed"
    assert worst < 1e-12
    # one compiled signature each: the start-up's (n = 1) — the cycle's arrays never compile anything anew
    assert [len(fused._compiled()[k].signatures) for k in ("breakout", "law")] == [1, 1]  # type: ignore[index]


def test_effects_use_the_numpy_path(base: LawParams) -> None:
    """Params with model-gap effects are computed by ``compensate`` (the kernels have no effects)."""
    from dragd.control.params import EffectArrays

    n = 6
    eff = EffectArrays(periodic_cycles=np.ones((n, 1)), periodic_sin_A=np.full((n, 1), 0.1),
                       periodic_cos_A=np.zeros((n, 1)), offset_A=np.full(n, 0.05), load_friction_A_per_Nm=np.zeros(n),
                       drift_change=np.zeros(n), drift_time_constant_s=np.ones(n), back_emf_knee_rad_s=np.zeros(n),
                       scratch=(np.zeros((n, 1)), np.zeros((n, 1))))
    p = base.replace(effects=eff)
    law = fused.DragLaw(p)
    law.state.reset(0.0)
    q, dq, g = np.full(n, 0.3), np.full(n, 0.2), np.full(n, 10.0)
    out = law.compensate(g, dq, 0.5, p, np.zeros(n), q)
    ref = compensate(g, dq, 0.5, p, LawOutput.zeros(n), Workspace(n), np.zeros(n), BreakoutState(n).configure(p), q)
    np.testing.assert_array_equal(out.current_A, ref.current_A)
    assert np.abs(out.effects_A).max() > 0.05


def test_the_numpy_path_when_not_compiled(base: LawParams) -> None:
    law = fused.DragLaw(base, compiled=False)
    assert not law.compiled
    law.state.reset(0.0)
    out = law.compensate(np.full(6, 10.0), np.full(6, 0.2), 0.01, base, np.zeros(6), np.zeros(6))
    st = BreakoutState(6).configure(base)
    st.reset(0.0)
    ref = compensate(np.full(6, 10.0), np.full(6, 0.2), 0.01, base, LawOutput.zeros(6), Workspace(6), np.zeros(6), st,
                     np.zeros(6))
    np.testing.assert_array_equal(out.current_A, ref.current_A)
