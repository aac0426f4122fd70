"""Amperes per unit of each torque and current quantity of one drive, from the objects that hold its bases.

Current per mille refers to the rated current (6075h or the object the profile names), torque per mille to the rated
torque (6076h or the profile's object); a torque becomes a current through the firmware's torque constant (the
profile's object, else the truth's K_m = rated torque / rated current). While a base object holds the value it was
commissioned with, the truth's exact value is used (so per mille of torque and of current agree to the last bit, as
a drive whose 6076h / 6075h is K_m does); a master that writes another value changes the scale as a real drive's
would. A base of 0 (e.g. EPOS4's 6076h as delivered) makes every torque 0 A, and actual values read 0.
"""

from __future__ import annotations

import math
from typing import Any

from sim.drive_profile import Binding, DriveProfile
from sim.od import ObjectStore


class Scaling:
    """Amperes per unit of each quantity (attributes named as the quantities), refreshed when a base object changes."""

    current_actual: float
    torque_actual: float
    torque_demand: float
    target_torque: float
    torque_offset: float
    max_torque: float
    max_current: float
    demand_per_target: float  # torque demand units per target torque unit

    def __init__(self, profile: DriveProfile, store: ObjectStore) -> None:
        self.profile = profile
        self.hw = profile.hardware
        self.store = store
        b = profile.bindings
        self._bases = [(b[name], self._slot(b[name])) for name in ("rated_current", "rated_torque", "torque_constant")]
        self.refresh()

    def _slot(self, binding: Binding) -> int | None:
        return None if binding.index is None else self.store.slot(binding.index, binding.subindex)

    def watched_indices(self) -> set[int]:
        """Indices whose writes change the scales (rated current / torque, torque constant objects)."""
        return {b.index for b, _ in self._bases if b.index is not None}

    def _live(self, binding: Binding, slot: int | None, truth: float) -> tuple[float, bool]:
        """(value in SI, whether it is the truth's exact value) of a base quantity."""
        if slot is None:
            return truth, True
        raw = self.store.cells[slot]
        if raw == self.profile.truth_raw[binding.quantity]:
            return truth, True
        per_si = binding.per_si
        return (raw if per_si is None else raw / per_si), False

    def refresh(self) -> None:
        hw = self.hw
        (b_I, s_I), (b_T, s_T), (b_K, s_K) = self._bases
        rated_I, _ = self._live(b_I, s_I, hw.rated_current_A)
        rated_T, exact_T = self._live(b_T, s_T, hw.rated_torque_Nm)
        k_m, exact_K = self._live(b_K, s_K, hw.torque_constant_Nm_per_A)
        current_permille = rated_I / 1000.0
        if exact_T and exact_K:
            torque_permille = hw.rated_current_A / 1000.0  # T_r / 1000 / K_m with K_m = T_r / I_r, exactly
        else:
            torque_permille = rated_T / 1000.0 / k_m if k_m > 0.0 else 0.0
        k_m_or_inf = k_m if k_m > 0.0 else math.inf
        b = self.profile.bindings

        def per_unit(name: str) -> float:
            per_si = b[name].per_si
            if name in ("current_actual", "max_current"):
                return current_permille if per_si is None else 1.0 / per_si
            return torque_permille if per_si is None else 1.0 / per_si / k_m_or_inf

        for name in ("target_torque", "torque_offset", "max_torque", "max_current"):
            setattr(self, name, per_unit(name))
        for name in ("current_actual", "torque_actual", "torque_demand"):  # divisors: a base of 0 reads 0
            setattr(self, name, per_unit(name) or math.inf)
        demand, target = per_unit("torque_demand"), self.target_torque
        self.demand_per_target = demand / target if demand and target else 1.0

    def after_write(self, sub: int, value: Any) -> None:
        self.refresh()
