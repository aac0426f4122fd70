"""The robot model: a Pinocchio model built from a URDF (constant) plus its scratch data.

One model serves the control law, identification, the model-gap workflow and the simulator.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

from dragd.robots import resolve_urdf


def _body_link(model: pin.Model, jid: int) -> str:
    """The URDF link joint ``jid`` moves: the body frame whose parent joint it is (first one, Pinocchio's order)."""
    for f in model.frames:
        if f.parentJoint == jid and f.type == pin.FrameType.BODY:
            return f.name
    return model.names[jid]


class RobotModel:
    """Pinocchio ``Model`` (constant) and ``Data`` (scratch) for a fixed-base serial arm of revolute joints."""

    def __init__(self, model: pin.Model, urdf_path: Path | None = None) -> None:
        for jid in range(1, model.njoints):
            if model.joints[jid].nq != 1:
                raise ValueError(f"{urdf_path or model.name}: joint '{model.names[jid]}' has {model.joints[jid].nq} "
                                 "position coordinates; dragd expects revolute/prismatic joints (1 each)")
        self.model = model
        self.data = model.createData()
        self.urdf_path = urdf_path
        self.joint_names: tuple[str, ...] = tuple(model.names[1:])
        self.nq: int = model.nq
        self._zero = np.zeros(model.nv)

    @classmethod
    def from_urdf(cls, name_or_path: str | Path, base_dir: Path | None = None,
                  gravity_m_s2: tuple[float, float, float] | None = None) -> RobotModel:
        """Load a bundled robot (``seed_cobot``) or any URDF file."""
        path = resolve_urdf(name_or_path, base_dir)
        try:
            model = pin.buildModelFromUrdf(str(path))
        except (RuntimeError, ValueError) as exc:
            raise ValueError(f"{path}: not a loadable URDF: {exc}") from exc
        if gravity_m_s2 is not None:
            model.gravity.linear = np.asarray(gravity_m_s2, dtype=float)
        return cls(model, path)

    @classmethod
    def from_config(cls, cfg: object) -> RobotModel:
        """The configuration's robot (URDF, gravity) with its ``payload`` (``dragd gap``'s payload_mass) on the flange."""
        model = cls.from_urdf(cfg.robot.urdf, cfg.base_dir, cfg.robot.gravity_m_s2)  # type: ignore[attr-defined]
        inertials = getattr(cfg, "inertials", None)
        if inertials:
            model.apply_inertials(inertials, getattr(cfg, "source", "config"))
        payload = getattr(cfg, "payload", None)
        if payload is not None:
            model.add_payload(payload.mass_kg, payload.com_m)
        return model

    def link_names(self) -> list[str]:
        """The URDF link each joint moves (the body of joint 1..n), in joint order."""
        return [_body_link(self.model, jid) for jid in range(1, self.model.njoints)]

    def apply_inertials(self, inertials: Mapping[str, Any], source: str = "params") -> None:
        """Replace link inertials (``inertials:`` of a params file, docs/MODEL.md) in the Pinocchio model.

        Keys are URDF link names (the link a joint moves; links fixed to it are merged into it by Pinocchio and
        the identified inertial replaces the merged one). Values: ``mass_kg``, ``com_m`` (link frame) and
        ``inertia_kgm2`` (ixx, ixy, ixz, iyy, iyz, izz about the COM), mappings or objects with those fields.
        """
        links = self.link_names()
        for name, val in inertials.items():
            if name not in links:
                raise ValueError(f"{source}: inertials: expected link names among {', '.join(links)}, got '{name}'")
            get = (lambda k: val[k]) if isinstance(val, Mapping) else (lambda k: getattr(val, k))  # noqa: E731
            xx, xy, xz, yy, yz, zz = (float(v) for v in get("inertia_kgm2"))
            I = np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])
            self.model.inertias[links.index(name) + 1] = pin.Inertia(float(get("mass_kg")),
                                                                      np.asarray(get("com_m"), dtype=float), I)
        self.data = self.model.createData()

    def add_payload(self, mass_kg: float, com_m: tuple[float, float, float] | np.ndarray) -> None:
        """Add a point mass in the last joint's frame (a tool or load the URDF does not have)."""
        if mass_kg > 0:
            body = self.model.njoints - 1
            self.model.inertias[body] = self.model.inertias[body] + pin.Inertia(
                float(mass_kg), np.asarray(com_m, dtype=float), np.zeros((3, 3)))
            self.data = self.model.createData()

    @property
    def position_limits_rad(self) -> tuple[np.ndarray, np.ndarray]:
        return self.model.lowerPositionLimit.copy(), self.model.upperPositionLimit.copy()

    @property
    def effort_limits_Nm(self) -> np.ndarray:
        return self.model.effortLimit.copy()

    def gravity(self, q_rad: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Generalised gravity torque G(q) [N·m]: the joint torques that hold the arm still at q."""
        g = pin.computeGeneralizedGravity(self.model, self.data, q_rad)
        if out is None:
            return np.array(g)
        out[:] = g
        return out

    def inverse_dynamics(self, q_rad: np.ndarray, dq_rad_s: np.ndarray | None = None,
                         ddq_rad_s2: np.ndarray | None = None) -> np.ndarray:
        """Joint torques M(q)q̈ + C(q,q̇)q̇ + G(q) [N·m] (RNEA)."""
        dq = self._zero if dq_rad_s is None else dq_rad_s
        ddq = self._zero if ddq_rad_s2 is None else ddq_rad_s2
        return np.array(pin.rnea(self.model, self.data, q_rad, dq, ddq))

    def check_q(self, q_rad: np.ndarray, what: str = "q") -> np.ndarray:
        """Return q as a float array, or raise naming the expected joint count."""
        q = np.asarray(q_rad, dtype=float).reshape(-1)
        if q.shape[0] != self.nq:
            raise ValueError(f"{what}: expected {self.nq} values ({', '.join(self.joint_names)}), got {q.shape[0]}")
        return q
