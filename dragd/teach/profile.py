"""Jerk-limited rest-to-rest motion profile in one coordinate (the "double S" of Biagiotti & Melchiorri).

A move of length L under |v| ≤ V, |a| ≤ A, |j| ≤ J takes seven phases of constant jerk (+J, 0, −J, 0, −J, 0, +J).
Scaling all three limits as V/k, A/k², J/k³ stretches the same profile in time by k, which is how the planners
slow a move down uniformly (speed override, limit verification).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SCurve:
    """A rest-to-rest double-S profile over ``length`` (≥ 0) reaching at most ``v_max``, ``a_max``, ``j_max``."""

    length: float
    v_max: float
    a_max: float
    j_max: float
    tj: float  # duration of each jerk phase
    ta: float  # duration of the acceleration (and of the deceleration) phase, jerk phases included
    tv: float  # duration of the constant-velocity phase

    @classmethod
    def plan(cls, length: float, v_max: float, a_max: float, j_max: float) -> SCurve:
        if not (v_max > 0 and a_max > 0 and j_max > 0):
            raise ValueError(f"profile: expected positive limits, got v {v_max}, a {a_max}, j {j_max}")
        L = float(length)
        if L < 0 or not math.isfinite(L):
            raise ValueError(f"profile: expected a length >= 0, got {length}")
        if L == 0.0:
            return cls(0.0, v_max, a_max, j_max, 0.0, 0.0, 0.0)
        V, A, J = float(v_max), float(a_max), float(j_max)
        if V * J >= A * A:  # the acceleration limit is reached on the way to V
            tj = A / J
            ta = tj + V / A
        else:
            tj = math.sqrt(V / J)
            ta = 2.0 * tj
        tv = L / V - ta
        if tv < 0.0:  # V is not reached
            tv = 0.0
            if L >= 2.0 * A ** 3 / J ** 2:
                tj = A / J
                ta = tj / 2.0 + math.sqrt(tj * tj / 4.0 + L / A)
            else:
                tj = (L / (2.0 * J)) ** (1.0 / 3.0)
                ta = 2.0 * tj
        return cls(L, V, A, J, tj, ta, tv)

    @property
    def duration(self) -> float:
        return 2.0 * self.ta + self.tv

    @property
    def peak_velocity(self) -> float:
        return self.j_max * self.tj * (self.ta - self.tj)

    def phases(self) -> list[tuple[float, float]]:
        """(duration, jerk) of the seven phases."""
        J, tj, ta, tv = self.j_max, self.tj, self.ta, self.tv
        mid = max(ta - 2.0 * tj, 0.0)
        return [(tj, J), (mid, 0.0), (tj, -J), (tv, 0.0), (tj, -J), (mid, 0.0), (tj, J)]

    def evaluate(self, t_s: np.ndarray | float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Position, velocity, acceleration and jerk at times ``t_s`` (clipped to [0, duration])."""
        t = np.clip(np.asarray(t_s, dtype=float), 0.0, self.duration)
        s = np.zeros_like(t)
        v = np.zeros_like(t)
        a = np.zeros_like(t)
        jk = np.zeros_like(t)
        if self.length == 0.0:
            return s, v, a, jk
        t0, s0, v0, a0 = 0.0, 0.0, 0.0, 0.0
        for k, (d, j) in enumerate(self.phases()):
            last = k == 6
            m = (t >= t0) if last else ((t >= t0) & (t < t0 + d))
            if np.any(m):
                x = t[m] - t0
                s[m] = s0 + v0 * x + a0 * x * x / 2.0 + j * x ** 3 / 6.0
                v[m] = v0 + a0 * x + j * x * x / 2.0
                a[m] = a0 + j * x
                jk[m] = j
            s0, v0, a0 = s0 + v0 * d + a0 * d * d / 2.0 + j * d ** 3 / 6.0, v0 + a0 * d + j * d * d / 2.0, a0 + j * d
            t0 += d
        # the closed form ends at `length` up to rounding: remove the residue so the move ends exactly there
        if s0 > 0.0:
            s *= self.length / s0
            v *= self.length / s0
            a *= self.length / s0
        return s, v, a, jk
