"""The compute step: the mode state machine and the command current of every mode, from the cycle's estimate.

    IDLE, FAULT   0
    HOLD          [G(q) + k_p·(q_hold − q) − k_d·q̇] / K_t
    DRAG          the zero-force law (dragd/control/law.py): G/K_t + friction + start-up + damping (+ effects)
    TRACK         the CSP torque offset (dragd/control/track.py): G/K_t + friction(q̇_ref) + feed-forward
                  (+ dragd's position loop: a replay's around the drives' CSP loops; CST joints' only one)
    every mode    + soft-limit walls (and in DRAG the speed cap), clamped to the current limits

A mode switch blends from the command at the switch instant to the new mode's over ``mode_ramp_s`` (smoothstep):
no jump in current. Stale feedback in DRAG holds the arm and resumes drag when it is fresh again; feedback lost
for longer faults. Faults and mode changes are recorded in ``events`` (drained by the daemon after the cycle:
nothing is logged or written from here). Pure: numpy arrays in, numpy arrays out; no I/O, no allocation per
cycle on the usual paths.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from dragd.control.contact import ONSET
from dragd.control.contact_watch import ContactWatch
from dragd.control.guard import GuardSettings, RunawayGuard, guard_command_kernel, guard_kernel
from dragd.control.fused import DragLaw
from dragd.control.hand import HandInputs
from dragd.control.permission import R_LEASE_CLOSED, R_LEASE_LAPSED, DragPermission
from dragd.control.modes import MODE_NAMES, Mode
from dragd.control.params import LawParams
from dragd.control.safety import SafetyTerms, safety_kernel
from dragd.control.track import CstLoop, Track, TrackLimits, Trip
from dragd.control.trajectory import Trajectory

if TYPE_CHECKING:
    from dragd.config import Config


@dataclass(frozen=True)
class Event:
    """Something the cycle decided that the daemon must record: a mode change, a fault, a motion's end."""

    kind: str  # mode | fault | protective_stop | track_end
    t_s: float
    joint: int | None = None
    text: str = ""
    code: int = 0
    fields: dict[str, Any] | None = None


@dataclass(frozen=True)
class Estimate:
    """The estimate step's arrays (SI units), filled in place every cycle."""

    q_rad: np.ndarray
    dq_rad_s: np.ndarray
    current_A: np.ndarray
    tau_g_Nm: np.ndarray
    p_Nms: np.ndarray | None = None  # generalised momentum M̄(q)·q̇ (the runaway guard's and the contact observer's)
    inputs: np.ndarray | None = None  # per joint the drive's digital inputs word (60FDh; the feedback's array)
    inputs_age: np.ndarray | None = None  # per joint cycles since the TPDO carrying it arrived

    @classmethod
    def zeros(cls, n: int) -> Estimate:
        return cls(np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n))


class Controller:
    """Modes, their laws, the blend between them and the safety terms for one arm."""

    def __init__(self, params: LawParams, safety: SafetyTerms, track_limits: TrackLimits, joint_names: list[str],
                 dt_s: float, hold_kp_Nm_per_rad: float, hold_kd_Nm_s_per_rad: float, mode_ramp_s: float,
                 fresh_cycles_resume: int, compiled: bool = True) -> None:
        n = self.n = params.n
        self.params = params
        self.safety = safety
        self.names = joint_names
        self.dt = dt_s
        self.hold_kp = hold_kp_Nm_per_rad
        self.hold_kd: float | np.ndarray = hold_kd_Nm_s_per_rad  # (the exit brake's, per joint, while it brakes)
        self.mode_ramp_s = mode_ramp_s
        self.fresh_cycles_resume = fresh_cycles_resume
        self.kt = params.kt_Nm_per_A
        self.neg_limit_A = -params.current_limit_A
        self.mode = Mode.IDLE
        self.prev_mode = Mode.IDLE
        self.t = 0.0
        self.q_hold = np.zeros(n)
        self.blend_t0 = -1.0
        self.blend_from_A = np.zeros(n)
        self.stop_after_hold_at: float | None = None
        self.feedback_hold = False  # HOLD forced by stale feedback; the requested mode returns when it is fresh
        self.resume_mode = Mode.IDLE
        self.fresh_cycles = 0
        self.feedback_holds = 0
        self.drive_csp = False  # the drives run CSP (their position loops hold q_ref / q_hold), else CST
        # the drag law and its latch (compiled kernels, or the numpy reference with ``compiled`` false)
        self.drag_law = DragLaw(params, compiled)
        self.breakout, self.law_out, self.ws = self.drag_law.state, self.drag_law.out, self.drag_law.ws
        self.track = Track(n, dt_s, track_limits, joint_names)
        self.extra_A = np.zeros(n)  # safety terms this cycle
        self.cmd_A = np.zeros(n)
        self.prev_cmd_A = np.zeros(n)
        self.ref_rad = np.zeros(n)  # the position reference (CSP target; where the arm is otherwise)
        self.clamp_cycles = 0
        self.events: list[Event] = []
        self._tmp = np.zeros(n)
        self._tmp2 = np.zeros(n)
        self.blend_ramp_s = mode_ramp_s
        # the gravity model will be wrong (docs/PAYLOAD.md)
        self.guard: RunawayGuard | None = None  # the runaway guard in DRAG (set by from_config / the daemon)
        self.guard_hold_ramp_s = 0.02
        self.guard_trips = 0
        self.last_trip: dict[str, Any] | None = None
        self.gravity_offset_A = np.zeros(n)  # `mode drag --accept`: measured hold current − model, in DRAG
        self.hold_current_A = np.zeros(n)  # the measured current while holding at rest (low-passed)
        self.hold_rest_s = 0.0  # how long HOLD has been at rest (the hold current's averaging time)
        self.hold_rest_q = np.zeros(n)
        self.hold_move: np.ndarray | None = None  # HOLD's pose moving to this target (payload estimate, check model)
        self.hold_move_speed = 0.1
        self._tau_in = np.zeros(n)
        # contact detection (dragd/control/contact_watch.py; set by from_config): see "contact" below
        self.contact: ContactWatch | None = None
        self.contact_stops = 0
        self._contact_drag_pending = False
        self._contact_target = np.zeros(n)
        self._contact_after_stop = ""  # the reaction that follows a motion's protective stop (retract, compliant)
        self.contact_stop_decel_rad_s2 = np.full(n, 10.0)  # the protective stop's bounds (contact.stop_*)
        self.contact_stop_jerk_rad_s3 = np.full(n, 1000.0)
        # --- drag permission and the hand's inputs (#30) ---
        self.permission = DragPermission("none", 0.5)  # what DRAG requires (from_config: drag.require)
        self.hand: HandInputs | None = None  # the guiding device's inputs (set_hand)
        self.drag_lease = 0  # the lease DRAG was entered with (0: none): when it lapses or closes, drag ends
        self.drag_exit_ramp_s = 0.02  # drag -> hold blend when the permission goes (drag.exit_ramp_s)
        self.drag_ends = 0  # drags the permission ended
        self.last_drag_end: dict[str, Any] | None = None
        self._stop_input = False  # a stop input held the arm last cycle
        self.drag_exit_kd = np.full(n, float(hold_kd_Nm_s_per_rad))  # the exit brake's damping, per joint
        self.drag_exit_brake_s = 0.15  # at most this long (drag.exit_brake_s)
        self._brake_t0 = -1.0  # the exit brake began (-1: not braking)
        self._hold_kd_cfg = hold_kd_Nm_s_per_rad
        # --- end of drag permission ---

    @classmethod
    def from_config(cls, cfg: Config, position_limits_rad: tuple[np.ndarray, np.ndarray]) -> Controller:
        """The configuration's controller; ``position_limits_rad``: the robot's (URDF) limits, per joint."""
        js, s, rc = cfg.joints, cfg.safety, cfg.replay
        params = LawParams.from_config(cfg)
        lo, hi = position_limits_rad
        lim_lo = np.array([j.position_limits_rad[0] if j.position_limits_rad else lo[i] for i, j in enumerate(js)])
        lim_hi = np.array([j.position_limits_rad[1] if j.position_limits_rad else hi[i] for i, j in enumerate(js)])
        dt = 1.0 / cfg.loop.rate_Hz
        kt = params.kt_Nm_per_A
        safety = SafetyTerms(lim_lo, lim_hi, s.soft_limit_margin_rad, s.wall_stiffness_Nm_per_rad,
                             s.wall_damping_Nm_s_per_rad, np.array([j.velocity_limit_rad_s for j in js]),
                             s.speed_cap_damping_Nm_s_per_rad, kt)

        def per_joint(v: Any) -> np.ndarray:
            return np.array(cfg.per_joint(v), dtype=float)

        limits = TrackLimits(
            tracking_error_rad=per_joint(rc.tracking_error_limit_rad),
            residual_current_A=per_joint(rc.residual_current_limit_A),
            residual_filter_alpha=1.0 - math.exp(-2.0 * math.pi * rc.residual_filter_Hz * dt),
            acceleration_rad_s2=per_joint(rc.acceleration_limits_rad_s2),
            kp_Nm_per_rad=per_joint(rc.position_kp_Nm_per_rad), kd_Nm_s_per_rad=per_joint(rc.position_kd_Nm_s_per_rad),
            ki_Nm_per_rad_s=per_joint(rc.position_ki_Nm_per_rad_s),
            integral_max_Nm=per_joint(rc.position_integral_limit_A) * kt,
            output_max_Nm=per_joint(rc.position_output_limit_A) * kt,
            ramp_s=rc.ramp_s, monitor_cycles=rc.monitor_cycles, position_lo_rad=lim_lo, position_hi_rad=lim_hi)
        if cfg.loop.compiled and (kernel := safety_kernel()) is not None:
            safety.use_kernel(kernel)
        c = cls(params, safety, limits, cfg.joint_names, dt, s.hold_kp_Nm_per_rad, s.hold_kd_Nm_s_per_rad,
                s.mode_ramp_s, cfg.loop.fresh_cycles_resume, cfg.loop.compiled)
        g = s.guard
        if g.runaway:
            c.guard = RunawayGuard(c.n, kt, dt, GuardSettings(
                observer_Hz=g.observer_Hz, speed_rad_s=g.speed_rad_s, residual_A=g.residual_A, confirm_s=g.confirm_s,
                keep_speed=g.keep_speed, unexplained_max=g.unexplained_max, decide_Hz=g.decide_Hz,
                drive_share=g.drive_share), None, cfg.joint_names)
            if cfg.loop.compiled and (kernel := guard_kernel()) is not None:
                c.guard.use_kernel(kernel, guard_command_kernel())
        c.guard_hold_ramp_s = g.hold_ramp_s
        # the joints whose drives follow motions in CST are set from their drive profiles (Daemon)
        c.track.use_cst(np.zeros(c.n, dtype=bool), CstLoop(
            kp_Nm_per_rad=per_joint(rc.cst_kp_Nm_per_rad), kd_Nm_s_per_rad=per_joint(rc.cst_kd_Nm_s_per_rad),
            ki_Nm_per_rad_s=per_joint(rc.cst_ki_Nm_per_rad_s), integral_max_Nm=per_joint(rc.cst_integral_limit_A) * kt))
        c.contact = ContactWatch.from_config(cfg, params, dt, cfg.loop.compiled)
        c.contact_stop_decel_rad_s2[:] = per_joint(cfg.contact.stop_deceleration_rad_s2)
        c.contact_stop_jerk_rad_s3[:] = per_joint(cfg.contact.stop_jerk_rad_s3)
        c.permission = DragPermission(cfg.drag.require, cfg.drag.lease_s)
        c.drag_exit_ramp_s = cfg.drag.exit_ramp_s
        exit_kd = cfg.drag.exit_damping_Nm_s_per_rad
        exit_kd = [5.0 * v for v in cfg.per_joint(rc.position_kd_Nm_s_per_rad)] if exit_kd is None else exit_kd
        c.drag_exit_kd[:] = np.maximum(per_joint(exit_kd), s.hold_kd_Nm_s_per_rad)
        c.drag_exit_brake_s = cfg.drag.exit_brake_s
        return c

    # ------------------------------------------------------------------------------------------ transitions

    def set_mode(self, mode: Mode, blend: bool = True, ramp_s: float | None = None) -> None:
        """Switch the law; with ``blend`` the command fades from its value at this instant over ``mode_ramp_s``
        (or ``ramp_s``)."""
        if mode == self.mode:
            return
        self._contact_drag_pending = False
        self.blend_from_A[:] = self.prev_cmd_A
        self.blend_t0 = self.t if blend else -1.0
        self.blend_ramp_s = self.mode_ramp_s if ramp_s is None else ramp_s
        self.prev_mode, self.mode = self.mode, mode
        if self.guard is not None:
            self.guard.disarm()  # armed again once the drag law is fully in
        if mode not in (Mode.DRAG, Mode.HOLD):
            self.gravity_offset_A.fill(0.0)
        if mode != Mode.HOLD:
            self.hold_move = None
        self.hold_rest_s = 0.0
        if mode == Mode.DRAG:
            self.breakout.reset(self.t)
        self.events.append(Event("mode", self.t, fields={"mode": MODE_NAMES[mode], "previous": MODE_NAMES[self.prev_mode]}))

    def start(self, q: np.ndarray) -> None:
        """Hold the pose ``q`` (the drives are being enabled); a running motion ends where the arm is."""
        if self.track.active:
            self.end_track("stopped (start)", q, hold_at_ref=False)
        self.q_hold[:] = q
        self.stop_after_hold_at = None
        self.feedback_hold = False
        self.gravity_offset_A.fill(0.0)
        self.drag_lease = 0
        if self.hand is not None:
            self.hand.acknowledge(self.t)  # the operator's start clears the input faults whose cause is gone
        self.set_mode(Mode.HOLD, blend=False)

    def stop(self, q: np.ndarray) -> None:
        """Ramp to hold where the arm is, then IDLE (the drives disable)."""
        if self.mode in (Mode.IDLE, Mode.FAULT):
            return
        self.feedback_hold = False
        if self.track.active:  # a motion: hold where the arm is, drives back to CST, then disable
            self.end_track("stopped (drives disabled)", q, hold_at_ref=False)
        if self.mode != Mode.HOLD:
            self.q_hold[:] = q
            self.set_mode(Mode.HOLD)
        self.stop_after_hold_at = self.t + self.mode_ramp_s + 0.05

    def request(self, target: Mode, q: np.ndarray, lease: int = 0, by_enable: bool = False) -> None:
        """An operator's ``hold`` or ``drag`` (IDLE: ``stop``); ValueError when the arm cannot take it now. ``lease``:
        the drag lease the request comes with (drag then ends when it lapses or closes); ``by_enable``: the request
        is the enabling switch's press (with ``drag.require: both`` it drags on the lease a client holds)."""
        name = MODE_NAMES[target]
        if target == Mode.IDLE:
            self.stop(q)
            return
        if self.mode in (Mode.IDLE, Mode.FAULT):
            raise ValueError(f"mode {name}: the drives are disabled ({MODE_NAMES[self.mode]}); run 'dragd start' first")
        if self.mode == Mode.TRACK:
            label = self.track.trajectory.label if self.track.trajectory else "track"
            raise ValueError(f"mode {name}: a {label} motion is running; stop it first")
        if target == Mode.DRAG:
            self._admit_drag(lease, by_enable)
        if target == Mode.HOLD:
            self.q_hold[:] = q
            self.hold_move = None
            self.drag_lease = 0
        self.stop_after_hold_at = None
        if self.feedback_hold:  # the feedback hold stays; the new request is what it resumes
            self.resume_mode = target
            return
        self.set_mode(target)

    def fault(self, joint: int | None, text: str, code: int = 0) -> None:
        """A safety reaction: mode FAULT (the drives quick-stop, brakes on); recorded as an event."""
        self.feedback_hold = False
        self.events.append(Event("fault", self.t, joint, text, code,
                                 {"motion": self.track.active, "new": self.mode != Mode.FAULT}))
        if self.mode != Mode.FAULT:
            self.prev_mode = self.mode
            self.mode = Mode.FAULT
            self.track.end()

    def take_over_feedback_hold(self, what: str) -> None:
        """A motion request supersedes a feedback hold's return to drag, once the feedback is fresh again."""
        if not self.feedback_hold:
            return
        if self.fresh_cycles < 10:
            raise ValueError(f"{what}: the arm is held because feedback was late (stale TPDOs); try again when "
                             "'dragd status' shows feedback_hold false")
        self.feedback_hold = False
        self.resume_mode = Mode.HOLD

    def begin_track(self, traj: Trajectory, q: np.ndarray, rate: float, cycles: int) -> None:
        """Enter TRACK along ``traj`` (the drives are in CSP, the arm held at its start)."""
        why = self.motion_refusal()
        if why is not None:
            raise ValueError(f"{traj.label}: refused: {why}")
        self.track.begin(traj, self.t, q, rate, cycles)
        self.set_mode(Mode.TRACK)

    def end_track(self, outcome: str, q: np.ndarray, hold_at_ref: bool = True, ramp_s: float | None = None) -> None:
        """Leave TRACK for HOLD (at the reference, or where the arm is; the hold's law in over ``ramp_s``, default
        the mode ramp); the daemon returns the drives to CST."""
        self.q_hold[:] = self.track.q_ref if hold_at_ref else q
        cycle = self.track.cycle
        tr = self.track.end()
        self.set_mode(Mode.HOLD, ramp_s=ramp_s)
        self.events.append(Event("track_end", self.t, text=outcome,
                                 fields={"label": tr.label if tr else None, "cycle": cycle}))

    def feedback(self, worst_stale: int, worst_joint: int, node_id: int, q: np.ndarray, hold_after: int,
                 disable_after: int) -> None:
        """Stale TPDOs: hold after ``hold_after`` cycles, fault after ``disable_after``; resume when fresh."""
        if worst_stale <= 1:  # a single late TPDO is jitter, not lost feedback: it does not restart the count
            self.fresh_cycles += 1
        else:
            self.fresh_cycles = 0
        if worst_stale >= disable_after and self.mode not in (Mode.IDLE, Mode.FAULT):
            self.fault(worst_joint, f"feedback lost: no TPDO from node {node_id} for {worst_stale} cycles")
            self.feedback_hold = False
        elif worst_stale >= hold_after and self.mode == Mode.DRAG:
            self.feedback_hold = True
            self.feedback_holds += 1
            self.resume_mode = self.mode
            self.q_hold[:] = q
            self.set_mode(Mode.HOLD)
        elif self.feedback_hold and self.mode == Mode.HOLD and self.fresh_cycles >= self.fresh_cycles_resume:
            self.feedback_hold = False
            self.set_mode(self.resume_mode)

    # ------------------------------------------------------------------------------------------ the cycle

    def advance(self, est: Estimate, stale_max: int) -> None:
        """The mode's state for this cycle (before the drives are supervised): the latch, the motion's clock.

        ``t`` (the cycle's time) is set by the cycle's tick."""
        t = self.t
        if self.contact is not None:
            if self.contact.code == ONSET:
                self._contact_react(est)
            elif self._contact_after_stop and self.mode != Mode.TRACK:
                self._contact_stopped()
            elif self._contact_drag_pending:
                self._contact_drag_when_cst()
        self._permission_step(est)
        if self.mode == Mode.HOLD:
            self._hold_step(est)
        if self.mode == Mode.DRAG and self.params.use_breakout and self.params.use_startup:
            self.drag_law.breakout(est.q_rad, est.dq_rad_s, t, self.params, est.tau_g_Nm)
        if self.track.active and self.mode == Mode.TRACK:
            res = self.track.step(t, est.q_rad, est.dq_rad_s, est.current_A, stale_max)
            if isinstance(res, Trip):
                self.events.append(Event("protective_stop", t, res.joint, res.text, fields={"kind": res.kind}))
                self.end_track(f"{res.kind}: {res.text}", est.q_rad, hold_at_ref=False)
            elif res is not None and self.track.state == "quick_stop":  # a contact's stop: held where it rests
                self.end_track(res, est.q_rad, hold_at_ref=False, ramp_s=self.guard_hold_ramp_s)
            elif res is not None:
                self.end_track(res, est.q_rad)

    def _hold_step(self, est: Estimate) -> None:
        """HOLD: move the hold pose toward ``hold_move`` at ``hold_move_speed``; average the measured current
        while the arm rests (``hold_current_A``, the effort that truly holds it, for the gravity check)."""
        if self.hold_move is not None:
            step = self.hold_move_speed * self.dt
            np.subtract(self.hold_move, self.q_hold, out=self._tmp)
            np.abs(self._tmp, out=self._tmp2)
            if float(self._tmp2.max()) <= step:
                self.q_hold[:] = self.hold_move  # arrived (exactly: the estimate waits for equality)
            else:
                np.clip(self._tmp, -step, step, out=self._tmp)
                self.q_hold += self._tmp
        if self.blend_t0 >= 0.0 or (self.hold_move is not None and not np.array_equal(self.q_hold, self.hold_move)):
            self.hold_rest_s = 0.0
            return
        # at rest: the velocity estimate below 0.03 rad/s (encoder quantisation and sampling jitter make ~0.01)
        # and the pose within 1 mrad of where the rest began
        np.abs(est.dq_rad_s, out=self._tmp)
        moving = float(self._tmp.max()) > 0.03
        if not moving and self.hold_rest_s > 0.0:
            np.subtract(est.q_rad, self.hold_rest_q, out=self._tmp)
            np.abs(self._tmp, out=self._tmp)
            moving = float(self._tmp.max()) > 1e-3
        if moving:
            self.hold_rest_s = 0.0
            return
        if self.hold_rest_s == 0.0:
            self.hold_current_A[:] = est.current_A
            self.hold_rest_q[:] = est.q_rad
        else:  # running mean over the rest so far (exact average, no time constant to tune)
            k = self.dt / (self.hold_rest_s + self.dt)
            np.subtract(est.current_A, self.hold_current_A, out=self._tmp)
            self._tmp *= k
            self.hold_current_A += self._tmp
        self.hold_rest_s += self.dt

    def compute(self, est: Estimate, enabled: np.ndarray) -> None:
        """``cmd_A`` ← the mode's command (+ safety terms), blended, zero where a drive is not enabled;
        ``ref_rad`` ← the position reference."""
        cmd = self.cmd_A
        self.safety.compute(est.q_rad, est.dq_rad_s, self.mode == Mode.DRAG, self.extra_A)
        self._mode_command(est, cmd)
        if self.blend_t0 >= 0.0:
            x = (self.t - self.blend_t0) / self.blend_ramp_s if self.blend_ramp_s > 0.0 else 1.0
            if x >= 1.0:
                self.blend_t0 = -1.0
            else:
                lam = x * x * (3.0 - 2.0 * x)
                # blend from the command at the switch instant to the new law's command
                cmd *= lam
                np.multiply(self.blend_from_A, 1.0 - lam, out=self._tmp)  # no temporary array in the cycle
                cmd += self._tmp
        if self.stop_after_hold_at is not None and self.t >= self.stop_after_hold_at:
            self.stop_after_hold_at = None
            self.set_mode(Mode.IDLE, blend=False)
        cmd *= enabled  # nothing is commanded to a drive that is not enabled
        if self.guard is not None and self.mode == Mode.DRAG and est.p_Nms is not None:
            self._guard_step(est, cmd)
        self.prev_cmd_A[:] = cmd
        if np.count_nonzero(self.law_out.clamped):
            self.clamp_cycles += 1
        # the position reference: TRACK the path; HOLD with the drives still in CSP (after a motion) the hold pose,
        # so the drive's own loop keeps pulling to the same point until it is back in CST; otherwise where it is
        if self.mode == Mode.TRACK:
            self.ref_rad[:] = self.track.q_ref
        elif self.mode == Mode.HOLD and self.drive_csp:
            self.ref_rad[:] = self.q_hold
        else:
            self.ref_rad[:] = est.q_rad

    def _guard_step(self, est: Estimate, cmd: np.ndarray) -> None:
        """The runaway guard (DRAG, once the law is fully in): a trip holds where the arm is (fast ramp)."""
        g = self.guard
        assert g is not None and est.p_Nms is not None
        if not g.armed:
            if self.blend_t0 < 0.0:
                g.arm(est.p_Nms, self.t)
            return
        lo = self.law_out  # τ_in = K_t·(I − gravity − offset − friction − start-up − effects), into _tau_in
        trip = g.update_from_command(self.t, est.q_rad, est.dq_rad_s, est.p_Nms, cmd, lo.gravity_A,
                                     self.gravity_offset_A, lo.friction_A, lo.startup_A,
                                     lo.effects_A if self.params.effects is not None else None, self.kt,
                                     self._tau_in)
        if trip is None:
            return
        self.guard_trips += 1
        self.last_trip = {"t_s": round(self.t, 4), "joint": self.names[trip.joint], "residual_Nm": round(trip.residual_Nm, 3),
                          "residual_A": round(trip.residual_A, 3), "speed_rad_s": round(trip.speed_rad_s, 4),
                          "payload_kg": None if trip.payload_kg != trip.payload_kg else round(trip.payload_kg, 3),
                          "unexplained": round(trip.unexplained, 3), "q_rad": est.q_rad.tolist()}
        self.events.append(Event("protective_stop", self.t, trip.joint, trip.text,
                                 fields={"kind": "runaway", **self.last_trip}))
        self.q_hold[:] = est.q_rad
        self.set_mode(Mode.HOLD, ramp_s=self.guard_hold_ramp_s)
        # hold with the missing torque the observer measured (the PD alone would sag by r/k_p)
        np.divide(g.r_f, self.kt, out=self._tmp)
        self.gravity_offset_A -= self._tmp  # the residual drives the motion: hold against it
        np.clip(self.gravity_offset_A, self.neg_limit_A, self.params.current_limit_A, out=self.gravity_offset_A)

    # ------------------------------------------------------------------------------------------ contact

    def contact_want(self) -> str:
        """What the contact detector watches this cycle (and select it): "" nothing, "drag" the residual alone (the
        hand's force), else the mode whose bands and reaction apply: "hold", "track", "identify"."""
        w = self.contact
        if w is None:
            return ""
        mode, why = self.mode, ""
        want = ""
        if not w.enabled:
            why = w.reason
        elif mode == Mode.DRAG:
            want = "drag"
        elif not w.calibrated:
            why = w.reason
        elif mode == Mode.TRACK and self.track.active:
            tr = self.track.trajectory
            want = "identify" if tr is not None and tr.label.startswith("identify") else "track"
        elif mode == Mode.HOLD:
            if self.stop_after_hold_at is not None:
                why = "stopping (the ramp before the drives disable)"
            elif self.feedback_hold:
                why = "feedback hold (stale TPDOs)"
            elif self.gravity_offset_A.any():
                why = "hold with a gravity offset the model lacks (mode drag --accept, a runaway-guard trip)"
            else:
                want = "hold"
        w.select(want, why)
        if w.ended is not None:
            self._contact_ended()
        return want

    def contact_step(self, est: Estimate, C: np.ndarray, stale_max: int) -> None:
        """The estimate step's contact part (after ``contact_want`` and Pinocchio's terms): the detector's update.
        A cycle with stale feedback is skipped (the next one integrates the elapsed time)."""
        w = self.contact
        assert w is not None and est.p_Nms is not None
        if stale_max > 0:
            w.code = 0
            return
        track = self.mode == Mode.TRACK
        w.step(self.t, est.dq_rad_s, est.p_Nms, est.current_A, est.tau_g_Nm, C, self.blend_t0 < 0.0,
               self.track.dq_ref if track else None)
        if w.ended is not None:
            self._contact_ended()

    def _contact_ended(self) -> None:
        w = self.contact
        assert w is not None and w.ended is not None
        self.events.append(Event("contact_end", self.t, fields={**w.ended, "names": [self.names[j] for j in
                                                                                      w.ended["joints"]]}))
        w.ended = None

    def _contact_react(self, est: Estimate) -> None:
        """An onset: the mode's reaction (``contact.<mode>.reaction``) and the fault entry. Rare path.

        A motion first comes to a protective stop (``Track.quick_stop``: from the arm's state to rest, bounded
        deceleration and jerk, the position loops holding it on that profile) and ends there into HOLD; a retract
        or a compliant reaction follows once it has (``_contact_stopped``). A held arm holds where it is now."""
        w = self.contact
        assert w is not None
        mode = w.watching
        reaction = w.modes[mode].reaction
        note = ""
        stopping = self.mode == Mode.TRACK and self.track.active and self.track.state == "quick_stop"
        if stopping:  # another onset while the motion stops from the first: recorded, the stop goes on
            reaction, note = "stop", "the motion is already stopping from a contact"
        if reaction == "compliant":
            refusal = self.drag_refusal()
            if refusal is not None:
                reaction, note = "stop", f"compliant refused: {refusal}"
        if reaction == "retract":
            sf = self.safety
            if not w.retract_step(est.q_rad, sf.wall_lo_rad, sf.wall_hi_rad, self._contact_target):
                reaction, note = "stop", "retract: no joint carries the contact"
            else:
                self._contact_target -= est.q_rad  # the step back, applied from where the arm comes to rest
        dom, text, fields = w.onset_record(self.names, reaction, note)
        self.contact_stops += 1
        if self.track.active and self.mode == Mode.TRACK and not stopping:
            T = self.track.quick_stop(self.t, est.q_rad, est.dq_rad_s, self.contact_stop_decel_rad_s2,
                                      self.contact_stop_jerk_rad_s3, f"contact: {text}")
            fields["stop_s"] = round(T, 4)
            self._contact_after_stop = reaction
        elif self.mode == Mode.HOLD:
            self.q_hold[:] = est.q_rad  # hold where it is now (the hold no longer springs back into the contact)
            self.hold_move = None
            self._contact_after_stop = reaction
        self.events.append(Event("protective_stop", self.t, dom, text, fields=fields))
        if self._contact_after_stop and self.mode != Mode.TRACK:
            self._contact_stopped()

    def _contact_stopped(self) -> None:
        """The arm has come to rest after a contact (the motion's protective stop ended into HOLD): the reaction's
        second part — retract: a hold move back along the residual from where it rests; compliant: drag."""
        reaction, self._contact_after_stop = self._contact_after_stop, ""
        if self.mode != Mode.HOLD:
            return
        if reaction == "retract":
            sf = self.safety
            np.add(self._contact_target, self.q_hold, out=self._contact_target)
            np.clip(self._contact_target, sf.wall_lo_rad, sf.wall_hi_rad, out=self._contact_target)
            self.hold_move = self._contact_target.copy()
            self.hold_move_speed = self.contact.retract_speed_rad_s if self.contact is not None else 0.1
        elif reaction == "compliant":
            self._contact_drag_pending = True
            self._contact_drag_when_cst()

    def _contact_drag_when_cst(self) -> None:
        """The compliant reaction: DRAG once the drives are back in torque mode (CST) after a motion, if drag is
        still permitted then; else the arm stays held."""
        if self.mode != Mode.HOLD or self.drive_csp:
            return
        refusal = self.drag_refusal()
        self._contact_drag_pending = False
        if refusal is not None:
            self.events.append(Event("protective_stop", self.t, None, f"contact: compliant refused: {refusal}; held",
                                     fields={"kind": "contact", "reaction": "stop", "note": refusal}))
            return
        self.set_mode(Mode.DRAG)

    # --- drag permission and the hand's inputs (#30; docs/HAND.md) --------------------------------------------------

    def set_hand(self, hand: HandInputs | None) -> None:
        """The guiding device's inputs (the daemon builds them with the drives' objects and TPDO timing)."""
        self.hand = hand
        self.permission.hand = hand

    def drag_refusal(self) -> str | None:
        """None when DRAG may be entered now, else why not (a constant string: safe inside the cycle). What a
        contact reaction asks before it drags (#29), and what ``mode drag`` and the enabling switch's press ask."""
        return self.permission.refusal()

    def motion_refusal(self) -> str | None:
        """None unless a stop input holds the arm (no motion, stream or hold move may start)."""
        return self.hand.stop_refusal() if self.hand is not None else None

    def _admit_drag(self, lease: int, by_enable: bool = False) -> None:
        """A drag request: refused (ValueError) without the permission; bound to ``lease`` when it names the active
        one (a lease that is not active is refused: its client believes it holds drag and would not). Where a lease
        is required, a client's request must name it; the enabling switch's press drags on the active one."""
        why = self.drag_refusal()
        if why is not None:
            raise ValueError(f"mode drag: refused: {why}")
        ls = self.permission.lease
        if lease:
            if lease != ls.id or not ls.active:
                raise ValueError(f"mode drag: refused: lease {lease} is not the active lease "
                                 f"({ls.status(self.t)['state']} lease {ls.id or 'none'}); open a new one")
            self.drag_lease = lease
        elif self.permission.needs_lease:
            if not by_enable:
                raise ValueError(f"mode drag: refused: drag.require is '{self.permission.require}': the request must "
                                 f"name the lease its client holds (field 'lease'; 'dragd mode drag --hold')")
            self.drag_lease = ls.id  # (active: the refusal said so) the enabling switch's press with `both`
        else:
            self.drag_lease = 0

    def _permission_step(self, est: Estimate) -> None:
        """The cycle: the hand's inputs, the lease's deadline; DRAG (or a feedback hold that would return to it) ends
        into HOLD the cycle its permission goes; a stop input ends motions and hold moves."""
        t = self.t
        hand = self.hand
        if hand is not None and est.inputs is not None and est.inputs_age is not None:
            hand.update(t, est.inputs, est.inputs_age)
            if hand.stop_active and not self._stop_input:
                self._stop_pressed(est.q_rad)
            self._stop_input = hand.stop_active
        ls = self.permission.lease
        if ls.step(t):
            self.events.append(Event("lease", t, text=f"drag lease {ls.id} of '{ls.holder}' lapsed: no renewal for "
                                                      f"{t - ls.renewed_t:.3f} s (period {ls.period_s:g} s)",
                                     fields={"action": "lapsed", "lease": ls.id, "holder": ls.holder,
                                             "since_renewal_s": round(t - ls.renewed_t, 4)}))
        if self._brake_t0 >= 0.0:
            self._brake_step(est)
        if self.mode != Mode.DRAG and not (self.feedback_hold and self.resume_mode == Mode.DRAG):
            return
        why = self.drag_refusal()
        if why is None and self.drag_lease and (ls.id != self.drag_lease or not ls.active):
            why = R_LEASE_LAPSED if ls.state == "lapsed" else R_LEASE_CLOSED
        if why is not None:
            self.end_drag(why, est.q_rad)

    def end_drag(self, why: str, q: np.ndarray) -> None:
        """Out of DRAG into HOLD where the arm is, blended over ``drag_exit_ramp_s`` (no jump in current); a
        feedback hold returns to HOLD instead of drag."""
        if self.feedback_hold:
            self.resume_mode = Mode.HOLD
        else:
            self.q_hold[:] = q
            self.set_mode(Mode.HOLD, ramp_s=self.drag_exit_ramp_s)
            if self.drag_exit_brake_s > 0.0 and float(self.drag_exit_kd.max()) > self._hold_kd_cfg:
                self._brake_t0 = self.t
                self.hold_kd = self.drag_exit_kd
        lease = self.drag_lease
        self.drag_lease = 0
        self.drag_ends += 1
        self.last_drag_end = {"t_s": round(self.t, 4), "reason": why, "q_rad": q.tolist(), "lease": lease or None}
        self.events.append(Event("drag_end", self.t, text=why, fields={"lease": lease or None}))

    def _brake_step(self, est: Estimate) -> None:
        """The exit brake: the hold's pose follows the arm (no spring back through it) under the strong damping
        until the arm rests or ``drag_exit_brake_s`` passed; then the hold's own gains where it is."""
        np.abs(est.dq_rad_s, out=self._tmp)
        if self.mode != Mode.HOLD or self.t - self._brake_t0 >= self.drag_exit_brake_s or float(self._tmp.max()) < 0.01:
            self._brake_t0 = -1.0
            self.hold_kd = self._hold_kd_cfg
        else:
            self.q_hold[:] = est.q_rad

    def _stop_pressed(self, q: np.ndarray) -> None:
        """A stop input: a motion ends where the arm is (protective stop), a hold move stops; DRAG ends through the
        permission (the same cycle)."""
        why = self.motion_refusal() or "the stop button is pressed"
        if self.mode == Mode.TRACK and self.track.active:
            self.events.append(Event("protective_stop", self.t, None, why, fields={"kind": "stop_input"}))
            self.end_track(f"stop_input: {why}", q, hold_at_ref=False)
        elif self.mode == Mode.HOLD and self.hold_move is not None:
            self.hold_move = None

    # --- end of drag permission ---------------------------------------------------------------------------------

    def _mode_command(self, est: Estimate, out: np.ndarray) -> None:
        mode = self.mode
        if mode in (Mode.IDLE, Mode.FAULT):
            out.fill(0.0)
            return
        if mode == Mode.DRAG:
            self.extra_A += self.gravity_offset_A  # `mode drag --accept` (zero otherwise)
            self.drag_law.compensate(est.tau_g_Nm, est.dq_rad_s, self.t, self.params, self.extra_A, est.q_rad)
            out[:] = self.law_out.current_A
            return
        if mode == Mode.TRACK:
            self.track.command(est.tau_g_Nm, self.params, out, self._tmp2)
        else:  # HOLD: gravity + joint PD around the pose (+ an accepted / measured gravity offset)
            np.subtract(self.q_hold, est.q_rad, out=out)
            out *= self.hold_kp
            np.multiply(est.dq_rad_s, self.hold_kd, out=self._tmp2)
            out -= self._tmp2
            out += est.tau_g_Nm
            out /= self.kt
            out += self.gravity_offset_A
        out += self.extra_A
        np.minimum(out, self.params.current_limit_A, out=out)
        np.maximum(out, self.neg_limit_A, out=out)
