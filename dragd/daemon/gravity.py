"""The gravity check: does the model's G(q)/K_t agree with the current that truly holds the arm?

Before drag (``mode drag``) the hold current HOLD measured at rest is compared with the model joint by joint; a
difference beyond the joint's static friction and tolerance refuses drag with the figures, or (``--accept``) drags
with the measured difference as a gravity offset (the flange load it implies, least squares on the payload
regressor). ``check_current`` refuses to enable or drag where holding the pose needs more than a joint's current
limit. ``explain_residual`` is the runaway guard's rare path (how much of a residual a flange load explains).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from dragd.control.modes import Mode

if TYPE_CHECKING:
    from dragd.config import Config
    from dragd.control.controller import Controller, Estimate
    from dragd.model import RobotModel

PAYLOAD_REACH_M = 0.3  # a flange load's centre of mass lies within this of the flange (the guard's plausibility test)


class GravityCheck:
    """The model's gravity against the measured hold current (docs/SAFETY.md, the runaway guard)."""

    def __init__(self, cfg: Config, model: RobotModel, controller: Controller) -> None:
        self.cfg, self.model, self.controller = cfg, model, controller
        self.joint_names = cfg.joint_names
        self.n = len(cfg.joints)

    def check_current(self, est: Estimate, what: str) -> None:
        """Refuse (ValueError) where holding the pose ``est`` holds needs more than a joint's current limit: the arm
        would sag under a clamped command instead of being held."""
        c = self.controller
        for j in range(self.n):
            need = abs(est.tau_g_Nm[j]) / c.kt[j]
            if need > c.params.current_limit_A[j]:
                raise ValueError(
                    f"{what}: {self.joint_names[j]} needs {need:.2f} A to hold its gravity load of "
                    f"{est.tau_g_Nm[j]:+.1f} N·m at {est.q_rad[j]:+.3f} rad, above its current_limit_A "
                    f"{c.params.current_limit_A[j]:.2f} A (check the URDF's masses, the payload, torque_constant)")

    def warm_up(self) -> None:
        """Run the cycle's rare paths once before the first cycle, after the memory is locked.

        The runaway guard's decision path solves a least-squares problem (LAPACK): OpenBLAS allocates its work
        buffers on its first call, and with the memory locked (mlockall MCL_FUTURE) every page of them is faulted in
        right then — 10–100 ms measured in the cycle thread the first time a hand pushed the arm in drag (the drives'
        RPDO watchdogs fired). Here that happens before the loop runs.
        """
        q = np.zeros(self.n)
        self.explain_residual(q, np.ones(self.n))
        self.model.momentum(q, q, np.zeros(self.n))

    def explain_residual(self, q: Any, r: Any) -> tuple[float, float]:
        """The runaway guard's rare path: the fraction of residual r no flange load explains at q, and that load's
        mass [kg] (least squares on the payload regressor)."""
        Y = self.model.payload_regressor(q)
        nrm = float(np.linalg.norm(r))
        if nrm == 0.0:
            return 1.0, float("nan")
        coef, *_ = np.linalg.lstsq(Y, r, rcond=1e-9)
        # a physical load: its centre of mass within PAYLOAD_REACH_M of the flange (a torque on one joint alone
        # needs an implausible lever to look like a load, e.g. the shoulder pushed by hand)
        if abs(coef[0]) > 1e-9 and float(np.linalg.norm(coef[1:])) > PAYLOAD_REACH_M * abs(float(coef[0])):
            return 1.0, float("nan")
        # Y·θ is the load's gravity torque (what holds it); the residual is the torque that moves the arm: −Y·θ
        return float(np.linalg.norm(r - Y @ coef)) / nrm, -float(coef[0])

    def rows(self) -> list[dict[str, Any]]:
        """Per joint: the current that truly holds the arm (HOLD's measured current, averaged at rest) against the
        model's G(q)/K_t, with the bound (the joint's static friction + tolerance). Empty until HOLD has rested
        ``safety.guard.check_settle_s``."""
        c, g = self.controller, self.cfg.safety.guard
        if c.mode != Mode.HOLD or c.hold_rest_s < g.check_settle_s:
            return []
        tau = self.model.gravity(c.hold_rest_q)
        p = c.params
        out = []
        for j in range(self.n):
            model_A = float(tau[j] / c.kt[j])
            hold_A = float(c.hold_current_A[j])
            friction_A = float(max(p.static_pos_A[j], -p.static_neg_A[j]))
            bound = friction_A + g.check_tolerance_A + g.check_tolerance_fraction * abs(model_A)
            out.append({"joint": self.joint_names[j], "hold_A": round(hold_A, 3), "model_A": round(model_A, 3),
                        "difference_A": round(hold_A - model_A, 3), "bound_A": round(bound, 3),
                        "ok": bool(abs(hold_A - model_A) <= bound)})
        return out

    def before_drag(self, accept: bool) -> dict[str, Any] | None:
        """Refuse DRAG (ValueError with the figures) where the hold current disagrees with the model beyond the bound;
        with ``accept`` drag with the measured hold currents as the gravity offset around this pose."""
        c, g = self.controller, self.cfg.safety.guard
        if not g.check or c.mode != Mode.HOLD:
            return None
        rows = self.rows()
        if not rows:
            if accept:
                raise ValueError(f"mode drag --accept: the hold current is not measured (the arm did not rest in hold "
                                 f"for {g.check_settle_s:g} s within the wait); let it come to rest and try again")
            return None  # not at rest long enough to judge (the runaway guard watches the drag)
        bad = [r for r in rows if not r["ok"]]
        if not bad:
            c.gravity_offset_A.fill(0.0)
            return {"checked": True}
        if accept:
                # the flange load the differences imply (least squares on Y(q)) gives the offset on every joint: a joint
            # whose stiction hid part of its load in HOLD still gets the load's share; a joint the load does not
            # explain beyond its bound (a sign or K_t error) gets its own measured difference
            diff = np.array([r["difference_A"] for r in rows])
            bound = np.array([r["bound_A"] for r in rows])
            Y = self.model.payload_regressor(c.hold_rest_q)
            coef, *_ = np.linalg.lstsq(Y, diff * c.kt, rcond=1e-9)
            off = Y @ coef / c.kt
            raw = np.abs(diff - off) > bound
            off[raw] = diff[raw]
            c.gravity_offset_A[:] = off
            return {"checked": True, "accepted_offset_A": [round(float(x), 3) for x in off],
                    "implied_payload_kg": round(float(coef[0]), 3)}
        r = np.array([row["hold_A"] - row["model_A"] for row in rows]) * c.kt
        frac, kg = self.explain_residual(c.hold_rest_q, -r)  # the hold current carries the load's gravity: −residual
        guess = (f"; a load of about {kg:.1f} kg at the flange would explain it" if frac < 0.35 and abs(kg) > 0.05
                 else "; not a flange load alone: check the joint's sign and torque constant (dragd check model)")
        worst = max(bad, key=lambda row: abs(row["difference_A"]) - row["bound_A"])
        raise ValueError(
            "mode drag: refused: the gravity model disagrees with the current that holds the arm: "
            + "; ".join(f"{row['joint']} needs {row['hold_A']:+.2f} A to hold, the model says {row['model_A']:+.2f} A "
                        f"(bound ±{row['bound_A']:.2f} A)" for row in bad)
            + f"{guess}. Run 'dragd payload estimate', or 'dragd mode drag --accept' to drag with the measured hold "
              f"currents as the gravity offset around this pose (worst: {worst['joint']})")
