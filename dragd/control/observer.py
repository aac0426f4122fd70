"""The generalised-momentum observer (De Luca's residual): one arithmetic for the runaway guard and the contact
detector.

With p = M̄(q)·q̇ the generalised momentum (M̄ = M + the rotor inertias) and τ_in every torque the model accounts for,

    ṗ = τ_in + τ_ext,    τ_in = K_t·(I − I_friction) − g(q) + Cᵀ(q, q̇)·q̇

the residual r = K_o·(p − p₀ − ∫(τ_in + r) dt) obeys ṙ = K_o·(τ_ext − r): a first-order low-pass (time constant 1/K_o)
of the torque nobody commanded — a hand, a collision, a load the model lacks, and the model's own error. No joint
acceleration is needed. The guard (dragd/control/guard.py, in drag) passes τ_in with gravity and the law's terms
already taken out of the command and neglects Cᵀq̇ (hand-guiding speeds); the contact detector
(dragd/control/contact.py) passes the whole τ_in of the identified model.

``observer_step`` is the compiled kernels' form (scalar loop, jitted into each kernel's module), ``observer_step_np``
the numpy reference: the same operations in the same order, so both give the same bits.
"""

from __future__ import annotations

import numpy as np


def observer_step(dt: float, k_o: float, tau_in: np.ndarray, p: np.ndarray, p0: np.ndarray, integ: np.ndarray,
                  r: np.ndarray) -> None:
    """integ += (τ_in + r)·dt;  r = K_o·(p − p₀ − integ), joint by joint (in place)."""
    for j in range(tau_in.shape[0]):
        a = tau_in[j] + r[j]
        a *= dt
        integ[j] += a
        a = p[j] - p0[j]
        a -= integ[j]
        r[j] = a * k_o


def observer_step_np(dt: float, k_o: float, tau_in: np.ndarray, p: np.ndarray, p0: np.ndarray, integ: np.ndarray,
                     r: np.ndarray, scratch: np.ndarray) -> None:
    """``observer_step`` with numpy ufuncs into ``scratch`` (no allocation)."""
    np.add(tau_in, r, out=scratch)
    scratch *= dt
    integ += scratch
    np.subtract(p, p0, out=scratch)
    scratch -= integ
    np.multiply(scratch, k_o, out=r)
