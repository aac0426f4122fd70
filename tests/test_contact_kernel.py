"""The contact detector's compiled update (dragd/control/contact.py ``_contact_kernel``) against its numpy reference,
and the observer both it and the runaway guard run (dragd/control/observer.py).

Two detectors, one with the kernel, fed the same randomised sequence: motion with reversals and accelerations, rests
(settling → held), pushes on a held arm and their release (the spring-back, the released state), impacts on a moving
arm, late samples. Every state array and every event (joints, peaks, states, times) must agree.
"""

from __future__ import annotations

import numpy as np
import pytest

from dragd.control.contact import (
    HELD,
    MOVING,
    RELEASED,
    SETTLING,
    ContactBands,
    ContactDetector,
    ContactSettings,
    contact_kernel,
)
from dragd.control.observer import observer_step, observer_step_np

pytestmark = pytest.mark.unit

N = 6
STATE = ("p0", "integ", "r", "e", "d", "band", "rest_s", "release_left_s", "anchor", "still_time", "state",
         "baseline", "over", "in_event", "peak", "first_state", "quiet_t", "pratio", "f_low", "f_speed", "f_acc",
         "f_arm")


def _bands() -> ContactBands:
    return ContactBands(base_A=np.array([0.5, 0.8, 0.5, 0.08, 0.1, 0.06]), slow_A=np.full(N, 0.4),
                        speed_A_s_per_rad=np.full(N, 0.2), accel_A_s2_per_rad=np.full(N, 0.3),
                        slow_speed_rad_s=np.full(N, 0.1), settling_A=np.array([1.8, 1.8, 0.9, 0.3, 0.4, 0.3]),
                        held_A=np.array([0.5, 0.7, 0.35, 0.1, 0.15, 0.14]), held_moving_A=np.full(N, 0.3))


def _sequence(seed: int, steps: int) -> list[tuple[float, np.ndarray, np.ndarray, np.ndarray]]:
    """(t, q̇, p, τ_in) samples: phases of motion and rest; pushes (a held arm) and impacts (a moving one)."""
    rng = np.random.default_rng(seed)
    kt = np.array([10.0, 10.7, 8.5, 9.0, 9.5, 10.1])
    out = []
    t, p = 0.0, np.zeros(N)
    dq = np.zeros(N)
    ext = np.zeros(N)
    moving = False
    for k in range(steps):
        t += 0.01 * (rng.integers(2, 4) if rng.random() < 0.01 else 1) + rng.normal(0.0, 1e-4)
        if k % 300 == 0:
            moving = bool(rng.random() < 0.5)
            dq = rng.normal(0.0, 0.4, N) if moving else np.zeros(N)
            dq[rng.random(N) < 0.3] = 0.0  # some joints rest while others move
        if k % 300 == 120:  # a contact: a push (rest) or an impact (motion), on a few joints
            ext = np.zeros(N)
            js = rng.choice(N, size=rng.integers(1, 4), replace=False)
            ext[js] = rng.normal(0.0, 3.0, js.size) * kt[js]
        if k % 300 == 170:  # released: the spring-back overshoots
            ext = -0.4 * ext
        if k % 300 == 200:
            ext = np.zeros(N)
        if k % 97 == 50 and moving:
            dq = -dq  # reversals
        v = dq + rng.normal(0.0, 0.002, N) * (dq != 0)
        tau = rng.normal(0.0, 0.5, N)  # the model's torque with its noise
        p = p + (tau + ext) * 0.01  # the momentum a missing torque builds
        out.append((t, v, p.copy(), tau))
    return out


@pytest.mark.skipif(contact_kernel() is None, reason="numba is not installed")
def _same(a: np.ndarray, b: np.ndarray, what: str) -> None:
    """Equal (integers, booleans) or within rtol = atol = 1e-12 (floats; NaN where NaN), step by step: ``a`` and
    ``b`` are the reference's and the kernel's values stacked over the steps (axis 0); a mismatch names its first
    step."""
    ok = np.isclose(b, a, rtol=1e-12, atol=1e-12, equal_nan=True) if a.dtype.kind == "f" else b == a
    bad = np.flatnonzero(~ok.reshape(ok.shape[0], -1).all(axis=1))
    if bad.size:
        k = int(bad[0])
        raise AssertionError(f"step {k}: {what}: kernel {b[k]!r} vs numpy {a[k]!r}")


@pytest.mark.parametrize("seed", [3, 17])
def test_the_contact_kernel_matches_the_numpy_update(seed: int) -> None:
    kt = np.array([10.0, 10.7, 8.5, 9.0, 9.5, 10.1])
    ref = ContactDetector(kt, _bands(), ContactSettings())
    got = ContactDetector(kt, _bands(), ContactSettings())
    got.use_kernel(contact_kernel())
    seq = _sequence(seed, 6000)
    for det in (ref, got):
        det.arm(seq[0][2], seq[0][0])
    seen: set[int] = set()
    states_ref: dict[str, list[np.ndarray]] = {f: [] for f in STATE}
    states_got: dict[str, list[np.ndarray]] = {f: [] for f in STATE}
    for k, (t, dq, p, tau) in enumerate(seq):
        a = ref.update(t, dq, p, tau)
        b = got.update(t, dq, p, tau)
        assert a == b, f"step {k}: code {a} vs {b}"
        for f in STATE:  # (kept per step, compared once at the end: the same test for each step's values)
            states_ref[f].append(np.array(getattr(ref, f), copy=True))
            states_got[f].append(np.array(getattr(got, f), copy=True))
        seen.update(int(x) for x in ref.state)
    for f in STATE:
        _same(np.stack(states_ref[f]), np.stack(states_got[f]), f)
    assert seen == {MOVING, SETTLING, HELD, RELEASED}, seen  # every state was visited
    assert len(ref.events) >= 5
    assert [e.to_json(list("abcdef")) for e in ref.events] == [e.to_json(list("abcdef")) for e in got.events]


def test_the_observer_step_forms_agree_and_the_residual_follows_a_step_torque() -> None:
    """ṙ = K_o(τ_ext − r): a step of external torque is reached to 63 % after 1/K_o."""
    k_o, dt = 25.0, 1e-3
    tau_ext = np.array([5.0, -2.0, 0.0])
    p0 = np.zeros(3)
    a_int, a_r = np.zeros(3), np.zeros(3)
    b_int, b_r = np.zeros(3), np.zeros(3)
    p, scratch = np.zeros(3), np.zeros(3)
    tau_in = np.array([1.0, 0.5, -0.3])
    for k in range(int(0.2 / dt)):
        p += (tau_in + tau_ext) * dt
        observer_step(dt, k_o, tau_in, p, p0, a_int, a_r)
        observer_step_np(dt, k_o, tau_in, p, p0, b_int, b_r, scratch)
        assert np.array_equal(a_r, b_r)
        if k + 1 == int(1.0 / k_o / dt):
            np.testing.assert_allclose(a_r, tau_ext * (1 - np.exp(-1.0)), rtol=0.02, atol=1e-9)
    np.testing.assert_allclose(a_r, tau_ext * (1 - np.exp(-k_o * 0.2)), rtol=1e-2, atol=1e-9)
