"""Drive sizing from a URDF alone: what a starting configuration (``dragd config init``) and a generated
simulator truth assume about a robot's joints before anything is measured.

Per joint: the peak torque is the URDF's effort limit, raised to 1.5 × the largest gravity torque over the joint's
range where the URDF's limit is missing or too low to hold the arm. Joints with a peak of ``LARGE_JOINT_Nm`` or
more get a large drive (4 A rated, 12 A limit, as the seed cobot's shoulder), the others a small one (2 A, 6 A);
the joint-side torque constant then delivers the peak torque at the current limit, through a 101:1 gear.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from dragd.robots.gravity import gravity_peaks, joint_ranges

if TYPE_CHECKING:
    from dragd.model import RobotModel

GEAR_RATIO = 101.0
ENCODER_COUNTS_PER_REV = 2**19
LARGE_JOINT_Nm = 60.0
GRAVITY_HEADROOM = 1.5  # peak torque >= this × the largest gravity torque
MIN_PEAK_Nm = 2.0


@dataclass(frozen=True)
class JointSizing:
    """One joint's assumed drive: currents, torque constant, speed cap, range, and the gravity it must hold."""

    name: str
    peak_torque_Nm: float  # at the current limit
    gravity_peak_Nm: float  # largest |G_j| over the range
    gravity_pose_rad: tuple[float, ...]
    rated_current_A: float
    current_limit_A: float
    velocity_limit_rad_s: float
    lower_rad: float
    upper_rad: float
    effort_limit_Nm: float | None  # the URDF's, when it gives one

    @property
    def large(self) -> bool:
        return self.peak_torque_Nm >= LARGE_JOINT_Nm

    @property
    def kt_Nm_per_A(self) -> float:
        """Joint-side torque constant: the peak torque at the current limit."""
        return self.peak_torque_Nm / self.current_limit_A

    @property
    def rated_motor_torque_Nm(self) -> float:
        """Motor-side rated torque (6076h): K_t / gear × rated current."""
        return self.kt_Nm_per_A / GEAR_RATIO * self.rated_current_A


def size_joints(model: RobotModel) -> list[JointSizing]:
    """Size every joint of ``model`` (with its payload, if one was added) from its URDF limits and gravity."""
    lo, hi = joint_ranges(model)
    peaks, poses = gravity_peaks(model, lo, hi)
    effort = model.effort_limits_Nm
    velocity = np.asarray(model.model.velocityLimit, dtype=float)
    out = []
    for i, name in enumerate(model.joint_names):
        e = float(effort[i]) if math.isfinite(effort[i]) and effort[i] > 0 else None
        base = e if e is not None else 2.0 * peaks[i]
        peak = max(base, GRAVITY_HEADROOM * float(peaks[i]), MIN_PEAK_Nm)
        rated = 4.0 if peak >= LARGE_JOINT_Nm else 2.0
        cap = 1.0 if peak >= LARGE_JOINT_Nm else 1.5
        v = float(velocity[i]) if math.isfinite(velocity[i]) and velocity[i] > 0 else cap
        out.append(JointSizing(name, peak, float(peaks[i]), tuple(float(x) for x in poses[i]), rated, 3.0 * rated,
                               min(v, cap), float(lo[i]), float(hi[i]), e))
    return out
