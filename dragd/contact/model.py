"""The identified model the contact detector's residual uses: one robot model (Pinocchio from the URDF + the params'
link inertials and rotor inertias), the identified friction (dragd's law, unscaled) and K_t.

    p = M̄(q)·q̇,   τ_in = K_t·(I − I_f(q̇) − I_L(q, q̇)) − g(q) + Cᵀ(q, q̇)·q̇,   M̄ = M + diag(J_a)

with I_L = w(q̇)·sign(q̇)·k_L·|g(q)|/K_t the load-dependent friction (params ``effects.load_friction_per_Nm``).

``terms`` evaluates them per sample into preallocated arrays with numpy (the reference); ``log_terms`` over a whole
log with the cycle's compiled arithmetic (dragd/control/contact.py ``contact_tau_in``: only Pinocchio's p, g and
C(q, q̇) outside it), or with ``terms`` where numba is missing or ``compiled`` is false.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin


class ContactModelError(ValueError):
    """A model the detector cannot use (the message names the file, joint and what was expected)."""


@dataclass
class ContactModel:
    robot: Any  # RobotModel with the identified inertials and rotor inertias applied
    law: Any  # LawParams: the identified friction (friction_scale 1: the model, not drag's under-compensation)
    kt_Nm_per_A: np.ndarray
    kt_source: str
    armature_kgm2: np.ndarray
    names: list[str]
    load_friction_per_Nm: np.ndarray | None = None  # k_L per joint (None: none)

    @classmethod
    def from_files(cls, robot: str | Path, params: Any, params_name: str = "params",
                   torque_constants: list[float] | None = None) -> ContactModel:
        """``robot`` (URDF or bundled name) with ``params`` (a ParamsFile): inertials, rotor inertias
        (notes.armature_kgm2), friction; K_t from ``torque_constants`` else the params' (every joint needs one)."""
        from dragd.identify.check import law_from_params
        from dragd.model import RobotModel

        rm = RobotModel.from_urdf(robot)
        names = list(rm.joint_names)
        unknown = sorted(set(params.joints) - set(names))
        if unknown:
            raise ContactModelError(f"{params_name}: joints: expected the robot's joints ({', '.join(names)}), got "
                                    f"{', '.join(unknown)}")
        if params.inertials:
            try:
                rm.apply_inertials(params.inertials, params_name)
            except ValueError as exc:
                raise ContactModelError(str(exc)) from None
        arm_notes = (params.notes or {}).get("armature_kgm2") or {}
        # the identified rotor inertias, else the joints' configured ones (effects.armature_kgm2), as the daemon's
        # model has them (dragd.model.configured_armature)
        arm = np.array([float(arm_notes[nm]) if arm_notes.get(nm) is not None
                        else float((jp := params.joints.get(nm)) is not None and jp.effects is not None
                                   and jp.effects.armature_kgm2 or 0.0) for nm in names])
        rm.model.armature = arm.copy()
        rm.data = rm.model.createData()
        rm._nograv = None
        law, _ = law_from_params(params, names)
        law = law.replace(friction_scale=1.0)
        if torque_constants is not None:
            if len(torque_constants) != len(names) or not all(k > 0 for k in torque_constants):
                raise ContactModelError(f"--torque-constants: expected {len(names)} positive joint-side torque "
                                        f"constants [N·m/A] ({', '.join(names)}), got {torque_constants}")
            kt, src = np.asarray(torque_constants, dtype=float), "given (--torque-constants)"
        else:
            kt = np.array([np.nan if (jp := params.joints.get(nm)) is None or jp.torque_constant_Nm_per_A is None
                           else float(jp.torque_constant_Nm_per_A) for nm in names])
            missing = [nm for nm, k in zip(names, kt, strict=True) if not np.isfinite(k)]
            if missing:
                raise ContactModelError(f"{params_name}: torque_constant_Nm_per_A is null for {', '.join(missing)}: "
                                        "the residual is a torque; give --torque-constants K1,..,KN (joint side, "
                                        "N·m/A) or fit with them (dragd identify fit --torque-constants)")
            src = f"{params_name} (torque_constant_Nm_per_A)"
        law = law.replace(kt_Nm_per_A=kt)
        k_load = np.array([float(jp.effects.load_friction_per_Nm) if (jp := params.joints.get(nm)) is not None else 0.0
                           for nm in names])
        return cls(rm, law, kt, src, arm, names, k_load if k_load.any() else None)

    def workspace(self) -> dict[str, np.ndarray]:
        from dragd.control.law import Workspace

        n = len(self.names)
        return {"fr": np.zeros(n), "ws": Workspace(n), "w": np.zeros(n), "tmp": np.zeros(n)}  # type: ignore[dict-item]

    def terms(self, q: np.ndarray, dq: np.ndarray, i_A: np.ndarray, p_out: np.ndarray, tau_out: np.ndarray,
              ws: dict[str, Any]) -> None:
        """p = M̄q̇ and τ_in = K_t·(I − I_f) − g + Cᵀq̇ at one sample, into the given arrays."""
        from dragd.control.law import _sliding_weight, friction_current

        m, d = self.robot.model, self.robot.data
        self.robot.momentum(q, dq, p_out)  # RNEA of a gravity-free copy at q̈ = q̇ (rotor inertias included)
        g = pin.computeGeneralizedGravity(m, d, q)
        C = pin.computeCoriolisMatrix(m, d, q, dq)
        fr = friction_current(dq, self.law, ws["fr"], ws["ws"])
        if self.load_friction_per_Nm is not None:  # w·sign(q̇)·k_L·|g|/K_t
            w = ws["w"]
            np.abs(dq, out=w)
            _sliding_weight(w, self.law, w, ws["tmp"], None)
            np.abs(g, out=ws["tmp"])
            w *= ws["tmp"]
            w *= self.load_friction_per_Nm
            w /= self.kt_Nm_per_A
            np.copysign(w, dq, out=w)
            fr += w
        np.subtract(i_A, fr, out=tau_out)
        tau_out *= self.kt_Nm_per_A
        tau_out -= g
        tau_out += C.T @ dq

    def pack(self) -> tuple[np.ndarray, np.ndarray]:
        """The packed model of ``contact_tau_in`` (dragd/control/contact.py ``pack_model``)."""
        from dragd.control.contact import pack_model

        return pack_model(self.law, self.kt_Nm_per_A, self.load_friction_per_Nm)

    def log_terms(self, q: np.ndarray, dq: np.ndarray, i_A: np.ndarray,
                  compiled: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """(p, τ_in) at every sample of a log, each (N, n): the cycle's arithmetic (``compiled``), else ``terms``."""
        from dragd.control.contact import contact_kernels

        N, n = q.shape
        P, T = np.empty((N, n)), np.empty((N, n))
        kernels = contact_kernels() if compiled else None
        if kernels is None:
            ws = self.workspace()
            for k in range(N):
                self.terms(q[k], dq[k], i_A[k], P[k], T[k], ws)
            return P, T
        tau_in = kernels["tau_in"]
        F, FS = self.pack()
        m, d = self.robot.model, self.robot.data
        q, dq, i_A = (np.ascontiguousarray(a, dtype=float) for a in (q, dq, i_A))
        for k in range(N):
            self.robot.momentum(q[k], dq[k], P[k])
            g = pin.computeGeneralizedGravity(m, d, q[k])
            C = pin.computeCoriolisMatrix(m, d, q[k], dq[k])
            tau_in(dq[k], i_A[k], g, C, F, FS, T[k])
        return P, T
