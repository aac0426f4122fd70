"""The safety terms' compiled compute (dragd/control/safety.py ``_safety_kernel``) against its numpy reference:
positions inside, near and beyond both walls, speeds below and above the caps, drag and other modes, ±0 and NaN."""

from __future__ import annotations

import numpy as np
import pytest

from dragd.control.safety import SafetyTerms, safety_kernel

pytestmark = [pytest.mark.unit, pytest.mark.skipif(safety_kernel() is None, reason="numba is not installed")]


def _terms() -> SafetyTerms:
    return SafetyTerms(lim_lo_rad=np.array([-3.0, -2.0, -2.5, -3.1, -2.0, -6.0]),
                       lim_hi_rad=np.array([3.0, 2.0, 2.5, 3.1, 2.0, 6.0]), margin_rad=0.1,
                       wall_stiffness_Nm_per_rad=200.0, wall_damping_Nm_s_per_rad=20.0,
                       speed_cap_rad_s=np.array([1.0, 1.0, 1.0, 1.5, 1.5, 1.5]), speed_cap_damping_Nm_s_per_rad=30.0,
                       kt_Nm_per_A=np.array([9.09, 9.09, 9.09, 4.545, 4.545, 4.545]))


def test_the_safety_kernel_matches_the_numpy_reference() -> None:
    rng = np.random.default_rng(12)
    ref, got = _terms(), _terms()
    got.use_kernel(safety_kernel())
    a, b = np.zeros(6), np.zeros(6)
    nonzero = 0
    for k in range(20000):
        q = rng.uniform(-1.1, 1.1, 6) * ref.lim_hi_rad  # inside, in the margin, beyond
        dq = rng.normal(0.0, 1.2, 6)
        if k % 97 == 0:
            dq[rng.integers(0, 6)] = rng.choice([0.0, -0.0, np.nan])
            q[rng.integers(0, 6)] = rng.choice([np.nan, ref.lim_hi_rad[0], ref.lim_lo_rad[0] + 0.1])
        cap = bool(k % 3)
        ref.compute(q, dq, cap, a)
        got.compute(q, dq, cap, b)
        assert np.array_equal(a, b, equal_nan=True), f"step {k}: {a} vs {b}"
        nonzero += bool(np.count_nonzero(a))
    assert nonzero > 5000  # walls and caps were hit
    assert len(safety_kernel().signatures) == 1
