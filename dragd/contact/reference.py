"""The textbook contact detector the real-robot benchmark compares with (issue #29; Mamedov & Mikhel 2020's baseline):

* model: ordinary least squares of the base rigid-body parameters + per joint viscous, Coulomb (sign of q̇) and offset,
  on the drive gain × current (``dragd.lab.bench.ident_real.Reference``, the dataset's own scripts);
* residual: the generalised-momentum observer (gain 25/s) on that model — p = M(q)q̇, g(q) and Cᵀ(q, q̇)q̇ all from
  the identified regressor Y(q, q̇, q̈)·β (p = Yβ(q, 0, q̇) − g; Cq̇ = Yβ(q, q̇, 0) − g; Ṁq̇ by a central difference
  of p along q̇; Cᵀq̇ = Ṁq̇ − Cq̇);
* thresholds: per joint 1.2 × the largest |residual| of the free-motion logs; an alarm while any joint is above its
  threshold, one event per rising edge.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from dragd.control.observer import observer_step_np

GAIN_PER_S = 25.0
THRESHOLD_FACTOR = 1.2


@dataclass
class ReferenceEvent:
    t_start_s: float
    t_end_s: float
    joints: list[int]


@dataclass
class ReferenceRun:
    t: np.ndarray
    r_A: np.ndarray  # residual / drive gain [A]
    events: list[ReferenceEvent]


class TextbookDetector:
    """Momentum observer + fixed per-joint thresholds on the OLS reference model (see the module docstring)."""

    def __init__(self, reference: Any, gain_per_s: float = GAIN_PER_S) -> None:
        self.ref = reference  # ident_real.Reference, fitted
        self.gain = gain_per_s
        self.K = reference.K
        self.n = reference.n
        nb = len(reference.cols)
        th = reference.theta
        self.beta = th[:nb]
        self.fric = th[nb:].reshape(self.n, 3)  # per joint [f_v, f_c, f_0] in N·m
        self.thresholds_A: np.ndarray | None = None

    def _yb(self, q: np.ndarray, v: np.ndarray, a: np.ndarray) -> np.ndarray:
        """Y(q, v, a)·β per sample, (N, n) [N·m]."""
        return self.ref.regressor(q, v, a)[:, :, self.ref.cols] @ self.beta

    def terms(self, q: np.ndarray, dq: np.ndarray, i_A: np.ndarray, eps: float = 1e-4) -> tuple[np.ndarray, np.ndarray]:
        """(p, τ_in) per sample: τ_in = K·i − friction − g + Cᵀq̇."""
        z = np.zeros_like(q)
        g = self._yb(q, z, z)
        p = self._yb(q, z, dq) - g

        def mom(qq: np.ndarray) -> np.ndarray:
            return self._yb(qq, z, dq) - self._yb(qq, z, z)

        mdot_v = (mom(q + eps * dq) - mom(q - eps * dq)) / (2 * eps)  # Ṁ(q, q̇)·q̇
        c_v = self._yb(q, dq, z) - g  # C(q, q̇)·q̇
        ct_v = mdot_v - c_v
        f = self.fric
        friction = f[:, 0] * dq + f[:, 1] * np.sign(dq) + f[:, 2]
        tau = self.K * i_A - friction - g + ct_v
        return p, tau

    def residual(self, t: np.ndarray, p: np.ndarray, tau: np.ndarray) -> np.ndarray:
        """The observer's residual / K [A] at every sample (started from the first sample's momentum)."""
        n = self.n
        p0, integ, r, scratch = p[0].copy(), np.zeros(n), np.zeros(n), np.zeros(n)
        out = np.empty_like(p)
        for k in range(t.shape[0]):
            dt = t[k] - t[k - 1] if k else 0.0
            observer_step_np(dt, self.gain, tau[k], p[k], p0, integ, r, scratch)
            out[k] = r / self.K
        return out

    def calibrate(self, residuals: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
        """Thresholds: 1.2 × the largest |residual| per joint over (residual, usable-sample mask) pairs;
        ``self.set_by`` names, per joint, the pair index and sample that set it."""
        top = np.zeros(self.n)
        self.set_by: list[tuple[int, int]] = [(-1, -1)] * self.n
        for idx, (r, ok) in enumerate(residuals):
            a = np.where(ok[:, None], np.abs(r), 0.0)
            k = np.argmax(a, axis=0)
            for j in range(self.n):
                if a[k[j], j] > top[j]:
                    top[j] = a[k[j], j]
                    self.set_by[j] = (idx, int(k[j]))
        self.thresholds_A = THRESHOLD_FACTOR * top
        return self.thresholds_A

    def detect(self, t: np.ndarray, r_A: np.ndarray, arm_s: float = 0.2) -> ReferenceRun:
        """Events: an alarm while any joint's |residual| is above its threshold (after ``arm_s``)."""
        assert self.thresholds_A is not None
        over = np.abs(r_A) > self.thresholds_A
        over[t - t[0] < arm_s] = False
        events: list[ReferenceEvent] = []
        on = over.any(axis=1)
        k = 0
        N = t.shape[0]
        while k < N:
            if on[k]:
                k0 = k
                while k < N and on[k]:
                    k += 1
                js = [int(j) for j in np.flatnonzero(over[k0:k].any(axis=0))]
                events.append(ReferenceEvent(float(t[k0]), float(t[min(k, N - 1)]), js))
            k += 1
        return ReferenceRun(t, r_A, events)
