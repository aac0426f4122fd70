"""Regressors of the rigid-body model from the URDF's kinematics, and their base (minimal) parameter sets.

Pinocchio's joint-torque regressor gives τ = Y(q, q̇, q̈)·π with π the 10 standard inertial parameters of every
body (m, m·c, I at the joint frame). Many combinations of π never show in τ; the base parameters are found
numerically (no hand rules): stack Y at random (q, q̇, q̈), QR with column pivoting, the first r pivots are the
independent columns, β = π_I + R₁₁⁻¹R₁₂·π_D. With q̇ = q̈ = 0 the same gives the minimal *gravity*
parameter set (seed 001 §2.2: 2(n − 1) = 10 for the UR-like seed cobot).

Identification from motor current works joint by joint (each joint has its own K_t), so besides the global
base there is a per-row base: the independent columns of joint j's row alone.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pinocchio as pin
from scipy.linalg import qr, solve_triangular

PARAM_NAMES = ("m", "mcx", "mcy", "mcz", "Ixx", "Ixy", "Iyy", "Ixz", "Iyz", "Izz")


@dataclass
class Base:
    """A base parameter set: ``cols`` independent columns of the full regressor, β = E·π (E = [I | K] mapped)."""

    cols: np.ndarray  # indices into the full parameter vector (length r)
    E: np.ndarray  # r × p: β = E @ π
    names: list[str]

    @property
    def r(self) -> int:
        return int(self.cols.shape[0])


def _base_from_samples(Y: np.ndarray, names: list[str], tol: float = 1e-8) -> Base:
    """Independent columns of a stacked regressor Y (S × p) and the map from full to base parameters."""
    p = Y.shape[1]
    norms = np.linalg.norm(Y, axis=0)
    live = np.nonzero(norms > tol * max(1.0, norms.max(initial=0.0)))[0]
    if live.size == 0:
        return Base(np.zeros(0, dtype=int), np.zeros((0, p)), [])
    Yl = Y[:, live]
    _, R, piv = qr(Yl, mode="economic", pivoting=True)
    d = np.abs(np.diag(R))
    r = int(np.sum(d > tol * d[0]))
    ind = live[piv[:r]]
    dep = live[piv[r:]]
    E = np.zeros((r, p))
    E[np.arange(r), ind] = 1.0
    if dep.size:
        K = solve_triangular(R[:r, :r], R[:r, r:])
        E[:, dep] = K
    # express names of the combinations
    out_names = []
    for k in range(r):
        terms = [names[ind[k]]] + [f"{E[k, c]:+.4g}·{names[c]}" for c in dep if abs(E[k, c]) > 1e-10]
        out_names.append(" ".join(terms))
    order = np.argsort(ind)
    return Base(ind[order], E[order], [out_names[k] for k in order])


class RegressorModel:
    """Regressors of one robot model (Pinocchio) and their base parameter sets, computed once."""

    def __init__(self, robot: Any, samples: int = 400, seed: int = 11) -> None:
        self.model: pin.Model = getattr(robot, "model", robot)
        self.data = self.model.createData()
        self.n = self.model.nv
        # parameters: 10 per body (Pinocchio's order), then one rotor inertia ("armature", J_a·q̈_j) per joint
        self.p = 11 * self.n
        self.names = [f"{self.model.names[i + 1]}.{k}" for i in range(self.n) for k in PARAM_NAMES] + \
                     [f"{self.model.names[i + 1]}.armature" for i in range(self.n)]
        self.pi_urdf = np.concatenate([self.model.inertias[i + 1].toDynamicParameters() for i in range(self.n)]
                                      + [np.asarray(self.model.armature, dtype=float)])
        rng = np.random.default_rng(seed)
        lo = np.maximum(self.model.lowerPositionLimit, -np.pi)
        hi = np.minimum(self.model.upperPositionLimit, np.pi)
        q = rng.uniform(lo, hi, (samples, self.n))
        v = rng.normal(0.0, 1.0, (samples, self.n))
        a = rng.normal(0.0, 1.0, (samples, self.n))
        Y = self.torque_regressor(q, v, a)
        Yg = self.torque_regressor(q)
        self.base_full = _base_from_samples(Y.reshape(-1, self.p), self.names)
        self.base_gravity = _base_from_samples(Yg.reshape(-1, self.p), self.names)
        self.row_full = [_base_from_samples(Y[:, j, :], self.names) for j in range(self.n)]
        self.row_gravity = [_base_from_samples(Yg[:, j, :], self.names) for j in range(self.n)]
        # torque [N·m] one unit of each per-row base parameter makes at most over the random states (|q̇|, |q̈| ~ 1)
        self.row_scale = [np.abs(Y[:, j, b.cols]).max(axis=0) if b.r else np.zeros(0)
                          for j, b in enumerate(self.row_full)]

    # ------------------------------------------------------------------------------------ evaluation

    def torque_regressor(self, q: np.ndarray, dq: np.ndarray | None = None,
                         ddq: np.ndarray | None = None) -> np.ndarray:
        """Y (T × n × 11n) with τ_t = Y_t·π (bodies, then armature); q̇ = q̈ = 0 when not given (gravity)."""
        T = q.shape[0]
        n = self.n
        out = np.zeros((T, n, self.p))
        z = np.zeros(n)
        m, d = self.model, self.data
        f = pin.computeJointTorqueRegressor
        if dq is None:
            for k in range(T):
                out[k, :, :10 * n] = f(m, d, q[k], z, z)
        else:
            for k in range(T):
                out[k, :, :10 * n] = f(m, d, q[k], dq[k], ddq[k] if ddq is not None else z)
            if ddq is not None:
                idx = np.arange(n)
                out[:, idx, 10 * n + idx] = ddq
        return out

    def gravity(self, q: np.ndarray) -> np.ndarray:
        """G(q) for every row of q (T × n) [N·m] with the model's own inertials."""
        out = np.empty_like(q)
        m, d = self.model, self.data
        for k in range(q.shape[0]):
            out[k] = pin.computeGeneralizedGravity(m, d, q[k])
        return out

    def rnea(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> np.ndarray:
        out = np.empty_like(q)
        m, d = self.model, self.data
        for k in range(q.shape[0]):
            out[k] = pin.rnea(m, d, q[k], dq[k], ddq[k])
        return out

    def gravity_free(self) -> list[bool]:
        """Joints whose torque has no gravity part in any pose (e.g. a vertical base axis, a flange roll axis)."""
        return [b.r == 0 for b in self.row_gravity]

    # ------------------------------------------------------------------------------------ excitation

    def row_matrix(self, j: int, Y: np.ndarray, ddq: np.ndarray, dq: np.ndarray) -> np.ndarray:
        """Joint j's identification columns: base rigid-body + rotor inertia, Coulomb (smoothed sign), viscous."""
        b = self.row_full[j]
        cols = [Y[:, j, b.cols], np.tanh(dq[:, j:j + 1] / 0.02), dq[:, j:j + 1]]
        return np.hstack(cols)

    def condition_numbers(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> list[float]:
        Y = self.torque_regressor(q, dq, ddq)
        out = []
        for j in range(self.n):
            W = self.row_matrix(j, Y, ddq, dq)
            W = W / np.maximum(np.linalg.norm(W, axis=0), 1e-12)
            s = np.linalg.svd(W, compute_uv=False)
            out.append(float(s[0] / max(s[-1], 1e-12)))
        return out

    def excitation_cost(self, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> float:
        return float(np.sum(np.log(self.condition_numbers(q, dq, ddq))))
