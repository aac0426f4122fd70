"""Gravity against the drives: the largest gravity torque and current of each joint over its range.

A joint whose gravity current |G(q)|/K_t can exceed its ``current_limit_A`` cannot hold the arm there: the drive
would clamp the current and the arm would sag. ``dragd config check`` makes that an error
(:func:`check_gravity_currents`); the daemon refuses to hold or drag at a pose where it happens
(:func:`gravity_excess_at`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import pinocchio as pin

if TYPE_CHECKING:
    from dragd.config import Config
    from dragd.model import RobotModel

SAMPLES = 512  # random poses over the joint ranges; the best few of each joint are then refined
REFINE_STARTS = 3


def joint_ranges(model: RobotModel, cfg: Config | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Position ranges [rad]: the configuration's ``position_limits_rad``, else the URDF's; ±π where neither is
    finite (gravity repeats every revolution)."""
    lo, hi = model.position_limits_rad
    if cfg is not None:
        for i, j in enumerate(cfg.joints[: lo.shape[0]]):
            if j.position_limits_rad is not None:
                lo[i], hi[i] = j.position_limits_rad
    bad = ~np.isfinite(lo) | ~np.isfinite(hi) | (lo >= hi)
    lo[bad], hi[bad] = -math.pi, math.pi
    return lo, hi


def gravity_peaks(model: RobotModel, lower_rad: np.ndarray, upper_rad: np.ndarray, samples: int = SAMPLES,
                  seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Per joint j: the largest |G_j(q)| [N·m] over the box [lower, upper] and the pose where it occurs.

    Random poses (seeded: the answer is reproducible), then bounded gradient ascent (L-BFGS-B on Pinocchio's
    gravity derivatives) from the best few of each joint. Returns (peaks_Nm (n,), poses_rad (n, n)).
    """
    from scipy.optimize import minimize

    m, d = model.model, model.model.createData()
    n = m.nv
    rng = np.random.default_rng(seed)
    Q = lower_rad + (upper_rad - lower_rad) * rng.random((samples, n))
    Q[0] = np.clip(0.0, lower_rad, upper_rad)  # the URDF's zero pose (often an outstretched arm)
    G = np.array([pin.computeGeneralizedGravity(m, d, q) for q in Q])
    peaks = np.zeros(n)
    poses = np.tile(Q[0], (n, 1))
    bounds = list(zip(lower_rad, upper_rad, strict=True))
    for j in range(n):
        best = np.argsort(-np.abs(G[:, j]))[:REFINE_STARTS]
        if abs(G[best[0], j]) < 1e-9:  # no gravity on this joint anywhere (a vertical axis): zero at the zero pose
            continue
        peaks[j], poses[j] = abs(G[best[0], j]), Q[best[0]]
        for k in best:
            s = math.copysign(1.0, G[k, j])

            def cost(q: np.ndarray, j: int = j, s: float = s) -> tuple[float, np.ndarray]:
                g = pin.computeGeneralizedGravity(m, d, q)
                dg = pin.computeGeneralizedGravityDerivatives(m, d, q)
                return -s * float(g[j]), -s * np.asarray(dg[j])

            res = minimize(cost, Q[k], jac=True, bounds=bounds, method="L-BFGS-B", options={"maxiter": 50})
            if -res.fun > peaks[j]:
                peaks[j], poses[j] = -res.fun, np.clip(res.x, lower_rad, upper_rad)
    return peaks, poses


@dataclass(frozen=True)
class GravityLoad:
    """The worst gravity load of one joint: torque, current at the configured K_t, and the current limit."""

    index: int
    joint: str
    q_rad: tuple[float, ...]
    torque_Nm: float  # |G_j| at q
    kt_Nm_per_A: float
    current_limit_A: float

    @property
    def current_A(self) -> float:
        return self.torque_Nm / self.kt_Nm_per_A

    @property
    def exceeds(self) -> bool:
        return self.current_A > self.current_limit_A

    def message(self, where: str = "over its range") -> str:
        pose = ", ".join(f"{round(x, 3) + 0.0:.3f}" for x in self.q_rad)
        return (f"joints[{self.index}] ({self.joint}): gravity needs {self.current_A:.2f} A {where} "
                f"at q = [{pose}] rad "
                f"(|G| {self.torque_Nm:.2f} N·m / K_t {self.kt_Nm_per_A:.4g} N·m/A), above its current_limit_A "
                f"{self.current_limit_A:g} A")

    def to_json(self) -> dict[str, Any]:
        return {"joint": self.joint, "q_rad": list(self.q_rad), "gravity_Nm": self.torque_Nm,
                "gravity_A": self.current_A, "current_limit_A": self.current_limit_A, "exceeds": self.exceeds}


def gravity_loads(cfg: Config, model: RobotModel, samples: int = SAMPLES) -> list[GravityLoad]:
    """Each joint's largest gravity current over the configured ranges (the model carries the payload:
    :meth:`RobotModel.from_config`)."""
    lo, hi = joint_ranges(model, cfg)
    peaks, poses = gravity_peaks(model, lo, hi, samples)
    return [GravityLoad(i, j.name, tuple(float(x) for x in poses[i]), float(peaks[i]), j.kt_Nm_per_A,
                        j.current_limit_A) for i, j in enumerate(cfg.joints)]


def check_gravity_currents(cfg: Config, model: RobotModel | None = None) -> list[GravityLoad]:
    """The gravity loads of every joint; ConfigError naming each joint whose gravity current can exceed its
    ``current_limit_A`` somewhere in its range (joint, pose, both currents)."""
    from dragd.config import ConfigError
    from dragd.model import RobotModel

    model = model or RobotModel.from_config(cfg)
    loads = gravity_loads(cfg, model)
    bad = [g for g in loads if g.exceeds]
    if bad:
        payload = f" with the {cfg.payload.mass_kg:g} kg payload" if cfg.payload and cfg.payload.mass_kg else ""
        raise ConfigError("\n".join(f"{cfg.source}: {g.message(f'over its range{payload}')}; raise current_limit_A "
                                    "(and the drive's 6073h), or check torque_constant_Nm_per_A, the payload and the "
                                    "URDF's masses" for g in bad))
    return loads


def gravity_excess_at(cfg: Config, model: RobotModel, q_rad: np.ndarray) -> str | None:
    """Why the arm cannot be held at ``q_rad`` (a joint's gravity current above its ``current_limit_A``), or None.

    For the daemon at ``start`` and ``mode drag``: the message names the joint, the pose and both currents.
    """
    q = model.check_q(q_rad)
    g = model.gravity(q)
    for i, j in enumerate(cfg.joints):
        load = GravityLoad(i, j.name, tuple(float(x) for x in q), abs(float(g[i])), j.kt_Nm_per_A, j.current_limit_A)
        if load.exceeds:
            return f"{cfg.source}: {load.message('here')}: the drive cannot hold the arm at this pose"
    return None
