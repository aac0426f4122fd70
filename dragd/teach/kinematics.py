"""Forward and inverse kinematics of a frame (default ``tool0``) with Pinocchio, and the Cartesian circle.

Inverse kinematics is damped least squares on the frame's 6-D pose error (``log6`` in the frame's own axes),
warm-started from a nearby joint configuration, so a path sampled finely stays on one arm configuration.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin


class KinematicsError(ValueError):
    """A pose that cannot be reached (or a degenerate geometry); the message says which and why."""


class Kinematics:
    """FK/IK of one frame of a Pinocchio model. Owns its ``Data`` (not shared with the control loop)."""

    def __init__(self, model: pin.Model, frame: str = "tool0") -> None:
        if not model.existFrame(frame):
            frames = ", ".join(f.name for f in model.frames if f.name != "universe")
            raise KinematicsError(f"frame '{frame}': not a frame of the robot (frames: {frames})")
        self.model = model
        self.data = model.createData()
        self.frame = frame
        self.frame_id = model.getFrameId(frame)
        self.lower = model.lowerPositionLimit.copy()
        self.upper = model.upperPositionLimit.copy()

    def pose(self, q: np.ndarray) -> pin.SE3:
        pin.framesForwardKinematics(self.model, self.data, np.asarray(q, dtype=float))
        return pin.SE3(self.data.oMf[self.frame_id])

    def position(self, q: np.ndarray) -> np.ndarray:
        return self.pose(q).translation.copy()

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        return pin.computeFrameJacobian(self.model, self.data, np.asarray(q, dtype=float), self.frame_id, pin.LOCAL)

    def ik(self, target: pin.SE3, q0: np.ndarray, *, tol: float = 1e-10, max_iter: int = 200,
           damping: float = 1e-6, max_step_rad: float = 0.2, accept: float = 1e-4) -> np.ndarray:
        """Joint positions placing the frame at ``target``, from ``q0`` (damped least squares, Newton steps).

        Iterates to ``tol``; near a singularity the damped step converges only linearly, so a solution whose pose
        error (‖log6‖: metres and radians) is within ``accept`` after ``max_iter`` steps is taken (0.1 mm / 0.1 mrad:
        far below a taught pose's repeatability). Raises KinematicsError when it does not converge (unreachable
        pose, singularity) or leaves the joint limits.
        """
        q = np.array(q0, dtype=float)
        err = np.inf
        for _ in range(max_iter):
            pin.framesForwardKinematics(self.model, self.data, q)
            e = pin.log6(self.data.oMf[self.frame_id].actInv(target)).vector  # error in the frame's axes
            err = float(np.linalg.norm(e))
            if err < tol:
                break
            J = pin.computeFrameJacobian(self.model, self.data, q, self.frame_id, pin.LOCAL)
            # J_log ≈ identity for small errors; keep the plain DLS step (robust, quadratic near the solution)
            dq = J.T @ np.linalg.solve(J @ J.T + damping * np.eye(6), e)
            step = float(np.abs(dq).max())
            if step > max_step_rad:
                dq *= max_step_rad / step
            q = q + dq
        else:
            if err <= accept:
                return self._within_limits(q)
            raise KinematicsError(f"inverse kinematics of '{self.frame}' did not converge (pose error {err:.2e}): the "
                                  "pose is out of reach or at a singularity")
        return self._within_limits(q)

    def _within_limits(self, q: np.ndarray) -> np.ndarray:
        if np.any(q < self.lower - 1e-9) or np.any(q > self.upper + 1e-9):
            j = int(np.argmax(np.maximum(self.lower - q, q - self.upper)))
            raise KinematicsError(f"inverse kinematics: the solution leaves the limits of {self.model.names[j + 1]} "
                                  f"({q[j]:.3f} rad, limits [{self.lower[j]:.3f}, {self.upper[j]:.3f}])")
        return q

    def manipulability(self, q: np.ndarray) -> float:
        J = self.jacobian(q)
        return float(np.sqrt(max(np.linalg.det(J @ J.T), 0.0)))


@dataclass(frozen=True)
class Circle:
    """The circle through three points: centre, radius, unit normal and in-plane basis (u toward p1)."""

    center: np.ndarray
    radius: float
    normal: np.ndarray
    u: np.ndarray
    w: np.ndarray
    angles: tuple[float, float, float]  # of p1 (0), p2, p3 along the direction p1 → p2 → p3, in [0, 2π)

    @classmethod
    def through(cls, p1: np.ndarray, p2: np.ndarray, p3: np.ndarray, min_radius_m: float = 1e-3) -> Circle:
        p1, p2, p3 = (np.asarray(p, dtype=float) for p in (p1, p2, p3))
        a, b = p2 - p1, p3 - p1
        n = np.cross(a, b)
        nn = float(np.linalg.norm(n))
        scale = max(float(np.linalg.norm(a)), float(np.linalg.norm(b)), 1e-12)
        if float(min(np.linalg.norm(a), np.linalg.norm(b), np.linalg.norm(p3 - p2))) < min_radius_m:
            raise KinematicsError("circle: two of the three points coincide (closer than "
                                  f"{min_radius_m * 1e3:.1f} mm); teach three distinct points")
        if nn < 1e-3 * scale * scale:  # sin(angle at p1) < 1e-3
            raise KinematicsError("circle: the three points are (nearly) on one line; no circle passes through them "
                                  "(use linear interpolation)")
        # circumcentre: p1 + (|a|² (b×n)... ) / (2|n|²) with n = a×b
        c = p1 + (np.dot(a, a) * np.cross(b, n) + np.dot(b, b) * np.cross(n, a)) / (2.0 * nn * nn)
        normal = n / nn
        r = float(np.linalg.norm(p1 - c))
        u = (p1 - c) / r
        w = np.cross(normal, u)

        def angle(p: np.ndarray) -> float:
            d = p - c
            return float(np.arctan2(np.dot(d, w), np.dot(d, u)) % (2.0 * np.pi))

        a2, a3 = angle(p2), angle(p3)
        if not 0.0 < a2 < a3 < 2.0 * np.pi:  # by construction of n, p1 → p2 → p3 runs counter-clockwise about n
            raise KinematicsError(f"circle: unexpected point order (angles {a2:.3f}, {a3:.3f} rad)")
        return cls(c, r, normal, u, w, (0.0, a2, a3))

    def point(self, theta: np.ndarray | float) -> np.ndarray:
        th = np.asarray(theta, dtype=float)[..., None]
        return self.center + self.radius * (np.cos(th) * self.u + np.sin(th) * self.w)
