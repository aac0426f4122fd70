"""The payload scenario's hooks in the simulated arm: a mass hung on the flange (or removed) while it runs.

``set_flange_payload`` replaces the truth's flange load (a point mass in the last joint's frame, on top of the
URDF's last link and the truth's own ``payload``) between physics steps; the sim's control socket calls it now or
at a given sim time (``PayloadSchedule``, polled by the loop). dragd never imports this module.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
import pinocchio as pin

if TYPE_CHECKING:
    from sim.physics import ArmPhysics


def set_flange_payload(physics: ArmPhysics, mass_kg: float, com_m: Any = (0.0, 0.0, 0.0)) -> dict[str, Any]:
    """Hang ``mass_kg`` at ``com_m`` (last joint's frame) on the flange in place of any earlier hung-on mass
    (0 kg: take it off). The truth's own hidden ``payload`` stays."""
    if not (isinstance(mass_kg, (int, float)) and np.isfinite(mass_kg) and mass_kg >= 0):
        raise ValueError(f"payload: mass_kg: expected a number >= 0 (kg), got {mass_kg!r}")
    com = np.asarray(com_m, dtype=float).reshape(-1)
    if com.shape != (3,) or not np.all(np.isfinite(com)):
        raise ValueError(f"payload: com_m: expected 3 finite numbers (m, last joint's frame), got {com_m!r}")
    m = physics.model
    body = m.njoints - 1
    base = getattr(physics, "_flange_base_inertia", None)
    if base is None:
        base = physics._flange_base_inertia = pin.Inertia(m.inertias[body])  # type: ignore[attr-defined]
    inertia = pin.Inertia(base)
    if mass_kg > 0:
        inertia = inertia + pin.Inertia(float(mass_kg), com, np.zeros((3, 3)))
    m.inertias[body] = inertia
    physics.data = m.createData()
    physics.hung_payload = {"mass_kg": float(mass_kg), "com_m": com.tolist(), "t_s": physics.t_s}  # type: ignore[attr-defined]
    return dict(physics.hung_payload)  # type: ignore[attr-defined]


@dataclass
class PayloadSchedule:
    """Payload changes due at sim times; ``apply_due`` runs them (the sim loop calls it each tick)."""

    pending: list[tuple[float, float, tuple[float, float, float]]] = field(default_factory=list)
    done: list[dict[str, Any]] = field(default_factory=list)

    def add(self, at_t_s: float, mass_kg: float, com_m: Any) -> None:
        self.pending.append((float(at_t_s), float(mass_kg), tuple(float(x) for x in com_m)))  # type: ignore[arg-type]
        self.pending.sort()

    def apply_due(self, physics: ArmPhysics) -> None:
        while self.pending and self.pending[0][0] <= physics.t_s:
            _, kg, com = self.pending.pop(0)
            self.done.append(set_flange_payload(physics, kg, com))
