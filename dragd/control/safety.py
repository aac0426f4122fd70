"""Safety terms added to every enabled mode's command: soft-limit walls and, in drag, the speed cap.

    wall (upper):  I −= [k·max(q − (hi − m), 0) + c·max(q̇, 0)·[penetrating]] / K_t     (lower: mirrored)
    speed cap:     I −= b·max(|q̇| − v_cap, 0)·sign(q̇) / K_t                            (drag only)

A spring–damper starts ``soft_limit_margin_rad`` inside each position limit and pushes back, damping only motion
further into the wall; the speed cap is a viscous brake on the speed above the joint's cap. Allocation-free; the
usual cycle (no joint near a wall, none above its cap) costs five ufuncs.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from dragd.jit import compile_kernels


def _safety_kernel(q: np.ndarray, dq: np.ndarray, speed_cap: bool, out: np.ndarray, lim_lo: np.ndarray,
                   lim_hi: np.ndarray, wall_lo: np.ndarray, wall_hi: np.ndarray, cap: np.ndarray, kt: np.ndarray,
                   margin: float, k_hi: float, k_lo: float, c: float, b: float) -> None:
    """``SafetyTerms.compute`` joint by joint (its numpy is the reference); ``k_hi``/``k_lo``: ±wall stiffness."""
    n = q.shape[0]
    near = False
    fast = False
    for j in range(n):
        out[j] = 0.0
        near = near or q[j] > wall_hi[j] or q[j] < wall_lo[j]
        fast = fast or (speed_cap and abs(dq[j]) > cap[j])
    if not (near or fast):
        return
    for j in range(n):
        if near:
            for lo in (False, True):
                pen = lim_lo[j] - q[j] if lo else q[j] - lim_hi[j]
                toward = dq[j] <= 0.0 if lo else dq[j] >= 0.0
                v = dq[j] if toward or dq[j] != dq[j] else 0.0  # np.minimum(dq, 0) / np.maximum(dq, 0)
                pen += margin
                pen = pen if (pen >= 0.0 or pen != pen) else 0.0
                v *= 1.0 if pen > 0.0 else 0.0
                pen *= k_lo if lo else k_hi
                v *= c
                out[j] -= pen
                out[j] -= v
        if fast:
            x = abs(dq[j]) - cap[j]
            x = x if (x >= 0.0 or x != x) else 0.0
            x *= 1.0 if dq[j] > 0.0 else (-1.0 if dq[j] < 0.0 else dq[j])  # np.sign
            x *= b
            out[j] -= x
        out[j] /= kt[j]


def safety_kernel() -> Any:
    """The compiled ``_safety_kernel`` (once per process), or None where numba cannot be imported."""
    f1 = np.zeros(1)
    k = compile_kernels(globals(), (), {"safety": (_safety_kernel, (
        f1, f1, True, f1.copy(), f1, f1, f1, f1, f1, np.ones(1), 0.1, 1.0, -1.0, 1.0, 1.0))})
    return None if k is None else k["safety"]


@dataclass
class SafetyTerms:
    """Walls and speed cap for n joints; ``compute`` writes the current [A] to add to the mode's command."""

    lim_lo_rad: np.ndarray
    lim_hi_rad: np.ndarray
    margin_rad: float
    wall_stiffness_Nm_per_rad: float
    wall_damping_Nm_s_per_rad: float
    speed_cap_rad_s: np.ndarray
    speed_cap_damping_Nm_s_per_rad: float
    kt_Nm_per_A: np.ndarray
    wall_hi_rad: np.ndarray = field(init=False)
    wall_lo_rad: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        n = self.kt_Nm_per_A.shape[0]
        self.wall_hi_rad = self.lim_hi_rad - self.margin_rad
        self.wall_lo_rad = self.lim_lo_rad + self.margin_rad
        self._p = np.zeros(n)
        self._v = np.zeros(n)
        self._m = np.zeros(n, dtype=bool)
        self._kernel: Any = None

    def use_kernel(self, kernel: Any) -> None:
        """``compute`` by the compiled kernel (``safety_kernel()``; the numpy below is its reference)."""
        self._kernel = kernel

    def compute(self, q: np.ndarray, dq: np.ndarray, speed_cap: bool, out: np.ndarray) -> None:
        """``out`` ← wall currents (+ the speed cap's when ``speed_cap``) [A]."""
        if self._kernel is not None:
            k = self.wall_stiffness_Nm_per_rad
            self._kernel(q, dq, speed_cap, out, self.lim_lo_rad, self.lim_hi_rad, self.wall_lo_rad, self.wall_hi_rad,
                         self.speed_cap_rad_s, self.kt_Nm_per_A, self.margin_rad, 1.0 * k, -1.0 * k,
                         self.wall_damping_Nm_s_per_rad, self.speed_cap_damping_Nm_s_per_rad)
            return
        p, v, m = self._p, self._v, self._m
        out.fill(0.0)
        np.greater(q, self.wall_hi_rad, out=m)
        near = bool(np.count_nonzero(m) > 0)  # (count_nonzero: 6× cheaper than .any() on a few joints)
        np.less(q, self.wall_lo_rad, out=m)
        near = near or bool(np.count_nonzero(m) > 0)
        fast = False
        if speed_cap:
            np.abs(dq, out=p)
            np.greater(p, self.speed_cap_rad_s, out=m)
            fast = bool(np.count_nonzero(m) > 0)
        if not (near or fast):
            return
        if near:
            # upper wall: penetration p = q - (hi - margin) > 0 pushes back, damping only while moving further in
            np.subtract(q, self.lim_hi_rad, out=p)
            np.maximum(dq, 0.0, out=v)
            self._wall(out, p, v, 1.0)
            np.subtract(self.lim_lo_rad, q, out=p)  # lower wall, mirrored
            np.minimum(dq, 0.0, out=v)
            self._wall(out, p, v, -1.0)
        if fast:  # drag speed cap: viscous brake on the excess speed
            np.abs(dq, out=p)
            p -= self.speed_cap_rad_s
            np.maximum(p, 0.0, out=p)
            np.sign(dq, out=v)
            p *= v
            p *= self.speed_cap_damping_Nm_s_per_rad
            out -= p
        out /= self.kt_Nm_per_A

    def _wall(self, out: np.ndarray, p: np.ndarray, v: np.ndarray, side: float) -> None:
        """out −= side·k·max(p + margin, 0) + c·v where penetrating (``v``: the speed component into the wall)."""
        m = self._m
        p += self.margin_rad
        np.maximum(p, 0.0, out=p)
        np.greater(p, 0.0, out=m)
        v *= m
        p *= side * self.wall_stiffness_Nm_per_rad
        v *= self.wall_damping_Nm_s_per_rad
        out -= p
        out -= v
