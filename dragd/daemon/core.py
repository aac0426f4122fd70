"""The servo daemon for one arm: wiring and lifecycle. Builds the parts from the configuration, each with what it
uses (never the daemon), runs them, and serves the control socket.

    Daemon ─┬─ Cycle (daemon/cycle.py): read → estimate → compute → write → log, every tick
            │     ├─ BusIO (hardware/io.py), Scaling (hardware/scaling.py), DriveSupervisor (hardware/drives.py)
            │     └─ Controller (control/controller.py): modes, laws, safety terms, blend, motions' reference
            ├─ Master (hardware/master.py): boot and SDO configuration of the drives
            ├─ FaultSink (daemon/faults.py): the controller's events recorded, the fault list, the journal
            ├─ GravityCheck (daemon/gravity.py): the model against the hold current (before drag, at start)
            ├─ Motions (daemon/motion.py): tracks, replays, the drives' CST ↔ CSP switch; Streams (daemon/stream.py)
            ├─ Teaching (daemon/teach.py), Recorder (daemon/recording.py), Guiding (daemon/hand.py)
            ├─ PayloadTools (daemon/payload.py), ModelCheck (daemon/modelcheck.py), CommsMonitor (daemon/comms.py)
            └─ the control socket (dragd/server.py) with the command table it is given (daemon/commands.py)

The cycle's decisions (faults, mode changes, a motion's end) come back as controller events; the fault sink records
them after each cycle and each command and hands each kind to the parts that registered for it (``attach``).
"""

from __future__ import annotations

import asyncio
import gc
import os
import signal
import sys
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any

import can

from dragd.clock import GUARD_S, Clock, LockstepClock, WallClock
from dragd.config import Config, check_joint_names
from dragd.control.controller import Controller
from dragd.control.estimate import VelocityEstimator
from dragd.control.modes import MODE_NAMES, Mode
from dragd.daemon import sdnotify
from dragd.daemon.comms import CommsMonitor
from dragd.daemon.cycle import Cycle
from dragd.daemon.faults import LOG_ERR, LOG_WARNING, FaultSink, print_log
from dragd.daemon.gravity import GravityCheck
from dragd.daemon.hand import Guiding
from dragd.daemon.modelcheck import ModelCheck
from dragd.daemon.motion import Motions, Planner
from dragd.daemon.payload import PayloadTools
from dragd.daemon.recording import Recorder
from dragd.daemon.stream import OFF_CYCLE_COMMANDS, Streams
from dragd.daemon.teach import Teaching
from dragd.hardware.bus import BusSpec, open_bus, parse_bus
from dragd.hardware.drives import STATE_NAMES, DriveSupervisor
from dragd.hardware.io import BusIO
from dragd.hardware.master import Master
from dragd.hardware.pdo import BusLayout
from dragd.hardware.plan import DrivePlan, plan_drives
from dragd.hardware.scaling import Scaling
from dragd.model import RobotModel
from dragd.realtime import CpuLatencyRequest, demote_current_thread, scheduler_label, set_realtime, thread_policies
from dragd.server import ThreadedControlServer

if TYPE_CHECKING:
    from dragd.server import CommandTable

class BusBudgetError(RuntimeError):
    """The configured PDO layout would load a bus beyond its limit."""


def go_realtime(loop: asyncio.AbstractEventLoop, priority: int | None, cpus: list[int] | None,
                lock_memory: bool = False, applied: dict[str, Any] | None = None) -> str:
    """Make the calling (cycle) thread SCHED_FIFO ``priority`` on ``cpus`` where permitted; return what applies.

    Threads started afterwards inherit policy and CPU set, so first the loop's default executor (``run_in_executor
    (None, ...)``, ``asyncio.to_thread``: trajectory resampling, program writes, telemetry open/close) gets threads
    that go below the cycle (SCHED_FIFO 1, off the cycle's CPUs; `demote_current_thread`): a helper at the cycle's
    priority doing seconds of Python would starve it, one at SCHED_OTHER could be preempted holding the GIL.
    With ``lock_memory`` (and a priority) the process's memory is locked (mlockall) where permitted; ``applied``
    receives what set_realtime reports.
    """
    avoid = set(cpus) if cpus else None
    loop.set_default_executor(ThreadPoolExecutor(thread_name_prefix="dragd-exec", initializer=demote_current_thread,
                                                 initargs=(avoid,)))
    info = set_realtime(priority, avoid, lock_memory=lock_memory and priority is not None)
    if applied is not None:
        applied.update(info)
    return scheduler_label(info, priority)


def bus_layouts(cfg: Config, plan: DrivePlan | None = None) -> dict[str, BusLayout]:
    """The PDO layout of every configured bus, planned from the joints' drive profiles; ConfigError listing every
    problem with the drives (their EDS files) at once."""
    from dragd.config import ConfigError

    plan = plan if plan is not None else drive_plan(cfg)
    if plan.errors:
        raise ConfigError(plan.error_text(cfg.source))
    return plan.layouts


def drive_plan(cfg: Config) -> DrivePlan:
    """Profiles and layouts of ``cfg``'s drives (ConfigError for an EDS that cannot be read)."""
    from dragd.config import ConfigError
    from dragd.hardware.profile import ProfileError

    try:
        return plan_drives(cfg, budget_findings=False)
    except ProfileError as exc:
        raise ConfigError(str(exc)) from None


def check_bus_budget(cfg: Config, layouts: dict[str, BusLayout]) -> dict[str, Any]:
    """Worst-case load of every bus from its real PDO layout; BusBudgetError with the numbers if over limit."""
    report: dict[str, Any] = {}
    for b in cfg.buses:
        r = layouts[b.name].budget(cfg.loop.rate_Hz, b.bitrate, b.data_bitrate, 1000.0 / cfg.master.heartbeat_ms)
        report[b.name] = {"load_pct": r.percent, "limit_pct": b.load_limit_pct, "table": r.table()}
        if r.percent > b.load_limit_pct:
            raise BusBudgetError(
                f"{cfg.source}: buses[{cfg.buses.index(b)}] '{b.name}': worst-case bus load {r.percent:.1f} % exceeds "
                f"load_limit_pct {b.load_limit_pct:.0f} % at {cfg.loop.rate_Hz:.0f} Hz "
                f"({'CAN FD' if b.fd else 'classic CAN'} {b.bitrate / 1e6:g} Mbit/s, "
                f"layout '{layouts[b.name].kind}'):\n{r.table()}\n"
                "Use CAN FD, layout 'compact', fewer joints per bus (split buses) or a lower loop.rate_Hz.")
    return report


class Daemon:
    """The servo daemon for one arm. ``await Daemon(cfg).run()`` runs until SIGTERM/SIGINT or ``request_exit``."""

    def __init__(self, cfg: Config, *, bus_override: str | None = None, socket_path: str | None = None,
                 telemetry_path: str | None = None, rerun: bool = False, allow_dirs: list[str] | None = None,
                 log: Callable[[str], None] | None = None, batch_frames: bool = False, lockstep: bool = False,
                 lockstep_guard_s: float = GUARD_S, lab_unguarded_drag: bool = False) -> None:
        """``lockstep``: the cycle runs on the lockstep clock (dragd/clock.py) against ``dragd sim --lockstep``:
        simulated time, advanced by grants (the ``clock`` command) and by the commands that wait for the arm.
        ``lab_unguarded_drag``: drag needs no lease (and no enabling switch where none is wired): a lab's setting,
        which status reports (``drag.require: none`` is accepted only with it)."""
        from dragd.daemon.paths import PathPolicy, allowed_dirs, spool_dir

        if lockstep:  # an SDO answer is late on simulated time only when its peer is silent: the guard's wall time
            cfg = cfg.model_copy(update={"master": cfg.master.model_copy(
                update={"sdo_timeout_s": max(cfg.master.sdo_timeout_s, lockstep_guard_s)})})
        self.cfg = cfg
        self.batch_frames = batch_frames  # udp_multicast: a cycle's command frames leave with the next SYNC
        self.paths = PathPolicy(allowed_dirs(cfg, telemetry_path, allow_dirs))  # where requests may read/write
        self.spool_dir = spool_dir(cfg)  # where clients leave trajectory files (status: spool_dir)
        self.log = log or print_log  # log(text) or log(text, priority)
        self.socket_path = socket_path or cfg.control.socket
        self.bus_specs = self._bus_specs(bus_override)
        self.drives = drive_plan(cfg)  # every joint's drive profile (its EDS) and every bus's PDO layout
        self.layouts = bus_layouts(cfg, self.drives)
        self.budget = check_bus_budget(cfg, self.layouts)
        self.model = RobotModel.from_config(cfg)  # URDF + the params' payload (docs/GAP.md)
        self.model.add_grip(cfg.contact.grip.frame, cfg.contact.grip.offset_m, cfg.source)  # the hand's force in drag
        check_joint_names(cfg, (self.model.joint_names, self.model.urdf_path or cfg.robot.urdf))
        self.n = len(cfg.joints)
        self.node_ids = [j.node_id for j in cfg.joints]
        period_s = 1.0 / cfg.loop.rate_Hz
        self.clock: Clock = (LockstepClock(period_s, [b.name for b in cfg.buses], guard_s=lockstep_guard_s)
                             if lockstep else WallClock(period_s))
        self.scaling = Scaling.from_config(cfg, self.drives.profiles)
        self.controller = Controller.from_config(cfg, self.model.position_limits_rad)
        self.controller.track.cst[:] = [p.motion_mode == "cst" for p in self.drives.profiles]  # (docs/DRIVES.md)
        self.gravity = GravityCheck(cfg, self.model, self.controller)  # the model against the hold current
        if self.controller.guard is not None:
            self.controller.guard.explain = self.gravity.explain_residual
            self.controller.guard.load_free[:] = self.model.load_free_joints()
        self._setup_drag_permission(lab_unguarded_drag)
        self.supervisor = DriveSupervisor(self.node_ids, cfg.master.enable_timeout_s)
        self.velocity = VelocityEstimator(self.scaling.counts_per_rev, cfg.law.velocity_filter_Hz,
                                          self.scaling.direction)
        self.recorder = Recorder(cfg, self.n, telemetry_path or cfg.telemetry.path, rerun or cfg.telemetry.rerun)
        self.fault_sink = FaultSink(self.controller, self.recorder, cfg.joint_names, self.node_ids, self.log)
        self.planner = Planner(set(cfg.loop.cpus or ()), self.clock)  # replays planned, programs written
        self.stop_requested = False
        self.scheduler = "not started"
        self.server: ThreadedControlServer | None = None  # the control socket (set by run)
        self.memory_locked = False  # mlockall applied (loop.lock_memory with loop.realtime_priority)
        self.cpu_latency: CpuLatencyRequest | None = None  # loop.cpu_latency_us's PM QoS request, while held
        self.cpu_latency_status: dict[str, Any] = {"requested_us": None, "applied": False, "reason": "not requested",
                                                   "effective_us": None}  # (without a request object)
        self.master: Master | None = None
        self.buses: dict[str, can.BusABC] = {}
        # built by attach(), on the buses: the cycle and the parts that use it
        self.io: BusIO
        self.cycle: Cycle
        self.motions: Motions
        self.streams: Streams
        self.teaching: Teaching
        self.payload: PayloadTools
        self.model_check: ModelCheck
        self.guiding: Guiding
        self.comms: CommsMonitor

    def _setup_drag_permission(self, lab: bool) -> None:
        """What drag requires (drag.require, or the lab flag) and the hand's inputs, timed by the TPDOs that carry
        them (docs/HAND.md)."""
        import numpy as np

        from dragd.control.hand import HandInputs
        from dragd.control.permission import DragPermission
        from dragd.hardware.plan import inputs_lost_after
        from dragd.hardware.profile import address

        cfg = self.cfg
        if cfg.drag.require == "none" and not lab:
            raise ValueError(f"{cfg.source}: drag.require: 'none' (drag with neither an enabling switch nor a lease) "
                             "is a lab's setting: start the daemon with --lab-unguarded-drag (status reports it), or "
                             "require 'lease', 'enable_input' or 'both'")
        objects = [address(p.inputs.index, p.inputs.sub) if p.inputs is not None else "60FDh"
                   for p in self.drives.profiles.profiles]
        hand = HandInputs.from_config(cfg, objects, np.array(inputs_lost_after(cfg, self.layouts), dtype=np.int64))
        if lab:  # a wired enabling switch still governs drag: its release ends it (a switch that does not is a lie)
            require = "enable_input" if hand is not None and hand.enable is not None else "none"
            self.controller.permission = DragPermission(require, cfg.drag.lease_s, lab=True)
        self.controller.set_hand(hand)

    def _bus_specs(self, override: str | None) -> dict[str, BusSpec]:
        specs = {}
        over = [s for s in (override or "").split(",") if s.strip()]
        if over and len(over) != len(self.cfg.buses):
            raise ValueError(f"--bus: expected {len(self.cfg.buses)} INTERFACE:CHANNEL value(s) "
                             f"(buses {', '.join(b.name for b in self.cfg.buses)}), got {len(over)}")
        for i, b in enumerate(self.cfg.buses):
            base = parse_bus(over[i]) if over else parse_bus(f"{b.interface}:{b.channel}")
            specs[b.name] = type(base)(interface=base.interface, channel=base.channel, bitrate=b.bitrate, fd=b.fd,
                                       data_bitrate=b.data_bitrate)
        return specs

    def attach(self, buses: dict[str, can.BusABC]) -> None:
        """Build the cycle on these (open) buses, and the parts that use it."""
        cfg = self.cfg
        self.buses = buses
        sink = self.fault_sink
        io = self.io = BusIO(self.layouts, buses, self.node_ids, cfg.master.node_id, sink.on_emcy)
        cycle = self.cycle = Cycle(
            io, self.scaling, self.model, self.controller, self.supervisor, self.velocity, self.recorder,
            rate_Hz=cfg.loop.rate_Hz, tpdo_deadline_us=cfg.loop.tpdo_deadline_us, heartbeat_ms=cfg.master.heartbeat_ms,
            stale_cycles_hold=cfg.loop.stale_cycles_hold, stale_cycles_disable=cfg.loop.stale_cycles_disable,
            node_ids=self.node_ids, plausible_speed_rad_s=cfg.safety.encoder_plausible_speed_rad_s,
            compiled=cfg.loop.compiled, clock=self.clock)
        self.recorder.attach(self.controller, cycle.est, io.feedback)
        if isinstance(self.clock, LockstepClock):
            io.on_time = self.clock.peer_time  # the simulator's TIME frames end its periods
            io.expect_lockstep()
            self.recorder.stamp_ns = self.clock.stamp_ns  # telemetry carries the clock's time
            self.clock.gates.append(self.recorder.rings_have_room)  # a row is never dropped for a fast clock
        c, rec = self.controller, self.recorder
        m = self.motions = Motions(cfg, c, cycle, io, self.model, self.scaling, self.planner, self.paths, rec, sink)
        self.streams = Streams(cfg, c, cycle, m, self.model, self.scaling, rec)
        t = self.teaching = Teaching(cfg, c, cycle, m, self.paths, rec, self.log)
        m.replay_refusal = t.replay_refusal
        self.payload = PayloadTools(cfg, c, cycle, self.model)
        self.model_check = ModelCheck(cfg, self.model, c, self.payload)
        g = self.guiding = Guiding(cfg, c, cycle, m, t, rec, sink, self.set_mode)  # the lease, the hand (HAND.md)
        self.comms = CommsMonitor(cfg, c, io.feedback, self.clock, sink, self.start)
        # the controller's events, recorded after each cycle and command, to the parts that handle them
        sink.before_record(g.drain_hand)
        sink.on("fault", m.on_fault)
        sink.on("fault", t.on_fault)
        sink.on("track_end", m.on_end)
        sink.on("lease", g.on_event)
        sink.on("drag_end", g.on_event)
        cycle.after_cycle = [sink.record, t.add]

    @property
    def faults(self) -> list[dict[str, Any]]:
        """The fault list (status ``faults``)."""
        return self.fault_sink.faults

    def record_events(self) -> None:
        """What the cycle (or a command) decided, recorded (daemon/faults.py)."""
        self.fault_sink.record()

    def _report_interrupted_teach(self) -> None:
        """Teach sessions a previous run did not finish (killed, power lost): their recordings are the autosave."""
        from dragd.teach.program import interrupted_sessions

        for m in interrupted_sessions(self.cfg.program_dir):
            self.fault_sink.log_at(f"warning: teach session '{m.stem}' was interrupted ({m} has no program file): "
                                   f"'dragd teach recover {m.stem}' writes it from the recording", LOG_WARNING)

    # ------------------------------------------------------------------------------------------ operator actions

    def start(self) -> None:
        """Enable the drives (fault reset first) and hold the pose."""
        c = self.controller
        self.gravity.check_current(self.cycle.est, "start")
        if c.mode == Mode.FAULT:
            self.fault_sink.faults.clear()
        c.start(self.cycle.est.q_rad)
        self.supervisor.request_enable(self.cycle.t)
        self.record_events()

    def stop(self) -> None:
        """Ramp to hold, then disable (brakes on)."""
        self.controller.stop(self.cycle.est.q_rad)
        self.record_events()

    def set_mode(self, name: str, accept: bool = False, lease: int = 0,
                 by_enable: bool = False) -> dict[str, Any] | None:
        modes = {"idle": Mode.IDLE, "hold": Mode.HOLD, "drag": Mode.DRAG}
        if name not in modes:
            raise ValueError(f"mode: expected one of {', '.join(modes)}, got '{name}'")
        check = None
        if modes[name] == Mode.DRAG:
            why = self.controller.drag_refusal()  # (before the checks below: the answer names what is missing)
            if why is not None:
                raise ValueError(f"mode drag: refused: {why}")
            if self.model_check.failed:
                raise ValueError("mode drag: refused: 'dragd check model' failed on "
                                 f"{', '.join(self.model_check.failed)} "
                                 "(a wrong sign or K_t scale); fix the configuration and run the check again")
            self.gravity.check_current(self.cycle.est, "mode drag")
            if self.controller.mode != Mode.DRAG:
                check = self.gravity.before_drag(accept)
        self.controller.request(modes[name], self.cycle.est.q_rad, lease=lease, by_enable=by_enable)
        self.record_events()
        return check

    async def wait_for(self, cond: Callable[[], bool], timeout_s: float) -> bool:
        """Run the arm until ``cond()`` holds or ``timeout_s`` passed on the cycle's clock; ``cond()`` at the end."""
        return await self.clock.wait_for(cond, timeout_s)

    # ------------------------------------------------------------------------------------------ status

    def _components(self) -> dict[str, list[float]]:
        """The drag law's current terms (zeros outside drag), as the telemetry row names them."""
        c = self.controller
        out = c.law_out
        drag = c.mode == Mode.DRAG
        zero = [0.0] * self.n
        return {name: (getattr(out, name).tolist() if drag and getattr(out, name, None) is not None else zero)
                for name in ("gravity_A", "friction_A", "startup_A", "damping_A", "back_emf_A", "effects_A")}

    def _boot_status(self) -> dict[tuple[str, int], list[str]]:
        """Each drive's boot status lines (the protection in force, fallbacks, warnings: hardware/master.py)."""
        if self.master is None:
            return {}
        return {(rt.name, n): list(info.status) for rt in self.master.runtimes.values() for n, info in rt.nodes.items()}

    def status(self) -> dict[str, Any]:
        c, cy, sup, io = self.controller, self.cycle, self.supervisor, self.io
        fb = io.feedback if io is not None else None
        boot = self._boot_status()
        drives = [{"joint": j.name, "node_id": j.node_id, "state": STATE_NAMES[sup.states[i]],
                   "statusword": int(fb.statusword[i]) if fb is not None else 0,
                   "stale_cycles": int(fb.stale[i]) if fb is not None else 0,
                   "eds": self.drives.profiles[i].eds_path.name, "boot": boot.get((j.bus, j.node_id), []),
                   "motion_mode": self.drives.profiles[i].motion_mode}
                  for i, j in enumerate(self.cfg.joints)]

        def pct(h: Any, p: float) -> float | None:
            return h.percentile(p) if h.count else None

        return {
            "mode": MODE_NAMES[c.mode],
            "drives_enabled": sup.all_enabled,
            "cycles": cy.cycles,
            "period_p50_us": pct(cy.period_hist, 50),
            "period_p99_us": pct(cy.period_hist, 99),
            "period_max_us": cy.period_hist.max if cy.period_hist.count else None,
            "compute_p50_us": pct(cy.compute_hist, 50),
            "compute_p99_us": pct(cy.compute_hist, 99),
            "missed_cycles": cy.missed,
            "missed_episodes": cy.missed_episodes,  # late ticks that missed one or more (`missed_ticks`: when)
            "late_tpdo_cycles": cy.late_tpdo,
            "tpdo_latency_p50_us": pct(cy.rx_hist, 50),
            "tpdo_latency_p99_us": pct(cy.rx_hist, 99),
            "feedback_hold": c.feedback_hold,
            "feedback_holds": c.feedback_holds,
            "scheduler": self.scheduler,
            "threads": thread_policies(),  # every thread's policy: helpers SCHED_FIFO 1 below a real-time cycle
            "memory_locked": self.memory_locked,  # the cycle thread's policy (SCHED_FIFO when configured and permitted)
            "cpu_latency": self.cpu_latency_status if self.cpu_latency is None else self.cpu_latency.status(),
            "requested_mode": MODE_NAMES[c.resume_mode if c.feedback_hold else c.mode],
            "q_rad": cy.est.q_rad.tolist(),
            "dq_rad_s": cy.est.dq_rad_s.tolist(),
            "current_A": cy.est.current_A.tolist(),
            "command_A": c.cmd_A.tolist(),
            "components_A": self._components(),
            "faults": list(self.faults),
            "fault_count": self.fault_sink.fault_count,
            "drives": drives,
            **self.motions.status(),
            "stream": self.streams.status(),
            # the control socket's requests: answered on its own thread (the stream's samples) / on the cycle's loop
            "control": ({"requests": srv.requests, "off_cycle": srv.answered_here, "on_cycle": srv.handed_over}
                        if (srv := self.server) is not None else None),
            "bus_load_pct": {k: round(v["load_pct"], 2) for k, v in self.budget.items()},
            "tx_errors": io.tx_errors if io is not None else 0,
            "rejected_frames": io.rejected_frames if io is not None else 0,
            "duplicate_tpdos": io.duplicate_tpdos if io is not None else 0,
            "deferred_statuswords": io.deferred_statuswords if io is not None else 0,
            "encoder_rejects": cy.encoders.rejects,
            "comms": self.comms.status(),
            "error_frames": io.error_frames if io is not None else 0,
            # the host-local udp_multicast bus's own counters (echoes, duplicates, gaps, kernel drops, ...)
            "bus_counters": {name: vars(bus.counters()) for name, bus in self.buses.items()
                             if hasattr(bus, "counters")},
            "clamp_cycles": c.clamp_cycles,
            "guard": {"armed": bool(c.guard is not None and c.guard.armed), "trips": c.guard_trips,
                      "hand_runs": c.guard.hand_runs if c.guard is not None else 0,
                      "stuck_deferrals": c.guard.stuck_deferrals if c.guard is not None else 0,
                      "last_trip": c.last_trip,
                      "gravity_offset_A": c.gravity_offset_A.tolist(), "hold_rest_s": round(c.hold_rest_s, 3)},
            "contact": (c.contact.status(self.cfg.joint_names) | {"stops": c.contact_stops}
                        if c.contact is not None else None),
            "payload": {"mass_kg": self.model.payload_mass_kg, "com_m": self.model.payload_com_m.tolist()},
            "telemetry": self.recorder.telemetry.stats() if self.recorder.telemetry is not None else None,
            "recording": self.recorder.recording_path,
            "t_s": cy.t,
            "clock": self.clock.status(),
            "spool_dir": self.spool_dir,
            "teach": self.teaching.recorder.status() if self.teaching.recorder is not None else None,
            "drag": self.guiding.status(),  # what drag requires, the lease, the hand's inputs (docs/HAND.md)
        }

    # ------------------------------------------------------------------------------------------ run

    def request_exit(self) -> None:
        self.stop_requested = True

    async def _shutdown_sequence(self) -> None:
        """SIGTERM: ramp to hold, disable (brakes), NMT pre-operational, then leave the loop."""
        c = self.controller
        if self.teaching.recorder is not None:  # keep what was taught
            try:
                await asyncio.wait_for(self.teaching.stop(), 15.0)
            except (TimeoutError, ValueError, RuntimeError, OSError) as exc:
                self.fault_sink.log_at(f"teach: the program could not be written at shutdown: {exc}", LOG_ERR)
        if c.mode not in (Mode.IDLE, Mode.FAULT):
            self.stop()
            await self.wait_for(lambda: c.mode in (Mode.IDLE, Mode.FAULT), self.cfg.safety.mode_ramp_s + 1.0)
        await self.wait_for(lambda: not self.supervisor.enabled.any(), 0.5)
        self.cycle.request_exit()

    async def _watchdog(self) -> None:
        period = sdnotify.watchdog_period_s()
        if not period:
            return
        last = -1
        while not self.cycle.exit_requested:
            await asyncio.sleep(period / 2)
            if self.cycle.cycles != last:  # only while the cycle runs
                sdnotify.watchdog_ping()
                last = self.cycle.cycles

    def _lock_run_dir(self) -> None:
        """One daemon per control socket: an exclusive lock on ``<socket>.lock``, held for the daemon's life and
        taken before any bus is opened (a second daemon must not send a single frame)."""
        import fcntl

        path = Path(self.socket_path + ".lock")
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
        except OSError as exc:
            raise ValueError(f"cannot create the run lock {path}: {exc.strerror}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            raise ValueError(f"another dragd holds {path} (its control socket {self.socket_path}); refusing to start "
                             "a second daemon") from None
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._run_lock = fd

    async def run(self, commands: Callable[[Daemon], CommandTable]) -> int:
        """Boot the drives, run the cycle and answer the control socket (the table ``commands(self)`` builds:
        daemon/commands.py's ``command_table``) until SIGTERM/SIGINT, a ``shutdown`` command or ``request_exit``."""

        loop = asyncio.get_running_loop()
        self.clock.attach(loop)  # (lockstep: the loop's executor jobs hold the clock)
        # a busy helper thread (SDO worker, telemetry encoder) would hold the GIL for the default 5 ms
        sys.setswitchinterval(5e-4)
        if self.recorder.rerun:
            from dragd.telemetry.sinks import rerun_unavailable

            reason = rerun_unavailable()
            if reason:
                raise ValueError(f"--rerun: {reason}")
        self._lock_run_dir()
        buses = {}
        try:
            for name, spec in self.bus_specs.items():
                buses[name] = open_bus(spec, batch_frames=self.batch_frames)
                # CANopen uses 11-bit ids only: 29-bit frames (whose ids can equal a COB-ID) never reach the stack
                buses[name].set_filters([{"can_id": 0, "can_mask": 0, "extended": False}])
        except BaseException:
            for bus in buses.values():
                bus.shutdown()
            raise
        self.attach(buses)
        server = None
        comms: asyncio.Task[None] | None = None
        try:
            # the cycle's I/O reads the buses; the SDO master's canopen networks listen through the same readers
            self.master = Master(self.cfg, self.buses, self.layouts, loop, self.drives.profiles,
                                 self.io.open_readers(loop), log=self.log)
            self.master.on_heartbeat = self.comms.on_heartbeat
            self.motions.master = self.comms.master = self.master  # the CST ↔ CSP switch; NMT, reconfiguration
            await self.master.boot()
            self.recorder.open_telemetry()
            rt: dict[str, Any] = {}
            self.scheduler = go_realtime(loop, self.cfg.loop.realtime_priority, self.cfg.loop.cpus,
                                         self.cfg.loop.lock_memory, rt)
            lock = rt.get("memory_lock") or {}
            self.memory_locked = bool(lock.get("applied"))
            if lock.get("requested") and not lock.get("applied"):
                self.fault_sink.log_at(f"warning: memory not locked: {lock.get('reason')}", LOG_WARNING)
            latency_us = self.cfg.loop.cpu_latency_us
            if latency_us is not None and self.cfg.loop.realtime_priority is None:
                self.cpu_latency_status["requested_us"] = latency_us
                self.cpu_latency_status["reason"] = ("needs a real-time priority (loop.realtime_priority or "
                                                     "--realtime-priority): the request goes with it")
                self.fault_sink.log_at(f"warning: loop.cpu_latency_us {latency_us} not applied: "
                             f"{self.cpu_latency_status['reason']}", LOG_WARNING)
            elif latency_us is not None:
                self.cpu_latency = CpuLatencyRequest(latency_us)
                if not self.cpu_latency.held:
                    self.fault_sink.log_at(f"warning: loop.cpu_latency_us {latency_us} not applied: "
                                 f"{self.cpu_latency.info['reason']}", LOG_WARNING)
            for sig in (signal.SIGTERM, signal.SIGINT):
                loop.add_signal_handler(sig, self.request_exit)
            self.gravity.warm_up()
            # everything built so far lives for the whole run: out of the cyclic collector's way, so its
            # occasional full collections (a heap of Pinocchio/scipy/numpy objects) cannot stall a cycle for ms
            gc.collect()
            gc.freeze()
            cycle = loop.create_task(self.cycle.run())
            comms = loop.create_task(self.comms.run())
            # the control socket on a thread of its own below the cycle: no client's request delays a cycle; the
            # stream's samples are answered there (daemon/stream.py), every other command on this loop
            avoid = set(self.cfg.loop.cpus) if self.cfg.loop.cpus else None
            server = self.server = ThreadedControlServer(self.socket_path, commands(self), here=OFF_CYCLE_COMMANDS,
                                                         thread_init=lambda: demote_current_thread(avoid))
            await server.start()
            self.log(f"running at {self.cfg.loop.rate_Hz:.0f} Hz; control socket {self.socket_path}; "
                     f"cycle thread: {self.scheduler}")
            sdnotify.ready(f"running, {self.n} drives")
            self._report_interrupted_teach()
            watchdog = loop.create_task(self._watchdog())
            while not self.stop_requested and not cycle.done():
                await asyncio.sleep(0.05)
            if cycle.done():
                cycle.result()  # re-raise what ended the cycle
            sdnotify.stopping("ramping down")
            await self._shutdown_sequence()
            await cycle
            watchdog.cancel()
            return 0
        finally:
            if self.cpu_latency is not None:  # first: the daemon is stopping, the CPUs need not poll through it
                self.cpu_latency.close()
            if comms is not None:
                comms.cancel()
            self.planner.close()
            if server is not None:
                await server.close()
            if self.master is not None:
                await self.master.shutdown()
            self.io.close_readers()
            await self.recorder.close(self.cycle.cycles)
            for bus in self.buses.values():
                bus.shutdown()
