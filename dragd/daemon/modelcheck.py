"""``dragd check model``: before the first drag, each joint's encoder direction, current sign and K_t's scale
against the gravity model (docs/PAYLOAD.md).

In HOLD, joint j alone moves to q₀ ∓ step and q₀ ± step (through HOLD's PD, slowly, inside the soft limits),
each approached from both sides and rested on (the two approaches cancel most of the static friction the last
motion leaves). The change of the current that holds it, ΔI_measured, against the model's ΔG_j/K_t,j:

    ratio = ΔI_measured / ΔI_model  ≈ +1  encoder direction, current sign and K_t agree with the model
                                     < 0  a sign is wrong (joints[].direction, or the drive's current sign)
                                     off by more than the tolerance: K_t (or the link's mass) is off by that much

A joint whose gravity hardly changes over the move (|ΔI_model| below ``MIN_DELTA_A``: the vertical first axis,
a wrist at this pose) is reported as not checkable here, with the reason. A failed check refuses DRAG until a
check passes.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from dragd.control.modes import Mode
from dragd.daemon.payload import APPROACH_RAD, MOVE_SPEED_RAD_S, PayloadTools

if TYPE_CHECKING:
    from dragd.config import Config
    from dragd.control.controller import Controller
    from dragd.model import RobotModel

TOLERANCE = 0.25  # |ratio − 1| beyond this: K_t's scale is refused
MIN_DELTA_A = 0.3  # the model's current change over the move must exceed this to judge (friction noise)


class ModelCheck:
    """``dragd check model``: each joint moved about the held pose; the hold current's change against the model's.

    A joint that fails (a wrong sign, K_t's scale off) is in ``failed`` until a check passes: drag is refused
    meanwhile. The moves are the payload tools' (``PayloadTools.goto``), which they share (``busy``)."""

    def __init__(self, cfg: Config, model: RobotModel, controller: Controller, poses: PayloadTools) -> None:
        self.cfg, self.model, self.controller, self.poses = cfg, model, controller, poses
        self.n = len(cfg.joints)
        self.failed: list[str] = []  # joints the last check refused

    async def run(self, step_rad: float = 0.25) -> dict[str, Any]:
        c, poses = self.controller, self.poses
        if not 0.02 <= step_rad <= 0.5:
            raise ValueError(f"check model: --step-rad: expected 0.02..0.5 rad, got {step_rad}")
        if c.mode != Mode.HOLD or c.track.active:
            raise ValueError("check model: expected HOLD ('dragd start' holds the arm), the arm is in "
                             f"{c.mode.name.lower()}")
        if poses.busy:
            raise ValueError("check model: a payload estimate is running")
        poses.busy = True
        q0 = c.q_hold.copy()
        s = c.safety
        lo, hi = s.wall_lo_rad + APPROACH_RAD + 0.02, s.wall_hi_rad - APPROACH_RAD - 0.02
        rows = []
        try:
            for j in range(self.n):
                ends = []
                for sign in (-1.0, 1.0):
                    q = q0.copy()
                    q[j] = float(np.clip(q0[j] + sign * step_rad, lo[j], hi[j]))
                    ends.append(q)
                g = [self.model.gravity(q) for q in ends]
                delta_model = float((g[1][j] - g[0][j]) / c.kt[j])
                name = self.cfg.joints[j].name
                if abs(delta_model) < MIN_DELTA_A:
                    rows.append({"joint": name, "verdict": "not checkable here", "slope_ratio": None,
                                 "delta_model_A": round(delta_model, 3), "delta_measured_A": None,
                                 "text": f"its gravity current changes by only {delta_model:+.2f} A over "
                                         f"±{step_rad:g} rad at this pose (a vertical axis, or a wrist near its "
                                         "balance): move the arm so that it carries a lever and check again"})
                    continue
                meas = []
                for q in ends:
                    I_sides = []
                    for side in (1.0, -1.0):
                        await poses.goto(q + side * APPROACH_RAD * np.eye(self.n)[j],
                                         float(np.abs(q - c.q_hold).max()) / MOVE_SPEED_RAD_S + 10.0)
                        await poses.goto(q, 10.0)
                        I_sides.append(float(c.hold_current_A[j]))
                    meas.append(sum(I_sides) / 2)
                delta_meas = meas[1] - meas[0]
                ratio = delta_meas / delta_model
                if ratio < 0:
                    verdict, text = "wrong sign", (f"the current that holds it changes by {delta_meas:+.2f} A where "
                                                   f"the model says {delta_model:+.2f} A: the encoder direction or "
                                                   "the current sign is inverted (joints[].direction, the drive's "
                                                   "polarity)")
                elif abs(ratio - 1.0) > TOLERANCE:
                    verdict, text = "scale off", (f"measured/model {ratio:.2f}: K_t (torque_constant_Nm_per_A) or "
                                                  f"the links' masses are off by {abs(ratio - 1) * 100:.0f} % "
                                                  f"(tolerance {TOLERANCE * 100:.0f} %); identify K_t (dragd "
                                                  "identify) or fix the URDF")
                else:
                    verdict, text = "ok", ""
                rows.append({"joint": name, "verdict": verdict, "slope_ratio": round(ratio, 3),
                             "delta_model_A": round(delta_model, 3), "delta_measured_A": round(delta_meas, 3),
                             "text": text})
            await poses.goto(q0, float(np.abs(q0 - c.q_hold).max()) / MOVE_SPEED_RAD_S + 10.0)
        finally:
            c.hold_move = None
            poses.busy = False
        ok = all(r["verdict"] in ("ok", "not checkable here") for r in rows)
        self.failed = [str(r["joint"]) for r in rows if r["verdict"] not in ("ok", "not checkable here")]
        return {"ok": ok, "tolerance": TOLERANCE, "step_rad": step_rad, "joints": rows}
