"""The dragd daemon: the 1 kHz torque cycle over CANopen, modes, safety reactions and the control surface.

Each cycle (ticked by a timerfd at absolute deadlines):

    read      SYNC → collect every drive's TPDO until all arrived or SYNC + tpdo_deadline_us
    estimate  q from counts, q̇ by filtered differentiation, measured current
    compute   the mode's law (idle / hold / drag / track) + safety terms, blended across mode switches
    write     controlwords + torque commands (+ CSP targets) in the command RPDO(s)
    log       one telemetry row handed to the MCAP writer thread; timing into histograms

The cycle works on preallocated numpy arrays and precompiled ``struct`` codecs; it does not log, block or
call SDO. Drive state changes (the CiA 402 walk, fault reset edges) are made by the controlwords it sends.
"""

from __future__ import annotations

import asyncio
import functools
import gc
import math
import signal
import sys
import struct
import time
from enum import IntEnum
from pathlib import Path
from typing import Any

import can
import numpy as np
from scipy.interpolate import CubicSpline  # imported at start-up: an import in the loop's process stalls it

from dragd.daemon import sdnotify
from dragd.hardware.bus import open_bus, parse_bus
from dragd.hardware.cia402 import (CMD_DISABLE_VOLTAGE, CMD_QUICK_STOP, CMD_SHUTDOWN, CW_FAULT_RESET, State,
                     decode_statusword, next_controlword)
from dragd.config import Config
from dragd.control.modes import MODE_NAMES, Mode
from dragd.protocol import ControlServer
from dragd.control.params import LawParams
from dragd.control.breakout import BreakoutState, breakout_update
from dragd.control.law import LawOutput, Workspace, compensate, friction_current
from dragd.hardware.master import MODE_CSP, MODE_CST, DriveError, Master
from dragd.model import RobotModel
from dragd.hardware.pdo import SYNC_COB_ID, BusLayout, RpdoEncoder, layout_for
from dragd.stats import Histogram
from dragd.teach.program import ProgramError, check_name, resolve_program
from dragd.teach.recorder import TeachRecorder
from dragd.realtime import Ticker, demote_current_thread, scheduler_label, set_realtime
from dragd.control.estimate import VelocityEstimator


DRIVE_STATE_NAMES = {s: s.name.lower() for s in State}


class BusBudgetError(RuntimeError):
    """The configured PDO layout would load a bus beyond its limit."""


def go_realtime(loop: asyncio.AbstractEventLoop, priority: int | None, cpus: list[int] | None) -> str:
    """Make the calling (cycle) thread SCHED_FIFO ``priority`` on ``cpus`` where permitted; return what applies.

    Threads started afterwards inherit policy and CPU set, so first the loop's default executor (``run_in_executor
    (None, ...)``, ``asyncio.to_thread``: trajectory resampling, program writes, telemetry open/close) gets threads
    that return to SCHED_OTHER off the cycle's CPUs: a FIFO helper doing seconds of Python would starve the cycle.
    """
    from concurrent.futures import ThreadPoolExecutor

    avoid = set(cpus) if cpus else None
    loop.set_default_executor(ThreadPoolExecutor(thread_name_prefix="dragd-exec", initializer=demote_current_thread,
                                                 initargs=(avoid,)))
    return scheduler_label(set_realtime(priority, avoid), priority)


def bus_layouts(cfg: Config) -> dict[str, BusLayout]:
    """The PDO layout of every configured bus."""
    out = {}
    for b in cfg.buses:
        idx = [i for i, j in enumerate(cfg.joints) if j.bus == b.name]
        out[b.name] = layout_for(b.name, idx, [cfg.joints[i].node_id for i in idx], fd=b.fd, kind=b.layout,
                                 rate_Hz=cfg.loop.rate_Hz)
    return out


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
                f"({'CAN FD' if b.fd else 'classic CAN'} {b.bitrate / 1e6:g} Mbit/s, layout '{b.layout}'):\n{r.table()}\n"
                "Use CAN FD, layout 'compact', fewer joints per bus (split buses) or a lower loop.rate_Hz.")
    return report


class Trajectory:
    """A joint trajectory for TRACK mode, resampled once (off the loop) at the loop period.

    From samples t [s] (from 0, increasing) and q [rad] with a clamped cubic spline; the cycle then indexes the
    table (O(1), no allocation). ``load`` reads the same from a .npz (arrays ``t_s``, ``q_rad``) or CSV file
    (``t,q1..qN``). ``from_table`` takes a table already at the loop period (replay plans) with optional velocity
    and feed-forward torque tables, a repeated part (rows ``body_row`` to the end) and the waypoint marks.
    """

    def __init__(self, t_s: np.ndarray, q_rad: np.ndarray, dt_s: float, label: str = "track") -> None:
        t_s = np.asarray(t_s, dtype=float)
        q_rad = np.asarray(q_rad, dtype=float)
        if t_s.ndim != 1 or q_rad.ndim != 2 or q_rad.shape[0] != t_s.shape[0] or t_s.shape[0] < 2:
            raise ValueError(f"trajectory: expected t (N ≥ 2,) and q (N, joints), got {t_s.shape} and {q_rad.shape}")
        if not (np.all(np.isfinite(t_s)) and np.all(np.isfinite(q_rad))):
            raise ValueError("trajectory: t and q must be finite numbers")
        if np.any(np.diff(t_s) <= 0):
            raise ValueError("trajectory: t must increase strictly")
        if t_s[0] != 0.0:
            raise ValueError(f"trajectory: t must start at 0, got {t_s[0]}")
        self.label = label
        self.dt_s = dt_s
        self.duration_s = float(t_s[-1])
        grid = np.arange(0.0, self.duration_s + dt_s / 2, dt_s)
        self.table = np.ascontiguousarray(CubicSpline(t_s, q_rad, bc_type="clamped")(grid))
        self.start_q = self.table[0].copy()
        self._init_tables(None, None, 0, [], {})

    def _init_tables(self, dq: np.ndarray | None, ff: np.ndarray | None, body_row: int,
                     marks: list[dict[str, Any]], info: dict[str, Any]) -> None:
        self.dq_table = dq  # rad/s at rate 1 (None: the cycle differentiates q_ref)
        self.ff_table = ff  # N·m of M(q)q̈ + C(q,q̇)q̇ at rate 1 (None: no inertial feed-forward)
        self.pred_table: np.ndarray | None = None  # the same for the residual monitor only (not commanded)
        self.residual_monitor = True
        self.body_row = int(body_row)
        self.body_start_s = self.body_row * self.dt_s
        self.marks = marks
        self.info = info
        self._d = np.zeros(self.table.shape[1])
        self.k = 0  # row and fraction of the last sample()
        self.f = 0.0

    @classmethod
    def from_table(cls, q: np.ndarray, dt_s: float, label: str = "replay", *, dq: np.ndarray | None = None,
                   ff_Nm: np.ndarray | None = None, body_row: int = 0, marks: list[dict[str, Any]] | None = None,
                   info: dict[str, Any] | None = None) -> Trajectory:
        q = np.ascontiguousarray(q, dtype=float)
        if q.ndim != 2 or q.shape[0] < 2 or not np.all(np.isfinite(q)):
            raise ValueError(f"trajectory: expected a finite table (N ≥ 2, joints), got {q.shape}")
        for name, a in (("dq", dq), ("ff_Nm", ff_Nm)):
            if a is not None and (a.shape != q.shape or not np.all(np.isfinite(a))):
                raise ValueError(f"trajectory: {name}: expected a finite table of shape {q.shape}, got {a.shape}")
        if not 0 <= body_row < q.shape[0] - 1:
            raise ValueError(f"trajectory: body_row: expected 0..{q.shape[0] - 2}, got {body_row}")
        self = cls.__new__(cls)
        self.label = label
        self.dt_s = dt_s
        self.table = q
        self.duration_s = (q.shape[0] - 1) * dt_s
        self.start_q = q[0].copy()
        self._init_tables(None if dq is None else np.ascontiguousarray(dq, dtype=float),
                          None if ff_Nm is None else np.ascontiguousarray(ff_Nm, dtype=float), body_row,
                          list(marks or []), dict(info or {}))
        return self

    @classmethod
    def load(cls, path: str | Path, dt_s: float, label: str = "track") -> Trajectory:
        path = Path(path)
        if not path.is_file():
            raise ValueError(f"trajectory file {path}: not found")
        try:
            if path.suffix == ".npz":
                with np.load(path) as z:
                    return cls(z["t_s"], z["q_rad"], dt_s, label)
            data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
        except (KeyError, ValueError, OSError) as exc:
            raise ValueError(f"trajectory file {path}: expected .npz with t_s, q_rad or CSV t,q1..qN: {exc}") from None
        return cls(data[:, 0], data[:, 1:], dt_s, label)

    def sample(self, t: float, out: np.ndarray) -> np.ndarray:
        """q at time ``t`` (linear interpolation between the table's rows; clamped to the ends)."""
        last = self.table.shape[0] - 1
        x = t / self.dt_s
        if x <= 0.0:
            k, f = 0, 0.0
        elif x >= last:
            k, f = last, 0.0
        else:
            k = int(x)
            f = x - k
        self.k, self.f = k, f
        return self.row(self.table, out)

    def row(self, table: np.ndarray, out: np.ndarray) -> np.ndarray:
        """Another table (velocity, feed-forward) at the time of the last ``sample``."""
        k, f = self.k, self.f
        out[:] = table[k]
        if f > 0.0:
            np.subtract(table[k + 1], table[k], out=self._d)
            self._d *= f
            out += self._d
        return out


class Daemon:
    """The servo daemon for one arm. ``await Daemon(cfg).run()`` runs until SIGTERM/SIGINT or ``request_exit``."""

    def __init__(self, cfg: Config, *, bus_override: str | None = None, socket_path: str | None = None,
                 telemetry_path: str | None = None, rerun: bool = False, log=None) -> None:  # noqa: ANN001
        self.cfg = cfg
        self.log = log or (lambda msg: print(f"dragd: {msg}", flush=True))
        self.socket_path = socket_path or cfg.control.socket
        self.telemetry_path = telemetry_path or cfg.telemetry.path
        self.rerun = rerun or cfg.telemetry.rerun
        self.bus_specs = self._bus_specs(bus_override)
        self.layouts = bus_layouts(cfg)
        self.budget = check_bus_budget(cfg, self.layouts)
        self.model = RobotModel.from_config(cfg)  # URDF + the params' payload (docs/GAP.md)
        if list(self.model.joint_names) != cfg.joint_names:
            raise ValueError(f"{cfg.source}: joints: expected the robot's joints {', '.join(self.model.joint_names)}, "
                             f"got {', '.join(cfg.joint_names)}")
        self.params = LawParams.from_config(cfg)
        n = self.n = len(cfg.joints)
        js = cfg.joints
        self.dt = 1.0 / cfg.loop.rate_Hz
        # constants per joint
        self.kt = self.params.kt_Nm_per_A
        self.rated_A = np.array([j.rated_current_A for j in js])
        self.direction = np.array([j.direction for j in js], dtype=float)
        self.cpr = np.array([j.encoder_counts_per_rev for j in js], dtype=float)
        self.offset_counts = np.array([j.encoder_offset_counts for j in js], dtype=np.int64)
        # unit conversions folded into one factor each (fewer numpy calls per cycle)
        self.rad_per_count = self.direction * 2.0 * math.pi / self.cpr
        self.counts_per_rad = self.cpr / (2.0 * math.pi) * self.direction  # (direction is ±1)
        self.A_per_permille = self.rated_A * self.direction / 1000.0
        self.permille_per_A = self.direction * 1000.0 / self.rated_A
        lo, hi = self.model.position_limits_rad
        self.lim_lo = np.array([j.position_limits_rad[0] if j.position_limits_rad else lo[i] for i, j in enumerate(js)])
        self.lim_hi = np.array([j.position_limits_rad[1] if j.position_limits_rad else hi[i] for i, j in enumerate(js)])
        self.vcap = np.array([j.velocity_limit_rad_s for j in js])
        self.neg_limit_A = -self.params.current_limit_A
        self.wall_hi = self.lim_hi - cfg.safety.soft_limit_margin_rad
        self.wall_lo = self.lim_lo + cfg.safety.soft_limit_margin_rad
        # cycle state (preallocated)
        self.counts = np.zeros(n, dtype=np.int64)
        self.statusword = np.zeros(n, dtype=np.int64)
        self.current_raw = np.zeros(n)  # per mille of rated current, drive's sign
        self.rx = np.zeros(n, dtype=bool)
        self.stale = np.zeros(n, dtype=np.int64)
        self.q = np.zeros(n)
        self.q_hold = np.zeros(n)
        self.q_ref = np.zeros(n)
        self.dq_ref = np.zeros(n)
        self.current_meas_A = np.zeros(n)
        self.tau_g = np.zeros(n)
        self.extra_A = np.zeros(n)
        self.sample_dt_s = self.dt  # interval between this cycle's SYNC and the previous one
        self.breakout = BreakoutState(n).configure(self.params)  # the start-up term's break-out latch (drag)
        self.hold_A = np.zeros(n)
        self.cmd_A = np.zeros(n)
        self.prev_cmd_A = np.zeros(n)
        self.blend_from_A = np.zeros(n)
        self.tmp = np.zeros(n)
        self.cw = np.zeros(n, dtype=np.int64)
        self.target_counts = np.zeros(n, dtype=np.int64)
        self.offset_permille = np.zeros(n, dtype=np.int64)
        self.states = [State.NOT_READY_TO_SWITCH_ON] * n
        self.law_out = LawOutput.zeros(n)
        self.ws = Workspace(n)
        self.vel = VelocityEstimator(self.cpr, cfg.law.velocity_filter_Hz, self.direction)
        self.dq = self.vel.velocity_rad_s
        # modes
        self.mode = Mode.IDLE
        self.prev_mode = Mode.IDLE
        self.blend_t0 = -1.0
        self.t = 0.0
        self.cycles = 0
        self.missed = 0
        self.late_tpdo = 0
        self.enable_t0: float | None = None
        self.fault_reset_phase = 0
        self.faults: list[dict[str, Any]] = []
        self.stop_requested = False
        self.exit_requested = False
        self.trajectory: Trajectory | None = None
        self.track_t0 = 0.0
        self.drive_mode = MODE_CST
        self.mode_switch_pending = False
        self.stop_after_hold_at: float | None = None
        self.feedback_hold = False  # HOLD forced by stale feedback; the requested mode returns when it is fresh
        self.resume_mode = Mode.IDLE
        self.fresh_cycles = 0
        self.feedback_holds = 0
        # TRACK clock: the trajectory time advances at ``track_rate`` (speed override, pause, controlled stop)
        rc = cfg.replay
        self.track_tau = 0.0
        self.track_rate = 1.0
        self.track_override = 1.0
        self.track_state = "idle"  # running | pausing | paused | stopping
        self.track_cycles = 1  # repetitions of the trajectory's body (0: until stopped)
        self.track_cycle = 0
        self._track_t_prev = 0.0
        self._rate_from = 1.0
        self._rate_target = 1.0
        self._rate_t0 = -1.0
        self._rate_T = 1.0
        self.replay: dict[str, Any] | None = None  # the running (or last) replay: program, options, outcome
        self.ff_Nm = np.zeros(n)  # inertial feed-forward of the trajectory sample
        self.pred_A = np.zeros(n)  # the model's current for the commanded motion (TRACK)
        self.pred_extra_Nm = np.zeros(n)  # rigid-body effort predicted but not commanded (plain tracks)
        self.residual_A = np.zeros(n)  # measured - predicted, low-pass filtered
        self.track_err = np.zeros(n)
        self.err_limit = np.array(cfg.per_joint(rc.tracking_error_limit_rad), dtype=float)
        self.res_limit = np.array(cfg.per_joint(rc.residual_current_limit_A), dtype=float)
        self._res_alpha = 1.0 - math.exp(-2.0 * math.pi * rc.residual_filter_Hz * self.dt)
        self._acc_limit = np.array(cfg.per_joint(rc.acceleration_limits_rad_s2), dtype=float)
        self.track_kp = np.array(cfg.per_joint(rc.position_kp_Nm_per_rad), dtype=float)
        self.track_kd = np.array(cfg.per_joint(rc.position_kd_Nm_s_per_rad), dtype=float)
        self.track_ki = np.array(cfg.per_joint(rc.position_ki_Nm_per_rad_s), dtype=float)
        self.track_int_max = np.array(cfg.per_joint(rc.position_integral_limit_A), dtype=float) * self.kt
        self.track_out_max = np.array(cfg.per_joint(rc.position_output_limit_A), dtype=float) * self.kt
        self._small = np.zeros(n, dtype=bool)
        self.track_pid_Nm = np.zeros(n)
        self.track_int_Nm = np.zeros(n)
        self._moving = np.zeros(n, dtype=bool)
        self._err_count = 0
        self._res_count = 0
        self._grace_until = -1.0
        self._grace_s = 0.05
        self._lim_count = 0
        self._over = np.zeros(n, dtype=bool)
        self.tmp3 = np.zeros(n)
        self._ref = self.q
        self.start_offset = np.zeros(n)
        self._start_blend_s = 0.0
        self._full_friction = False
        self._planning = False  # a replay is being planned (the arm held in CSP meanwhile)
        self._cst_task: asyncio.Task | None = None  # the drives' return to CST after a motion
        self.protective_stops = 0
        # teach
        self.teach: TeachRecorder | None = None
        self._worker = None  # the planner process (dragd.teach.worker), started on first use
        self._helper = None  # normal-priority thread that talks to it
        # timing
        self.period_hist = Histogram(0.0, 20_000.0, 10.0)
        self.compute_hist = Histogram(0.0, 5_000.0, 2.0)
        self.rx_hist = Histogram(0.0, 5_000.0, 5.0)
        self.clamp_cycles = 0
        # I/O set up in run()
        self.master: Master | None = None
        self.buses: dict[str, can.BusABC] = {}
        self.encoders: list[RpdoEncoder] = []
        self.telemetry = None
        self.recording = None  # a second writer for a time window (`record start|stop`)
        self.recording_path: str | None = None
        self._writers: list[Any] = []
        self._cols = self._layout_columns()
        self._waiter: asyncio.Future | None = None
        self._rx_count = 0  # joints whose position TPDO arrived this cycle (the read step ends at n)
        self._tpdo: dict[str, dict[int, tuple[int, struct.Struct, tuple[str, ...]]]] = {}
        self.enabled = np.zeros(n, dtype=bool)
        self._cw_mode: Mode | None = None
        self._cw_statusword = np.full(n, -1, dtype=np.int64)
        self._cw_changed = np.zeros(n, dtype=bool)
        self._near = np.zeros(n, dtype=bool)
        self.tmp2 = np.zeros(n)
        self._sync_msgs: list[tuple[can.BusABC, can.Message]] = []
        self._hb_msgs: list[tuple[can.BusABC, can.Message]] = []
        self._cmd_msgs: list[tuple[can.BusABC, can.Message, RpdoEncoder]] = []

    # ------------------------------------------------------------------------------------------ setup

    def _bus_specs(self, override: str | None) -> dict[str, Any]:
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

    def _build_io(self) -> None:
        for name, layout in self.layouts.items():
            bus = self.buses[name]
            fd = layout.fd
            table = self._tpdo.setdefault(name, {})
            for fr in layout.frames:
                if fr.direction == "tpdo":
                    (slot,) = fr.slots
                    table[fr.cob_id] = (slot.joint, struct.Struct(slot.fmt), slot.fields)
                else:
                    enc = RpdoEncoder(fr, fd, min_interval_s=1.0 / fr.max_rate_Hz)
                    msg = can.Message(arbitration_id=fr.cob_id, data=enc.buffer, is_extended_id=False,
                                      is_fd=fd, bitrate_switch=fd, dlc=len(enc.buffer))
                    self._cmd_msgs.append((bus, msg, enc))
            self._sync_msgs.append((bus, can.Message(arbitration_id=SYNC_COB_ID, data=b"", is_extended_id=False)))
            self._hb_msgs.append((bus, can.Message(arbitration_id=0x700 + self.cfg.master.node_id, data=b"\x05",
                                                   is_extended_id=False)))
        self._emcy = {0x80 + j.node_id: i for i, j in enumerate(self.cfg.joints)}

    def _listener(self, bus_name: str) -> can.Listener:
        on_frame, table = self._on_frame, self._tpdo.setdefault(bus_name, {})

        class _Rx(can.Listener):
            def on_message_received(self, msg: can.Message) -> None:
                on_frame(msg, table)

        return _Rx()

    def _on_frame(self, msg: can.Message, table: dict[int, tuple[int, struct.Struct, tuple[str, ...]]]) -> None:
        """Runs in the loop thread (Notifier with add_reader): decode TPDOs into the cycle's arrays.

        Error frames are counted, never decoded: their class bits can equal a COB-ID (0x081 = a node 1 EMCY).
        """
        if msg.is_error_frame:
            self.error_frames += 1
            return
        entry = table.get(msg.arbitration_id)
        if entry is not None:
            j, codec, fields = entry
            if len(msg.data) < codec.size:
                return
            values = codec.unpack_from(msg.data)
            for f, v in zip(fields, values):
                if f == "position":
                    self.counts[j] = v
                elif f == "current":
                    self.current_raw[j] = v
                else:
                    self.statusword[j] = v
            if "position" in fields and not self.rx[j]:
                self.rx[j] = True
                self._rx_count += 1
                if self._rx_count >= self.n and self._waiter is not None and not self._waiter.done():
                    self._waiter.set_result(True)
            return
        j = self._emcy.get(msg.arbitration_id)
        if j is not None and len(msg.data) >= 3:
            code = msg.data[0] | (msg.data[1] << 8)
            if code != 0:
                self._fault(j, f"EMCY 0x{code:04X} (error register 0x{msg.data[2]:02X}) from node "
                               f"{self.cfg.joints[j].node_id}", code)

    # ------------------------------------------------------------------------------------------ safety

    def _fault(self, j: int | None, text: str, code: int = 0) -> None:
        """A safety reaction: every axis to a safe state (quick stop → brakes), mode FAULT."""
        self.faults.append({"t_s": round(self.t, 4), "joint": self.cfg.joints[j].name if j is not None else None,
                            "node_id": self.cfg.joints[j].node_id if j is not None else None, "code": code,
                            "text": text})
        if len(self.faults) > 100:
            del self.faults[:-100]
        try:  # logged after this cycle, not inside it
            asyncio.get_running_loop().call_soon(self.log, f"fault at t={self.t:.3f} s: {text}")
        except RuntimeError:
            self.log(f"fault: {text}")
        self.feedback_hold = False
        if self.replay is not None and self.replay.get("outcome") is None and self.trajectory is not None:
            self.replay["outcome"] = f"fault: {text}"
            self.replay["ended_t_s"] = round(self.t, 4)
        if self.teach is not None and self.telemetry is not None:
            self.telemetry.event("teach_fault", program=self.teach.name, text=text)
        if self.mode != Mode.FAULT:
            self.prev_mode = self.mode
            self.mode = Mode.FAULT
            self.enable_t0 = None
            self.trajectory = None
            self.track_state = "idle"
            self.ff_Nm.fill(0.0)
            if self.telemetry is not None:
                self.telemetry.event("fault", text=text, code=code)

    # ------------------------------------------------------------------------------------------ commands

    def start(self) -> None:
        """Enable the drives (fault reset first) and hold the pose."""
        if self.mode == Mode.FAULT:
            self.faults.clear()
        self.q_hold[:] = self.q
        self.stop_after_hold_at = None
        self.feedback_hold = False
        self.fault_reset_phase = 2  # two cycles: bit 7 low, then high (rising edge), for drives in fault
        self._set_mode(Mode.HOLD, blend=False)
        self.enable_t0 = self.t

    def stop(self) -> None:
        """Ramp to hold, then disable (brakes on)."""
        if self.mode in (Mode.IDLE, Mode.FAULT):
            return
        self.feedback_hold = False
        if self.trajectory is not None:  # a motion: hold where the arm is, drives back to CST, then disable
            self._end_track("stopped (drives disabled)", hold_at_ref=False)
        if self.mode != Mode.HOLD:
            self.q_hold[:] = self.q
            self._set_mode(Mode.HOLD)
        self.stop_after_hold_at = self.t + self.cfg.safety.mode_ramp_s + 0.05

    def set_mode(self, name: str) -> None:
        modes = {"idle": Mode.IDLE, "hold": Mode.HOLD, "drag": Mode.DRAG}
        if name not in modes:
            raise ValueError(f"mode: expected one of {', '.join(modes)}, got '{name}'")
        target = modes[name]
        if target == Mode.IDLE:
            self.stop()
            return
        if self.mode in (Mode.IDLE, Mode.FAULT):
            raise ValueError(f"mode {name}: the drives are disabled ({MODE_NAMES[self.mode]}); run 'dragd start' first")
        if self.mode == Mode.TRACK:
            raise ValueError(f"mode {name}: a {self.trajectory.label if self.trajectory else 'track'} motion is running; "
                             "stop it first")
        if target == Mode.HOLD:
            self.q_hold[:] = self.q
        self.stop_after_hold_at = None
        if self.feedback_hold:  # the feedback hold stays; the new request is what it resumes
            self.resume_mode = target
            return
        self._set_mode(target)

    def _set_mode(self, mode: Mode, blend: bool = True) -> None:
        if mode == self.mode:
            return
        self.blend_from_A[:] = self.prev_cmd_A
        self.blend_t0 = self.t if blend else -1.0
        self.prev_mode, self.mode = self.mode, mode
        if mode == Mode.DRAG:
            self.breakout.reset(self.t)
        if self.telemetry is not None:
            self.telemetry.event("mode", mode=MODE_NAMES[mode], previous=MODE_NAMES[self.prev_mode])

    async def track(self, traj: Trajectory, *, rate: float = 1.0, cycles: int = 1) -> None:
        """Switch the drives to CSP and follow ``traj`` (entry point of identification runs and replay).

        ``rate`` is the speed override (the trajectory clock's rate), ``cycles`` the repetitions of its body
        (rows ``body_row`` to the end; 0: until ``track_stop``).
        """
        if self.mode not in (Mode.HOLD, Mode.DRAG):
            raise ValueError(f"track: expected the arm enabled in hold or drag, it is {MODE_NAMES[self.mode]}")
        if self.trajectory is not None:
            raise ValueError("track: a motion is running; stop it first")
        if traj.table.shape[1] != self.n:
            raise ValueError(f"track: expected {self.n} joints per sample, got {traj.table.shape[1]}")
        if not 0.0 < rate <= 1.0:
            raise ValueError(f"track: speed: expected a fraction in (0, 1], got {rate}")
        self._take_over_feedback_hold("track")
        start_err = np.abs(traj.start_q - self.q)
        if np.any(start_err > 0.02):
            raise ValueError(f"track: the trajectory starts {np.degrees(start_err.max()):.2f}° from the current pose "
                             "(max 1.1°); move there first")
        if self.mode != Mode.HOLD:
            self.q_hold[:] = self.q
        self._set_mode(Mode.HOLD)
        await self._settle_drive_mode()
        if self.drive_mode != MODE_CSP:
            await self._switch_drive_mode(MODE_CSP)
        if self.mode != Mode.HOLD:  # a fault or stop while the drives switched
            raise ValueError(f"track: the arm left hold while the drives switched to CSP ({MODE_NAMES[self.mode]})")
        self.track_tau = 0.0
        self.track_rate = self._rate_from = self._rate_target = self.track_override = float(rate)
        self._rate_t0 = -1.0
        self.track_state = "running"
        self.track_cycles = int(cycles)
        self.track_cycle = 0
        self._track_t_prev = self.t
        self._err_count = self._res_count = self._lim_count = 0
        self.residual_A.fill(0.0)
        self.ff_Nm.fill(0.0)
        self.pred_extra_Nm.fill(0.0)
        self.track_pid_Nm.fill(0.0)
        self.track_int_Nm.fill(0.0)
        traj.sample(0.0, self.q_ref)
        # a replay's move to start begins exactly where the arm is: the small difference to the planned start
        # fades out over the move (no step in the position target)
        np.subtract(self.q, self.q_ref, out=self.start_offset)
        self._start_blend_s = traj.body_start_s if traj.body_start_s > 0.0 else 0.0
        if self._start_blend_s > 0.0:
            self.q_ref += self.start_offset
        self.dq_ref.fill(0.0)
        self._full_friction = traj.dq_table is not None  # replay plans; identification tracks as before
        self.trajectory = traj
        self.track_t0 = self.t
        self._set_mode(Mode.TRACK)

    def _take_over_feedback_hold(self, what: str) -> None:
        """A motion request supersedes a feedback hold's return to drag, once the feedback is fresh again."""
        if not self.feedback_hold:
            return
        if self.fresh_cycles < 10:
            raise ValueError(f"{what}: the arm is held because feedback was late (stale TPDOs); try again when "
                             "'dragd status' shows feedback_hold false")
        self.feedback_hold = False
        self.resume_mode = Mode.HOLD

    # -- TRACK clock: speed override, pause / resume, controlled stop (all decelerate along the path)

    def _ramp_rate(self, target: float) -> None:
        """Ramp the trajectory clock's rate to ``target`` (smoothstep), slower when the path is fast."""
        tr = self.trajectory
        delta = abs(target - self.track_rate)
        T = self.cfg.replay.ramp_s * max(delta, 0.25)
        if tr is not None and tr.dq_table is not None:
            # the extra acceleration q'(τ)·dr/dt stays within half the configured acceleration limit
            tr.row(tr.dq_table, self.tmp3)
            np.abs(self.tmp3, out=self.tmp3)
            need = 1.5 * delta * float(np.max(self.tmp3 / self._acc_limit)) / 0.5
            T = max(T, need)
        self._rate_from = self.track_rate
        self._rate_target = float(target)
        self._rate_t0 = self.t
        self._rate_T = max(T, 0.02)

    def track_pause(self) -> str:
        if self.trajectory is None or self.mode != Mode.TRACK:
            raise ValueError("pause: no motion is running")
        if self.track_state == "stopping":
            raise ValueError("pause: the motion is stopping")
        if self.track_state in ("running",):
            self.track_state = "pausing"
            self._ramp_rate(0.0)
        return self.track_state

    def track_resume(self) -> str:
        if self.trajectory is None or self.mode != Mode.TRACK:
            raise ValueError("resume: no motion is running")
        if self.track_state == "stopping":
            raise ValueError("resume: the motion is stopping")
        if self.track_state in ("pausing", "paused"):
            self.track_state = "running"
            self._ramp_rate(self.track_override)
        return self.track_state

    def track_stop(self) -> str:
        """Controlled stop: decelerate along the path, then hold where the path stopped."""
        if self.trajectory is None or self.mode != Mode.TRACK:
            raise ValueError("stop: no motion is running")
        if self.track_state != "stopping":
            self.track_state = "stopping"
            if self.track_rate > 0.0:
                self._ramp_rate(0.0)
            else:
                self._rate_t0 = -1.0
        return self.track_state

    def set_speed_override(self, speed: float) -> float:
        if not 0.0 < speed <= 1.0:
            raise ValueError(f"speed: expected a fraction in (0, 1], got {speed}")
        self.track_override = float(speed)
        if self.trajectory is not None and self.mode == Mode.TRACK and self.track_state == "running":
            self._ramp_rate(self.track_override)
        return self.track_override

    def _end_track(self, outcome: str, hold_at_ref: bool = True) -> None:
        """Leave TRACK for HOLD (at the reference, or where the arm is), drives back to CST."""
        if hold_at_ref:
            self.q_hold[:] = self.q_ref
        else:
            self.q_hold[:] = self.q
        tr = self.trajectory
        self.trajectory = None
        self.track_state = "idle"
        self.ff_Nm.fill(0.0)
        self._set_mode(Mode.HOLD)
        if self.replay is not None and self.replay.get("outcome") is None:
            self.replay["outcome"] = outcome
            self.replay["ended_t_s"] = round(self.t, 4)
            self.replay["cycles_done"] = self.track_cycle + (1 if outcome == "done" else 0)
        if self.telemetry is not None:
            self.telemetry.event("track_end", label=tr.label if tr else None, outcome=outcome)
        self._cst_task = asyncio.get_running_loop().create_task(self._switch_drive_mode(MODE_CST))

    async def _settle_drive_mode(self) -> None:
        """Let a pending return of the drives to CST finish before switching them again."""
        task = self._cst_task
        if task is not None and not task.done():
            try:
                await task
            except DriveError:
                pass

    def _protective_stop(self, j: int | None, kind: str, text: str) -> None:
        """A monitor tripped during TRACK: stop now and hold where the arm is (not a drive fault)."""
        self.protective_stops += 1
        self.faults.append({"t_s": round(self.t, 4), "joint": self.cfg.joints[j].name if j is not None else None,
                            "node_id": self.cfg.joints[j].node_id if j is not None else None, "code": 0,
                            "text": text, "reaction": "hold", "kind": kind})
        if len(self.faults) > 100:
            del self.faults[:-100]
        try:
            asyncio.get_running_loop().call_soon(self.log, f"protective stop at t={self.t:.3f} s: {text}")
        except RuntimeError:
            self.log(f"protective stop: {text}")
        if self.telemetry is not None:
            self.telemetry.event("protective_stop", kind=kind, text=text)
        self._end_track(f"{kind}: {text}", hold_at_ref=False)

    def _track_step(self) -> None:
        """One cycle of TRACK: advance the clock, sample the reference (+ velocity, feed-forward), monitor."""
        tr = self.trajectory
        assert tr is not None
        elapsed = self.t - self._track_t_prev
        self._track_t_prev = self.t
        if elapsed > 2.5 * self.dt:
            # the loop stalled (missed cycles): the reference waits instead of jumping ahead along the path, and
            # after a long stall the monitors give the drives' catch-up transient a moment
            if elapsed > 5.5 * self.dt:
                self._grace_until = self.t + self._grace_s
            elapsed = self.dt
        if self._rate_t0 >= 0.0:
            x = (self.t - self._rate_t0) / self._rate_T
            if x >= 1.0:
                self.track_rate = self._rate_target
                self._rate_t0 = -1.0
            else:
                self.track_rate = self._rate_from + (self._rate_target - self._rate_from) * x * x * (3.0 - 2.0 * x)
        self.track_tau += self.track_rate * elapsed
        finished = False
        if self.track_tau >= tr.duration_s:
            more = self.track_cycles == 0 or self.track_cycle + 1 < self.track_cycles
            if more and self.track_state != "stopping" and tr.duration_s > tr.body_start_s:
                self.track_tau -= tr.duration_s - tr.body_start_s
                self.track_cycle += 1
            else:
                self.track_tau = tr.duration_s
                finished = True
        if self._rate_t0 < 0.0 and self.track_rate == 0.0:
            if self.track_state == "pausing":
                self.track_state = "paused"
            elif self.track_state == "stopping":
                finished = True
        self.dq_ref[:] = self.q_ref
        tr.sample(self.track_tau, self.q_ref)
        if tr.dq_table is not None:
            tr.row(tr.dq_table, self.dq_ref)
            self.dq_ref *= self.track_rate
        else:
            self.dq_ref -= self.q_ref
            self.dq_ref /= -max(elapsed, self.dt)
        if tr.ff_table is not None:
            tr.row(tr.ff_table, self.ff_Nm)
            self.ff_Nm *= self.track_rate * self.track_rate
        if tr.pred_table is not None:
            tr.row(tr.pred_table, self.pred_extra_Nm)
            self.pred_extra_Nm *= self.track_rate * self.track_rate
        if self._start_blend_s > 0.0 and self.track_cycle == 0 and self.track_tau < self._start_blend_s:
            x = self.track_tau / self._start_blend_s
            np.multiply(self.start_offset, 1.0 - x * x * (3.0 - 2.0 * x), out=self.tmp3)
            self.q_ref += self.tmp3
            np.multiply(self.start_offset, -6.0 * x * (1.0 - x) / self._start_blend_s * self.track_rate, out=self.tmp3)
            self.dq_ref += self.tmp3
        if finished:
            self._end_track("stopped" if self.track_state == "stopping" else "done")
            return
        if self._full_friction:
            self._position_loop(elapsed)
        self._monitor()

    def _position_loop(self, elapsed: float) -> None:
        """Replay: PD + integral on q_ref − q into the torque offset, around the drives' own CSP loops.

        The feed-forward leaves the model's errors (a torque constant 1-2 % off under 60 N·m of gravity is
        ≈ 1 N·m) to the drive's position loop, whose stiffness turns them into position error. The daemon's loop
        adds stiffness and learns the bias with an integral that only runs while a joint's reference moves (kinetic
        friction; at rest stiction would make it hunt) and is frozen at the stops.
        """
        e, v, pid = self.tmp3, self.tmp, self.track_pid_Nm
        np.subtract(self.q_ref, self.q, out=e)
        np.abs(self.dq_ref, out=v)
        np.greater(v, 0.005, out=self._moving)
        np.abs(e, out=v)  # a large error is a disturbance (or a stall), not a bias to learn
        np.less(v, 0.0035, out=self._small)
        self._moving &= self._small
        np.multiply(e, self.track_ki * elapsed, out=v)
        v *= self._moving
        self.track_int_Nm += v
        np.minimum(self.track_int_Nm, self.track_int_max, out=self.track_int_Nm)
        np.maximum(self.track_int_Nm, -self.track_int_max, out=self.track_int_Nm)
        np.multiply(e, self.track_kp, out=pid)
        np.subtract(self.dq_ref, self.dq, out=v)
        v *= self.track_kd
        pid += v
        pid += self.track_int_Nm
        np.minimum(pid, self.track_out_max, out=pid)  # bounded authority: the drive's loop stays in charge
        np.maximum(pid, -self.track_out_max, out=pid)

    def _monitor(self) -> None:
        """Tracking error, residual current and position limits during TRACK: beyond a bound → stop, hold."""
        k = self.cfg.replay.monitor_cycles
        if self.stale.max() >= 5:  # positions several cycles old (late TPDOs): count again once they are fresh
            self._grace_until = max(self._grace_until, self.t + 0.03)
        # after a loop stall or late feedback: a bound exceeded counts only at twice the bound (a real collision
        # or blockage still stops the motion; the drives' catch-up transient does not)
        m = 2.0 if self.t < self._grace_until else 1.0
        np.subtract(self.q, self.q_ref, out=self.track_err)
        np.abs(self.track_err, out=self.tmp3)
        self.tmp3 /= self.err_limit
        if self.tmp3.max() > m:
            self._err_count += 1
            if self._err_count >= k:
                j = int(self.tmp3.argmax())
                self._protective_stop(j, "tracking_error",
                                      f"tracking error of {self.cfg.joints[j].name} "
                                      f"{math.degrees(abs(self.track_err[j])):.2f}° beyond "
                                      f"{math.degrees(self.err_limit[j]):.2f}°")
                return
        else:
            self._err_count = 0
        # residual: measured current minus the model's current for the commanded motion (low-pass)
        np.subtract(self.current_meas_A, self.pred_A, out=self.tmp3)
        self.tmp3 -= self.residual_A
        self.tmp3 *= self._res_alpha
        self.residual_A += self.tmp3
        np.abs(self.residual_A, out=self.tmp3)
        self.tmp3 /= self.res_limit
        if self.tmp3.max() > m and self.trajectory.residual_monitor:
            self._res_count += 1
            if self._res_count >= k:
                j = int(self.tmp3.argmax())
                self._protective_stop(j, "residual_current",
                                      f"residual current of {self.cfg.joints[j].name} {self.residual_A[j]:+.2f} A beyond "
                                      f"±{self.res_limit[j]:.2f} A (collision?)")
                return
        else:
            self._res_count = 0
        np.less(self.q, self.lim_lo, out=self._over)
        over = np.count_nonzero(self._over) > 0
        np.greater(self.q, self.lim_hi, out=self._over)
        if over or np.count_nonzero(self._over):
            self._lim_count += 1
            if self._lim_count >= k:
                np.subtract(self.lim_lo, self.q, out=self.tmp3)
                np.maximum(self.tmp3, self.q - self.lim_hi, out=self.tmp3)
                j = int(self.tmp3.argmax())
                self._protective_stop(j, "soft_limit", f"{self.cfg.joints[j].name} at {self.q[j]:.3f} rad outside its "
                                                       f"limits [{self.lim_lo[j]:.3f}, {self.lim_hi[j]:.3f}]")
        else:
            self._lim_count = 0

    async def _switch_drive_mode(self, mode: int) -> None:
        assert self.master is not None
        self.mode_switch_pending = True
        try:
            for rt in self.master.runtimes.values():
                for node_id in rt.nodes:
                    await self.master.run_sdo(self.master.set_mode, rt, node_id, mode)
            self.drive_mode = mode
        finally:
            self.mode_switch_pending = False

    # ------------------------------------------------------------------------------------------ cycle

    def _drive_controlwords(self) -> None:
        """CiA 402 walk per drive from its statusword, toward the state the mode needs.

        Skipped (the controlwords stay) while no statusword, mode or reset phase changed and no enable is pending.
        """
        want_enabled = self.mode in (Mode.HOLD, Mode.DRAG, Mode.TRACK)
        if (self.fault_reset_phase == 0 and self.enable_t0 is None and self.mode == self._cw_mode
                and np.count_nonzero(np.not_equal(self.statusword, self._cw_statusword, out=self._cw_changed)) == 0):
            return
        self._cw_mode = self.mode
        self._cw_statusword[:] = self.statusword
        for i in range(self.n):
            try:
                st = decode_statusword(int(self.statusword[i]))
            except ValueError:
                st = State.NOT_READY_TO_SWITCH_ON
            self.states[i] = st
            self.enabled[i] = st == State.OPERATION_ENABLED
            if self.mode == Mode.FAULT:
                self.cw[i] = CMD_QUICK_STOP if st == State.OPERATION_ENABLED else CMD_DISABLE_VOLTAGE
            elif want_enabled:
                if st in (State.FAULT, State.FAULT_REACTION_ACTIVE):
                    # rising edge of bit 7: one cycle low, then high
                    self.cw[i] = CW_FAULT_RESET if self.fault_reset_phase == 1 else CMD_DISABLE_VOLTAGE
                else:
                    self.cw[i] = next_controlword(st, State.OPERATION_ENABLED)
            else:
                self.cw[i] = CMD_SHUTDOWN if st not in (State.FAULT, State.FAULT_REACTION_ACTIVE) else CMD_DISABLE_VOLTAGE
        if self.fault_reset_phase > 0:
            self.fault_reset_phase -= 1
        if want_enabled and self.enable_t0 is not None:
            if all(s == State.OPERATION_ENABLED for s in self.states):
                self.enable_t0 = None
            elif self.t - self.enable_t0 > self.cfg.master.enable_timeout_s:
                bad = [f"node {self.cfg.joints[i].node_id} in {DRIVE_STATE_NAMES[s]} (statusword 0x{int(self.statusword[i]):04X})"
                       for i, s in enumerate(self.states) if s != State.OPERATION_ENABLED]
                self._fault(None, f"drives did not reach operation enabled within "
                                  f"{self.cfg.master.enable_timeout_s:.1f} s: {', '.join(bad)}")
        elif want_enabled and self.enable_t0 is None:
            for i, s in enumerate(self.states):
                if s in (State.FAULT, State.FAULT_REACTION_ACTIVE):
                    self._fault(i, f"node {self.cfg.joints[i].node_id} reports {DRIVE_STATE_NAMES[s]} "
                                   f"(statusword 0x{int(self.statusword[i]):04X})")
                    break
                if s == State.QUICK_STOP_ACTIVE or s == State.SWITCH_ON_DISABLED:
                    self._fault(i, f"node {self.cfg.joints[i].node_id} left operation enabled: {DRIVE_STATE_NAMES[s]} "
                                   f"(statusword 0x{int(self.statusword[i]):04X})")
                    break

    def _safety_terms(self, out: np.ndarray) -> None:
        """Soft-limit walls (spring/damper before the hard stops) and, in drag, the speed cap: as current [A].

        Allocation-free; the usual cycle (no joint near a wall, none above its speed cap) costs five ufuncs."""
        s = self.cfg.safety
        q, dq, p, v, m = self.q, self.dq, self.tmp, self.tmp2, self._near
        out.fill(0.0)
        np.greater(q, self.wall_hi, out=m)
        near = np.count_nonzero(m) > 0  # (count_nonzero: 6× cheaper than .any() on a few joints)
        np.less(q, self.wall_lo, out=m)
        near = near or np.count_nonzero(m) > 0
        fast = False
        if self.mode == Mode.DRAG:
            np.abs(dq, out=p)
            np.greater(p, self.vcap, out=m)
            fast = np.count_nonzero(m) > 0
        if not (near or fast):
            return
        if near:
            # upper wall: penetration p = q - (hi - margin) > 0 pushes back, damping only while moving further in
            np.subtract(q, self.lim_hi, out=p)
            np.maximum(dq, 0.0, out=v)
            self._wall(out, p, v, 1.0)
            np.subtract(self.lim_lo, q, out=p)  # lower wall, mirrored
            np.minimum(dq, 0.0, out=v)
            self._wall(out, p, v, -1.0)
        if fast:  # drag speed cap: viscous brake on the excess speed
            np.abs(dq, out=p)
            p -= self.vcap
            np.maximum(p, 0.0, out=p)
            np.sign(dq, out=v)
            p *= v
            p *= s.speed_cap_damping_Nm_s_per_rad
            out -= p
        out /= self.kt

    def _wall(self, out: np.ndarray, p: np.ndarray, v: np.ndarray, side: float) -> None:
        """out −= side·k·max(p + margin, 0) + c·v where penetrating (``v``: the speed component into the wall)."""
        s, m = self.cfg.safety, self._near
        p += s.soft_limit_margin_rad
        np.maximum(p, 0.0, out=p)
        np.greater(p, 0.0, out=m)
        v *= m
        p *= side * s.wall_stiffness_Nm_per_rad
        v *= s.wall_damping_Nm_s_per_rad
        out -= p
        out -= v

    def _mode_command(self, mode: Mode, out: np.ndarray) -> None:
        """The command current [A] of one mode (before the blend)."""
        s = self.cfg.safety
        if mode in (Mode.IDLE, Mode.FAULT):
            out.fill(0.0)
            return
        if mode == Mode.DRAG:
            compensate(self.tau_g, self.dq, self.t, self.params, self.law_out, self.ws, self.extra_A, self.breakout,
                       self.q)
            out[:] = self.law_out.current_A
            return
        if mode == Mode.TRACK:  # CSP: the drive's position loop tracks; the offset feeds gravity + friction forward
            friction_current(self.dq_ref, self.params, out, self.ws)
            if self._full_friction and 0.0 < self.params.friction_scale != 1.0:
                out /= self.params.friction_scale  # replay: the full belief (the drag law's under-compensation
                # guards a released joint against run-away; in CSP it would only leave more to the drive's loop)
            out *= self.kt
            out += self.ff_Nm  # + the planned motion's M(q)q̈ + C(q,q̇)q̇ (replay plans)
        else:  # HOLD: gravity + joint PD around the pose
            np.subtract(self.q_hold, self.q, out=out)
            out *= s.hold_kp_Nm_per_rad
            np.multiply(self.dq, s.hold_kd_Nm_s_per_rad, out=self.tmp2)
            out -= self.tmp2
        out += self.tau_g
        out /= self.kt
        if mode == Mode.TRACK:  # the model's current for the commanded motion (residual monitor)
            np.divide(self.pred_extra_Nm, self.kt, out=self.pred_A)
            self.pred_A += out
            if self._full_friction:  # replay: the daemon's position loop around the drive's own
                np.divide(self.track_pid_Nm, self.kt, out=self.tmp2)
                out += self.tmp2
        out += self.extra_A
        np.minimum(out, self.params.current_limit_A, out=out)
        np.maximum(out, self.neg_limit_A, out=out)

    def cycle_compute(self) -> None:
        """estimate → compute: from the arrays the read step filled to the command arrays (no I/O)."""
        # estimate
        np.subtract(self.counts, self.offset_counts, out=self.tmp, casting="unsafe")
        np.multiply(self.tmp, self.rad_per_count, out=self.q)
        self.vel.update(self.counts, self.sample_dt_s, self.rx)
        np.multiply(self.current_raw, self.A_per_permille, out=self.current_meas_A)
        self.model.gravity(self.q, self.tau_g)
        if self.mode == Mode.DRAG and self.params.use_breakout and self.params.use_startup:
            breakout_update(self.q, self.dq, self.t, self.params, self.breakout, self.tau_g)
        if self.trajectory is not None and self.mode == Mode.TRACK:
            self._track_step()
        if self.teach is not None:
            self.teach.add(self.t, self.q)
        # compute
        self._drive_controlwords()
        self._safety_terms(self.extra_A)
        self._mode_command(self.mode, self.cmd_A)
        if self.blend_t0 >= 0.0:
            x = (self.t - self.blend_t0) / self.cfg.safety.mode_ramp_s
            if x >= 1.0:
                self.blend_t0 = -1.0
            else:
                lam = x * x * (3.0 - 2.0 * x)
                # blend from the command at the switch instant to the new law's command
                self.cmd_A *= lam
                np.multiply(self.blend_from_A, 1.0 - lam, out=self.tmp)  # no temporary array in the cycle
                self.cmd_A += self.tmp
        if self.stop_after_hold_at is not None and self.t >= self.stop_after_hold_at:
            self.stop_after_hold_at = None
            self._set_mode(Mode.IDLE, blend=False)
        self.cmd_A *= self.enabled  # nothing is commanded to a drive that is not enabled
        self.prev_cmd_A[:] = self.cmd_A
        if np.count_nonzero(self.law_out.clamped):
            self.clamp_cycles += 1
        # drive units
        np.multiply(self.cmd_A, self.permille_per_A, out=self.tmp)
        np.rint(self.tmp, out=self.tmp)
        np.minimum(self.tmp, 32767.0, out=self.tmp)
        np.maximum(self.tmp, -32768.0, out=self.tmp)
        self.offset_permille[:] = self.tmp
        # CSP target: the reference; after a motion (hold while the drives are still in CSP) the hold pose, so
        # the drive's own position loop keeps pulling to the same point until it is back in CST
        if self.mode == Mode.TRACK:
            ref = self.q_ref
        elif self.mode == Mode.HOLD and self.drive_mode == MODE_CSP:
            ref = self.q_hold
        else:
            ref = self.q
        self._ref = ref
        np.multiply(ref, self.counts_per_rad, out=self.tmp)
        np.rint(self.tmp, out=self.tmp)
        self.target_counts[:] = self.tmp
        self.target_counts += self.offset_counts

    def _write(self) -> None:
        for bus, msg, enc in self._cmd_msgs:
            buf = enc.buffer
            for j, off, codec, fields in enc.slots:
                if len(fields) == 3:
                    codec.pack_into(buf, off, int(self.cw[j]), int(self.target_counts[j]), int(self.offset_permille[j]))
                elif fields[0] == "torque_offset":
                    codec.pack_into(buf, off, int(self.offset_permille[j]))
                else:
                    codec.pack_into(buf, off, int(self.cw[j]))
            if not enc.due(self.t):
                continue
            try:
                bus.send(msg, timeout=0)
                enc.sent(self.t)
            except can.CanError:
                self.tx_errors += 1

    tx_errors = 0
    error_frames = 0
    scheduler = "not started"

    def _log_row(self, period_us: float, compute_us: float) -> None:
        for tw in self._writers:
            row = tw.begin()
            if row is not None:
                self._fill_row(row, period_us, compute_us)
                tw.commit()

    def _fill_row(self, row: np.ndarray, period_us: float, compute_us: float) -> None:
        c = self._cols
        row[c["t_s"]] = self.t
        row[c["mode"]] = int(self.mode)
        row[c["q_rad"]] = self.q
        row[c["dq_rad_s"]] = self.dq
        row[c["current_measured_A"]] = self.current_meas_A
        row[c["current_command_A"]] = self.cmd_A
        if self.mode == Mode.DRAG:
            row[c["gravity_A"]] = self.law_out.gravity_A
        else:
            np.divide(self.tau_g, self.kt, out=row[c["gravity_A"]])  # into the row: no temporary array
        row[c["friction_A"]] = self.law_out.friction_A if self.mode == Mode.DRAG else 0.0
        row[c["startup_A"]] = self.law_out.startup_A if self.mode == Mode.DRAG else 0.0
        row[c["damping_A"]] = self.law_out.damping_A if self.mode == Mode.DRAG else 0.0
        row[c["back_emf_A"]] = self.law_out.back_emf_A if self.mode == Mode.DRAG else 0.0
        row[c["effects_A"]] = (self.law_out.effects_A if self.mode == Mode.DRAG and self.params.effects is not None
                               else 0.0)  # with the terms above (+ safety walls) the command before the clamp
        row[c["statusword"]] = self.statusword
        row[c["rx"]] = self.rx
        row[c["period_us"]] = period_us
        row[c["compute_us"]] = compute_us
        # the position reference (TRACK: the path; HOLD: the hold pose, whether the drives' CSP loop or the PD
        # of CST holds it; otherwise where the arm is)
        row[c["q_ref_rad"]] = self.q_hold if self.mode == Mode.HOLD else self._ref
        track = self.mode == Mode.TRACK
        row[c["track_t_s"]] = self.track_tau if track else -1.0
        row[c["residual_A"]] = self.residual_A if track else 0.0

    async def _cycle_loop(self) -> None:
        loop = asyncio.get_running_loop()
        ticker = Ticker(self.dt, loop)
        ticker.start()
        deadline_s = self.cfg.loop.tpdo_deadline_us * 1e-6
        hb_every = max(1, round(self.cfg.master.heartbeat_ms * 1e-3 / self.dt))
        last_tick = None
        hold_after = self.cfg.loop.stale_cycles_hold
        disable_after = self.cfg.loop.stale_cycles_disable
        primed = False
        try:
            while not self.exit_requested:
                expirations = await ticker.wait()
                t_tick = time.perf_counter()
                if expirations > 1:
                    self.missed += expirations - 1
                period_us = (t_tick - last_tick) * 1e6 if last_tick is not None else self.dt * 1e6
                self.sample_dt_s = period_us * 1e-6  # SYNC goes out right after the tick: the sampling interval
                last_tick = t_tick
                self.t += self.dt * expirations
                # read
                self.rx.fill(False)
                self._rx_count = 0
                self._waiter = loop.create_future()
                for bus, msg in self._sync_msgs:
                    try:
                        bus.send(msg, timeout=0)
                    except can.CanError:
                        self.tx_errors += 1
                handle = loop.call_at(loop.time() + deadline_s, self._deadline)
                await self._waiter
                handle.cancel()
                self._waiter = None
                t_rx = time.perf_counter()
                self.rx_hist.add((t_rx - t_tick) * 1e6)
                complete = self._rx_count >= self.n
                if not complete:
                    self.late_tpdo += 1
                np.add(self.stale, 1, out=self.stale)
                np.copyto(self.stale, 0, where=self.rx)  # (a boolean-mask assignment would allocate)
                if not primed:
                    if not complete:
                        continue  # wait for a first full set of positions before computing anything
                    self.vel.reset(self.counts)
                    primed = True
                self._feedback_watch(hold_after, disable_after)
                # estimate + compute
                self.cycle_compute()
                # write
                self._write()
                if self.cycles % hb_every == 0:
                    for bus, msg in self._hb_msgs:
                        try:
                            bus.send(msg, timeout=0)
                        except can.CanError:
                            self.tx_errors += 1
                t_done = time.perf_counter()
                compute_us = (t_done - t_rx) * 1e6
                self.compute_hist.add(compute_us)
                if self.cycles > 0:
                    self.period_hist.add(period_us)
                self.cycles += 1
                self._log_row(period_us, compute_us)
        finally:
            ticker.close()

    def _feedback_watch(self, hold_after: int, disable_after: int) -> None:
        """Stale TPDOs: hold after ``hold_after`` cycles, fault (disable) after ``disable_after``; resume when fresh."""
        worst = 0 if self._rx_count >= self.n else int(self.stale.max())  # every TPDO in: all fresh
        if worst <= 1:  # a single late TPDO is jitter, not lost feedback: it does not restart the count
            self.fresh_cycles += 1
        else:
            self.fresh_cycles = 0
        if worst >= disable_after and self.mode not in (Mode.IDLE, Mode.FAULT):
            j = int(self.stale.argmax())
            self._fault(j, f"feedback lost: no TPDO from node {self.cfg.joints[j].node_id} for {worst} cycles")
            self.feedback_hold = False
        elif worst >= hold_after and self.mode == Mode.DRAG:
            self.feedback_hold = True
            self.feedback_holds += 1
            self.resume_mode = self.mode
            self.q_hold[:] = self.q
            self._set_mode(Mode.HOLD)
        elif (self.feedback_hold and self.mode == Mode.HOLD
              and self.fresh_cycles >= self.cfg.loop.fresh_cycles_resume):
            self.feedback_hold = False
            self._set_mode(self.resume_mode)

    def _deadline(self) -> None:
        if self._waiter is not None and not self._waiter.done():
            self._waiter.set_result(False)

    # ------------------------------------------------------------------------------------------ status

    def status(self) -> dict[str, Any]:
        drives = [{"joint": j.name, "node_id": j.node_id, "state": DRIVE_STATE_NAMES[self.states[i]],
                   "statusword": int(self.statusword[i]), "stale_cycles": int(self.stale[i])}
                  for i, j in enumerate(self.cfg.joints)]
        return {
            "mode": MODE_NAMES[self.mode],
            "drives_enabled": all(s == State.OPERATION_ENABLED for s in self.states),
            "cycles": self.cycles,
            "period_p50_us": self.period_hist.percentile(50) if self.period_hist.count else None,
            "period_p99_us": self.period_hist.percentile(99) if self.period_hist.count else None,
            "period_max_us": self.period_hist.max if self.period_hist.count else None,
            "compute_p50_us": self.compute_hist.percentile(50) if self.compute_hist.count else None,
            "compute_p99_us": self.compute_hist.percentile(99) if self.compute_hist.count else None,
            "missed_cycles": self.missed,
            "late_tpdo_cycles": self.late_tpdo,
            "tpdo_latency_p50_us": self.rx_hist.percentile(50) if self.rx_hist.count else None,
            "tpdo_latency_p99_us": self.rx_hist.percentile(99) if self.rx_hist.count else None,
            "feedback_hold": self.feedback_hold,
            "feedback_holds": self.feedback_holds,
            "scheduler": self.scheduler,  # the cycle thread's policy (SCHED_FIFO when configured and permitted)
            "requested_mode": MODE_NAMES[self.resume_mode if self.feedback_hold else self.mode],
            "q_rad": self.q.tolist(),
            "dq_rad_s": self.dq.tolist(),
            "current_A": self.current_meas_A.tolist(),
            "command_A": self.cmd_A.tolist(),
            "faults": list(self.faults),
            "drives": drives,
            "drive_mode": {MODE_CSP: "csp", MODE_CST: "cst"}.get(self.drive_mode, str(self.drive_mode)),
            "trajectory": (None if self.trajectory is None else
                           {"label": self.trajectory.label, "t_s": self.track_tau,
                            "duration_s": self.trajectory.duration_s, "state": self.track_state,
                            "rate": self.track_rate, "cycle": self.track_cycle + 1,
                            "cycles": self.track_cycles}),
            "bus_load_pct": {k: round(v["load_pct"], 2) for k, v in self.budget.items()},
            "tx_errors": self.tx_errors,
            "error_frames": self.error_frames,
            "clamp_cycles": self.clamp_cycles,
            "telemetry": self.telemetry.stats() if self.telemetry is not None else None,
            "recording": self.recording_path,
            "t_s": self.t,
            "replay": self._replay_status(),
            "teach": self.teach.status() if self.teach is not None else None,
            "speed_override": self.track_override,
        }

    async def _handle(self, req: dict[str, Any]) -> dict[str, Any]:
        cmd = req.get("cmd")
        try:
            if cmd == "status":
                return {"ok": True, **self.status()}
            if cmd == "start":
                self.start()
                ok = await self._wait_for(lambda: self.mode == Mode.FAULT or
                                          all(s == State.OPERATION_ENABLED for s in self.states),
                                          self.cfg.master.enable_timeout_s + 0.5)
                if self.mode == Mode.FAULT or not ok:
                    return {"ok": False, "error": "enable failed: " + (self.faults[-1]["text"] if self.faults else "timeout")}
                if self.drive_mode != MODE_CST and self.trajectory is None and not self.mode_switch_pending:
                    await self._switch_drive_mode(MODE_CST)  # e.g. a fault during a motion left them in CSP
                return {"ok": True, "mode": MODE_NAMES[self.mode]}
            if cmd == "stop":
                self.stop()
                await self._wait_for(lambda: self.mode in (Mode.IDLE, Mode.FAULT), 5.0)
                return {"ok": True, "mode": MODE_NAMES[self.mode]}
            if cmd == "mode":
                target = str(req.get("mode"))
                if target in ("hold", "drag") and self.trajectory is None and self.mode not in (Mode.IDLE, Mode.FAULT) \
                        and (self.mode_switch_pending or self.drive_mode != MODE_CST):
                    # after a motion the drives return to CST; a law in torque mode waits for that (bumpless)
                    await self._wait_for(lambda: not self.mode_switch_pending and self.drive_mode == MODE_CST, 2.0)
                    if self.drive_mode != MODE_CST:
                        raise ValueError(f"mode {target}: the drives did not return to CST after the motion")
                self.set_mode(target)
                return {"ok": True, "mode": MODE_NAMES[self.mode]}
            if cmd == "track":
                # built off the loop: resampling a long trajectory would stall the cycle
                loop = asyncio.get_running_loop()
                label = str(req.get("label", "track"))
                if "file" in req:
                    traj = await loop.run_in_executor(None, Trajectory.load, req["file"], self.dt, label)
                else:
                    traj = await loop.run_in_executor(None, Trajectory, req["t_s"], req["q_rad"], self.dt, label)
                # the residual monitor's rigid-body effort of the motion (in the planner process: seconds of
                # Pinocchio calls for a long run would hold the GIL against the cycle)
                try:
                    traj.pred_table = await self._work("rigid_body_effort", str(self.model.urdf_path),
                                                       tuple(self.cfg.robot.gravity_m_s2), traj.table, self.dt)
                except RuntimeError as exc:
                    self.log(f"track: no rigid-body prediction ({exc}); the residual-current monitor is off for it")
                    traj.residual_monitor = False
                await self.track(traj)
                return {"ok": True, "mode": MODE_NAMES[self.mode], "duration_s": traj.duration_s}
            if cmd == "record":
                action = req.get("action")
                if action == "start":
                    path = await self.start_recording(str(req["path"]), str(req.get("label", "")))
                    return {"ok": True, "recording": path}
                if action == "stop":
                    return {"ok": True, **(await self.stop_recording())}
                return {"ok": False, "error": f"record: action: expected 'start' or 'stop', got {action!r}"}
            if cmd == "teach":
                action = req.get("action")
                if action == "start":
                    rate = req.get("rate_Hz")
                    return {"ok": True, **(await self.teach_start(str(req["name"]), None if rate is None else float(rate),
                                                                  bool(req.get("overwrite", False))))}
                if action == "mark":
                    name = req.get("name")
                    return {"ok": True, **self.teach_mark(None if name is None else str(name))}
                if action == "stop":
                    return {"ok": True, **(await self.teach_stop())}
                if action == "list":
                    return {"ok": True, "program_dir": str(self.cfg.program_dir),
                            "programs": await self._work("list_programs", str(self.cfg.program_dir))}
                return {"ok": False, "error": f"teach: action: expected start, mark, stop or list, got {action!r}"}
            if cmd == "replay":
                cycles = req.get("cycles", 1)
                return {"ok": True, **(await self.replay_start(
                    str(req["program"]), interp=str(req.get("interp", "linear")), speed=float(req.get("speed", 1.0)),
                    cycles=int(cycles), source=req.get("source")))}
            if cmd in ("replay_pause", "replay_resume", "replay_stop", "replay_speed"):
                if cmd == "replay_speed":
                    speed = self.set_speed_override(float(req["speed"]))
                    return {"ok": True, "speed_override": speed, "state": self.track_state}
                if cmd == "replay_pause":
                    state = self.track_pause()
                    if req.get("wait", True):
                        await self._wait_for(lambda: self.track_state != "pausing", self._rate_T + 0.5)
                elif cmd == "replay_resume":
                    state = self.track_resume()
                else:
                    state = self.track_stop()
                    if req.get("wait", True):
                        await self._wait_for(lambda: self.trajectory is None, self._rate_T + 1.0)
                state = self.track_state if self.trajectory is not None else MODE_NAMES[self.mode]
                return {"ok": True, "state": state, "mode": MODE_NAMES[self.mode], "replay": self._replay_status()}
            if cmd == "shutdown":
                self.request_exit()
                return {"ok": True}
            return {"ok": False, "error": f"unknown command '{cmd}'; expected status, start, stop, mode, track, record, "
                                         "teach, replay, replay_pause, replay_resume, replay_stop, replay_speed, shutdown"}
        except KeyError as exc:
            return {"ok": False, "error": f"{cmd}: missing field {exc}"}
        except (ValueError, DriveError, OSError, RuntimeError) as exc:
            return {"ok": False, "error": str(exc)}

    # ------------------------------------------------------------------------------------------ teach & replay

    def _planner(self) -> tuple[Any, Any]:
        """The helper thread (normal priority, off the cycle's CPUs) and the planner process it talks to."""
        if self._helper is None:
            from concurrent.futures import ThreadPoolExecutor

            from dragd.teach.worker import Worker

            avoid = set(self.cfg.loop.cpus or ())
            self._helper = ThreadPoolExecutor(1, thread_name_prefix="dragd-planner",
                                              initializer=demote_current_thread, initargs=(avoid or None,))
            self._worker = Worker(avoid)
        return self._helper, self._worker

    async def _work(self, name: str, *args: Any, **kwargs: Any) -> Any:
        helper, worker = self._planner()
        return await asyncio.get_running_loop().run_in_executor(helper, functools.partial(worker.call, name, *args,
                                                                                          **kwargs))

    def _warm_planner(self) -> None:
        task = asyncio.get_running_loop().create_task(self._work("warm_up"))
        task.add_done_callback(lambda t: t.exception())  # a failure shows at the next real call

    async def teach_start(self, name: str, rate_Hz: float | None = None, overwrite: bool = False) -> dict[str, Any]:
        """Start teaching: the raw MCAP window, positions at ``rate_Hz`` and marks; the arm goes to drag."""
        if self.teach is not None:
            raise ValueError(f"teach start: already teaching '{self.teach.name}'; 'dragd teach stop' first")
        if self.mode not in (Mode.HOLD, Mode.DRAG) or self.trajectory is not None or self._planning:
            raise ValueError(f"teach start: expected the arm enabled in hold or drag, it is {MODE_NAMES[self.mode]}"
                             + (" (a motion is running)" if self.trajectory is not None or self._planning else ""))
        if self.recording is not None:
            raise ValueError(f"teach start: a record window is open ({self.recording_path}); 'record stop' first")
        rc = self.cfg.replay
        rate = rc.record_rate_Hz if rate_Hz is None else float(rate_Hz)
        if not 0.0 < rate <= self.cfg.loop.rate_Hz:
            raise ValueError(f"teach start: rate: expected (0, {self.cfg.loop.rate_Hz:.0f}] Hz, got {rate}")
        try:
            path = resolve_program(name, self.cfg.program_dir)
            check_name(path.stem)
        except ProgramError as exc:
            raise ValueError(f"teach start: {exc}") from None
        if path.suffix not in (".yaml", ".yml"):
            path = path.with_suffix(".yaml")
        mcap = path.with_suffix(".mcap")
        exists = [str(p) for p in (path, mcap) if p.exists()]
        if exists and not overwrite:
            raise ValueError(f"teach start: {' and '.join(exists)} exist(s); choose another name or overwrite")
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            for p in (path, mcap):
                if overwrite and p.exists():
                    p.unlink()
        except OSError as exc:
            raise ValueError(f"teach start: cannot write programs to {path.parent}: {exc.strerror} "
                             "(replay.program_dir, or give a path)") from None
        await self.start_recording(str(mcap), label=f"teach {path.stem}")
        self.teach = TeachRecorder(path.stem, path, mcap, self.cfg.joint_names, rate, self.dt, rc.max_record_s, self.t)
        self._warm_planner()
        if self.mode == Mode.HOLD and not self.feedback_hold:
            if self.mode_switch_pending or self.drive_mode != MODE_CST:
                await self._wait_for(lambda: not self.mode_switch_pending and self.drive_mode == MODE_CST, 2.0)
            if self.drive_mode == MODE_CST:
                self.set_mode("drag")
        return {**self.teach.status(), "mode": MODE_NAMES[self.mode]}

    def teach_mark(self, name: str | None = None) -> dict[str, Any]:
        """Mark the present pose (absolute encoders) as the next waypoint."""
        if self.teach is None:
            raise ValueError("teach mark: not teaching; 'dragd teach start NAME' first")
        if name is not None:
            try:
                check_name(name)
            except ProgramError as exc:
                raise ValueError(f"teach mark: {exc}".replace("program name", "waypoint name")) from None
        m = self.teach.mark(self.t, self.q, name)
        ev = {"waypoint": m["name"], "t_s": m["t_s"], "q_rad": m["q_rad"]}
        if self.recording is not None:
            self.recording.event("mark", **ev)
        if self.telemetry is not None:
            self.telemetry.event("mark", program=self.teach.name, **ev)
        return {"program": self.teach.name, "index": len(self.teach.marks), **m,
                "q_deg": [round(math.degrees(x), 4) for x in m["q_rad"]]}

    async def teach_stop(self) -> dict[str, Any]:
        """Stop teaching: close the MCAP, write the program file (in the planner process)."""
        if self.teach is None:
            raise ValueError("teach stop: not teaching")
        rec, self.teach = self.teach, None
        snap = rec.snapshot()
        stats = await self.stop_recording() if self.recording is not None else {}
        args = (snap, str(self.cfg.robot.urdf), self.cfg.replay.frame, self.cfg.source)
        try:
            result = await self._work("write_program", *args)
        except RuntimeError as exc:  # the worker died: write it here rather than lose what was taught
            from dragd.teach.recorder import write_program

            self.log(f"teach: planner worker failed ({exc}); writing the program in the daemon")
            result = await asyncio.get_running_loop().run_in_executor(None, write_program, *args)
        return {**result, "mcap": stats.get("path"), "mcap_rows": stats.get("written")}

    async def replay_start(self, program: str, interp: str = "linear", speed: float = 1.0, cycles: int = 1,
                           source: str | None = None) -> dict[str, Any]:
        """Plan (in the planner process, from the held pose) and run a taught program in CSP."""
        from dragd.teach.plan import INTERPS, SOURCES

        if self.teach is not None:
            raise ValueError(f"replay: teaching '{self.teach.name}' is in progress; 'dragd teach stop' first")
        compact = [name for name, lay in self.layouts.items() if lay.kind != "shared"]
        if compact:
            raise ValueError(f"replay: bus(es) {', '.join(compact)} use the 'compact' PDO layout, which carries no "
                             "position targets; replay (CSP) needs the 'shared' layout")
        if self.mode not in (Mode.HOLD, Mode.DRAG):
            raise ValueError(f"replay: expected the arm enabled in hold or drag, it is {MODE_NAMES[self.mode]}")
        if self.trajectory is not None or self._planning:
            raise ValueError("replay: a motion is running (or being planned); 'dragd replay stop' first")
        if interp not in INTERPS:
            raise ValueError(f"replay: interp: expected one of {', '.join(INTERPS)}, got '{interp}'")
        if source is not None and source not in SOURCES:
            raise ValueError(f"replay: source: expected one of {', '.join(SOURCES)}, got '{source}'")
        if not 0.0 < speed <= 1.0:
            raise ValueError(f"replay: speed: expected a fraction in (0, 1], got {speed}")
        if cycles < 0:
            raise ValueError(f"replay: cycles: expected 0 (until stopped) or more, got {cycles}")
        self._take_over_feedback_hold("replay")
        try:
            path = resolve_program(program, self.cfg.program_dir)
        except ProgramError as exc:
            raise ValueError(f"replay: {exc}") from None
        if not path.is_file():
            raise ValueError(f"replay: program {path} not found")
        self._planning = True
        try:
            return await self._replay_start(path, interp, speed, cycles, source)
        finally:
            self._planning = False

    async def _replay_start(self, path: Path, interp: str, speed: float, cycles: int,
                            source: str | None) -> dict[str, Any]:
        from dragd.teach.plan import ReplayRequest, limits_from_config

        was = self.mode
        # hold where the arm is (not where an older hold wanted it), stiffly: the drives' own position loops (CSP)
        # keep the pose while the plan is made, and the plan starts there
        self.q_hold[:] = self.q
        self._set_mode(Mode.HOLD)
        try:
            await self._settle_drive_mode()
            await self._switch_drive_mode(MODE_CSP)
        except DriveError:
            self._fault(None, "replay: the drives did not switch to CSP")
            raise
        if self.mode != Mode.HOLD:
            raise ValueError(f"replay: the arm left hold ({MODE_NAMES[self.mode]})")
        rc = self.cfg.replay
        req = ReplayRequest(program=str(path), q_start=self.q_hold.tolist(), dt=self.dt, urdf=str(self.model.urdf_path),
                            gravity_m_s2=tuple(self.cfg.robot.gravity_m_s2),
                            limits=limits_from_config(self.cfg, self.model.model).as_dict(), interp=interp,
                            source=source, frame=rc.frame, move_to_start_speed=rc.move_to_start_speed,
                            settle_s=rc.settle_s, keyframe_tolerance_rad=rc.keyframe_tolerance_rad,
                            feedforward=rc.inertia_feedforward)
        try:
            res = await self._work("plan_replay", req)
            summary = res["summary"]
            traj = Trajectory.from_table(res["q"], self.dt, f"replay {path.stem}", dq=res["dq"], ff_Nm=res["ff_Nm"],
                                         body_row=res["body_row"], marks=res["marks"], info=summary)
            replay = {"program": str(path), "name": path.stem, "interp": interp, "source": summary.get("source"),
                      "speed": speed, "cycles": cycles, "started_t_s": round(self.t, 4), "outcome": None,
                      "marks": [{k: v for k, v in m.items() if k != "q_rad"} for m in res["marks"]],
                      "duration_s": summary["duration_s"], "cycle_s": summary["cycle_s"],
                      "move_to_start_s": summary["move_to_start_s"]}
            await self.track(traj, rate=speed, cycles=cycles)
            self.replay = replay  # (no await since TRACK began: the cycle cannot have ended it yet)
        except (ValueError, RuntimeError):
            if self.mode == Mode.HOLD and self.trajectory is None:
                await self._switch_drive_mode(MODE_CST)
                if was == Mode.DRAG and self.mode == Mode.HOLD:
                    self._set_mode(Mode.DRAG)  # back to the hand
            raise
        if self.telemetry is not None:
            self.telemetry.event("replay", program=str(path), interp=interp, speed=speed, cycles=cycles)
        return {"mode": MODE_NAMES[self.mode], "program": str(path), **summary}

    def _replay_status(self) -> dict[str, Any] | None:
        r = self.replay
        if r is None:
            return None
        active = self.trajectory is not None and self.trajectory.label == f"replay {r['name']}" and r["outcome"] is None
        out = {k: v for k, v in r.items() if k != "marks"}
        out["state"] = self.track_state if active else (r["outcome"] or "ended")
        if active:
            tau = self.track_tau
            out.update(t_s=round(tau, 4), cycle=self.track_cycle + 1, rate=round(self.track_rate, 4),
                       speed_override=self.track_override,
                       segment=next((s["label"] for s in self.trajectory.info.get("segments", [])
                                     if s["t0_s"] <= tau < s["t1_s"]), None),
                       next_waypoint=next((m["name"] for m in r["marks"] if m["t_s"] > tau), None))
        return out

    async def _wait_for(self, cond, timeout_s: float) -> bool:  # noqa: ANN001
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if cond():
                return True
            await asyncio.sleep(0.01)
        return cond()

    # ------------------------------------------------------------------------------------------ run

    def request_exit(self) -> None:
        self.stop_requested = True

    async def _shutdown_sequence(self) -> None:
        """SIGTERM: ramp to hold, disable (brakes), NMT pre-operational, then leave the loop."""
        if self.teach is not None:  # keep what was taught
            try:
                await asyncio.wait_for(self.teach_stop(), 15.0)
            except (ValueError, RuntimeError, OSError, asyncio.TimeoutError) as exc:
                self.log(f"teach: the program could not be written at shutdown: {exc}")
        if self.mode not in (Mode.IDLE, Mode.FAULT):
            self.stop()
            await self._wait_for(lambda: self.mode in (Mode.IDLE, Mode.FAULT), self.cfg.safety.mode_ramp_s + 1.0)
        await self._wait_for(lambda: all(s != State.OPERATION_ENABLED for s in self.states), 0.5)
        self.exit_requested = True

    async def _watchdog(self) -> None:
        period = sdnotify.watchdog_period_s()
        if not period:
            return
        last = -1
        while not self.exit_requested:
            await asyncio.sleep(period / 2)
            if self.cycles != last:  # only while the cycle runs
                sdnotify.watchdog_ping()
                last = self.cycles

    def _telemetry_layout(self) -> dict[str, Any]:
        from dragd.telemetry.writer import Field

        n = self.n
        return {"t_s": 1, "mode": Field(1, kind="int", labels={int(m): name for m, name in MODE_NAMES.items()}), "q_rad": n, "dq_rad_s": n, "current_measured_A": n, "current_command_A": n,
                "gravity_A": n, "friction_A": n, "startup_A": n, "damping_A": n, "statusword": Field(n, kind="int"), "rx": Field(n, kind="bool"), "period_us": 1,
                "compute_us": 1, "q_ref_rad": n, "track_t_s": 1, "residual_A": n, "back_emf_A": n, "effects_A": n}

    def _layout_columns(self) -> dict[str, Any]:
        """Column index (width 1) or slice of every telemetry field in a row."""
        cols, k = {}, 0
        for name, f in self._telemetry_layout().items():
            width = f if isinstance(f, int) else f.width
            cols[name] = k if width == 1 else slice(k, k + width)
            k += width
        return cols

    async def start_recording(self, path: str, label: str = "") -> str:
        """Record every cycle to a separate MCAP file until ``stop_recording`` (identification runs, teach)."""
        from dragd.telemetry.writer import TelemetryWriter

        if self.recording is not None:
            raise ValueError(f"record: already recording to {self.recording_path}; stop it first")
        loop = asyncio.get_running_loop()
        writer = await loop.run_in_executor(None, lambda: TelemetryWriter(
            path, self._telemetry_layout(), capacity=self.cfg.telemetry.capacity_rows, on_exists="error",
            metadata={"label": label, "config": self.cfg.source}, avoid_cpus=set(self.cfg.loop.cpus or ())))
        self.recording, self.recording_path = writer, str(path)
        writer.event("record_start", label=label, joints=self.cfg.joint_names)
        self._writers = [w for w in (self.telemetry, self.recording) if w is not None]
        return self.recording_path

    async def stop_recording(self) -> dict[str, Any]:
        if self.recording is None:
            raise ValueError("record: not recording")
        writer, path = self.recording, self.recording_path
        self.recording, self.recording_path = None, None
        self._writers = [w for w in (self.telemetry,) if w is not None]
        writer.event("record_stop")
        await writer.aclose()
        return {"path": path, **writer.stats()}

    def _open_telemetry(self) -> None:
        if not self.telemetry_path:
            return
        from dragd.telemetry.writer import TelemetryWriter

        tc = self.cfg.telemetry
        self.telemetry = TelemetryWriter(self.telemetry_path, self._telemetry_layout(), capacity=tc.capacity_rows,
                                         rerun=self.rerun, max_bytes=tc.max_file_MiB * 2**20,
                                         keep_rotated=tc.keep_rotated, avoid_cpus=set(self.cfg.loop.cpus or ()))
        self._writers = [w for w in (self.telemetry, self.recording) if w is not None]
        self.telemetry.event("start", config=self.cfg.source, joints=self.cfg.joint_names)

    async def run(self) -> int:
        loop = asyncio.get_running_loop()
        # a busy helper thread (SDO worker, telemetry encoder) would hold the GIL for the default 5 ms
        sys.setswitchinterval(5e-4)
        if self.rerun:
            from dragd.telemetry.writer import rerun_unavailable

            reason = rerun_unavailable()
            if reason:
                raise ValueError(f"--rerun: {reason}")
        for name, spec in self.bus_specs.items():
            self.buses[name] = open_bus(spec)
        self._build_io()
        self.master = Master(self.cfg, self.buses, self.layouts, loop,
                             {name: [self._listener(name)] for name in self.buses}, log=self.log)
        server = None
        try:
            await self.master.boot()
            self._open_telemetry()
            self.scheduler = go_realtime(loop, self.cfg.loop.realtime_priority, self.cfg.loop.cpus)
            for sig in (signal.SIGTERM, signal.SIGINT):
                loop.add_signal_handler(sig, self.request_exit)
            # everything built so far lives for the whole run: out of the cyclic collector's way, so its
            # occasional full collections (a heap of Pinocchio/scipy/numpy objects) cannot stall a cycle for ms
            gc.collect()
            gc.freeze()
            cycle = loop.create_task(self._cycle_loop())
            server = ControlServer(self.socket_path, self._handle)
            await server.start()
            self.log(f"running at {self.cfg.loop.rate_Hz:.0f} Hz; control socket {self.socket_path}; "
                     f"cycle thread: {self.scheduler}")
            sdnotify.ready(f"running, {self.n} drives")
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
            if self._worker is not None:
                self._worker.close()
            if self._helper is not None:
                self._helper.shutdown(wait=False)
            if server is not None:
                await server.close()
            if self.master is not None:
                await self.master.shutdown()
            if self.recording is not None:
                await self.stop_recording()
            if self.telemetry is not None:
                self.telemetry.event("stop", cycles=self.cycles)
                await self.telemetry.aclose()
            for bus in self.buses.values():
                bus.shutdown()
