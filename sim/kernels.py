"""The simulated arm's compiled kernels (numba, through dragd.jit): stiction holding the stuck DOFs.

``sim.physics.hold_stuck`` (``_solve_spd`` and the break-away loop over lists) is the reference; :func:`_hold_kernel`
does the same arithmetic in the same order on arrays — one call instead of an O(m³) elimination in Python per step
and per break-away (at 12 joints with most of them at rest that was the simulator's largest single cost, ~40 µs a
step). tests/test_sim_kernels.py holds the two to each other.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from dragd.jit import compile_kernels


def _solve_into(minv: np.ndarray, idx: np.ndarray, m: int, a: np.ndarray, rows: np.ndarray,
                lam: np.ndarray) -> None:
    """lam[:m] ← x solving minv[S, S]·x = −a[S], S = idx[:m] (``sim.physics._solve_spd``'s elimination)."""
    if m == 1:
        k = idx[0]
        lam[0] = -a[k] / minv[k, k]
        return
    for r in range(m):
        i = idx[r]
        for c in range(m):
            rows[r, c] = minv[i, idx[c]]
        rows[r, m] = -a[i]
    for c in range(m):
        inv = 1.0 / rows[c, c]
        for r in range(c + 1, m):
            f = rows[r, c] * inv
            if f != 0.0:
                for k in range(c, m + 1):
                    rows[r, k] -= f * rows[c, k]
    for c in range(m - 1, -1, -1):
        s = rows[c, m]
        for k in range(c + 1, m):
            s -= rows[c, k] * lam[k]
        lam[c] = s / rows[c, c]


def _hold_kernel(minv: np.ndarray, a: np.ndarray, stuck: np.ndarray, lim_pos: np.ndarray, lim_neg: np.ndarray,
                 fric: np.ndarray, dirs: np.ndarray, idx: np.ndarray, rows: np.ndarray, lam: np.ndarray) -> None:
    """``sim.physics.hold_stuck`` on arrays (``stuck`` bool; ``idx``, ``rows``, ``lam``: work arrays of the DOF
    count)."""
    nf = a.shape[0]
    m = 0
    for k in range(nf):
        if stuck[k]:
            idx[m] = k
            m += 1
    while m > 0:
        _solve_into(minv, idx, m, a, rows, lam)
        worst, worst_excess = -1, 0.0
        for i in range(m):
            k = idx[i]
            lk = lam[i]
            excess = lk - lim_neg[k] if lk > 0.0 else -lk - lim_pos[k]
            if excess > worst_excess:
                worst, worst_excess = i, excess
        if worst < 0:
            break
        k = idx[worst]
        d = -1.0 if lam[worst] > 0.0 else 1.0  # it moves against the torque that would have held it
        f = -d * (lim_pos[k] if d > 0.0 else lim_neg[k])
        for i in range(nf):
            a[i] += minv[i, k] * f
        fric[k] = f
        stuck[k] = False
        dirs[k] = d
        for i in range(worst, m - 1):
            idx[i] = idx[i + 1]
        m -= 1
    for i in range(m):
        k = idx[i]
        lk = lam[i]
        fric[k] = lk
        for r in range(nf):
            a[r] += minv[r, k] * lk
    for i in range(m):
        a[idx[i]] = 0.0


def hold_kernel() -> Any | None:
    """The compiled :func:`_hold_kernel` (None where numba is missing: the Python reference runs)."""
    n = 2
    warm = (np.eye(n), np.zeros(n), np.ones(n, dtype=np.bool_), np.ones(n), np.ones(n), np.zeros(n), np.zeros(n),
            np.zeros(n, dtype=np.int64), np.zeros((n, n + 1)), np.zeros(n))
    kernels = compile_kernels(globals(), ("_solve_into",), {"hold": (_hold_kernel, warm)})
    return None if kernels is None else kernels["hold"]
