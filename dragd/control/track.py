"""TRACK mode: the trajectory clock, the reference it samples, the position loops and the monitors.

The drives follow the reference with their own position loops (CSP); the command current is the torque offset
that feeds gravity, friction and the planned motion's inertia forward (``Track.command``). The clock runs at a
rate (speed override, pause, controlled stop: all smoothstep ramps along the path, never a jump), repeats the
trajectory's body, and waits rather than jumping ahead after a stalled loop. A replay adds a PD + integral loop on
q_ref − q around the drives' own loops. Joints whose drives follow motions in CST (``cst``: a drive without a torque
offset, whose CSP would ignore the feed-forward) have dragd's loop as their only position loop, with full authority.
The monitors (tracking error, residual current, position limits) end the motion with a protective stop; the
residual compares the measured current with the model's feed-forward, never with a position loop's output.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dragd.control.law import Workspace, friction_current
from dragd.control.params import LawParams
from dragd.control.trajectory import Trajectory

GRACE_S = 0.05  # after a long loop stall the monitors count only at twice their bounds for this long
CST_FADE_S = 0.2  # a CST joint's integral fades with this time constant while its reference rests
MOVING_RAD_S = 0.005  # a joint's reference moves (its loop's integral learns) above this speed
QUICK_STOP_MIN_S = 0.02  # a protective stop's deceleration takes at least this long (a slow arm: a smooth catch)
QUICK_STOP_REST_RAD_S = 0.01  # ... and ends once every joint is slower than this after the profile: held there at
QUICK_STOP_REST_S = 0.0  # once (a contact's rebound caught at its turning point: no return into the contact)
QUICK_STOP_SETTLE_S = 0.5  # ... or this long after the profile (a contact that keeps pushing)


@dataclass(frozen=True)
class TrackLimits:
    """Per-joint bounds and gains of TRACK (from the configuration's ``replay`` section)."""

    tracking_error_rad: np.ndarray
    residual_current_A: np.ndarray
    residual_filter_alpha: float
    acceleration_rad_s2: np.ndarray
    kp_Nm_per_rad: np.ndarray
    kd_Nm_s_per_rad: np.ndarray
    ki_Nm_per_rad_s: np.ndarray
    integral_max_Nm: np.ndarray
    output_max_Nm: np.ndarray
    ramp_s: float
    monitor_cycles: int
    position_lo_rad: np.ndarray
    position_hi_rad: np.ndarray


@dataclass(frozen=True)
class CstLoop:
    """Gains of dragd's position loop for the joints whose drives follow motions in CST (``replay.cst_*``)."""

    kp_Nm_per_rad: np.ndarray
    kd_Nm_s_per_rad: np.ndarray
    ki_Nm_per_rad_s: np.ndarray
    integral_max_Nm: np.ndarray


@dataclass(frozen=True)
class Trip:
    """A monitor that ended the motion: which, on which joint, and what it saw."""

    kind: str  # tracking_error | residual_current | soft_limit
    joint: int
    text: str


class Track:
    """State of the motion in TRACK (one at a time); all arrays preallocated, ``step`` allocation-free."""

    def __init__(self, n: int, dt_s: float, limits: TrackLimits, joint_names: list[str]) -> None:
        self.n, self.dt, self.lim, self.names = n, dt_s, limits, joint_names
        self.trajectory: Trajectory | None = None
        self.tau = 0.0  # trajectory time
        self.rate = 1.0  # the clock's rate (d tau / dt)
        self.override = 1.0  # the speed override the clock returns to after a pause
        self.state = "idle"  # running | pausing | paused | stopping | quick_stop | idle
        self.cycles = 1  # repetitions of the trajectory's body (0: until stopped)
        self.cycle = 0
        self.t_prev = 0.0
        self._rate_from = 1.0
        self._rate_target = 1.0
        self._rate_t0 = -1.0
        self.rate_T = 1.0
        self.q_ref = np.zeros(n)
        self.dq_ref = np.zeros(n)
        self.ff_Nm = np.zeros(n)  # inertial feed-forward of the trajectory sample
        self.pred_A = np.zeros(n)  # the model's current for the commanded motion (residual monitor)
        self.pred_extra_Nm = np.zeros(n)  # rigid-body effort predicted but not commanded (plain tracks)
        self.residual_A = np.zeros(n)  # measured − predicted, low-pass filtered
        self.error_rad = np.zeros(n)
        self.pid_Nm = np.zeros(n)
        self.int_Nm = np.zeros(n)
        self.start_offset = np.zeros(n)
        self.start_blend_s = 0.0
        self.full_friction = False  # replay plans: the full friction belief and the position loop
        self.cst = np.zeros(n, dtype=bool)  # joints whose drives follow motions in CST (set from their profiles)
        self.cst_loop: CstLoop | None = None
        self.loop_on = False  # a position loop runs this motion (a replay's, or a CST joint's)
        # the position loop's per-joint gains for this motion (a CST joint's; a replay's outer loop; or none)
        self._kp, self._kd, self._ki = np.zeros(n), np.zeros(n), np.zeros(n)
        self._int_max, self._out_max = np.zeros(n), np.zeros(n)
        self._gate = np.zeros(n)  # the integral learns while |q_ref − q| is below this
        self._fade = np.ones(n)  # ... and is multiplied by this each cycle while the reference rests
        self._ref_moving = np.zeros(n, dtype=bool)
        self._moving = np.zeros(n, dtype=bool)
        self._small = np.zeros(n, dtype=bool)
        self._over = np.zeros(n, dtype=bool)
        self._err_count = 0
        self._res_count = 0
        self._lim_count = 0
        self._grace_until = -1.0
        self._a = np.zeros(n)
        self._b = np.zeros(n)
        self._ws = Workspace(n)
        # the protective stop after a contact (quick_stop): from the arm's state at the detection to rest
        self._qs_q0 = np.zeros(n)
        self._qs_v0 = np.zeros(n)
        self._qs_t0 = 0.0
        self._qs_rest_t0 = -1.0
        self.quick_stop_T = 0.0
        self._qs_outcome = ""

    @property
    def active(self) -> bool:
        return self.trajectory is not None

    def use_cst(self, joints: np.ndarray, loop: CstLoop) -> None:
        """The joints whose drives follow motions in CST, and dragd's position loop for them."""
        self.cst[:] = joints
        self.cst_loop = loop

    def _loop_gains(self) -> None:
        """This motion's position loop per joint: a CST joint's (full authority, an integral that learns while the
        reference moves within half the tracking bound and fades at rest), a replay's outer loop around the drive's
        CSP loop (bounded authority, integral frozen at rest), or none."""
        lim, c, outer = self.lim, self.cst, self.full_friction
        for dst, cst_v, csp_v in ((self._kp, "kp_Nm_per_rad", lim.kp_Nm_per_rad),
                                  (self._kd, "kd_Nm_s_per_rad", lim.kd_Nm_s_per_rad),
                                  (self._ki, "ki_Nm_per_rad_s", lim.ki_Nm_per_rad_s),
                                  (self._int_max, "integral_max_Nm", lim.integral_max_Nm)):
            dst[:] = csp_v if outer else 0.0
            if self.cst_loop is not None:
                np.copyto(dst, getattr(self.cst_loop, cst_v), where=c)
        self._out_max[:] = lim.output_max_Nm if outer else 0.0
        np.copyto(self._out_max, np.inf, where=c)
        self._gate[:] = 0.0035
        np.copyto(self._gate, 0.5 * lim.tracking_error_rad, where=c)
        self._fade[:] = 1.0
        np.copyto(self._fade, math.exp(-self.dt / CST_FADE_S), where=c)
        self.loop_on = outer or (self.cst_loop is not None and bool(c.any()))

    # -- starting and ending

    def begin(self, traj: Trajectory, t: float, q: np.ndarray, rate: float, cycles: int) -> None:
        """Start following ``traj`` at time ``t`` from the pose ``q`` (checked by the caller)."""
        self.tau = 0.0
        self.rate = self._rate_from = self._rate_target = self.override = float(rate)
        self._rate_t0 = -1.0
        self.state = "running"
        self.cycles = int(cycles)
        self.cycle = 0
        self.t_prev = t
        self._err_count = self._res_count = self._lim_count = 0
        self.residual_A.fill(0.0)
        self.ff_Nm.fill(0.0)
        self.pred_extra_Nm.fill(0.0)
        self.pid_Nm.fill(0.0)
        self.int_Nm.fill(0.0)
        traj.sample(0.0, self.q_ref)
        # a replay's move to start begins exactly where the arm is: the small difference to the planned start
        # fades out over the move (no step in the position target)
        np.subtract(q, self.q_ref, out=self.start_offset)
        self.start_blend_s = traj.body_start_s if traj.body_start_s > 0.0 else 0.0
        if self.start_blend_s > 0.0:
            self.q_ref += self.start_offset
        self.dq_ref.fill(0.0)
        self.full_friction = traj.dq_table is not None  # replay plans; identification tracks as before
        self._loop_gains()
        self.trajectory = traj

    def end(self) -> Trajectory | None:
        tr, self.trajectory = self.trajectory, None
        self.state = "idle"
        self.ff_Nm.fill(0.0)
        return tr

    # -- the clock: speed override, pause / resume / controlled stop (all decelerate along the path)

    def _ramp_rate(self, target: float, t: float) -> None:
        """Ramp the clock's rate to ``target`` (smoothstep), slower when the path is fast."""
        tr = self.trajectory
        delta = abs(target - self.rate)
        T = self.lim.ramp_s * max(delta, 0.25)
        if tr is not None and tr.dq_table is not None:
            # the extra acceleration q'(τ)·dr/dt stays within half the configured acceleration limit
            tr.row(tr.dq_table, self._a)
            np.abs(self._a, out=self._a)
            need = 1.5 * delta * float(np.max(self._a / self.lim.acceleration_rad_s2)) / 0.5
            T = max(T, need)
        self._rate_from = self.rate
        self._rate_target = float(target)
        self._rate_t0 = t
        self.rate_T = max(T, 0.02)

    def pause(self, t: float) -> str:
        if self.state in ("stopping", "quick_stop"):
            raise ValueError("pause: the motion is stopping")
        if self.state == "running":
            self.state = "pausing"
            self._ramp_rate(0.0, t)
        return self.state

    def resume(self, t: float) -> str:
        if self.state in ("stopping", "quick_stop"):
            raise ValueError("resume: the motion is stopping")
        if self.state in ("pausing", "paused"):
            self.state = "running"
            self._ramp_rate(self.override, t)
        return self.state

    def stop(self, t: float) -> str:
        """Controlled stop: decelerate along the path, then hold where the path stopped."""
        if self.state not in ("stopping", "quick_stop"):
            self.state = "stopping"
            if self.rate > 0.0:
                self._ramp_rate(0.0, t)
            else:
                self._rate_t0 = -1.0
        return self.state

    def set_override(self, speed: float, t: float) -> None:
        self.override = float(speed)
        if self.trajectory is not None and self.state == "running":
            self._ramp_rate(self.override, t)

    # -- the protective stop after a contact: from where the arm is, bounded jerk, within the stop's deceleration

    def quick_stop(self, t: float, q: np.ndarray, dq: np.ndarray, decel_rad_s2: np.ndarray, jerk_rad_s3: np.ndarray,
                   outcome: str) -> float:
        """Leave the path: the reference starts at the arm's state (``q``, ``dq``) — no step for the loops, nothing
        that pushes on into the contact — and brings every joint to rest together in T with the velocity
        v(t) = v₀·(1 − s(t/T)), s the smoothstep: the deceleration 6x(1−x)·v₀/T starts and ends at zero and peaks at
        1.5·v₀/T ≤ ``decel_rad_s2``, the jerk ≤ 6·v₀/T² ≤ ``jerk_rad_s3``; the stop takes v₀·T/2. dragd's
        position loop holds every joint on it beside the drive's own (an identification track has none otherwise)
        with the full-authority gains of replay.cst_* (the replay's outer loop is bounded to 0.6 A: too little
        against a contact), the integral frozen. Ends (``outcome``) once every joint is slower than
        QUICK_STOP_REST_RAD_S after the profile (at most QUICK_STOP_SETTLE_S later); the controller then holds the
        arm where it rests, taking over within ``safety.guard.hold_ramp_s``: a contact that displaced the arm is not
        undone by the loop's spring pulling it back (into the contact). Returns T. Rare path."""
        v = np.abs(dq)
        T = max(QUICK_STOP_MIN_S, float(np.max(1.5 * v / decel_rad_s2)), float(np.max(np.sqrt(6.0 * v / jerk_rad_s3))))
        self._qs_q0[:] = q
        self._qs_v0[:] = dq
        self._qs_t0 = t
        self._qs_rest_t0 = -1.0
        self.quick_stop_T = T
        self._qs_outcome = outcome
        self.state = "quick_stop"
        self._rate_t0 = -1.0
        # the stop holds against the contact with full authority (the drives' current limits clamp the command) and
        # the full-authority loop's damping (replay.cst_*: near critical on the arm's inertia), the integral frozen
        loop = self.cst_loop
        self._kp[:] = loop.kp_Nm_per_rad if loop is not None else self.lim.kp_Nm_per_rad
        self._kd[:] = loop.kd_Nm_s_per_rad if loop is not None else self.lim.kd_Nm_s_per_rad
        self._out_max[:] = np.inf
        self._ki[:] = 0.0
        self._fade[:] = 1.0
        self.loop_on = True
        self.ff_Nm.fill(0.0)
        self.pred_extra_Nm.fill(0.0)
        self._err_count = 0
        return T

    def _quick_stop_step(self, t: float, elapsed: float, q: np.ndarray, dq: np.ndarray, current_A: np.ndarray,
                         stale_max: int) -> str | Trip | None:
        T = self.quick_stop_T
        x = min(max((t - self._qs_t0) / T, 0.0), 1.0)
        np.multiply(self._qs_v0, T * (x - x * x * x + 0.5 * x * x * x * x), out=self.q_ref)
        self.q_ref += self._qs_q0
        np.multiply(self._qs_v0, 1.0 - x * x * (3.0 - 2.0 * x), out=self.dq_ref)
        if x >= 1.0:
            np.abs(dq, out=self._a)
            if float(self._a.max()) >= QUICK_STOP_REST_RAD_S:
                self._qs_rest_t0 = -1.0
            elif self._qs_rest_t0 < 0.0:
                self._qs_rest_t0 = t
            if (self._qs_rest_t0 >= 0.0 and t - self._qs_rest_t0 >= QUICK_STOP_REST_S) or \
                    t - self._qs_t0 - T >= QUICK_STOP_SETTLE_S:
                return self._qs_outcome
        self._position_loop(elapsed, q, dq)
        return self._monitor(t, q, current_A, stale_max)  # (the residual monitor rests: it is the contact)

    # -- one cycle

    def step(self, t: float, q: np.ndarray, dq: np.ndarray, current_A: np.ndarray, stale_max: int) -> str | Trip | None:
        """Advance the clock, sample the reference (+ velocity, feed-forward), run the loop and the monitors.

        Returns "done"/"stopped" when the motion ended, a :class:`Trip` when a monitor stopped it, else None.
        """
        tr = self.trajectory
        assert tr is not None
        elapsed = t - self.t_prev
        self.t_prev = t
        if elapsed > 2.5 * self.dt:
            # the loop stalled (missed cycles): the reference waits instead of jumping ahead along the path, and
            # after a long stall the monitors give the drives' catch-up transient a moment
            if elapsed > 5.5 * self.dt:
                self._grace_until = t + GRACE_S
            elapsed = self.dt
        if self.state == "quick_stop":
            return self._quick_stop_step(t, elapsed, q, dq, current_A, stale_max)
        if self._rate_t0 >= 0.0:
            x = (t - self._rate_t0) / self.rate_T
            if x >= 1.0:
                self.rate = self._rate_target
                self._rate_t0 = -1.0
            else:
                self.rate = self._rate_from + (self._rate_target - self._rate_from) * x * x * (3.0 - 2.0 * x)
        self.tau += self.rate * elapsed
        finished = False
        if self.tau >= tr.duration_s:
            more = self.cycles == 0 or self.cycle + 1 < self.cycles
            if more and self.state != "stopping" and tr.duration_s > tr.body_start_s:
                self.tau -= tr.duration_s - tr.body_start_s
                self.cycle += 1
            else:
                self.tau = tr.duration_s
                finished = True
        if self._rate_t0 < 0.0 and self.rate == 0.0:
            if self.state == "pausing":
                self.state = "paused"
            elif self.state == "stopping":
                finished = True
        self.dq_ref[:] = self.q_ref
        tr.sample(self.tau, self.q_ref)
        if tr.dq_table is not None:
            tr.row(tr.dq_table, self.dq_ref)
            self.dq_ref *= self.rate
        else:
            self.dq_ref -= self.q_ref
            self.dq_ref /= -max(elapsed, self.dt)
        if tr.ff_table is not None:
            tr.row(tr.ff_table, self.ff_Nm)
            self.ff_Nm *= self.rate * self.rate
        if tr.pred_table is not None:
            tr.row(tr.pred_table, self.pred_extra_Nm)
            self.pred_extra_Nm *= self.rate * self.rate
        if self.start_blend_s > 0.0 and self.cycle == 0 and self.tau < self.start_blend_s:
            x = self.tau / self.start_blend_s
            np.multiply(self.start_offset, 1.0 - x * x * (3.0 - 2.0 * x), out=self._a)
            self.q_ref += self._a
            np.multiply(self.start_offset, -6.0 * x * (1.0 - x) / self.start_blend_s * self.rate, out=self._a)
            self.dq_ref += self._a
        if finished:
            return "stopped" if self.state == "stopping" else tr.outcome
        if self.loop_on:
            self._position_loop(elapsed, q, dq)
        return self._monitor(t, q, current_A, stale_max)

    def _position_loop(self, elapsed: float, q: np.ndarray, dq: np.ndarray) -> None:
        """PD + integral on q_ref − q into the command, per joint with this motion's gains (``_loop_gains``).

        Replay, around the drives' own CSP loops: the feed-forward leaves the model's errors (a torque constant
        1-2 % off under 60 N·m of gravity is ≈ 1 N·m) to the drive's position loop, whose stiffness turns them into
        position error. This loop adds stiffness and learns the bias with an integral that only runs while a joint's
        reference moves (kinetic friction; at rest stiction would make it hunt) and is frozen at the stops.
        CST joints: the only position loop; its integral learns friction the same way and fades at rest, where the
        feed-forward (gravity) holds the arm and kinetic friction is gone.
        """
        e, v, pid = self._a, self._b, self.pid_Nm
        np.subtract(self.q_ref, q, out=e)
        np.abs(self.dq_ref, out=v)
        np.greater(v, MOVING_RAD_S, out=self._ref_moving)
        np.abs(e, out=v)  # a large error is a disturbance (or a stall), not a bias to learn
        np.less(v, self._gate, out=self._small)
        np.logical_and(self._ref_moving, self._small, out=self._moving)
        np.multiply(e, self._ki, out=v)
        v *= elapsed
        v *= self._moving
        self.int_Nm += v
        np.copyto(v, self._fade)
        np.copyto(v, 1.0, where=self._ref_moving)
        self.int_Nm *= v
        np.minimum(self.int_Nm, self._int_max, out=self.int_Nm)
        np.negative(self._int_max, out=v)
        np.maximum(self.int_Nm, v, out=self.int_Nm)
        np.multiply(e, self._kp, out=pid)
        np.subtract(self.dq_ref, dq, out=v)
        v *= self._kd
        pid += v
        pid += self.int_Nm
        np.minimum(pid, self._out_max, out=pid)  # a replay's bounded authority: the drive's loop stays in charge
        np.negative(self._out_max, out=v)
        np.maximum(pid, v, out=pid)

    def _monitor(self, t: float, q: np.ndarray, current_A: np.ndarray, stale_max: int) -> Trip | None:
        """Tracking error, residual current and position limits: beyond a bound for ``monitor_cycles`` → trip."""
        lim, a = self.lim, self._a
        k = lim.monitor_cycles
        if stale_max >= 5:  # positions several cycles old (late TPDOs): count again once they are fresh
            self._grace_until = max(self._grace_until, t + 0.03)
        # after a loop stall or late feedback: a bound exceeded counts only at twice the bound (a real collision
        # or blockage still stops the motion; the drives' catch-up transient does not)
        m = 2.0 if t < self._grace_until else 1.0
        np.subtract(q, self.q_ref, out=self.error_rad)
        np.abs(self.error_rad, out=a)
        a /= lim.tracking_error_rad
        if a.max() > m:
            self._err_count += 1
            if self._err_count >= k:
                j = int(a.argmax())
                return Trip("tracking_error", j, f"tracking error of {self.names[j]} "
                                                 f"{math.degrees(abs(self.error_rad[j])):.2f}° beyond "
                                                 f"{math.degrees(lim.tracking_error_rad[j]):.2f}°")
        else:
            self._err_count = 0
        # residual: measured current minus the model's current for the commanded motion (low-pass; the prediction
        # is the previous cycle's command)
        np.subtract(current_A, self.pred_A, out=a)
        a -= self.residual_A
        a *= lim.residual_filter_alpha
        self.residual_A += a
        np.abs(self.residual_A, out=a)
        a /= lim.residual_current_A
        assert self.trajectory is not None
        if a.max() > m and self.trajectory.residual_monitor and self.state != "quick_stop":
            self._res_count += 1
            if self._res_count >= k:
                j = int(a.argmax())
                return Trip("residual_current", j, f"residual current of {self.names[j]} {self.residual_A[j]:+.2f} A "
                                                   f"beyond ±{lim.residual_current_A[j]:.2f} A (collision?)")
        else:
            self._res_count = 0
        np.less(q, lim.position_lo_rad, out=self._over)
        over = np.count_nonzero(self._over) > 0
        np.greater(q, lim.position_hi_rad, out=self._over)
        if over or np.count_nonzero(self._over):
            self._lim_count += 1
            if self._lim_count >= k:
                np.subtract(lim.position_lo_rad, q, out=a)
                np.maximum(a, q - lim.position_hi_rad, out=a)
                j = int(a.argmax())
                return Trip("soft_limit", j, f"{self.names[j]} at {q[j]:.3f} rad outside its limits "
                                             f"[{lim.position_lo_rad[j]:.3f}, {lim.position_hi_rad[j]:.3f}]")
        else:
            self._lim_count = 0
        return None

    # -- the command

    def command(self, tau_g_Nm: np.ndarray, p: LawParams, out: np.ndarray, tmp: np.ndarray) -> None:
        """CSP torque offset [A]: gravity + friction at the reference velocity + the planned motion's inertia
        (+ the replay's position loop); ``pred_A`` ← the model's current for the commanded motion."""
        friction_current(self.dq_ref, p, out, self._ws)
        if 0.0 < p.friction_scale != 1.0:
            # replay and CST joints: the full belief (the drag law's under-compensation guards a released joint
            # against run-away; in a motion it would only leave more to the position loop)
            if self.full_friction:
                out /= p.friction_scale
            elif self.loop_on:
                np.divide(out, p.friction_scale, out=out, where=self.cst)
        out *= p.kt_Nm_per_A
        out += self.ff_Nm  # + the planned motion's M(q)q̈ + C(q,q̇)q̇ (replay plans)
        out += tau_g_Nm
        out /= p.kt_Nm_per_A
        np.divide(self.pred_extra_Nm, p.kt_Nm_per_A, out=self.pred_A)
        self.pred_A += out
        if self.loop_on:  # the daemon's position loop: a replay's around the drive's own, a CST joint's alone
            np.divide(self.pid_Nm, p.kt_Nm_per_A, out=tmp)
            out += tmp
