"""The contact detector in the daemon's cycle: what it watches in each mode, and the hand's force in drag.

The controller (dragd/control/controller.py) owns one ``ContactWatch``. Every cycle the estimate step hands it
Pinocchio's p = M̄(q)·q̇, g(q) and C(q, q̇) (dragd/daemon/cycle.py) and it runs one compiled call
(dragd/control/contact.py ``_contact_cycle_kernel``):

* **HOLD, TRACK** (replay, ``track``, streams) and **identify run** (a TRACK whose label starts with "identify"):
  the detector — the residual against the calibrated bands × 1/sensitivity of the mode — armed once the mode's law
  is fully in (the blend over), not while the controller ramps to a stop, holds for stale feedback or holds with a
  gravity offset the model does not have. In TRACK a joint whose reference moves is never at rest. An onset is
  handed to the controller, which reacts as the mode's ``reaction`` says (``stop``, ``retract``, ``compliant``).
* **DRAG**: the same residual without bands — the operator's hand plus the model's error — mapped to the force at
  the grip point: f = (J_vᵀ)⁺·r (least squares: the hand's force that best explains the joint torques, J_v the grip
  point's linear Jacobian, world axes; a joint at rest — within its start-up zone, held by static friction — weighs
  ``contact.grip.rest_weight`` of a moving one), low-passed at ``contact.wrench_Hz``.

Without calibrated bands (a params file without ``contact``: ``dragd contact calibrate``) only the drag residual
runs; status says why the detector does not. ``contact.enabled: false`` turns both off (the cycle makes none of
their calls).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from dragd.control.contact import (
    ENDED,
    ONSET,
    QUIET,
    ContactBands,
    ContactDetector,
    ContactSettings,
    contact_kernels,
    pack_model,
)
from dragd.jit import compile_kernels

if TYPE_CHECKING:
    from dragd.config import Config
    from dragd.control.params import LawParams

WATCHED = ("hold", "track", "identify")  # the modes the detector judges (their config sections)


@dataclass(frozen=True)
class WatchMode:
    sensitivity: float
    reaction: str  # stop | retract | compliant


def grip_force(J: np.ndarray, r: np.ndarray, w: np.ndarray, out: np.ndarray) -> bool:
    """f = (J_vᵀ)⁺·r into ``out`` (3): the force at the grip point (J: its 6×n Jacobian, linear rows first, world
    axes) whose joint torques J_vᵀ·f come closest to r, joint k's equation weighted by ``w[k]`` (the inverse square
    of how uncertain its residual is). False (``out`` untouched) where the weighted J_v is singular."""
    n = r.shape[0]
    a00 = a01 = a02 = a11 = a12 = a22 = 0.0
    b0 = b1 = b2 = 0.0
    for k in range(n):
        wk = w[k]
        x, y, z = J[0, k], J[1, k], J[2, k]
        a00 += wk * x * x
        a01 += wk * x * y
        a02 += wk * x * z
        a11 += wk * y * y
        a12 += wk * y * z
        a22 += wk * z * z
        b0 += wk * x * r[k]
        b1 += wk * y * r[k]
        b2 += wk * z * r[k]
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    det = a00 * c00 + a01 * c01 + a02 * c02
    scale = a00 + a11 + a22
    if not det > 1e-9 * scale * scale * scale:
        return False
    c11 = a00 * a22 - a02 * a02
    c12 = a01 * a02 - a00 * a12
    c22 = a00 * a11 - a01 * a01
    out[0] = (c00 * b0 + c01 * b1 + c02 * b2) / det
    out[1] = (c01 * b0 + c11 * b1 + c12 * b2) / det
    out[2] = (c02 * b0 + c12 * b1 + c22 * b2) / det
    return True


def _grip_force_kernel(J: np.ndarray, r: np.ndarray, w: np.ndarray, raw: np.ndarray, filt: np.ndarray,
                       alpha: float) -> bool:
    ok = grip_force(J, r, w, raw)
    if ok:
        for k in range(3):
            filt[k] += (raw[k] - filt[k]) * alpha
    return ok


def _kernels() -> dict[str, Any] | None:
    z = np.zeros(3)
    return compile_kernels(globals(), ("grip_force",), {
        "grip": (_grip_force_kernel, (np.eye(6)[:, :6].copy(), np.zeros(6), np.ones(6), z.copy(), z.copy(), 0.1))})


class ContactWatch:
    """The detector of one arm in the daemon (settings constant, state in the detector and here)."""

    def __init__(self, detector: ContactDetector, modes: dict[str, WatchMode], calibrated: bool, reason: str,
                 retract_rad: float, retract_speed_rad_s: float, wrench_alpha: float, compiled: bool = True) -> None:
        self.det = detector
        self.modes = modes
        self.calibrated = calibrated
        self.enabled = not reason.startswith("disabled")  # contact.enabled: false: no residual in any mode
        self.reason = reason  # why the detector does not judge (not calibrated, disabled); "" when it does
        self.retract_rad = retract_rad
        self.retract_speed_rad_s = retract_speed_rad_s
        self.wrench_alpha = wrench_alpha
        n = detector.n
        self.watching = ""  # the mode judged now ("" none; "drag": the residual alone)
        self.why_not = ""  # why nothing is judged in a mode that could be ("feedback hold", ...)
        self.ref_moving = np.zeros(n, dtype=bool)
        self.force_raw_N = np.zeros(3)
        self.force_N = np.zeros(3)  # the hand's force at the grip point, low-passed (drag; zeros otherwise)
        self.force_valid = False
        self.grip_m = np.zeros(3)  # the grip point's position (world), where the force acts
        self.onsets = 0
        self.last: dict[str, Any] | None = None  # the last event (status)
        self.ended: dict[str, Any] | None = None  # an event that ended since the controller last looked
        self.code = QUIET
        self._abs = np.zeros(n)
        # the hand's force: a joint's equation weight (1 moving, rest_weight² at rest: below its start-up zone)
        self.grip_w = np.ones(n)
        self.rest_speed_rad_s = np.full(n, 0.03)
        self.rest_weight2 = 0.03 ** 2
        self._grip = None
        if compiled:
            ks = contact_kernels()
            if ks is not None:
                detector.use_cycle_kernels(ks)
            gk = _kernels()
            self._grip = None if gk is None else gk["grip"]

    @classmethod
    def from_config(cls, cfg: Config, params: LawParams, dt_s: float, compiled: bool = True) -> ContactWatch:
        cc = cfg.contact
        cal = cfg.contact_calibration
        names = cfg.joint_names
        n = len(names)
        reason = ""
        if not cc.enabled:
            reason = "disabled (contact.enabled: false)"
        elif cal is None:
            reason = ("not calibrated: the params file has no contact bands ('dragd contact calibrate --params P "
                      "--log FREE.csv ... --out P2', then params: P2)")
        if cal is not None:
            missing = [nm for nm in names if nm not in cal.joints]
            if missing:
                from dragd.config import ConfigError

                raise ConfigError(f"{cfg.source}: params contact.joints: expected bands for every joint, missing "
                                  f"{', '.join(missing)}")
            rows = {k: np.array([getattr(cal.joints[nm], k) for nm in names]) for k in (
                "base_A", "slow_A", "speed_A_s_per_rad", "accel_A_s2_per_rad", "slow_speed_rad_s", "settling_A",
                "held_A", "held_moving_A")}
            bands = ContactBands(**rows)
            settings = ContactSettings(observer_gain_per_s=cal.observer_gain_per_s)
        else:
            bands = ContactBands.uniform(n)  # (unused: nothing is judged)
            settings = ContactSettings()
        law = params.replace(friction_scale=1.0)
        k_load = np.array([float(j.effects.load_friction_per_Nm) for j in cfg.joints])
        det = ContactDetector(params.kt_Nm_per_A, bands, settings)
        F, FS = pack_model(law, params.kt_Nm_per_A, k_load if k_load.any() else None)
        det.set_model(F, FS)
        modes = {m: WatchMode(getattr(cc, m).sensitivity, getattr(cc, m).reaction) for m in WATCHED}
        alpha = 1.0 - math.exp(-2.0 * math.pi * cc.wrench_Hz * dt_s)
        w = cls(det, modes, cal is not None and cc.enabled, reason, cc.retract_rad, cc.retract_speed_rad_s,
                alpha, compiled)
        w.rest_speed_rad_s[:] = params.rest_threshold_rad_s + params.fade_width_rad_s  # the law's start-up zone
        w.rest_weight2 = cc.grip.rest_weight ** 2
        return w

    # ------------------------------------------------------------------------------------------ the cycle

    def select(self, want: str, why_not: str = "") -> None:
        """The mode to watch from now on ("" none, "drag" the residual alone, else one of WATCHED)."""
        self.why_not = why_not
        if want == self.watching:
            return
        det = self.det
        if det.active and det.events:  # an event cut short by the switch: it ends here
            self._ended(det._t_last)
        det.disarm()
        self.watching = want
        self.force_valid = False
        self.force_N.fill(0.0)
        if want in self.modes:
            self.det.set_scale(1.0 / self.modes[want].sensitivity)

    def step(self, t_s: float, dq: np.ndarray, p: np.ndarray, i_A: np.ndarray, g: np.ndarray, C: np.ndarray,
             ready: bool, dq_ref: np.ndarray | None) -> int:
        """One cycle: arm once ``ready`` (the mode's law fully in, the feedback fresh), then update; the code."""
        det = self.det
        self.code = QUIET
        if not self.watching:
            return QUIET
        if not det.armed:
            if ready:
                det.arm(p, t_s)
            return QUIET
        if self.watching == "drag":
            det.observe_cycle(t_s, dq, p, i_A, g, C)
            # the hand's force weighs a resting joint's equation by rest_weight²: held by its static friction (and
            # dithered by the start-up sine), its residual is not the hand's torque
            np.abs(dq, out=self._abs)
            np.greater_equal(self._abs, self.rest_speed_rad_s, out=self.ref_moving)
            self.grip_w.fill(self.rest_weight2)
            np.copyto(self.grip_w, 1.0, where=self.ref_moving)
            return QUIET
        if dq_ref is not None:
            np.abs(dq_ref, out=self._abs)
            np.greater_equal(self._abs, det.s.rest_speed_rad_s, out=self.ref_moving)
        else:
            self.ref_moving.fill(False)
        self.code = det.update_cycle(t_s, dq, p, i_A, g, C, self.ref_moving)
        if self.code == ONSET:
            self.onsets += 1
        elif self.code == ENDED:
            self._ended(t_s)
        if len(det.events) > 64:  # (a long session: the status keeps the last one, the fault list the rest)
            del det.events[:-16]
        return self.code

    def _ended(self, t_s: float) -> None:
        """The event's end and peaks into ``last`` and ``ended`` (the controller records it). Rare path."""
        ev = self.det.events[-1]
        end = {"t_end_s": round(t_s, 4), "joints": [int(j) for j in ev.joints],
               "peak_Nm": [round(x, 3) for x in ev.peak_Nm], "peak_A": [round(x, 3) for x in ev.peak_A]}
        if self.last is not None:
            self.last.update(t_end_s=end["t_end_s"], peak_Nm=end["peak_Nm"], peak_A=end["peak_A"])
        self.ended = end

    def grip_force(self, J: np.ndarray) -> None:
        """Drag: the hand's force at the grip point from the residual (``J``: the grip point's 6×n Jacobian)."""
        if self.watching != "drag" or not self.det.armed:
            return
        if self._grip is not None:
            ok = self._grip(J, self.det.r, self.grip_w, self.force_raw_N, self.force_N, self.wrench_alpha)
        else:
            ok = grip_force(J, self.det.r, self.grip_w, self.force_raw_N)
            if ok:
                self.force_N += (self.force_raw_N - self.force_N) * self.wrench_alpha
        self.force_valid = bool(ok)

    # ------------------------------------------------------------------------------------------ reactions

    def retract_step(self, q: np.ndarray, lo: np.ndarray, hi: np.ndarray, out: np.ndarray) -> bool:
        """The retract's target into ``out``: from q along the residual (the way the contact pushes the arm: in
        joint space that always moves the contact point away from the contact force, Δx·f = Δqᵀ·Jᵀf > 0) over the
        joints that carry the contact (|d| above half their band), the largest joint step ``retract_rad``, clipped
        to [lo, hi]. False where no joint carries it (nothing to back off along)."""
        det = self.det
        np.abs(det.d, out=self._abs)
        np.copyto(out, det.r)
        out *= self._abs >= det.band * det.s.hysteresis
        top = float(np.abs(out).max())
        if not top > 0.0:
            return False
        out *= self.retract_rad / top
        out += q
        np.clip(out, lo, hi, out=out)
        return True

    def onset_record(self, names: list[str], reaction: str, note: str = "") -> tuple[int, str, dict[str, Any]]:
        """The event that just began, for the fault entry: (dominant joint, text, fields). Rare path (allocates)."""
        det = self.det
        ev = det.events[-1]
        js = ev.joints
        dom = max(js, key=lambda j: abs(det.d[j]) / det.band[j] if det.band[j] > 0 else 0.0)
        residual_A = [round(float(det.e[j]), 3) for j in js]
        contact_Nm = [round(float(abs(det.d[j]) * det.kt[j]), 2) for j in js]
        jn = [names[j] for j in js]
        text = (f"contact in {self.watching} on {', '.join(jn)}: residual "
                f"{', '.join(f'{x:+.2f}' for x in residual_A)} A (band "
                f"{', '.join(f'{det.band[j]:.2f}' for j in js)} A), estimated contact torque "
                f"{', '.join(f'{x:.1f}' for x in contact_Nm)} N·m; {reaction}" + (f" ({note})" if note else ""))
        fields = {"kind": "contact", "mode": self.watching, "reaction": reaction, "joints": jn,
                  "residual_A": residual_A, "band_A": [round(float(det.band[j]), 3) for j in js],
                  "contact_Nm": contact_Nm, "states": list(ev.states), "t_start_s": round(ev.t_start_s, 4),
                  "t_end_s": None}
        if note:
            fields["note"] = note
        self.last = dict(fields)
        return dom, text, fields

    def status(self, names: list[str]) -> dict[str, Any]:
        det = self.det
        b = det.bands
        judging = self.watching in self.modes and det.armed
        return {
            "calibrated": self.calibrated,
            "reason": self.reason or None,
            "watching": self.watching or None,
            "armed": bool(det.armed),
            "not_watching_because": self.why_not or None,
            "observer_gain_per_s": det.s.observer_gain_per_s,
            "modes": {m: {"sensitivity": w.sensitivity, "reaction": w.reaction} for m, w in self.modes.items()},
            "retract_rad": self.retract_rad,
            "thresholds_A": {m: [round(float(x) / w.sensitivity, 4) for x in b.base_A]
                             for m, w in self.modes.items()} if self.calibrated else None,
            "bands_A": {nm: {"base_A": float(b.base_A[j]), "slow_A": float(b.slow_A[j]),
                             "speed_A_s_per_rad": float(b.speed_A_s_per_rad[j]),
                             "accel_A_s2_per_rad": float(b.accel_A_s2_per_rad[j]),
                             "settling_A": float(b.settling_A[j]), "held_A": float(b.held_A[j]),
                             "held_moving_A": float(b.held_moving_A[j])}
                        for j, nm in enumerate(names)} if self.calibrated else None,
            "residual_A": det.e.tolist() if det.armed else None,
            "band_A": det.band.tolist() if judging else None,
            "ratio_max": round(float(np.max(np.abs(det.d) / det.band)), 3) if judging and det.band.all() else None,
            "states": [("moving", "settling", "held", "released")[int(s)] for s in det.state] if judging else None,
            "event_active": bool(det.active),
            "onsets": self.onsets,
            "last_event": self.last,
            "hand_force_N": self.force_N.tolist() if self.watching == "drag" and self.force_valid else None,
            "grip_m": self.grip_m.tolist() if self.watching == "drag" and self.force_valid else None,
            "hand_force_norm_N": (round(float(np.linalg.norm(self.force_N)), 2)
                                  if self.watching == "drag" and self.force_valid else None),
        }
