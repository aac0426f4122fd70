"""The cycle's estimate and output steps compiled (numba): encoder plausibility, counts → rad, per mille → A, the
velocity filter, and A → 60B2h per mille, rad → 607Ah counts.

The numpy code stays the reference (``EncoderPlausibility._check``, ``Scaling``, ``VelocityEstimator.update``):
these kernels do the same arithmetic in the same order per joint — one call each instead of 30-odd ufunc calls on
six-element arrays — and tests/test_cycle_kernels.py holds them to it over randomised sequences (wrap-around, late
and missing samples, jumps, saturation). The rare paths stay in Python: a rejected sample
(``EncoderPlausibility._reject``) and the velocity filter's reset. ``loop.compiled: false`` runs the reference.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from dragd.jit import compile_kernels

INT16_MIN, INT16_MAX = -32768.0, 32767.0


def _plausible_kernel(counts: np.ndarray, rx: np.ndarray, prev: np.ndarray, since: np.ndarray, run: np.ndarray,
                      step: np.ndarray, mask: np.ndarray) -> int:
    """``mask`` ← samples that moved further than ``step``·``since`` counts; with none, the bookkeeping too."""
    n_bad = 0
    for j in range(counts.shape[0]):
        bad = rx[j] and abs(float(counts[j] - prev[j])) > step[j] * since[j]
        mask[j] = bad
        n_bad += 1 if bad else 0
    if n_bad == 0:
        for j in range(counts.shape[0]):
            since[j] += 1.0
            if rx[j]:
                prev[j] = counts[j]
                since[j] = 1.0
                run[j] = 0
    return n_bad


def _inputs_kernel(counts: np.ndarray, offset: np.ndarray, rad_per_count: np.ndarray, q: np.ndarray,
                   permille: np.ndarray, A_per_permille: np.ndarray, current: np.ndarray) -> None:
    """q [rad] from 6064h counts; the motor current [A] from 6078h per mille."""
    for j in range(counts.shape[0]):
        q[j] = float(counts[j] - offset[j]) * rad_per_count[j]
        current[j] = permille[j] * A_per_permille[j]


def _velocity_kernel(counts: np.ndarray, fresh: np.ndarray, last: np.ndarray, v: np.ndarray, age: np.ndarray,
                     rad_per_count: np.ndarray, k: np.ndarray, dt: float, gain: float, uniform: bool) -> bool:
    """``VelocityEstimator.update`` after priming (dt > 0); returns the new ``uniform``."""
    n = counts.shape[0]
    all_fresh = True
    for j in range(n):
        all_fresh = all_fresh and fresh[j]
    if all_fresh and uniform:
        for j in range(n):
            raw = float(np.int32(counts[j] - last[j])) * rad_per_count[j]  # int32: 6064h wraps
            raw /= dt
            raw -= v[j]
            raw *= gain
            v[j] += raw
            last[j] = counts[j]
        return True
    for j in range(n):
        raw = float(np.int32(counts[j] - last[j])) * rad_per_count[j]
        age[j] += dt
        raw /= age[j]
        alpha = 1.0 - math.exp(age[j] * k[j])
        raw -= v[j]
        raw *= alpha
        if all_fresh or fresh[j]:
            v[j] += raw
            last[j] = counts[j]
            age[j] = 0.0
    return all_fresh


def _outputs_kernel(current: np.ndarray, permille_per_A: np.ndarray, torque: np.ndarray, q_ref: np.ndarray,
                    counts_per_rad: np.ndarray, offset: np.ndarray, target: np.ndarray) -> None:
    """60B2h torque offset (rounded, saturated to int16) from the command [A]; 607Ah target counts from q_ref [rad]."""
    for j in range(current.shape[0]):
        x = np.rint(current[j] * permille_per_A[j])
        x = x if (x <= INT16_MAX or x != x) else INT16_MAX  # np.minimum / np.maximum: NaN stays
        x = x if (x >= INT16_MIN or x != x) else INT16_MIN
        torque[j] = np.int64(x)
        target[j] = np.int64(np.rint(q_ref[j] * counts_per_rad[j])) + offset[j]


def kernels() -> dict[str, Any] | None:
    """The compiled kernels (once per process), or None where numba cannot be imported."""
    i1, f1, b1 = np.zeros(1, dtype=np.int64), np.zeros(1), np.zeros(1, dtype=bool)
    return compile_kernels(globals(), (), {
        "plausible": (_plausible_kernel, (i1, b1, i1.copy(), f1, i1.copy(), f1, b1.copy())),
        "inputs": (_inputs_kernel, (i1, i1, f1, f1.copy(), f1, f1, f1.copy())),
        "velocity": (_velocity_kernel, (i1, b1, i1.copy(), f1, f1.copy(), f1, f1, 1e-3, 0.2, True)),
        "outputs": (_outputs_kernel, (f1, f1, i1, f1, f1, i1, i1.copy()))})
