"""The 1 kHz cycle, ticked by its clock (dragd/clock.py: a timerfd at absolute deadlines, or the lockstep clock):

    read      SYNC → every drive's TPDO until all arrived or SYNC + tpdo_deadline_us   (hardware/io.py: BusIO.cycle)
    estimate  implausible jumps rejected, q from counts, q̇ by filtered differentiation,    (here; control/plausible.py,
              measured current, G(q)                                                  control/estimate.py)
    compute   the mode's state and law + safety terms, blended; the CiA 402 walk        (control/controller.py,
                                                                                         hardware/drives.py)
    write     controlwords, torque offsets, CSP targets in the command RPDOs           (hardware/io.py)
    log       one telemetry row to the MCAP writer's ring; timing into histograms      (daemon/recording.py)

``step`` is the synchronous part after the read (what the golden traces replay); ``run`` is the loop. The estimate
and output steps run as compiled kernels (daemon/kernels.py) or as their numpy reference (``loop.compiled: false``),
chosen once when the cycle is built. On the
lockstep clock the read step has no wall deadline: it ends when every TPDO arrived or the simulator's TIME frame
ended the period (what did not arrive by then is late, as a deadline would have judged it). Nothing in
a cycle allocates per cycle on the usual paths, logs, blocks or calls SDO: decisions the cycle makes (faults, mode
changes, the end of a motion) are queued as events and recorded by the daemon after the cycle.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from dragd.clock import Clock, WallClock
from dragd.control.controller import Controller, Estimate
from dragd.control.estimate import VelocityEstimator
from dragd.control.modes import Mode
from dragd.control.plausible import EncoderPlausibility
from dragd.daemon.kernels import kernels
from dragd.hardware.drives import DriveSupervisor, Target
from dragd.hardware.io import BusIO, Feedback
from dragd.hardware.scaling import Scaling
from dragd.model import RobotModel
from dragd.stats import Histogram

if TYPE_CHECKING:
    from dragd.daemon.recording import Recorder

_TARGETS = {Mode.IDLE: Target.DISABLED, Mode.FAULT: Target.QUICK_STOP}
MISSED_LOG = 512  # missed-tick episodes kept for the `missed_ticks` command (a storm of short stalls fits)


class Cycle:
    """One arm's cycle: the estimate, the controller, the drives' supervision and the process data."""

    def __init__(self, io: BusIO, scaling: Scaling, model: RobotModel, controller: Controller,
                 supervisor: DriveSupervisor, velocity: VelocityEstimator, recorder: Recorder, *, rate_Hz: float,
                 tpdo_deadline_us: float, heartbeat_ms: float, stale_cycles_hold: int, stale_cycles_disable: int,
                 node_ids: list[int], plausible_speed_rad_s: float = 6.0, compiled: bool = True,
                 clock: Clock | None = None) -> None:
        n = controller.n
        self.io, self.scaling, self.model = io, scaling, model
        self.controller, self.supervisor, self.velocity, self.recorder = controller, supervisor, velocity, recorder
        self.dt = 1.0 / rate_Hz
        self.clock = clock if clock is not None else WallClock(self.dt)
        self._lockstep = self.clock.lockstep
        self.deadline_s = tpdo_deadline_us * 1e-6
        self.heartbeat_every = max(1, round(heartbeat_ms * 1e-3 / self.dt))
        self._hb_period_s = self.heartbeat_every * self.dt
        self._last_hb_t = -1e9
        self.hold_after, self.disable_after = stale_cycles_hold, stale_cycles_disable
        self.node_ids = node_ids
        self._p_Nms = np.zeros(n)  # the observers' momentum (the estimate's p_Nms)
        self.est = Estimate(np.zeros(n), velocity.velocity_rad_s, np.zeros(n), np.zeros(n), self._p_Nms,
                            inputs=io.feedback.inputs, inputs_age=io.feedback.inputs_age)
        self.target_counts = np.zeros(n, dtype=np.int64)
        self.torque_permille = np.zeros(n, dtype=np.int64)
        self._tmp = np.zeros(n)
        self.t = 0.0
        self.sample_dt_s = self.dt  # interval between this cycle's SYNC and the previous one (the clock's)
        self.cycles = 0
        self.missed = 0
        # the last MISSED_LOG episodes of missed ticks: (CLOCK_MONOTONIC s of the late tick, ticks missed), so a
        # bench can tell the machine's stalls from the daemon's own (dragd/lab/bench/stalls.py)
        self._missed_log = np.zeros((MISSED_LOG, 2))
        self.missed_episodes = 0
        self.late_tpdo = 0
        self.primed = False  # a first full set of positions arrived
        self.exit_requested = False
        self.period_hist = Histogram(0.0, 20_000.0, 10.0)
        self.compute_hist = Histogram(0.0, 5_000.0, 2.0)
        self.rx_hist = Histogram(0.0, 5_000.0, 5.0)
        self.after_cycle: list[object] = []  # callables run after each cycle (the daemon records events)
        self._t_tick = -1.0  # perf_counter at this cycle's tick callback (-1: none yet in this run)
        self._period_us = self.dt * 1e6  # since the previous one (wall: the status histogram)
        self._row_period_us = self.dt * 1e6  # ... as the telemetry row records it (lockstep: the clock's period)
        # the estimate and output steps by compiled kernels (dragd/daemon/kernels.py) or by the numpy reference they
        # are tested against (loop.compiled: false): chosen here, once; ``step`` calls whichever was chosen
        self.decode_inputs: Callable[[Feedback], None] = self._inputs
        self.encode_outputs: Callable[[], None] = self._outputs
        k = kernels() if compiled else None  # (None where numba cannot be imported: the reference)
        # encoder plausibility (control/plausible.py): a sample further from the last accepted one than
        # plausible_speed allows is rejected (treated as a missing TPDO); rejected for stale_cycles_hold cycles in a
        # row, it is an encoder fault
        self.encoders = EncoderPlausibility(scaling.counts_per_rev, self.dt, plausible_speed_rad_s, stale_cycles_hold,
                                            node_ids, controller.fault, None if k is None else k["plausible"])
        if k is not None:
            velocity.use_kernel(k["velocity"])
            self._k_inputs, self._k_outputs = k["inputs"], k["outputs"]
            self.decode_inputs = self._inputs_compiled
            self.encode_outputs = self._outputs_compiled

    def tick(self, period_us: float, expirations: int) -> None:
        """A tick: the cycle's time advances (a late tick samples later and counts the ticks it missed)."""
        if expirations > 1:
            self.missed += expirations - 1
            # the encoder plausibility bound grows with the time since each joint's last accepted sample: the
            # periods this tick slept through count (a stalled host must not make real motion look like a jump)
            self.encoders.skip(expirations - 1)
            # and the feedback's age: a joint already silent counts the periods it stayed silent, so the hold and
            # fault thresholds (stale_cycles_hold / stale_cycles_disable) mean time, not steps (the read step resets
            # every joint that reports this cycle)
            np.add(self.io.feedback.stale, expirations - 1, out=self.io.feedback.stale)
            np.add(self.io.feedback.inputs_age, expirations - 1, out=self.io.feedback.inputs_age)
        self.sample_dt_s = period_us * 1e-6  # SYNC goes out right after the tick: the sampling interval
        self.t += self.dt * expirations
        self.controller.t = self.t  # (commands during the read see the cycle's time)

    def step(self, complete: bool) -> bool:
        """Everything after the read step; False while no full set of positions has arrived yet."""
        io, fb, c, est = self.io, self.io.feedback, self.controller, self.est
        if not complete:
            self.late_tpdo += 1
        if not self.primed:
            if not complete:
                io.statuswords_seen()  # (nothing judges them before the first full set: the newest stands)
                return False  # wait for a first full set of positions before computing anything
            self.velocity.reset(fb.counts)
            self.encoders.prime(fb.counts)
            self.primed = True
        fb.rx_count -= self.encoders.check(fb.counts, fb.rx, fb.stale)
        worst, j = fb.worst_stale()
        c.feedback(worst, j, self.node_ids[j], est.q_rad, self.hold_after, self.disable_after)
        # estimate
        self.decode_inputs(fb)
        self.velocity.update(fb.counts, self.sample_dt_s, fb.rx)
        self.model.gravity_at(est.q_rad, self.t, est.tau_g_Nm)  # (blended while a payload change ramps in)
        watch = c.contact_want()  # the contact observer's mode ("": none)
        if watch or (c.mode == Mode.DRAG and c.guard is not None):
            self.model.momentum(est.q_rad, est.dq_rad_s, self._p_Nms)  # the observers' p = M̄(q)·q̇
        if watch:  # the contact detector (HOLD, TRACK) or, in DRAG, the hand's force: one compiled call after these
            c.contact_step(est, self.model.coriolis(est.q_rad, est.dq_rad_s), worst)
            if watch == "drag" and self.model.grip_frame_id >= 0:
                w = c.contact
                w.grip_force(self.model.grip_jacobian(est.q_rad))  # type: ignore[union-attr]
                self.model.grip_position(w.grip_m)  # type: ignore[union-attr]
        # compute
        c.advance(est, worst)  # (the stalest joint's count: fb.stale.max(), 0 when every TPDO arrived)
        fault = self.supervisor.update(fb.statusword, _TARGETS.get(c.mode, Target.ENABLED), self.t)
        io.statuswords_seen()
        if fault is not None:
            c.fault(*fault)
        c.compute(est, self.supervisor.enabled)
        self.encode_outputs()
        # write
        io.write(self.supervisor.cw, self.target_counts, self.torque_permille, self.t)
        # the master heartbeat by time as well as by count: a loaded host's missed ticks must not stretch it past
        # the drives' consumer time (1016h)
        if self.cycles % self.heartbeat_every == 0 or self.t - self._last_hb_t >= self._hb_period_s - 0.5 * self.dt:
            io.heartbeat()
            self._last_hb_t = self.t
        return True

    def missed_since(self, since: int) -> tuple[list[list[float]], int]:
        """The missed-tick episodes numbered ``since`` on that are still kept, oldest first, as [CLOCK_MONOTONIC s
        of the late tick, ticks missed]; and how many of those numbers were overwritten (more than MISSED_LOG)."""
        n = self.missed_episodes
        first = max(0, since, n - MISSED_LOG)
        rows = [[float(self._missed_log[k % MISSED_LOG, 0]), int(self._missed_log[k % MISSED_LOG, 1])]
                for k in range(first, n)]
        return rows, max(0, n - MISSED_LOG - since)

    # ------------------------------------------------------------------------------------------ estimate, output
    # (each as the compiled kernel and as its numpy reference; __init__ chose one of each)

    def _inputs_compiled(self, fb: Feedback) -> None:
        sc, est = self.scaling, self.est
        self._k_inputs(fb.counts, sc.offset_counts, sc.rad_per_count, est.q_rad, fb.current_permille,
                       sc.A_per_permille, est.current_A)

    def _inputs(self, fb: Feedback) -> None:
        """q [rad] and the motor current [A] from the drive's counts and per mille."""
        self.scaling.position_rad(fb.counts, self.est.q_rad, self._tmp)
        self.scaling.current_A(fb.current_permille, self.est.current_A)

    def _outputs_compiled(self) -> None:
        sc, c = self.scaling, self.controller
        self._k_outputs(c.cmd_A, sc.permille_per_A, self.torque_permille, c.ref_rad, sc.counts_per_rad,
                        sc.offset_counts, self.target_counts)

    def _outputs(self) -> None:
        """The current command → 60B2h per mille, the reference → 607Ah counts."""
        c = self.controller
        self.scaling.torque_permille(c.cmd_A, self.torque_permille, self._tmp)
        self.scaling.target_counts(c.ref_rad, self.target_counts, self._tmp)

    async def run(self) -> None:
        """The loop until ``exit_requested``: tick → read → step → log as one chain of loop callbacks.

        The clock's callback (``_on_tick``) makes the period's one call to the buses, ``BusIO.cycle`` (SYNC out with
        the commands waiting for it, the TPDOs decoded as they come); the bus reader's callback ends the read step
        once the wake-up's frames are decoded, or the deadline timer does, and calls ``_on_feedback`` (step, log):
        two loop wake-ups a cycle and no future or task between them. An exception in either ends the loop and is raised
        here; cancelling this coroutine stops the loop."""
        loop = asyncio.get_running_loop()
        self._loop = loop
        self._done: asyncio.Future[None] = loop.create_future()
        done = self._done
        self._t_tick = -1.0
        clock = self.clock
        try:
            if self._lockstep:
                clock.on_peer_done = self.io.end_read_step  # type: ignore[attr-defined]
                clock.call_each(loop, self._on_tick, self._finish)  # type: ignore[call-arg]
            else:
                clock.call_each(loop, self._on_tick)
            await done
        finally:
            clock.close()
            self.io.abandon_read()
            self.io.flush()

    def request_exit(self) -> None:
        """End ``run`` after the cycle in progress (at the next tick; on the lockstep clock, which ticks only when
        asked, at once when no read step is open)."""
        self.exit_requested = True
        if self._lockstep and not self.io.reading and getattr(self, "_done", None) is not None:
            self._finish(None)

    def _on_tick(self, expirations: int) -> None:
        try:
            if self.io.reading:  # the previous read is still open (its deadline was not served before this tick)
                self.io.end_read_step()
            if self.exit_requested:
                self._finish(None)
                return
            t_tick = time.perf_counter()  # (CLOCK_MONOTONIC on Linux)
            if expirations > 1:
                k = self.missed_episodes % MISSED_LOG
                self._missed_log[k, 0] = t_tick
                self._missed_log[k, 1] = expirations - 1
                self.missed_episodes += 1
            period_us = (t_tick - self._t_tick) * 1e6 if self._t_tick >= 0.0 else self.dt * 1e6
            self._t_tick = t_tick
            self._period_us = period_us
            if self._lockstep:  # the sample interval is the clock's; no wall deadline (the TIME frame ends the read)
                self.tick(self._row_period_us, expirations)
                self.io.cycle(None, self._on_feedback, self._loop)
                return
            self._row_period_us = period_us
            self.tick(period_us, expirations)
            self.io.cycle(self.deadline_s, self._on_feedback, self._loop)
        except Exception as exc:  # the loop must not swallow it: the daemon stops the arm
            self._finish(exc)

    def _on_feedback(self, complete: bool) -> None:
        try:
            t_rx = time.perf_counter()
            self.rx_hist.add((t_rx - self._t_tick) * 1e6)
            if not self.step(complete):
                return
            compute_us = (time.perf_counter() - t_rx) * 1e6
            self.compute_hist.add(compute_us)
            period_us = self._period_us
            if self.cycles > 0:
                self.period_hist.add(period_us)
            self.cycles += 1
            self.recorder.log_row(self._row_period_us, 0.0 if self._lockstep else compute_us)
            for fn in self.after_cycle:
                fn()  # type: ignore[operator]
            if self.exit_requested:
                self._finish(None)
        except Exception as exc:
            self._finish(exc)

    def _finish(self, exc: Exception | None) -> None:
        """End ``run``: no further tick or read step is served."""
        self.exit_requested = True
        done = self._done
        if not done.done():
            if exc is None:
                done.set_result(None)
            else:
                done.set_exception(exc)
