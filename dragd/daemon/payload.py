"""The flange payload through the daemon (docs/PAYLOAD.md): estimate it from hold currents, set it, clear it.

``estimate``: from HOLD, the hold pose moves (slowly, through HOLD's own PD, inside the soft limits) to a few poses
around where the arm is; at each the arm is approached from both sides of the pose and rests, and the measured
current that holds it is averaged (the two approaches cancel most of the static friction that the last motion leaves
in the joint). The residual K_t·I − G_arm(q) (the model without any payload) over all poses is fitted by least
squares to the flange-load regressor Y(q)·[m, m·c]: mass and centre of mass in the last joint's frame, with each
parameter's standard deviation and a plain statement of what the poses could not observe.

``set``/``clear``/``estimate --apply``: the running law takes the new payload without restart, its gravity blended
over ``RAMP_S`` (RobotModel.set_payload), and it is written to the params file's ``payload:``.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from dragd.config import ParamsFile, Payload, load_params, save_params
from dragd.control.modes import Mode

if TYPE_CHECKING:
    from dragd.config import Config
    from dragd.control.controller import Controller
    from dragd.daemon.cycle import Cycle
    from dragd.model import RobotModel

RAMP_S = 0.5  # gravity blend of a payload change
MOVE_SPEED_RAD_S = 0.25
APPROACH_RAD = 0.03  # each pose approached from both sides by this much
SETTLE_S = 0.4  # rest before and while the hold current is averaged
# pose offsets from the start pose (joint index, rad): wrist moves tilt the flange (centre of mass), shoulder and
# elbow change the lever (mass)
POSE_STEPS = [(), ((4, 0.5),), ((4, -0.5),), ((3, 0.4), (5, 0.8)), ((3, -0.4), (5, -0.8)), ((2, 0.25), (4, 0.3)),
              ((1, -0.15), (5, 1.6)), ((2, -0.25), (3, 0.3), (4, -0.3))]
OBSERVABLE_STD_KG = 0.05  # a mass std above this is reported as not determined
OBSERVABLE_STD_M = 0.01  # a centre-of-mass component std above this is reported as not observable


class PayloadTools:
    """The payload commands, and the held pose moved to a target and rested there (``goto``: the model check's too)."""

    def __init__(self, cfg: Config, controller: Controller, cycle: Cycle, model: RobotModel) -> None:
        self.cfg, self.controller, self.cycle, self.model = cfg, controller, cycle, model
        self.n = len(cfg.joints)
        self.busy = False  # an estimate (or the model check) moves the arm

    def params_path(self) -> Path | None:
        cfg = self.cfg
        return (cfg.base_dir / cfg.params) if cfg.params else None

    def _write(self, mass_kg: float, com_m: list[float], what: str) -> str | None:
        """The payload into the params file (created when missing); the path, or None without a params file."""
        path = self.params_path()
        if path is None:
            return None
        params = load_params(path) if path.exists() else ParamsFile()
        payload = None if mass_kg <= 0 else Payload(mass_kg=mass_kg, com_m=tuple(com_m))  # type: ignore[arg-type]
        notes = dict(params.notes)
        notes["payload"] = what
        save_params(params.model_copy(update={"payload": payload, "notes": notes}), path)
        return str(path)

    def apply(self, mass_kg: float, com_m: list[float], what: str, write: bool = True) -> dict[str, Any]:
        """The running law takes the payload (gravity blended over RAMP_S); written to the params file."""
        if not (np.isfinite(mass_kg) and mass_kg >= 0):
            raise ValueError(f"payload: mass_kg: expected a number >= 0 (kg), got {mass_kg}")
        com = [float(x) for x in com_m]
        if len(com) != 3 or not all(np.isfinite(com)):
            raise ValueError("payload: com_m: expected 3 finite numbers X,Y,Z (m, the last joint's frame), "
                             f"got {com_m}")
        c = self.controller
        t = self.cycle.t
        before = self._max_gravity_need(mass_kg, com)
        if before is not None:
            raise ValueError(before)
        self.model.set_payload(mass_kg, np.array(com), ramp_s=RAMP_S, t_s=t)
        if np.count_nonzero(c.gravity_offset_A):  # an accepted / guard-measured offset was this payload's stand-in:
            c.gravity_offset_A.fill(0.0)  # it goes, and the command blends over the same ramp (no jump)
            c.blend_from_A[:] = c.prev_cmd_A
            c.blend_t0 = c.t
            c.blend_ramp_s = RAMP_S
        path = self._write(mass_kg, com, what) if write else None
        return {"mass_kg": mass_kg, "com_m": com, "ramp_s": RAMP_S, "params": path,
                "note": None if path or not write else "no params file configured (config 'params:'): applied to the "
                "running daemon only"}

    def _max_gravity_need(self, mass_kg: float, com: list[float]) -> str | None:
        """Refuse a payload whose gravity at the present pose exceeds a joint's current limit."""
        c = self.controller
        q = self.cycle.est.q_rad
        Y = self.model.payload_regressor(q)
        old = np.r_[self.model.payload_mass_kg, self.model.payload_mass_kg * self.model.payload_com_m]
        new = np.r_[mass_kg, mass_kg * np.asarray(com)]
        need = np.abs((self.model.gravity(q) + Y @ (new - old)) / c.kt)
        over = np.flatnonzero(need > c.params.current_limit_A)
        if over.size:
            j = int(over[0])
            return (f"payload: {mass_kg:g} kg: {self.cfg.joints[j].name} would need {need[j]:.2f} A to hold this "
                    f"pose, above its current_limit_A {c.params.current_limit_A[j]:.2f} A")
        return None

    # ------------------------------------------------------------------------------------------ estimate

    async def goto(self, target: np.ndarray, timeout_s: float) -> None:
        c = self.controller
        c.hold_move_speed = MOVE_SPEED_RAD_S
        c.hold_move = target.copy()
        c.hold_rest_s = 0.0
        ok = await self.cycle.clock.wait_for(lambda: c.mode != Mode.HOLD or (c.hold_move is not None and
                                                              np.array_equal(c.q_hold, c.hold_move) and
                                                              c.hold_rest_s >= SETTLE_S), timeout_s)
        if c.mode != Mode.HOLD:
            raise RuntimeError(f"payload estimate: stopped: the arm left HOLD ({c.mode.name.lower()}); nothing applied")
        if not ok:
            raise RuntimeError(f"payload estimate: the arm did not come to rest at a pose within {timeout_s:.0f} s "
                               "(is something touching it?); nothing applied")

    def _poses(self, q0: np.ndarray, n_poses: int) -> list[np.ndarray]:
        s = self.controller.safety
        lo, hi = s.wall_lo_rad + APPROACH_RAD + 0.02, s.wall_hi_rad - APPROACH_RAD - 0.02
        poses = []
        for steps in POSE_STEPS[:n_poses]:
            q = q0.copy()
            for j, dq in steps:
                if j < q.shape[0]:
                    q[j] += dq
            poses.append(np.clip(q, lo, hi))
        return poses

    async def estimate(self, n_poses: int = 6, apply: bool = False) -> dict[str, Any]:
        c = self.controller
        if not 3 <= n_poses <= len(POSE_STEPS):
            raise ValueError(f"payload estimate: --poses: expected 3..{len(POSE_STEPS)}, got {n_poses}")
        if c.mode != Mode.HOLD or c.track.active:
            raise ValueError(f"payload estimate: expected HOLD (the arm held still; 'dragd mode hold'), the arm is in "
                             f"{c.mode.name.lower()}")
        if self.busy:
            raise ValueError("payload estimate: already running")
        self.busy = True
        q0 = c.q_hold.copy()
        rows_q, rows_i = [], []
        try:
            for q in self._poses(q0, n_poses):
                dist = float(np.abs(q - c.q_hold).max())
                for side in (1.0, -1.0):
                    await self.goto(q + side * APPROACH_RAD, dist / MOVE_SPEED_RAD_S + 10.0)
                    dist = 2 * APPROACH_RAD
                    await self.goto(q, 10.0)
                    rows_q.append(c.hold_rest_q.copy())
                    rows_i.append(c.hold_current_A.copy())
            await self.goto(q0, float(np.abs(q0 - c.q_hold).max()) / MOVE_SPEED_RAD_S + 10.0)
        finally:
            c.hold_move = None
            self.busy = False
        res = self.fit(np.array(rows_q), np.array(rows_i))
        res["poses"] = n_poses
        if apply:
            res["applied"] = self.apply(res["mass_kg"], res["com_m"], f"dragd payload estimate ({n_poses} poses)")
        return res

    def fit(self, q: np.ndarray, current_A: np.ndarray) -> dict[str, Any]:
        """Least squares of the hold currents' residual against the model without payload on Y(q)·[m, m·c]."""
        c = self.controller
        m = self.model
        th_now = np.r_[m.payload_mass_kg, m.payload_mass_kg * m.payload_com_m]
        A, b = [], []
        for qk, ik in zip(q, current_A, strict=True):
            Y = m.payload_regressor(qk)
            g_arm = m.gravity(qk) - Y @ th_now  # the arm without the payload the model carries now
            A.append(Y)
            b.append(ik * c.kt - g_arm)
        A_, b_ = np.vstack(A), np.concatenate(b)
        theta, *_ = np.linalg.lstsq(A_, b_, rcond=1e-9)
        resid = b_ - A_ @ theta
        dof = max(1, A_.shape[0] - 4)
        sigma2 = float(resid @ resid) / dof
        cov = sigma2 * np.linalg.pinv(A_.T @ A_)
        std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        mass = float(theta[0])
        com = (theta[1:] / mass).tolist() if mass > 1e-6 else [0.0, 0.0, 0.0]
        com_std = (np.sqrt(std[1:] ** 2 / mass ** 2 + (theta[1:] * std[0] / mass ** 2) ** 2)).tolist() if mass > 1e-6 \
            else [float("inf")] * 3
        unobs = [ax for ax, s in zip("xyz", com_std, strict=True) if not s <= OBSERVABLE_STD_M]
        sv = np.linalg.svd(A_, compute_uv=False)
        out: dict[str, Any] = {"mass_kg": round(mass, 4), "mass_std_kg": round(float(std[0]), 4),
               "com_m": [round(x, 4) for x in com], "com_std_m": [round(float(x), 4) for x in com_std],
               "rms_residual_Nm": round(float(np.sqrt(np.mean(resid ** 2))), 4),
               "samples": int(q.shape[0]), "singular_values": [round(float(x), 3) for x in sv]}
        if mass < 0.02:
            out["observability"] = "no load found on the flange (mass within noise); the centre of mass is meaningless"
        elif unobs:
            out["observability"] = (f"centre of mass along {', '.join(unobs)} not determined by these poses (std > "
                                    f"{OBSERVABLE_STD_M * 1000:.0f} mm): a component along the last joint's axis is "
                                    "only seen when that axis tilts against gravity; use more --poses or move the "
                                    "wrist first")
        else:
            out["observability"] = "mass and all three centre-of-mass components determined"
        if not float(std[0]) <= OBSERVABLE_STD_KG:
            out["observability"] += f"; the mass itself is uncertain (std {std[0]:.2f} kg)"
        return out
