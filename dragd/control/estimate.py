"""Joint velocity from encoder counts: filtered differentiation.

q̇_raw[k] = Δcounts·(2π/cpr)/Δt, then a first-order low-pass y += α(q̇_raw − y) with
α = 1 − exp(−2π f_c Δt). For signals well below f_c the estimate lags by ≈ 1/(2π f_c) + Δt/2
(the filter's group delay plus half a sample of the backward difference): 4.5 ms at f_c = 40 Hz, 1 kHz.
One encoder count per sample is (2π/cpr)/Δt: 0.012 rad/s for 2^19 counts/rev at 1 kHz, which the filter
averages down. A late or missed sample is handled by passing the real Δt (and the joints whose sample is fresh).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np


class VelocityEstimator:
    """Per-joint filtered differentiation of int32 encoder counts (wrap-safe); allocation-free ``update``."""

    def __init__(self, counts_per_rev: np.ndarray, cutoff_Hz: float, direction: np.ndarray | None = None) -> None:
        self.rad_per_count = 2.0 * math.pi / np.asarray(counts_per_rev, dtype=float)
        if direction is not None:
            self.rad_per_count = self.rad_per_count * np.asarray(direction, dtype=float)
        self.cutoff_Hz = float(cutoff_Hz)
        n = self.rad_per_count.shape[0]
        self.velocity_rad_s = np.zeros(n)
        self._last = np.zeros(n, dtype=np.int64)
        self._delta = np.zeros(n, dtype=np.int32)  # int32: a difference of 6064h values wraps by itself
        self._raw = np.zeros(n)
        self._alpha = np.zeros(n)
        self._age = np.zeros(n)  # seconds since each joint's last fresh sample
        self._uniform = True  # every joint's last sample was fresh: ages all zero
        self._k = np.full(n, -2.0 * math.pi * self.cutoff_Hz)
        self._primed = False
        self._all_fresh = np.ones(n, dtype=bool)
        self._kernel: Any = None

    def use_kernel(self, kernel: Any) -> None:
        """``update`` by a compiled kernel (dragd/daemon/kernels.py; this class's numpy code is its reference)."""
        self._kernel = kernel

    def delay_s(self, dt_s: float) -> float:
        """Low-frequency delay of the estimate."""
        return 1.0 / (2.0 * math.pi * self.cutoff_Hz) + dt_s / 2.0

    def reset(self, counts: np.ndarray) -> None:
        if np.asarray(counts).dtype.kind not in "iu":  # update() wraps differences with an unsafe integer cast
            raise TypeError("VelocityEstimator: encoder counts must be an integer array, "
                            f"got {np.asarray(counts).dtype}")
        self._last[:] = counts
        self.velocity_rad_s.fill(0.0)
        self._age.fill(0.0)
        self._uniform = True
        self._primed = True

    def update(self, counts: np.ndarray, dt_s: float, fresh: np.ndarray | None = None) -> np.ndarray:
        """Feed the latest counts (int array) sampled ``dt_s`` after the previous sampling instant; return q̇ [rad/s].

        ``dt_s`` is the real interval (a late SYNC samples later: dividing by the nominal period would turn
        timing jitter into velocity noise). ``fresh`` marks the joints whose counts are new this cycle; the
        others keep their estimate and their next fresh sample spans the whole gap.
        """
        if not self._primed or dt_s <= 0.0:
            self.reset(counts)
            return self.velocity_rad_s
        if self._kernel is not None:
            gain = 1.0 - math.exp(-2.0 * math.pi * self.cutoff_Hz * dt_s)
            self._uniform = self._kernel(counts, self._all_fresh if fresh is None else fresh, self._last,
                                         self.velocity_rad_s, self._age, self.rad_per_count, self._k, dt_s, gain,
                                         self._uniform)
            return self.velocity_rad_s
        all_fresh = fresh is None or np.count_nonzero(fresh) == fresh.shape[0]
        self._counts_to_rad(counts)
        if all_fresh and self._uniform:  # the usual cycle: one interval for every joint, a scalar filter gain
            self._raw /= dt_s
            self._raw -= self.velocity_rad_s
            self._raw *= 1.0 - math.exp(-2.0 * math.pi * self.cutoff_Hz * dt_s)
            self.velocity_rad_s += self._raw
            self._last[:] = counts
            return self.velocity_rad_s
        age = self._age
        age += dt_s
        self._raw /= age
        np.multiply(age, self._k, out=self._alpha)  # α = 1 − exp(−2π f_c·age)
        np.exp(self._alpha, out=self._alpha)
        np.subtract(1.0, self._alpha, out=self._alpha)
        self._raw -= self.velocity_rad_s
        self._raw *= self._alpha
        if all_fresh:
            self.velocity_rad_s += self._raw
            self._last[:] = counts
            age.fill(0.0)
            self._uniform = True
        else:
            self._uniform = False
            np.add(self.velocity_rad_s, self._raw, out=self.velocity_rad_s, where=fresh)
            np.copyto(self._last, counts, where=fresh)
            np.copyto(age, 0.0, where=fresh)
        return self.velocity_rad_s

    def _counts_to_rad(self, counts: np.ndarray) -> None:
        """``_raw`` ← counts − last sample's, wrap-safe (int32 wrap-around of 6064h), in rad."""
        d = self._delta
        np.subtract(counts, self._last, out=d, casting="unsafe")  # modulo 2^32 into [-2^31, 2^31)
        np.multiply(d, self.rad_per_count, out=self._raw)
