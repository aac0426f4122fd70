"""Drive units ↔ SI per joint: encoder counts (6064h/607Ah) ↔ rad, the current object's unit ↔ A, A ↔ the torque
command's unit.

Each conversion is folded into one factor per joint with the joint's direction (``joints[].direction``: +1 when
the drive's positive is the URDF's) and its encoder offset (counts at the URDF's zero). The current and command
factors come from the joint's drive profile (hardware/profile.py): 6078h per mille of the rated current, 6077h and
the command (60B2h/6071h) per mille of the rated torque, or a vendor object's unit; dragd's own joint drive reports
and takes per mille of the rated current. (The names ``*_permille`` are those units.) Allocation-free: every call
writes into arrays the caller owns.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from dragd.config import Config
    from dragd.hardware.profile import Profiles

INT16_MIN, INT16_MAX = -32768.0, 32767.0


@dataclass(frozen=True)
class Scaling:
    rad_per_count: np.ndarray  # direction · 2π / counts per joint revolution
    counts_per_rad: np.ndarray
    offset_counts: np.ndarray  # int64
    A_per_permille: np.ndarray  # direction · amperes per unit of the current object (rated current / 1000 for 6078h)
    permille_per_A: np.ndarray  # direction · torque command units (per mille of the rated torque) per ampere
    counts_per_rev: np.ndarray  # float, unsigned
    direction: np.ndarray  # ±1.0

    @classmethod
    def from_config(cls, cfg: Config, profiles: Profiles | None = None) -> Scaling:
        """Factors of ``cfg``'s joints; without ``profiles``: dragd's own joint drive (per mille of rated current)."""
        js = cfg.joints
        direction = np.array([j.direction for j in js], dtype=float)
        cpr = np.array([j.encoder_counts_per_rev for j in js], dtype=float)
        if profiles is None:
            rated = np.array([j.rated_current_A for j in js])
            a_per_unit, unit_per_A = rated / 1000.0, 1000.0 / rated
        else:  # (the same numbers for a 6078h/6075h drive: rated / 1000 and 1000 / rated)
            a_per_unit = np.array([p.A_per_current_unit() for p in profiles.profiles])
            unit_per_A = np.array([p.command_per_A() for p in profiles.profiles])
        return cls(rad_per_count=direction * 2.0 * math.pi / cpr,
                   counts_per_rad=cpr / (2.0 * math.pi) * direction,  # (direction is ±1)
                   offset_counts=np.array([j.encoder_offset_counts for j in js], dtype=np.int64),
                   A_per_permille=a_per_unit * direction, permille_per_A=direction * unit_per_A,
                   counts_per_rev=cpr, direction=direction)

    def position_rad(self, counts: np.ndarray, out: np.ndarray, tmp: np.ndarray) -> None:
        """q [rad] from 6064h counts."""
        np.subtract(counts, self.offset_counts, out=tmp, casting="unsafe")
        np.multiply(tmp, self.rad_per_count, out=out)

    def current_A(self, permille: np.ndarray, out: np.ndarray) -> None:
        """Motor current [A] from the current object (6078h: per mille of the rated current; the drive's sign)."""
        np.multiply(permille, self.A_per_permille, out=out)

    def torque_permille(self, current_A: np.ndarray, out: np.ndarray, tmp: np.ndarray) -> None:
        """The torque command (60B2h/6071h, INTEGER16 per mille of the rated torque) for a current [A], rounded and
        saturated."""
        np.multiply(current_A, self.permille_per_A, out=tmp)
        np.rint(tmp, out=tmp)
        np.minimum(tmp, INT16_MAX, out=tmp)
        np.maximum(tmp, INT16_MIN, out=tmp)
        out[:] = tmp

    def target_counts(self, q_rad: np.ndarray, out: np.ndarray, tmp: np.ndarray) -> None:
        """607Ah target position [counts] for q [rad]."""
        np.multiply(q_rad, self.counts_per_rad, out=tmp)
        np.rint(tmp, out=tmp)
        out[:] = tmp
        out += self.offset_counts
