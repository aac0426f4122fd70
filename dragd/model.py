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


def configured_armature(cfg: object, names: tuple[str, ...] | list[str]) -> np.ndarray:
    """Each joint's rotor inertia at the joint [kg·m²] (Pinocchio's armature, in M̄ = M + diag(J_a)): the identified
    one (the params' ``notes.armature_kgm2``, ``identify fit``) where there is one, else the joint's
    ``effects.armature_kgm2`` (a datasheet's rotor inertia × gear², or what ``dragd gap`` found), else 0. One source
    for the law's model, the observers (runaway guard, contact), identification's prior and the replay's
    feed-forward (docs/CONTACT.md, docs/MODEL.md)."""
    identified = getattr(cfg, "armature_kgm2", None) or {}
    joints = {j.name: j for j in getattr(cfg, "joints", None) or []}
    out = np.zeros(len(names))
    for k, nm in enumerate(names):
        if identified.get(nm) is not None:
            out[k] = float(identified[nm])
        elif nm in joints and getattr(joints[nm].effects, "armature_kgm2", None) is not None:
            out[k] = float(joints[nm].effects.armature_kgm2)
    return out


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
        self._payload_base: pin.Inertia | None = None  # the last body's inertia without the payload
        self.payload_mass_kg = 0.0
        self.payload_com_m = np.zeros(3)
        self._ramp: tuple[pin.Model, pin.Data, float, float] | None = None  # (old model, data, t0, duration)
        self._g_old = np.zeros(model.nv)
        self._nograv: tuple[pin.Model, pin.Data] | None = None
        self.grip_frame_id = -1  # (add_grip)

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
        """The configuration's robot (URDF, gravity) with its ``payload`` (``dragd gap``'s payload_mass) on the
        flange."""
        model = cls.from_urdf(cfg.robot.urdf, cfg.base_dir, cfg.robot.gravity_m_s2)  # type: ignore[attr-defined]
        inertials = getattr(cfg, "inertials", None)
        if inertials:
            model.apply_inertials(inertials, getattr(cfg, "source", "config"))
        payload = getattr(cfg, "payload", None)
        if payload is not None:
            model.add_payload(payload.mass_kg, payload.com_m)
        model.set_armature(configured_armature(cfg, model.joint_names))
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
            fields = (val if isinstance(val, Mapping)
                      else {k: getattr(val, k) for k in ("mass_kg", "com_m", "inertia_kgm2")})
            xx, xy, xz, yy, yz, zz = (float(v) for v in fields["inertia_kgm2"])
            inertia = np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])
            self.model.inertias[links.index(name) + 1] = pin.Inertia(float(fields["mass_kg"]),
                                                                      np.asarray(fields["com_m"], dtype=float), inertia)
        self.data = self.model.createData()

    def add_payload(self, mass_kg: float, com_m: tuple[float, float, float] | np.ndarray) -> None:
        """Add a point mass in the last joint's frame (a tool or load the URDF does not have)."""
        if mass_kg > 0:
            body = self.model.njoints - 1
            if self._payload_base is None:
                self._payload_base = pin.Inertia(self.model.inertias[body])
            self.model.inertias[body] = self.model.inertias[body] + pin.Inertia(
                float(mass_kg), np.asarray(com_m, dtype=float), np.zeros((3, 3)))
            self.payload_mass_kg += float(mass_kg)
            self.payload_com_m = np.asarray(com_m, dtype=float)
            self.data = self.model.createData()
            self._nograv = None

    # ------------------------------------------------------------------------------ payload (docs/PAYLOAD.md)

    def set_payload(self, mass_kg: float, com_m: tuple[float, float, float] | np.ndarray,
                    ramp_s: float = 0.0, t_s: float = 0.0) -> None:
        """Replace the flange payload (a point mass in the last joint's frame; 0 kg: none), outside the cycle.

        With ``ramp_s`` > 0 :meth:`gravity_at` blends G(q) from the previous payload's to the new one's over
        ``ramp_s`` from the cycle time ``t_s`` (smoothstep): the running law takes it without a jump in current.
        """
        body = self.model.njoints - 1
        if self._payload_base is None:
            self._payload_base = pin.Inertia(self.model.inertias[body])
        old = pin.Model(self.model)
        new = pin.Model(self.model)
        inertia = pin.Inertia(self._payload_base)
        if mass_kg > 0:
            inertia = inertia + pin.Inertia(float(mass_kg), np.asarray(com_m, dtype=float), np.zeros((3, 3)))
        new.inertias[body] = inertia
        self._ramp = (old, old.createData(), float(t_s), float(ramp_s)) if ramp_s > 0 else None
        self.model, self.data = new, new.createData()
        self.payload_mass_kg = float(mass_kg)
        self.payload_com_m = np.asarray(com_m, dtype=float).copy()
        self._nograv = None

    def gravity_at(self, q_rad: np.ndarray, t_s: float, out: np.ndarray) -> np.ndarray:
        """G(q) as :meth:`gravity`, blended from the previous payload's while a :meth:`set_payload` ramp runs."""
        self.gravity(q_rad, out)
        r = self._ramp
        if r is None:
            return out
        x = (t_s - r[2]) / r[3]
        if x >= 1.0:
            self._ramp = None
            return out
        x = max(x, 0.0)
        lam = 1.0 - x * x * (3.0 - 2.0 * x)  # weight of the old payload's gravity
        self._g_old[:] = pin.computeGeneralizedGravity(r[0], r[1], q_rad)
        self._g_old -= out
        self._g_old *= lam
        out += self._g_old
        return out

    @property
    def payload_ramping(self) -> bool:
        return self._ramp is not None

    def momentum(self, q_rad: np.ndarray, dq_rad_s: np.ndarray, out: np.ndarray) -> np.ndarray:
        """Generalised momentum p = M(q)·q̇ [N·m·s] (RNEA of a gravity-free copy with q̈ = q̇)."""
        if self._nograv is None:
            m = pin.Model(self.model)
            m.gravity.linear = np.zeros(3)
            self._nograv = (m, m.createData())
        m, d = self._nograv
        out[:] = pin.rnea(m, d, q_rad, self._zero, dq_rad_s)
        return out

    def set_armature(self, armature_kgm2: np.ndarray) -> None:
        """Rotor inertias reflected to the joints [kg·m²] (identified: params ``notes.armature_kgm2``): M̄ = M +
        diag(J_a) in the momentum, the Coriolis matrix and inverse dynamics (Pinocchio's ``armature``)."""
        self.model.armature = np.asarray(armature_kgm2, dtype=float).copy()
        self.data = self.model.createData()
        self._nograv = None

    def coriolis(self, q_rad: np.ndarray, dq_rad_s: np.ndarray) -> np.ndarray:
        """The Coriolis matrix C(q, q̇) (Pinocchio's, Christoffel form: Ṁ − 2C skew), as Pinocchio returns it."""
        return pin.computeCoriolisMatrix(self.model, self.data, q_rad, dq_rad_s)

    def add_grip(self, frame: str, offset_m: tuple[float, float, float] | np.ndarray, source: str = "config") -> int:
        """A frame at the grip point: ``offset_m`` in ``frame`` (a URDF frame; "tool0" falls back to the last joint
        where the URDF has none). Its id for :meth:`grip_jacobian`."""
        m = self.model
        if not m.existFrame(frame):
            if frame != "tool0":
                names = [f.name for f in m.frames if f.name != "universe"]
                raise ValueError(f"{source}: contact.grip.frame: expected a frame of the robot ({', '.join(names)}), "
                                 f"got {frame!r}")
            frame = m.names[m.njoints - 1]
        parent = m.frames[m.getFrameId(frame)]
        place = parent.placement * pin.SE3(np.eye(3), np.asarray(offset_m, dtype=float))
        fid = m.addFrame(pin.Frame("dragd_grip", parent.parentJoint, m.getFrameId(frame), place,
                                   pin.FrameType.OP_FRAME))
        self.data = m.createData()
        self._nograv = None
        self.grip_frame_id = fid
        return fid

    def grip_jacobian(self, q_rad: np.ndarray) -> np.ndarray:
        """The grip point's 6×n Jacobian (linear rows first, world-aligned axes at the point), as Pinocchio gives it."""
        return pin.computeFrameJacobian(self.model, self.data, q_rad, self.grip_frame_id, pin.LOCAL_WORLD_ALIGNED)

    def grip_position(self, out: np.ndarray) -> np.ndarray:
        """The grip point's position [m] (world) at the pose of the last :meth:`grip_jacobian`."""
        out[:] = self.data.oMf[self.grip_frame_id].translation
        return out

    def payload_unexplained(self, q_rad: np.ndarray, residual_Nm: np.ndarray) -> float:
        """The fraction of a joint-torque residual that no flange load's gravity can produce at q:
        ‖r − P_Y r‖/‖r‖ with P_Y the projection on span Y(q) (0: exactly payload-like, 1: orthogonal).
        Allocates: for the runaway guard's rare decision path."""
        Y = self.payload_regressor(q_rad)
        nrm = float(np.linalg.norm(residual_Nm))
        if nrm == 0.0:
            return 1.0
        coef, *_ = np.linalg.lstsq(Y, residual_Nm, rcond=1e-9)
        return float(np.linalg.norm(residual_Nm - Y @ coef)) / nrm

    def payload_regressor(self, q_rad: np.ndarray) -> np.ndarray:
        """Y(q) (n×4): the gravity torque of a flange point mass is Y·[m, m·c_x, m·c_y, m·c_z] (c in the last
        joint's frame). Allocates: for estimation and the guard's rare path, not every cycle."""
        m = self.model
        d = m.createData()
        body = m.njoints - 1
        pin.computeJointJacobians(m, d, q_rad)
        pin.updateFramePlacements(m, d)
        J = pin.getJointJacobian(m, d, body, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)  # 6×n at the joint origin
        R = d.oMi[body].rotation
        g = np.asarray(m.gravity.linear, dtype=float)
        Y = np.zeros((m.nv, 4))
        Y[:, 0] = -J[:3].T @ g  # τ = −Jᵀ·f, f = m·g at the joint origin
        for k in range(3):  # moment (R c) × (m g) at the origin: τ = −J_ωᵀ·((R e_k) × g)·(m c_k)
            Y[:, 1 + k] = -J[3:].T @ np.cross(R[:, k], g)
        return Y

    def load_free_joints(self, samples: int = 16) -> np.ndarray:
        """Joints whose payload-regressor row is zero at every pose (a first axis parallel to gravity): no flange load
        torques them. Checked at ``samples`` pseudo-random poses within the limits (a fixed seed: deterministic)."""
        rng = np.random.default_rng(0)
        lo, hi = self.position_limits_rad
        lo, hi = np.maximum(lo, -np.pi), np.minimum(hi, np.pi)
        top = np.zeros(self.model.nv)
        for _ in range(samples):
            np.maximum(top, np.abs(self.payload_regressor(rng.uniform(lo, hi))).max(axis=1), out=top)
        return top < 1e-9

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
