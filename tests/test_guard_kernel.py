"""The runaway guard's compiled update (dragd/control/guard.py ``_guard_kernel``) against its numpy reference.

Two guards, one with the kernel, fed the same randomised drag: rests, hand runs (the residual brakes or drives),
a load that drives a joint (trips), direction changes, late cycles, re-arming. Every state array, every decision
(hand runs, payload-likeness checks, trips with their joint and text) must agree.
"""

from __future__ import annotations

import numpy as np
import pytest

from dragd.control.guard import GuardSettings, RunawayGuard, guard_command_kernel, guard_kernel

pytestmark = [pytest.mark.unit, pytest.mark.skipif(guard_kernel() is None, reason="numba is not installed")]

N = 6
STATE = ("p0", "integ", "r", "r_f", "v_f", "run_s", "peak", "sign", "hand")


def _explain(q: np.ndarray, r: np.ndarray) -> tuple[float, float]:
    """A deterministic stand-in for the payload-likeness test: payload-like when joint 2 carries most of it."""
    share = abs(float(r[1])) / (float(np.abs(r).sum()) or 1.0)
    return 1.0 - share, float(r[1]) / 10.0


def _same(a: np.ndarray, b: np.ndarray, what: str) -> None:
    """Equal (integers, booleans) or within rtol = atol = 1e-12 (floats; NaN fails), step by step: ``a`` and ``b``
    are the reference's and the kernel's values stacked over the steps (axis 0); a mismatch names its first step."""
    ok = np.isclose(b, a, rtol=1e-12, atol=1e-12) if a.dtype.kind == "f" else b == a
    bad = np.flatnonzero(~ok.reshape(ok.shape[0], -1).all(axis=1))
    if bad.size:
        k = int(bad[0])
        raise AssertionError(f"step {k}: {what}: kernel {b[k]!r} vs numpy {a[k]!r}")


@pytest.mark.parametrize("entry", ["update", "command", "command_effects"])
def test_the_guard_kernel_matches_the_numpy_update(entry: str) -> None:
    """``update`` (τ_in given) and ``update_from_command`` (τ_in from the command and the law's terms, fused into
    the command kernel; with and without model-gap effects): the same states, decisions and τ_in."""
    rng = np.random.default_rng(11)
    kt = np.array([9.09, 9.09, 9.09, 4.545, 4.545, 4.545])
    names = [f"joint{i}" for i in range(1, N + 1)]
    ref = RunawayGuard(N, kt, 1e-3, GuardSettings(), _explain, names)
    got = RunawayGuard(N, kt, 1e-3, GuardSettings(), _explain, names)
    got.use_kernel(guard_kernel(), guard_command_kernel())
    t, p = 0.0, np.zeros(N)
    tau_ref, tau_got = np.zeros(N), np.zeros(N)
    q = rng.uniform(-1, 1, N)
    trips_ref: list[str] = []
    trips_got: list[str] = []
    for g in (ref, got):
        g.arm(p, t)
    dq = np.zeros(N)
    load = np.zeros(N)
    states_ref: dict[str, list[np.ndarray]] = {f: [] for f in STATE}
    states_got: dict[str, list[np.ndarray]] = {f: [] for f in STATE}
    for k in range(30000):
        t += 1e-3 * (rng.integers(2, 5) if rng.random() < 0.01 else 1)  # late cycles
        if k % 1500 == 0:  # a new phase: rest, a hand (braking or driving), or a load on joint 2
            phase = rng.integers(0, 4)
            dq = np.zeros(N) if phase == 0 else rng.normal(0.0, 0.3, N)
            load = np.zeros(N)
            if phase == 2:
                load = rng.normal(0.0, 8.0, N)  # a hand: spread over the joints
            if phase == 3:
                load[1] = rng.choice([-1.0, 1.0]) * rng.uniform(3.0, 20.0)  # a load: joint 2 alone
                dq[1] = np.sign(load[1]) * abs(dq[1])
        dq = dq + rng.normal(0.0, 0.002, N)
        if k % 700 == 350:
            dq = -dq  # direction changes
        q = q + dq * 1e-3
        p = p + (load + rng.normal(0.0, 0.2, N)) * 1e-3  # the momentum the missing torque builds
        if entry == "update":
            tau = rng.normal(0.0, 0.5, N)
            a = ref.update(t, q, dq, p, tau)
            b = got.update(t, q, dq, p, tau)
        else:  # the command and the law's terms [A], K_t: τ_in ~ N(0, 0.5) N·m as above
            cmd, grav, offset, fric, start = (rng.normal(0.0, 0.05, N) for _ in range(5))
            effects = rng.normal(0.0, 0.02, N) if entry == "command_effects" else None
            a = ref.update_from_command(t, q, dq, p, cmd, grav, offset, fric, start, effects, kt, tau_ref)
            b = got.update_from_command(t, q, dq, p, cmd, grav, offset, fric, start, effects, kt, tau_got)
            assert np.array_equal(tau_got, tau_ref), f"step {k}: tau_in"  # (the same operations in the same order)
        assert (a is None) == (b is None), f"step {k}: {a} vs {b}"
        if a is not None and b is not None:
            trips_ref.append(a.text)
            trips_got.append(b.text)
            assert a.joint == b.joint and a.residual_Nm == pytest.approx(b.residual_Nm, rel=1e-12)
        for f in STATE:  # (kept per step, compared once at the end: the same test for each step's values)
            states_ref[f].append(getattr(ref, f).copy())
            states_got[f].append(getattr(got, f).copy())
        assert (ref.running, ref.checks, ref.hand_runs, ref.stuck_deferrals, ref.retest_at, ref.armed) == \
            (got.running, got.checks, got.hand_runs, got.stuck_deferrals, got.retest_at, got.armed), f"step {k}"
        assert (ref._stuck_open, ref._stuck_since, ref._retest_stuck_at) == \
            (got._stuck_open, got._stuck_since, got._retest_stuck_at), f"step {k}"
        if not ref.armed:  # after a trip: armed again, as the controller does when drag resumes
            for g in (ref, got):
                g.arm(p, t)
    for f in STATE:
        _same(np.stack(states_ref[f]), np.stack(states_got[f]), f)
    assert trips_got == trips_ref and len(trips_ref) >= 2, "the sequence must trip"
    assert ref.hand_runs >= 2, "the sequence must have hand runs"
    assert ref.stuck_deferrals >= 1, "the sequence must defer a verdict (a joint at rest)"
    used = guard_kernel() if entry == "update" else guard_command_kernel()
    assert len(used.signatures) == 1  # (compiled once, at start, with the cycle's types: none mid-cycle)
