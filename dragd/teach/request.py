"""What a replay asks of the planner: the request and its limits, plain data the daemon builds and the planner
process (dragd/teach/plan.py) takes. Light on purpose: the daemon imports this, never the planner's numerics (a
late import of scipy in the cycle's process holds the GIL for a third of a second)."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

INTERPS = ("linear", "circular", "spline")
SOURCES = ("waypoints", "path")


@dataclass(frozen=True)
class Limits:
    """Per-joint velocity [rad/s], acceleration [rad/s²], jerk [rad/s³]; soft position limits [rad]; TCP limits."""

    velocity: np.ndarray
    acceleration: np.ndarray
    jerk: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    cartesian_speed_m_s: float = 0.5
    cartesian_acceleration_m_s2: float = 2.0

    def scaled(self, s: float) -> Limits:
        """Slower: velocity, acceleration and jerk (and the TCP limits) times ``s``."""
        return replace(self, velocity=self.velocity * s, acceleration=self.acceleration * s, jerk=self.jerk * s,
                       cartesian_speed_m_s=self.cartesian_speed_m_s * s,
                       cartesian_acceleration_m_s2=self.cartesian_acceleration_m_s2 * s)

    def as_dict(self) -> dict[str, Any]:
        return {"velocity_rad_s": self.velocity.tolist(), "acceleration_rad_s2": self.acceleration.tolist(),
                "jerk_rad_s3": self.jerk.tolist(), "lower_rad": self.lower.tolist(), "upper_rad": self.upper.tolist(),
                "cartesian_speed_m_s": self.cartesian_speed_m_s,
                "cartesian_acceleration_m_s2": self.cartesian_acceleration_m_s2}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Limits:
        return cls(np.asarray(d["velocity_rad_s"], float), np.asarray(d["acceleration_rad_s2"], float),
                   np.asarray(d["jerk_rad_s3"], float), np.asarray(d["lower_rad"], float),
                   np.asarray(d["upper_rad"], float), float(d["cartesian_speed_m_s"]),
                   float(d["cartesian_acceleration_m_s2"]))


@dataclass
class ReplayRequest:
    """Everything the planner needs (plain data: it runs in a worker process)."""

    program: str  # path of the program file
    q_start: list[float]
    dt: float
    urdf: str  # resolved URDF path
    gravity_m_s2: tuple[float, float, float]
    limits: dict[str, Any]
    interp: str = "linear"
    source: str | None = None  # waypoints | path (default: waypoints if ≥ 2, else the path)
    frame: str = "tool0"
    move_to_start_speed: float = 0.25
    settle_s: float = 0.3
    keyframe_tolerance_rad: float = math.radians(0.5)
    feedforward: bool = True
    max_samples: int = 2_000_000


def limits_from_config(cfg: Any, model: Any) -> Limits:
    """The replay limits of a dragd configuration (``replay:`` section, joints' limits, the URDF)."""
    rc = cfg.replay
    n = len(cfg.joints)

    def vec(v: Any, default: np.ndarray) -> np.ndarray:
        if v is None:
            return default
        a = np.asarray(v, dtype=float).reshape(-1)
        return np.full(n, a[0]) if a.size == 1 else a

    urdf_v = np.asarray(model.velocityLimit, dtype=float)
    v = vec(rc.velocity_limits_rad_s, np.array([j.velocity_limit_rad_s for j in cfg.joints]))
    v = np.minimum(v, np.where(urdf_v > 0, urdf_v, np.inf))
    a = vec(rc.acceleration_limits_rad_s2, np.full(n, 2.0))
    jk = vec(rc.jerk_limits_rad_s3, np.full(n, 20.0))
    lo_u, hi_u = model.lowerPositionLimit, model.upperPositionLimit
    lo = np.array([j.position_limits_rad[0] if j.position_limits_rad else lo_u[i] for i, j in enumerate(cfg.joints)])
    hi = np.array([j.position_limits_rad[1] if j.position_limits_rad else hi_u[i] for i, j in enumerate(cfg.joints)])
    m = cfg.safety.soft_limit_margin_rad
    return Limits(v, a, jk, lo + m, hi - m, rc.cartesian_speed_m_s, rc.cartesian_acceleration_m_s2)
