"""The simulated robot's process: drives on a CAN bus plus arm physics in real time, a control socket, a report.

Threads: the main thread runs the physics on an absolute-deadline 1 ms timerfd grid and executes
``physics_rate_Hz / 1000`` steps per tick (each step: every drive's ``update``, then ``ArmPhysics.step``);
a tick that wakes late catches up (``late_steps``), one that is hopelessly late drops steps (``dropped_steps``,
the sim then runs behind real time: rtf < 1). The SimNetwork reader thread answers the bus; the control socket
(JSON lines, dragd's protocol) runs in its own asyncio thread. The physics lock is held for one tick's batch.

On the wall clock the drives' clock is CLOCK_MONOTONIC read through ``OwnStalls``, which notes when the simulator
itself was not running. A real drive's firmware watches the bus whatever the host does; the simulated drive watches it
only while the simulator runs. When the host freezes the VM (both processes stop: nothing can be sent, nothing is
watched) or the OS does not schedule the simulator, that time is not time the drive saw a silent bus: its reception
watchdogs (RPDO deadlines, heartbeat consumers) leave it out (CI once saw EMCY 8250h after an 88 ms freeze of both
processes). A daemon silent beside a running simulator still times the drives out, as a real one would; what the drives
send (heartbeats, event TPDOs) stays on CLOCK_MONOTONIC and catches up at once, as a real drive's queued frames would.

On the lockstep clock (``--lockstep``, sim/lockstep.py) the SYNC (of every bus) runs one period of the same steps
(``_period``) in the bus reader's thread instead of the timerfd, and the period's answer ends with a TIME frame; the
drives' communication clock is the simulated time; ``rtf`` is then as fast as the two processes go.

Control commands: ``state``, ``operator`` (scenario dict or file, starting now), ``operator_events``,
``set_q`` (teleport, only while every drive's power stage is off), ``drives``, ``fault`` (inject a
device fault into one drive), ``inject`` (a bus or node fault: sim/faults.py; a fault of the guiding device at the
hand: sim/hand.py), ``hand`` (press / let go a button of the guiding device now), ``stop``.
"""

from __future__ import annotations

import asyncio
import collections
import ctypes
import ctypes.util
import gc
import math
import os
import signal
import struct
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from dragd.hardware.bus import BusSpec, UdpMulticastCanBus, open_bus, parse_bus
from dragd.hardware.cia402 import EMCY_OVER_CURRENT
from dragd.protocol import ControlError
from dragd.realtime import demote_current_thread, scheduler_label, set_realtime
from dragd.server import CommandTable, ControlServer
from sim.axis import AxisIO
from sim.drive import SimDrive
from sim.faults import FaultError, FaultInjector
from sim.hand import KINDS as HAND_KINDS
from sim.hand import HandDevice, HandError
from sim.lockstep import LockstepSync
from sim.network import SimNetwork
from sim.operator import Operator, ScenarioError, load_scenario, validate_scenario
from sim.physics import ArmPhysics
from sim.scenario_payload import PayloadSchedule, set_flange_payload
from sim.truth import Truth, drive_params

TICK_NS = 1_000_000
RUN_CLOCK_MAX_GAP_S = 0.002  # a running simulator reads its clock every tick (1 ms): a longer gap: not running
MAX_CATCHUP_TICKS = 100  # a wake-up later than this (100 ms) drops the excess steps instead of catching up
LATENCY_RING = 1 << 16

_CLOCK_MONOTONIC = 1
_TFD_CLOEXEC = os.O_CLOEXEC
_TFD_TIMER_ABSTIME = 1
_U64 = struct.Struct("=Q")


class _Timespec(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


class _Itimerspec(ctypes.Structure):
    _fields_ = [("it_interval", _Timespec), ("it_value", _Timespec)]


class TimerFd:
    """Blocking periodic CLOCK_MONOTONIC timerfd with absolute deadlines (no drift, counts missed ticks)."""

    def __init__(self, period_ns: int) -> None:
        if not sys.platform.startswith("linux"):
            raise OSError(f"TimerFd needs Linux timerfd; this platform is {sys.platform!r}")
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        libc.timerfd_create.argtypes = [ctypes.c_int, ctypes.c_int]
        libc.timerfd_settime.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.POINTER(_Itimerspec),
                                         ctypes.POINTER(_Itimerspec)]
        self._libc = libc
        self.period_ns = period_ns
        self.fd = libc.timerfd_create(_CLOCK_MONOTONIC, _TFD_CLOEXEC)
        if self.fd < 0:
            err = ctypes.get_errno()
            raise OSError(err, f"timerfd_create failed: {os.strerror(err)}")
        self.deadline_ns = 0  # deadline of the last expiration returned by wait()

    def start(self, first_deadline_ns: int | None = None) -> None:
        first = time.monotonic_ns() + self.period_ns if first_deadline_ns is None else first_deadline_ns
        spec = _Itimerspec(_Timespec(0, self.period_ns), _Timespec(first // 1_000_000_000, first % 1_000_000_000))
        if self._libc.timerfd_settime(self.fd, _TFD_TIMER_ABSTIME, ctypes.byref(spec), None) != 0:
            err = ctypes.get_errno()
            raise OSError(err, f"timerfd_settime failed: {os.strerror(err)}")
        self.deadline_ns = first - self.period_ns

    def wait(self) -> int:
        """Block until the next deadline; return the number of periods elapsed (>1: ticks were missed)."""
        n = _U64.unpack(os.read(self.fd, 8))[0]
        self.deadline_ns += n * self.period_ns
        return n

    def close(self) -> None:
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1


class OwnStalls:
    """CLOCK_MONOTONIC (s) as the simulator's threads read it, and the stalls of the simulator it shows.

    Every thread of the simulator reads ``now`` where it works (the physics loop every tick and every tick it catches
    up, the bus reader at each wake and each frame): a gap between two readings longer than ``max_gap_s`` is time none
    of them ran (the host froze the VM, or did not schedule this process) — a stall from ``max_gap_s`` after the
    earlier reading to the later one. ``held(a, b)``: how much of [a, b] was stalled (the drives' reception watchdogs
    leave it out: sim/drive.py). Readings never go backwards; thread-safe; the last ``keep`` stalls are kept.
    ``source`` is the clock read (tests inject one)."""

    def __init__(self, max_gap_s: float = RUN_CLOCK_MAX_GAP_S, source: Callable[[], float] = time.monotonic,
                 keep: int = 256) -> None:
        self.max_gap_s = max_gap_s
        self._source = source
        self._lock = threading.Lock()
        self._last = source()
        self._stalls: collections.deque[tuple[float, float]] = collections.deque(maxlen=keep)  # (start, end)
        self.count = 0
        self.total_s = 0.0
        self.max_s = 0.0

    def now(self) -> float:
        with self._lock:
            raw = self._source()
            last = self._last
            if raw - last > self.max_gap_s:
                start = last + self.max_gap_s
                self._stalls.append((start, raw))
                held = raw - start
                self.count += 1
                self.total_s += held
                if held > self.max_s:
                    self.max_s = held
            if raw > last:
                self._last = raw
            return self._last

    def held(self, a: float, b: float) -> float:
        """Seconds of [a, b] during which the simulator did not run (as far as the kept stalls tell)."""
        total = 0.0
        with self._lock:  # (called only once a deadline has passed by the clock: the rare path)
            for start, end in reversed(self._stalls):  # newest first
                if end <= a:
                    break
                if start < b:
                    total += min(end, b) - max(start, a)
        return total

    def reset_counts(self) -> None:
        """Start the counts afresh (the real-time loop starts: setting up is not a stall)."""
        with self._lock:
            self._last = self._source()
            self.count, self.total_s, self.max_s = 0, 0.0, 0.0

    def report(self) -> dict[str, Any]:
        """The simulator's own stalls: the host's, beside the daemon's missed cycles."""
        return {"count": self.count, "total_s": round(self.total_s, 6), "max_s": round(self.max_s, 6),
                "gap_threshold_s": self.max_gap_s}


class SimProcess:
    """Drives + network + physics + control socket of one simulated arm on one bus."""

    def __init__(self, truth: Truth, bus: str | None = None, *, scenario: str | Path | dict[str, Any] | None = None,
                 control_path: str | Path | None = None, seconds: float | None = None,
                 realtime_priority: int | None = None, cpus: set[int] | None = None,
                 batch_frames: bool = False, lockstep: bool = False, period_s: float = 0.001) -> None:
        self.truth = truth
        self.lockstep_period_s = period_s if lockstep else None
        self.lockstep: LockstepSync | None = None
        self.stalls: OwnStalls | None = None  # the drives' clock on the wall clock, and the simulator's stalls (run)
        self.batch_frames = batch_frames
        self.realtime_priority = realtime_priority
        self.cpus = cpus
        self.realtime: dict[str, Any] | None = None
        self.robot = truth.load_model()
        self.axes = [AxisIO() for _ in truth.joints]
        self.physics = ArmPhysics(truth, self.robot, self.axes)
        # the guiding device at the wrist: its contacts on one drive's digital inputs (sim/hand.py)
        self.hand = None if truth.hand is None else HandDevice(truth.hand, [j.name for j in truth.joints], self.axes)
        # one or more buses ("A,B"): joint j's drive sits on bus truth.joints[j].bus_index
        self.specs: list[BusSpec] = [parse_bus(b, fd=truth.bus.fd) for b in (bus or truth.bus.channel).split(",") if b]
        for j in truth.joints:
            if j.bus_index >= len(self.specs):
                raise ValueError(f"{truth.source}: joints.{j.name}.bus_index: expected < {len(self.specs)} "
                                 f"(the number of buses given: {', '.join(map(str, self.specs))}), got {j.bus_index}")
        self.scenario = None if scenario is None else (
            load_scenario(scenario) if isinstance(scenario, (str, Path)) else validate_scenario(scenario))
        self.control_path = None if control_path is None else str(control_path)
        self.seconds = seconds
        self.operator: Operator | None = None
        self.payloads = PayloadSchedule()  # hung-on / removed flange masses (sim/scenario_payload.py)
        self.lock = threading.Lock()
        self._stop = threading.Event()
        self.buses: list[Any] = []
        self.drives: list[SimDrive] = []
        self.networks: list[SimNetwork] = []
        self.injectors: list[FaultInjector] = []
        # run statistics
        self.substeps = truth.physics_rate_Hz // 1000
        self.ticks = 0
        self.late_ticks = 0
        self.late_steps = 0
        self.dropped_steps = 0
        self.max_busy_ns = 0
        self.late_tick_times: list[float] = []  # sim time of the first late ticks (diagnostics)
        self._thread_cpu_ns = 0  # CPU time of the physics thread in the loop (lockstep: the bus readers, which run it)
        self.busy_ns = 0
        self._latency_us = np.zeros(LATENCY_RING, dtype=np.float32)
        self._wall_start = 0.0
        self._wall_end = 0.0
        self._cpu_start = 0.0
        self._cpu_end = 0.0
        self._limit_steps: int | None = None
        self._control_loop: asyncio.AbstractEventLoop | None = None
        self._control_thread: threading.Thread | None = None
        self._control_ready = threading.Event()
        self._control_error: BaseException | None = None

    # ------------------------------------------------------------------------------------------- lifecycle

    def request_stop(self) -> None:
        self._stop.set()

    def run(self, ready: Callable[[SimProcess], None] | None = None) -> dict[str, Any]:
        """Open the bus, boot the drives, serve control, run physics in real time until stopped; the summary.

        ``ready(self)`` is called once everything is up, just before the real-time loop starts.
        """
        if self.realtime_priority is not None or self.cpus is not None:
            # before any thread starts: the bus reader inherits it (it answers SYNC); the control thread demotes
            self.realtime = set_realtime(self.realtime_priority, self.cpus)
        try:
            self.buses = [open_bus(spec, batch_frames=self.batch_frames) for spec in self.specs]
            # the drives' communication clock: it stamps the frames they receive and times their watchdogs
            clock: Callable[[], float]
            if self.lockstep_period_s is None:
                self.stalls = OwnStalls()
                clock = self.stalls.now
            else:
                self.lockstep = LockstepSync(self.buses, self.lockstep_period_s, self.physics.dt_s)
                self._limit_steps = None if self.seconds is None else int(round(self.seconds / self.physics.dt_s))
                self.lockstep.run_period = self._period
                clock = self.lockstep.clock.now
            self.injectors = [FaultInjector(bus, clock=clock, lockstep=self.lockstep is not None) for bus in self.buses]
            for j, ax in zip(self.truth.joints, self.axes, strict=True):
                spec, inj = self.specs[j.bus_index], self.injectors[j.bus_index]
                node = drive_params(j, spec.fd).node_id
                self.drives.append(SimDrive(drive_params(j, spec.fd), ax, inj.sender(node),
                                            send_data=inj.data_sender(node), clock=clock))
                if self.stalls is not None:
                    self.drives[-1].not_running = self.stalls.held
            on_bus = [[d for d, j in zip(self.drives, self.truth.joints, strict=True) if j.bus_index == k]
                      for k in range(len(self.buses))]
            self.networks = [SimNetwork(bus, on_bus[k], lockstep=self.lockstep, bus_index=k, clock=clock)
                             for k, bus in enumerate(self.buses)]
            for net, inj in zip(self.networks, self.injectors, strict=True):
                net.rx_muted = inj.rx_muted
            if self.control_path is not None:
                self._start_control()
            if self.scenario is not None:
                self._set_operator(self.scenario)
            if self.hand is not None:
                self.hand.apply(self.physics.t_s)  # the contacts as wired, before anyone reads them (the boot)
            for net in self.networks:
                net.start(boot=True)
            try:
                gc.collect()
                gc.freeze()  # long-lived objects out of the collector's way: no multi-ms full collections
                if ready is not None:
                    ready(self)
                self._loop()
            finally:
                for net in self.networks:
                    net.stop()
                if self.lockstep is not None:  # the periods ran in the bus readers (their CPU: SYNC answers included)
                    self._thread_cpu_ns = sum(net.cpu_ns for net in self.networks)
        finally:
            self._stop_control()
            for bus in self.buses:
                bus.shutdown()
        return self.summary()

    def _loop(self) -> None:
        """Real time: a tick of the timerfd runs the steps due (catching up after a late wake-up). On the lockstep
        clock the SYNCs run the periods (``_period``, in the bus reader's thread); this thread waits for the end."""
        physics, substeps = self.physics, self.substeps
        lockstep = self.lockstep
        lat, ring = self._latency_us, LATENCY_RING
        stop = self._stop
        self._limit_steps = None if self.seconds is None else int(round(self.seconds / physics.dt_s))
        self._wall_start = time.monotonic()
        self._cpu_start = time.process_time()
        thread_cpu0 = time.thread_time_ns()
        if lockstep is not None:
            lockstep.run_period = self._period
            try:
                stop.wait()
            finally:
                self._wall_end = time.monotonic()
                self._cpu_end = time.process_time()
            return
        timer = TimerFd(TICK_NS)
        if self.stalls is not None:
            self.stalls.reset_counts()
        timer.start()
        try:
            while not stop.is_set():
                n = timer.wait()
                wake = time.monotonic_ns()
                lat[self.ticks % ring] = (wake - timer.deadline_ns) * 1e-3
                if n > 1:
                    self.late_ticks += 1
                    if len(self.late_tick_times) < 20:
                        self.late_tick_times.append(round(physics.t_s, 4))
                    if n > MAX_CATCHUP_TICKS:
                        self.dropped_steps += (n - MAX_CATCHUP_TICKS) * substeps
                        n = MAX_CATCHUP_TICKS
                    self.late_steps += (n - 1) * substeps
                if not self._period(n * substeps, wake):
                    break
        finally:
            self._wall_end = time.monotonic()
            self._cpu_end = time.process_time()
            self._thread_cpu_ns = time.thread_time_ns() - thread_cpu0
            timer.close()

    def _period(self, steps: int, wake_ns: int = 0) -> bool:
        """``steps`` physics steps (every drive's ``update`` before each), payload changes due, then the drives'
        communication timers at the end (wall: CLOCK_MONOTONIC; lockstep: the sim time the period ends at, and the
        faults due by then); False once ``--seconds`` of sim time have run."""
        physics, drives, dt = self.physics, self.drives, self.physics.dt_s
        wake = wake_ns or time.monotonic_ns()
        self.ticks += 1
        limit = self._limit_steps
        if limit is not None:
            steps = max(0, min(steps, limit - physics.steps))
        stalls, substeps = self.stalls, self.substeps
        if stalls is not None:
            stalls.now()  # (the wake: a gap since the last reading is time this process did not run)
        with self.lock:
            for i in range(steps):
                t = physics.t_s
                for d in drives:
                    d.update(t, dt)
                physics.step()
                if stalls is not None and i % substeps == substeps - 1:
                    stalls.now()  # (catching up is running: readings go on while it does)
            if self.payloads.pending:
                self.payloads.apply_due(physics)
            if self.hand is not None:
                self.hand.apply(physics.t_s)  # the drive reads its inputs (next SYNC's TPDO, its event TPDOs)
            if self.lockstep is not None:
                now = self.lockstep.clock.t_s = physics.t_s
                for inj in self.injectors:
                    inj.release_due(now)
            else:
                now = time.monotonic() if stalls is None else stalls.now()
        for d in drives:
            d.comm(now)
        busy = time.monotonic_ns() - wake
        self.busy_ns += busy
        if busy > self.max_busy_ns:
            self.max_busy_ns = busy
        if limit is not None and physics.steps >= limit:
            self.request_stop()
            return False
        return True

    # ------------------------------------------------------------------------------------------- reports

    def rtf(self) -> float:
        wall = (self._wall_end or time.monotonic()) - self._wall_start if self._wall_start else 0.0
        return self.physics.t_s / wall if wall > 0 else 0.0

    def state(self) -> dict[str, Any]:
        with self.lock:
            snap = self.physics.snapshot()
            op = self.operator
            op_info = None if op is None else {"name": op.scenario.name, "segment": op.segment_index, "done": op.done}
        return {
            "t": snap["t"], "q_rad": snap["q_rad"], "dq_rad_s": snap["dq_rad_s"], "current_A": snap["current_A"],
            "tau_ext_Nm": snap["tau_ext_Nm"], "brakes": snap["brakes"], "rtf": self.rtf(),
            "late_steps": self.late_steps, "steps": snap["steps"],
            "current_measured_A": snap["current_measured_A"], "current_demand_A": snap["current_demand_A"],
            "tau_motor_Nm": snap["tau_motor_Nm"], "tau_friction_Nm": snap["tau_friction_Nm"],
            "power_on": snap["power_on"], "stuck": snap["stuck"], "temperature_C": snap["temperature_C"],
            "dropped_steps": self.dropped_steps, "operator": op_info, "scheduler": self._scheduler(),
            "hand": None if self.hand is None else self.hand.state(),
        }

    def _scheduler(self) -> str:
        """The physics thread's scheduling policy as applied (``--realtime-priority``), e.g. "SCHED_FIFO 60"."""
        return scheduler_label(self.realtime or {}, self.realtime_priority)

    def drive_report(self) -> dict[str, Any]:
        out = {}
        for d in self.drives:
            c = d.counters
            out[str(d.node_id)] = {"state": d.state.name, "nmt": d.nmt_state.name, **vars(c)}
        return out

    def summary(self) -> dict[str, Any]:
        wall = (self._wall_end or time.monotonic()) - self._wall_start if self._wall_start else 0.0
        cpu = (self._cpu_end or time.process_time()) - self._cpu_start
        n = min(self.ticks, LATENCY_RING)
        lat = np.sort(self._latency_us[:n]) if n else np.zeros(1, dtype=np.float32)
        report: dict[str, Any] = {
            "ok": True,
            "robot": self.truth.robot,
            "bus": ",".join(map(str, self.specs)),
            "physics_rate_Hz": self.truth.physics_rate_Hz,
            "sim_time_s": round(self.physics.t_s, 6),
            "wall_time_s": round(wall, 6),
            "rtf": round(self.physics.t_s / wall, 6) if wall > 0 else 0.0,
            "steps": self.physics.steps,
            "ticks": self.ticks,
            "late_ticks": self.late_ticks,
            "late_steps": self.late_steps,
            "dropped_steps": self.dropped_steps,
            "wake_latency_us": {"p50": float(lat[int(0.5 * (len(lat) - 1))]),
                                "p99": float(lat[int(0.99 * (len(lat) - 1))]), "max": float(lat[-1])},
            "tick_busy_us": {"mean": self.busy_ns / self.ticks / 1e3 if self.ticks else 0.0,
                             "max": self.max_busy_ns / 1e3},
            "late_tick_times_s": list(self.late_tick_times),
            # the simulator's own stalls (the drives' clock held over them): the host's, beside the daemon's misses
            **({"own_stalls": self.stalls.report()} if self.stalls is not None else {}),
            "cpu_s": round(cpu, 3),
            "cpu_pct": round(100.0 * cpu / wall, 1) if wall > 0 else 0.0,  # the whole process
            "physics_cpu_pct": round(100.0 * self._thread_cpu_ns * 1e-9 / wall, 1) if wall > 0 else 0.0,
            "physics_step_us": round(self._thread_cpu_ns * 1e-3 / self.physics.steps, 2) if self.physics.steps else 0.0,
            "drives": self.drive_report(),
        }
        if self.realtime is not None:
            report["realtime"] = self.realtime
        if self.networks:
            report["network"] = [vars(net.counters).copy() for net in self.networks]
            if len(self.networks) == 1:
                report["network"] = report["network"][0]
        counters = [vars(b.counters()) for b in self.buses if isinstance(b, UdpMulticastCanBus)]
        if counters:
            report["bus_counters"] = counters[0] if len(counters) == 1 else counters
        if self.operator is not None:
            report["operator_events"] = list(self.operator.events)
        report["final_state"] = {k: v for k, v in self.state().items() if k in ("t", "q_rad", "dq_rad_s", "brakes")}
        return report

    # ------------------------------------------------------------------------------------------- control

    def _set_operator(self, scenario: Any) -> Operator:
        op = Operator(scenario, self.physics.model, start_t_s=self.physics.t_s, hand=self.hand)
        self.operator = op
        self.physics.operator = op
        return op

    def _commands(self) -> CommandTable:
        table = CommandTable()

        @table.command("state")
        def state() -> dict[str, Any]:
            return self.state()

        @table.command("operator")
        def operator(scenario: Any) -> dict[str, Any]:
            """Start a scenario now (a mapping, or a file path / bundled scenario name)."""
            try:
                scen = (load_scenario(scenario) if isinstance(scenario, str)
                        else validate_scenario(scenario, "<control>"))
                with self.lock:
                    op = self._set_operator(scen)
                    t = self.physics.t_s
            except ScenarioError as exc:
                raise ControlError(str(exc)) from None
            return {"name": op.scenario.name, "segments": len(op.scenario.segments), "t": t}

        @table.command("operator_events")
        def operator_events() -> dict[str, Any]:
            with self.lock:
                op = self.operator
                if op is None:
                    return {"events": [], "done": True, "name": None}
                return {"events": list(op.events), "done": op.done, "name": op.scenario.name}

        @table.command("operator_trace")
        def operator_trace(since_t_s: float | None = None) -> dict[str, Any]:
            """The operator's Cartesian force (truth) every ms since ``since_t_s`` (sim time): t_s, force_N, at_m."""
            with self.lock:
                op = self.operator
                t = self.physics.t_s
                if op is None:
                    return {"t_s": [], "force_N": [], "at_m": [], "now_s": t}
                return {**op.trace(-math.inf if since_t_s is None else float(since_t_s)), "now_s": t}

        @table.command("set_q")
        def set_q(q_rad: list[float]) -> dict[str, Any]:
            """Teleport the arm (zero velocity); only while every drive's power stage is off."""
            if not isinstance(q_rad, list) or len(q_rad) != self.physics.n or \
                    not all(isinstance(v, (int, float)) and math.isfinite(v) for v in q_rad):
                raise ControlError(f"set_q: q_rad: expected a list of {self.physics.n} finite "
                                   f"numbers (rad), got {q_rad!r}")
            for i, (v, j) in enumerate(zip(q_rad, self.truth.joints, strict=True)):  # (length checked above)
                if not j.hard_stops.lower_rad <= v <= j.hard_stops.upper_rad:
                    raise ControlError(f"set_q: q_rad[{i}]: expected within the hard stops [{j.hard_stops.lower_rad}, "
                                       f"{j.hard_stops.upper_rad}] of {j.name}, got {v}")
            with self.lock:
                powered = [j.name for j, ax in zip(self.truth.joints, self.axes, strict=True) if ax.power_stage_on]
                if powered:
                    raise ControlError("set_q: only while the drives are disabled; power stage "
                                       f"on at {', '.join(powered)}")
                self.physics.set_state(np.array(q_rad, dtype=float))
                return {"q_rad": self.physics.q_rad.tolist(), "t": self.physics.t_s}

        @table.command("payload")
        def payload(mass_kg: float, com_m: list[float] | None = None, at_t_s: float | None = None) -> dict[str, Any]:
            """Hang a mass on the flange (0: take it off), now or at sim time ``at_t_s`` (the payload scenario)."""
            com = [0.0, 0.0, 0.0] if com_m is None else com_m
            try:
                with self.lock:
                    if at_t_s is None:
                        return set_flange_payload(self.physics, mass_kg, com)
                    if not (isinstance(mass_kg, (int, float)) and mass_kg >= 0 and isinstance(at_t_s, (int, float))):
                        raise ValueError("payload: expected mass_kg >= 0 and a sim time at_t_s, "
                                         f"got {mass_kg!r}, {at_t_s!r}")
                    self.payloads.add(float(at_t_s), float(mass_kg), com)
                    return {"scheduled": True, "at_t_s": float(at_t_s), "mass_kg": float(mass_kg),
                            "t": self.physics.t_s}
            except (ValueError, TypeError) as exc:
                raise ControlError(str(exc)) from None

        @table.command("drives")
        def drives() -> dict[str, Any]:
            return {"drives": self.drive_report()}

        @table.command("fault")
        def fault(node_id: int, code: int = EMCY_OVER_CURRENT) -> dict[str, Any]:
            """Raise a device fault in one drive (EMCY + its fault reaction), e.g. 2310h over-current."""
            drive = next((d for d in self.drives if d.node_id == node_id), None)
            if drive is None:
                raise ControlError("fault: node_id: expected one of "
                                   f"{[d.node_id for d in self.drives]}, got {node_id!r}")
            if not 0 < int(code) <= 0xFFFF:
                raise ControlError(f"fault: code: expected an EMCY error code 0x0001..0xFFFF, got {code!r}")
            drive.inject_fault(int(code))
            return {"node_id": node_id, "code": int(code)}

        @table.command("hand")
        def hand(action: str, button: str, position: str = "middle") -> dict[str, Any]:
            """Press (``press``) or let go (``let_go``) a button of the guiding device now (sim/hand.py)."""
            if self.hand is None:
                raise ControlError("hand: the simulated arm has no guiding device (the truth's hand is null)")
            try:
                with self.lock:
                    t = self.physics.t_s
                    if action == "press":
                        self.hand.press(t, button, position)
                    elif action == "let_go":
                        self.hand.let_go(t, button)
                    else:
                        raise HandError(f"hand: action: expected press or let_go, got {action!r}")
                    self.hand.apply(t)  # the drive's inputs follow the contacts (also before any SYNC: the boot)
                    return {"t": t, **self.hand.state()}
            except HandError as exc:
                raise ControlError(str(exc)) from None

        @table.command("inject")
        def inject(kind: str, node_id: int | None = None, **args: Any) -> dict[str, Any]:
            """Inject a bus or node fault now (sim/faults.py lists the kinds and their arguments), or a fault of the
            guiding device at the hand (sim/hand.py: stuck_enable, chattering, inputs_cut)."""
            if kind in HAND_KINDS:
                if self.hand is None:
                    raise ControlError(f"inject {kind}: the simulated arm has no guiding device (the truth's hand)")
                try:
                    with self.lock:
                        return self.hand.inject(self.physics.t_s, kind, args)
                except HandError as exc:
                    raise ControlError(str(exc)) from None
            if node_id is not None:
                args["node_id"] = node_id
            bus_index = 0
            if node_id is not None:
                k = next((i for i, d in enumerate(self.drives) if d.node_id == node_id), None)
                if k is not None:
                    bus_index = self.truth.joints[k].bus_index
            drives = {d.node_id: d for d in self.drives}
            try:
                return self.injectors[bus_index].inject(kind, drives, args, self.lock)
            except FaultError as exc:
                raise ControlError(str(exc)) from None

        @table.command("stop")
        def stop() -> dict[str, Any]:
            # a moment later, so this answer is written before the control thread shuts down
            asyncio.get_running_loop().call_later(0.05, self.request_stop)
            return {"stopping": True}

        return table

    def _start_control(self) -> None:
        table = self._commands()
        path = self.control_path
        assert path is not None

        def serve() -> None:
            if self.realtime is not None:
                demote_current_thread()
            loop = asyncio.new_event_loop()
            self._control_loop = loop
            server = ControlServer(path, table, mode=0o600)
            try:
                loop.run_until_complete(server.start())
            except BaseException as exc:  # noqa: BLE001 - reported to the starting thread
                self._control_error = exc
                self._control_ready.set()
                loop.close()
                return
            self._control_ready.set()
            try:
                loop.run_forever()
            finally:
                loop.run_until_complete(server.close())
                loop.close()

        self._control_thread = threading.Thread(target=serve, name="sim-control", daemon=True)
        self._control_thread.start()
        self._control_ready.wait(10.0)
        if self._control_error is not None:
            raise self._control_error

    def _stop_control(self) -> None:
        loop, thread = self._control_loop, self._control_thread
        if loop is not None and thread is not None and thread.is_alive():
            loop.call_soon_threadsafe(loop.stop)
            thread.join(5.0)


def run(truth: Truth, bus: str | None = None, *, scenario: str | Path | dict[str, Any] | None = None,
        control_path: str | Path | None = None, seconds: float | None = None,
        realtime_priority: int | None = None, cpus: set[int] | None = None, batch_frames: bool = False,
        ready: Callable[[SimProcess], None] | None = None, lockstep: bool = False,
        period_s: float = 0.001) -> dict[str, Any]:
    """Run the sim process in this (main) thread until SIGTERM/SIGINT, ``stop`` or ``seconds``; the summary.
    ``lockstep``: a period of ``period_s`` per SYNC instead of real time (sim/lockstep.py)."""
    proc = SimProcess(truth, bus, scenario=scenario, control_path=control_path, seconds=seconds,
                      realtime_priority=realtime_priority, cpus=cpus, batch_frames=batch_frames, lockstep=lockstep,
                      period_s=period_s)
    previous = {sig: signal.signal(sig, lambda *_: proc.request_stop()) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        return proc.run(ready)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
