"""One simulated CiA 301 / CiA 402 joint drive, built from its EDS and its profile (sim/drive_profile.py).

The drive is small parts, one per service, wired here: the object dictionary (sim/od.py), NMT and heartbeats
(sim/nmt.py), the SDO server (sim/sdo_server.py), PDOs (sim/pdo.py), errors and EMCY (sim/emcy.py), the 402 state
machine (sim/ds402.py) and the power stage with its control laws and stops (sim/motion.py, sim/stops.py), scaled by
sim/scaling.py. A profile swaps what differs between drive models: which objects exist (absent ones abort SDO with
0602 0000 and cannot be mapped), their access and mapping flags, the PDOs and their COB-IDs, dummy usage, 6502h, where
the process quantities live and in which unit; what the EDS does not say is assumed as docs/SIM_DRIVES.md lists.

Threads: ``on_message`` / ``on_data`` / ``on_sync`` run in the network's reader thread, ``update`` in the physics
thread. All take the drive's re-entrant lock for their (short) work. Only ``update`` writes the AxisIO outputs.

Clocks: the drive reads no clock of its own. Communication timing (heartbeats, RPDO deadlines, inhibit and event times)
runs on the time handed in by ``comm(now)`` and ``on_sync(t)``; a frame is received at ``on_data(..., now)``'s time,
else at the ``clock`` the drive was built with (the simulator's process: CLOCK_MONOTONIC on the wall clock), else at the
latest time handed in. Reception deadlines are also judged against the time up to which the reader has handed frames
over (``rx_caught_up``), and leave out the time the simulator itself was not running (``not_running``: a frozen host
stops the master too; the simulated drive's hardware clock is the simulator's). Motion timing (brake release, stop
ramps, torque slope) runs on the physics time of ``update``.
"""

from __future__ import annotations

import itertools
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import can

from dragd.hardware.cia301 import (
    COB_ID_MASK,
    HEARTBEAT_BASE,
    NMT_COB_ID,
    NODE_ID_MAX,
    NODE_ID_MIN,
    OD_COMMUNICATION_AREA,
    OD_PRODUCER_HEARTBEAT,
    OD_SDO_SERVER,
    OD_SYNC_COB_ID,
    SDO_RX_BASE,
    SDO_TX_BASE,
    SYNC_COB_ID,
    SYNC_COB_ID_GENERATE,
    NmtCommand,
    NmtState,
)
from dragd.hardware.cia402 import (
    EMCY_COMMUNICATION,
    EMCY_HEARTBEAT,
    EMCY_RPDO_TIMEOUT,
    ERR_REG_COMMUNICATION,
    ERR_REG_GENERIC,
    OD_ABORT_CONNECTION_OPTION,
    OD_CONTROLWORD,
    OD_DISABLE_OPERATION_OPTION,
    OD_FAULT_REACTION_OPTION,
    OD_FOLLOWING_ERROR_ACTUAL,
    OD_MODES_OF_OPERATION,
    OD_MODES_OF_OPERATION_DISPLAY,
    OD_POSITION_ACTUAL,
    OD_PROFILE_DECELERATION,
    OD_QUICK_STOP_DECELERATION,
    OD_QUICK_STOP_OPTION,
    OD_SHUTDOWN_OPTION,
    OD_STATUSWORD,
    OD_TARGET_POSITION,
    OD_TARGET_VELOCITY,
    OD_TORQUE_SLOPE,
    OD_VELOCITY_ACTUAL,
    OD_VELOCITY_OFFSET,
    Mode,
    State,
)
from dragd.resources import eds_path
from sim.axis import AxisIO
from sim.drive_profile import ASSUMED_OPTIONS, DriveProfile, Hardware, ProfileSpec, build_profile
from sim.ds402 import DeviceControl
from sim.emcy import Errors
from sim.motion import Motion, Regime
from sim.nmt import HeartbeatConsumers, Nmt
from sim.od import ABORT_VALUE_RANGE, STRUCT_CODES, ObjectStore, SdoAbort
from sim.pdo import PdoChannel, PdoService
from sim.scaling import Scaling
from sim.sdo_server import SdoServer

DEFAULT_EDS_PATH = eds_path()
COMM_TICK_S = 0.001  # period of the communication watchdog / heartbeat / event-TPDO checks
_INT32_MIN, _INT32_MAX = -(1 << 31), (1 << 31) - 1
_CST = int(Mode.CYCLIC_SYNC_TORQUE)
_TYPE_RANGES = {"b": (-(1 << 7), (1 << 7) - 1), "h": (-(1 << 15), (1 << 15) - 1), "i": (_INT32_MIN, _INT32_MAX),
                "q": (-(1 << 63), (1 << 63) - 1), "B": (0, 0xFF), "H": (0, 0xFFFF), "I": (0, 0xFFFFFFFF),
                "Q": (0, (1 << 64) - 1)}


@dataclass(frozen=True)
class DriveParams:
    """Hardware facts of one joint drive (from the sim's truth config). Currents are motor currents."""

    node_id: int
    rated_current_A: float  # the rated current object (6075h unless the profile names another)
    rated_torque_Nm: float  # the rated torque object (6076h ...), motor side; K_m = rated torque / rated current
    max_current_A: float  # the current limit object (6073h ...)
    encoder_counts_per_rev: int  # per joint revolution
    max_torque_permille: int = 1000  # 6072h default
    csp_kp_A_per_rad: float = 40.0
    csp_kd_A_s_per_rad: float = 2.0  # also the CSV velocity-loop gain
    csp_ki_A_per_rad_s: float = 0.0  # integral of the CSP position error
    quickstop_kd_A_s_per_rad: float = 3.0  # stop velocity loop, proportional
    quickstop_ki_A_per_rad: float = 30.0  # stop velocity loop, integral
    quickstop_decel_rad_s2: float = 10.0  # 6085h default
    slowdown_decel_rad_s2: float = 4.0  # 6084h default
    standstill_velocity_rad_s: float = 0.01
    standstill_time_s: float = 0.02
    stop_timeout_s: float = 3.0  # a stop that does not reach standstill ends with the brake after this
    brake_release_delay_s: float = 0.05
    fd: bool = False  # the bus is CAN FD (PDOs up to 64 bytes where the drive supports it, see profile.can_fd)
    identity: tuple[int, int, int] | None = None  # 1018h sub 1..3; None: the EDS's [DeviceInfo]
    profile: ProfileSpec = field(default_factory=ProfileSpec)  # EDS, vendor objects, commissioned values
    base_dir: str | None = None  # relative EDS paths are relative to it (the truth file's folder)

    def __post_init__(self) -> None:
        def need(ok: bool, field_name: str, expected: str) -> None:
            if not ok:
                raise ValueError(f"DriveParams(node_id={self.node_id}).{field_name}="
                                 f"{getattr(self, field_name)!r}: expected {expected}")

        need(1 <= self.node_id <= 127, "node_id", "1..127")
        need(self.rated_current_A > 0, "rated_current_A", "> 0 A")
        need(self.rated_torque_Nm > 0, "rated_torque_Nm", "> 0 N·m")
        need(0 < self.max_current_A <= 65.535 * self.rated_current_A, "max_current_A",
             "> 0 A and <= 65.535 x rated_current_A (6073h is UNSIGNED16 per mille)")
        need(self.encoder_counts_per_rev > 0, "encoder_counts_per_rev", "> 0")
        need(0 < self.max_torque_permille <= 0xFFFF, "max_torque_permille", "1..65535")
        for name in ("csp_kp_A_per_rad", "csp_kd_A_s_per_rad", "csp_ki_A_per_rad_s", "quickstop_kd_A_s_per_rad",
                     "quickstop_ki_A_per_rad", "standstill_time_s", "brake_release_delay_s"):
            need(getattr(self, name) >= 0, name, ">= 0")
        for name in ("quickstop_decel_rad_s2", "slowdown_decel_rad_s2", "standstill_velocity_rad_s",
                     "stop_timeout_s"):
            need(getattr(self, name) > 0, name, "> 0")

    def hardware(self) -> Hardware:
        return Hardware(node_id=self.node_id, rated_current_A=self.rated_current_A,
                        rated_torque_Nm=self.rated_torque_Nm, max_current_A=self.max_current_A,
                        max_torque_permille=self.max_torque_permille, counts_per_rev=self.encoder_counts_per_rev,
                        quickstop_decel_rad_s2=self.quickstop_decel_rad_s2,
                        slowdown_decel_rad_s2=self.slowdown_decel_rad_s2, identity=self.identity)

    def build_profile(self, eds: str | Path | None = None) -> DriveProfile:
        """The drive's profile (EDS loaded, bindings resolved); ``eds`` replaces the profile's EDS."""
        spec = self.profile if eds is None else ProfileSpec(**{**vars(self.profile), "eds": str(eds)})
        return build_profile(spec, self.hardware(), Path(self.base_dir) if self.base_dir else None)


@dataclass
class DriveCounters:
    """Frame and event counts of one drive (read by the sim's reports and tests)."""

    nmt_commands: int = 0
    syncs: int = 0
    rpdos_received: int = 0
    rpdos_applied: int = 0
    rpdo_length_errors: int = 0
    rpdo_invalid_mode: int = 0
    tpdos_sent: int = 0
    emcys_sent: int = 0
    heartbeats_sent: int = 0
    send_errors: int = 0
    rpdo_timeouts: int = 0
    heartbeat_losses: int = 0
    stop_timeouts: int = 0
    watchdog_waits: int = 0  # reception deadlines past by the clock, not yet by what the reader has read (stalled sim)
    watchdog_holds: int = 0  # reception deadlines past by the clock, not over the time the simulator ran (frozen host)


_ROUTE_GENERATIONS = itertools.count(1)


def _range(store: ObjectStore, slot: int) -> tuple[int, int]:
    """(min, max) of an integer object's data type (internal cells: INTEGER16)."""
    var = store.vars[slot]
    if var is None or var.data_type is None:
        return _TYPE_RANGES["h"]
    return _TYPE_RANGES.get(STRUCT_CODES.get(var.data_type, "h"), _TYPE_RANGES["h"])


class SimDrive:
    """A CANopen joint drive node backed by an EDS, exchanging signals with the physics through AxisIO."""

    routes_generation = 0  # renewed by every drive whose COB-ID routing changes (SimNetwork rebuilds its tables)

    def __init__(self, params: DriveParams, io: AxisIO, send: Callable[[can.Message], None],
                 eds_path: str | Path | None = None,
                 send_data: Callable[[int, bytes, bool], None] | None = None,
                 profile: DriveProfile | None = None, clock: Callable[[], float] | None = None) -> None:
        """``send`` transmits a frame; ``send_data(cob_id, data, fd)``, when given, the PDOs (no ``can.Message``).
        ``eds_path`` replaces the EDS of ``params.profile``; ``profile``, when given, is used as built. ``clock``, when
        given, stamps a frame's reception (the simulator's process passes CLOCK_MONOTONIC on the wall clock, so a
        stalled physics thread does not age what the reader received); without it, the latest time handed in."""
        self.params = params
        self.io = io
        self.node_id = params.node_id
        self._send = send
        self.counters = DriveCounters()
        self._lock = threading.RLock()
        self.profile = profile if profile is not None else params.build_profile(eds_path)
        self.store = store = ObjectStore(self.profile.od)
        for (index, sub), value in self.profile.commissioned.items():
            store.set_default(index, sub, value)
        self._counts_per_rad = params.encoder_counts_per_rev / (2.0 * math.pi)
        self._now = 0.0  # the communication clock: the latest time handed in (comm, on_sync, on_data)
        self._clock = clock
        self._sim_t = 0.0
        self._steady = False  # the last update's outputs hold until something reaches the drive (see ``update``)
        self.encoder_offset_counts = 0  # an injected encoder jump (sim/faults.py), added to 6064h
        # set by the SimNetwork: the time up to which every frame that reached this process has been handed to the
        # drives, given now — the reception watchdogs judge against it: a stall of the simulator's reader is not a
        # silent bus
        self.rx_caught_up: Callable[[float], float] | None = None
        # set by the simulator's process (sim/runner.py OwnStalls.held): how much of [a, b] the simulator did not run —
        # the reception watchdogs leave it out: a drive watches the bus only while its firmware runs
        self.not_running: Callable[[float, float], float] | None = None
        self.s = s = self._bind_slots()
        self.scaling = Scaling(self.profile, store)
        self.nmt = Nmt(store, self.node_id, self._tx, self.counters)
        self.errors = Errors(store, self.node_id, lambda: self.nmt.state, self._tx, self.counters)
        self.motion = Motion(params, io, store.cells, s, self.scaling, self.counters, self._stopped)
        self.control = DeviceControl(store.cells, s, self.motion, self.errors, self.profile.supported_modes)
        self.consumers = HeartbeatConsumers(store, self._load_routing)
        self.sdo = SdoServer(store, self._send_sdo)
        self.pdo = PdoService(store, fd=params.fd and self.profile.can_fd, counters=self.counters,
                              nmt_state=lambda: self.nmt.state, sample=lambda: self._sample(self.io),
                              tx=self._tx, send_data=send_data, raise_error=self._raise_error,
                              clear_error=self.control.clear_error, refresh=self.control.refresh_statusword,
                              routing_changed=self._load_routing)
        self.pdo.rpdo_hooks[s.mode] = self._rpdo_mode
        self.pdo.rpdo_hooks[s.controlword] = self.control.on_controlword
        self.rpdos: list[PdoChannel] = self.pdo.rpdos
        self.tpdos: list[PdoChannel] = self.pdo.tpdos
        self._install_hooks()
        store.written = self._unsteady
        self._reset_application_state()
        self._reset_communication_state()

    # ==================================================================================================
    # construction
    # ==================================================================================================
    def _bind_slots(self) -> SimpleNamespace:
        """Slots of the objects the device control and the laws use: the dictionary's, else internal cells holding
        the values docs/SIM_DRIVES.md assumes."""
        st, b, p, hw = self.store, self.profile.bindings, self.params, self.profile.hardware
        counts_per_rad = self._counts_per_rad

        def std(index: int, name: str, value: Any) -> int:
            return st.slot_or_internal(index, 0, name, value)

        def bound(name: str, value: Any) -> int:
            binding = b[name]
            if binding.index is None:
                return st.internal(name, value)
            return st.slot(binding.index, binding.subindex)

        s = SimpleNamespace(
            controlword=st.slot(OD_CONTROLWORD),
            statusword=st.slot(OD_STATUSWORD),
            position=st.slot(OD_POSITION_ACTUAL),
            velocity=std(OD_VELOCITY_ACTUAL, "velocity_actual", 0),
            mode=std(OD_MODES_OF_OPERATION, "modes_of_operation", 0),
            mode_display=std(OD_MODES_OF_OPERATION_DISPLAY, "modes_of_operation_display", 0),
            abort_option=std(OD_ABORT_CONNECTION_OPTION, "abort_connection_option",
                             ASSUMED_OPTIONS[OD_ABORT_CONNECTION_OPTION][0]),
            qs_option=std(OD_QUICK_STOP_OPTION, "quick_stop_option", ASSUMED_OPTIONS[OD_QUICK_STOP_OPTION][0]),
            shutdown_option=std(OD_SHUTDOWN_OPTION, "shutdown_option", ASSUMED_OPTIONS[OD_SHUTDOWN_OPTION][0]),
            disable_op_option=std(OD_DISABLE_OPERATION_OPTION, "disable_operation_option",
                                  ASSUMED_OPTIONS[OD_DISABLE_OPERATION_OPTION][0]),
            fault_option=std(OD_FAULT_REACTION_OPTION, "fault_reaction_option",
                             ASSUMED_OPTIONS[OD_FAULT_REACTION_OPTION][0]),
            target_position=std(OD_TARGET_POSITION, "target_position", 0),
            target_velocity=std(OD_TARGET_VELOCITY, "target_velocity", 0),
            velocity_offset=std(OD_VELOCITY_OFFSET, "velocity_offset", 0),
            following_error=std(OD_FOLLOWING_ERROR_ACTUAL, "following_error", 0),
            torque_slope=std(OD_TORQUE_SLOPE, "torque_slope", 0),
            torque_slope_internal=not st.has(OD_TORQUE_SLOPE),
            profile_decel=std(OD_PROFILE_DECELERATION, "profile_deceleration",
                              max(1, round(p.slowdown_decel_rad_s2 * counts_per_rad))),
            quickstop_decel=std(OD_QUICK_STOP_DECELERATION, "quick_stop_deceleration",
                                max(1, round(p.quickstop_decel_rad_s2 * counts_per_rad))),
            current_actual=bound("current_actual", 0),
            torque_actual=bound("torque_actual", 0),
            torque_demand=bound("torque_demand", 0),
            target_torque=bound("target_torque", 0),
            torque_offset=bound("torque_offset", 0),
            max_torque=bound("max_torque", 0xFFFF),
            max_current=bound("max_current", round(1000.0 * hw.max_current_A / hw.rated_current_A)),
        )
        s.digital_inputs = bound("digital_inputs", 0)
        lo, hi = _range(st, s.digital_inputs) if st.vars[s.digital_inputs] is not None else (0, 0xFFFFFFFF)
        s.inputs_mask = hi if lo == 0 else (hi << 1) | 1  # (a signed object: its bits)
        s.inputs_signed = lo < 0
        watchdog = b["rpdo_watchdog"]
        s.rpdo_watchdog = None if watchdog.index is None else st.slot(watchdog.index, watchdog.subindex)
        s.rpdo_watchdog_s_per_unit = 1.0 / (watchdog.per_si or 1000.0)
        s.position_range = _range(st, s.position)
        s.current_range = _range(st, s.current_actual)
        s.torque_range = _range(st, s.torque_actual)
        s.torque_demand_range = _range(st, s.torque_demand)
        s.velocity_range = _range(st, s.velocity) if st.vars[s.velocity] is not None else (_INT32_MIN, _INT32_MAX)
        return s

    def _install_hooks(self) -> None:
        st, control = self.store, self.control
        st.before_write[OD_SYNC_COB_ID] = self._check_sync_cob
        st.after_write[OD_SYNC_COB_ID] = lambda sub, value: self._load_routing()
        st.hook_after(OD_PRODUCER_HEARTBEAT, lambda sub, value: self.nmt.schedule(self._comm_now()))
        st.before_write[OD_QUICK_STOP_OPTION] = control.check_quick_stop_option
        st.before_write[OD_MODES_OF_OPERATION] = control.check_mode
        st.after_write[OD_MODES_OF_OPERATION] = lambda sub, value: control.set_mode(value)
        st.after_write[OD_CONTROLWORD] = lambda sub, value: control.on_controlword(value)
        for index in self.scaling.watched_indices():
            st.hook_after(index, self._rescale)

    def _rescale(self, sub: int, value: Any) -> None:
        self.scaling.refresh()
        self._same_torque_current = (self.scaling.torque_actual == self.scaling.current_actual
                                     and self.s.torque_range == self.s.current_range)

    def _reset_application_state(self) -> None:
        """402 side back to power-on: no torque, brake engaged, no errors."""
        self.motion.reset()
        self.control.reset()
        self.errors.forget()
        self._rescale(0, None)

    def _reset_communication_state(self) -> None:
        """Communication side from the current store values (after a store reset or at construction)."""
        self.sdo.reset()
        self.pdo.load_all()
        self.consumers.load()  # also reloads the routing (COB-IDs consumed)
        self.nmt.schedule(self._comm_now())
        self._next_comm_s = 0.0

    # ==================================================================================================
    # public API
    # ==================================================================================================
    @property
    def nmt_state(self) -> NmtState:
        return self.nmt.state

    @property
    def state(self) -> State:
        """The CiA 402 state."""
        return self.control.state

    def boot(self) -> None:
        """Power-on: initialisation, boot-up frame, NMT pre-operational, 402 switch on disabled."""
        with self._lock:
            self._steady = False
            self.control.enter(State.SWITCH_ON_DISABLED)
            self.nmt.bootup(self._comm_now())

    def rx_cob_ids(self) -> frozenset[int]:
        """COB-IDs this drive consumes (NMT, SYNC, SDO request, RPDOs, consumed heartbeats)."""
        return self._rx_ids

    def sync_cob_id(self) -> int:
        """The SYNC COB-ID from 1005h."""
        return self._sync_cob

    def inject_fault(self, code: int, error_register_bits: int = ERR_REG_GENERIC,
                     manufacturer: bytes = b"") -> None:
        """Raise a device fault (EMCY + fault reaction), e.g. from a sim scenario."""
        with self._lock:
            self._steady = False
            self.control.fault(code, error_register_bits, manufacturer)

    def raise_error(self, code: int, error_register_bits: int = ERR_REG_GENERIC, manufacturer: bytes = b"") -> None:
        """An error condition without a fault reaction (EMCY, error register, warning bit), e.g. sim/faults.py's."""
        with self._lock:
            self._raise_error(code, error_register_bits, manufacturer)
            self.control.refresh_statusword()

    def force_state(self, state: State) -> None:
        """Put the 402 state machine in ``state`` as the firmware would on its own (sim/faults.py)."""
        with self._lock:
            self._steady = False
            self.control.enter(state)

    def on_message(self, msg: can.Message) -> None:
        """Handle one received frame (NMT, SYNC, SDO request, RPDO, heartbeat); ignores the rest."""
        if msg.is_extended_id or msg.is_error_frame or msg.is_remote_frame:
            return
        self.on_data(msg.arbitration_id, msg.data)

    def on_data(self, cob: int, data: bytes | bytearray, now: float | None = None) -> None:
        """`on_message` for a plain data frame (11-bit id, not remote): its COB-ID and payload; ``now``, when given,
        the reception time on the communication clock (else the latest time handed in)."""
        with self._lock:
            if now is None:
                clock = self._clock
                now = self._now if clock is None else clock()
            elif now > self._now:
                self._now = now
            self._steady = False  # (whatever the frame changes, the next physics step computes the outputs afresh)
            if cob == NMT_COB_ID:
                self._on_nmt(data)
                return
            nmt = self.nmt.state
            if nmt is NmtState.INITIALISING:
                return
            if cob == self._sync_cob:
                self.on_sync(now)
                return
            if cob == self._sdo_rx_cob:
                if nmt is not NmtState.STOPPED:
                    self._sample(self.io)  # an upload of an actual value reads it now
                    self.sdo.on_request(bytes(data))  # (a bytearray from some buses)
                return
            channels = self.pdo.rpdo_by_cob.get(cob)
            if channels is not None:
                if nmt is NmtState.OPERATIONAL:
                    for ch in channels:
                        self.pdo.receive(ch, data, now)
                return
            consumer = self.consumers.by_node.get(cob - HEARTBEAT_BASE)
            if consumer is not None and HEARTBEAT_BASE + NODE_ID_MIN <= cob <= HEARTBEAT_BASE + NODE_ID_MAX:
                if self.consumers.received(consumer, now):
                    self.control.clear_error(EMCY_HEARTBEAT)

    def on_sync(self, t: float | None = None) -> None:
        """SYNC: send the synchronous TPDOs with the latest sampled values, then apply latched RPDOs.

        ``t`` is the SYNC's reception time on the communication clock (default: the latest time handed in); it times
        the event-driven TPDOs that a controlword applied here may trigger.
        """
        if t is None:
            t = self._now
        elif t > self._now:
            self._now = t
        if self.nmt.state is not NmtState.OPERATIONAL:
            return
        with self._lock:
            self._steady = False
            self.counters.syncs += 1
            self._sample(self.io)  # the actual values as of this SYNC
            self.pdo.on_sync(t)

    def update(self, t: float, dt: float) -> None:
        """One physics step: sample io, run the 402 timers and control law, write the io outputs.

        A drive whose outputs cannot change by themselves (power stage off, or cyclic synchronous torque with the
        brake released: the demand is the last applied command) skips the steps until something reaches it — a
        frame, a SYNC, a fault, a watchdog (``_steady``). Actual values are sampled where they are read: a SYNC's
        TPDOs, an SDO upload, an event TPDO, and each computed step (the CSP following error).
        """
        motion = self.motion
        if self._steady:
            self._sim_t = motion.t = t
            return
        io = self.io
        with self._lock:
            self._sim_t = motion.t = t
            self._sample(io)
            regime = motion.regime
            if regime is Regime.COMMAND:
                demand_A = motion.command_current(t, dt)
                if not motion.brake_released and t - motion.enabled_at_s >= self.params.brake_release_delay_s:
                    motion.brake_released = True
            elif regime is Regime.STOPPING:
                demand_A = motion.stop_current(t, dt)
            else:
                demand_A = 0.0
            if motion.regime is Regime.OFF:
                io.current_demand_A = 0.0
                io.power_stage_on = False
                io.brake_engaged = True
            else:
                io.current_demand_A = demand_A
                io.power_stage_on = True
                io.brake_engaged = not motion.brake_released
            self.control.refresh_statusword()
            self._steady = motion.regime is Regime.OFF or (
                motion.regime is Regime.COMMAND and motion.mode == _CST and motion.brake_released)

    def _comm_now(self) -> float:
        """The communication clock now: the clock given, else the latest time handed in."""
        clock = self._clock
        return self._now if clock is None else clock()

    def _unsteady(self) -> None:
        self._steady = False

    def comm(self, now: float) -> None:
        """The communication side's timers (watchdogs, heartbeat, event TPDOs), due every ``COMM_TICK_S``; ``now`` on
        the communication clock. Called once per millisecond tick by the simulator's loop."""
        if now > self._now:
            self._now = now
        if now >= self._next_comm_s:
            self._comm_tick(now)

    # ==================================================================================================
    # sampling
    # ==================================================================================================
    def _sample(self, io: AxisIO) -> None:
        cells, s, k = self.store.cells, self.s, self.scaling
        cells[s.position] = _wrap_int32(round(io.position_rad * self._counts_per_rad) + self.encoder_offset_counts)
        word = io.digital_inputs & s.inputs_mask  # the contacts wired to the drive (sim/hand.py)
        if s.inputs_signed and word > s.inputs_mask >> 1:
            word -= s.inputs_mask + 1
        cells[s.digital_inputs] = word
        v = round(io.velocity_rad_s * self._counts_per_rad)
        cells[s.velocity] = _INT32_MIN if v < _INT32_MIN else _INT32_MAX if v > _INT32_MAX else v
        current_A = io.current_measured_A
        lo, hi = s.current_range
        v = round(current_A / k.current_actual)
        cells[s.current_actual] = v = lo if v < lo else hi if v > hi else v
        if self._same_torque_current:
            cells[s.torque_actual] = v  # K_m = rated torque / rated current: torque and current per mille agree
        else:
            lo, hi = s.torque_range
            v = round(current_A / k.torque_actual)
            cells[s.torque_actual] = lo if v < lo else hi if v > hi else v

    def _stopped(self, then: State | None) -> None:
        self.control.stopped(then)

    def _raise_error(self, code: int, register_bits: int, manufacturer: bytes = b"") -> None:
        self._steady = False
        self.errors.raise_error(code, register_bits, manufacturer)

    def _rpdo_mode(self, mode: int) -> None:
        if not self.control.rpdo_mode(mode):
            self.counters.rpdo_invalid_mode += 1

    # ==================================================================================================
    # NMT
    # ==================================================================================================
    def _on_nmt(self, data: bytes | bytearray) -> None:
        command = self.nmt.command(data)
        if command is None:
            return
        self.counters.nmt_commands += 1
        if command == NmtCommand.START:
            self._set_nmt(NmtState.OPERATIONAL)
        elif command == NmtCommand.STOP:
            self._set_nmt(NmtState.STOPPED)
            self.control.abort_connection(EMCY_COMMUNICATION)
        elif command == NmtCommand.PRE_OPERATIONAL:
            self._set_nmt(NmtState.PRE_OPERATIONAL)
        elif command == NmtCommand.RESET_NODE:
            self.reset_node()
        elif command == NmtCommand.RESET_COMMUNICATION:
            self.reset_communication()

    def _set_nmt(self, state: NmtState) -> None:
        self._steady = False
        previous = self.nmt.state
        if state is previous:
            return
        self.nmt.state = state
        self.pdo.on_nmt(previous, state)
        if state is NmtState.OPERATIONAL:
            self._next_comm_s = 0.0

    def reset_node(self) -> None:
        """NMT reset node: application and communication objects back to defaults, boot-up."""
        with self._lock:
            self._steady = False
            self.nmt.state = NmtState.INITIALISING
            self.store.reset()
            self._reset_application_state()
            self._reset_communication_state()
            self.control.enter(State.SWITCH_ON_DISABLED)
            self.nmt.bootup(self._comm_now())

    def reset_communication(self) -> None:
        """NMT reset communication: 1000h-1FFFh back to defaults, boot-up (6007h reaction first)."""
        with self._lock:
            self._steady = False
            self.control.abort_connection(EMCY_COMMUNICATION)
            self.nmt.state = NmtState.INITIALISING
            self.store.reset(OD_COMMUNICATION_AREA)
            self.errors.update_register()
            self._reset_communication_state()
            self.nmt.bootup(self._comm_now())

    # ==================================================================================================
    # communication watchdogs, heartbeat
    # ==================================================================================================
    def _comm_tick(self, now: float) -> None:
        if now > self._now:
            self._now = now
        with self._lock:
            # on a COMM_TICK_S grid: called once per tick by the simulator's loop, a tick that comes a little early
            # must not push the next one a whole period further (at most one period is made up after a stall)
            self._next_comm_s = max(self._next_comm_s + COMM_TICK_S, now - COMM_TICK_S)
            nmt = self.nmt
            if nmt.state is NmtState.INITIALISING:
                return
            if nmt.period_s > 0.0 and now >= nmt.next_s:
                nmt.tick(now)
            for node, consumer in self.consumers.by_node.items():
                if consumer.last_rx_s is not None and not consumer.expired \
                        and self._deadline_passed(consumer.last_rx_s, consumer.timeout_s, now):
                    consumer.expired = True
                    self._heartbeat_lost(node)
            if nmt.state is not NmtState.OPERATIONAL:
                return
            pdo = self.pdo
            for ch in pdo.deadline_rpdos:
                if (ch.last_rx_s is not None and not ch.timed_out
                        and self._deadline_passed(ch.last_rx_s, ch.event_s, now)):
                    ch.timed_out = True
                    self._rpdo_timeout(ch.number)
            watchdog = self.s.rpdo_watchdog
            if watchdog is not None and pdo.last_rx_s is not None and not pdo.watchdog_expired:
                limit_s = self.store.cells[watchdog] * self.s.rpdo_watchdog_s_per_unit
                if limit_s > 0.0 and self._deadline_passed(pdo.last_rx_s, limit_s, now):
                    pdo.watchdog_expired = True
                    self._rpdo_timeout(0)
            if pdo.event_tpdos:
                pdo.poll_event_tpdos(now)

    def _deadline_passed(self, last_rx_s: float, timeout_s: float, now: float) -> bool:
        """Whether a reception deadline has passed — by the clock, over the time the simulator was running, and by what
        the reader has handed over: a real drive's controller takes each frame off the wire as it comes and never stops,
        this process may have been frozen with the master (counted in ``watchdog_holds``) or not scheduled to read the
        frames yet (``watchdog_waits``)."""
        if now - last_rx_s <= timeout_s:
            return False
        not_running = self.not_running
        if not_running is not None and now - last_rx_s - not_running(last_rx_s, now) <= timeout_s:
            self.counters.watchdog_holds += 1
            return False
        caught_up = self.rx_caught_up
        if caught_up is None:
            return True
        seen = min(now, caught_up(now))
        if seen - last_rx_s - (0.0 if not_running is None else not_running(last_rx_s, seen)) > timeout_s:
            return True
        self.counters.watchdog_waits += 1
        return False

    def _heartbeat_lost(self, node: int) -> None:
        self._steady = False
        self.counters.heartbeat_losses += 1
        self._raise_error(EMCY_HEARTBEAT, ERR_REG_COMMUNICATION, bytes((node,)))
        self.control.abort_connection(EMCY_HEARTBEAT)
        state = self.nmt.state_after_heartbeat_loss()
        if state is not None:
            self._set_nmt(state)
        self.control.refresh_statusword()

    def _rpdo_timeout(self, number: int) -> None:
        """An RPDO deadline passed (``number``: the RPDO's; 0: the vendor's watchdog over all RPDOs)."""
        self._steady = False
        self.counters.rpdo_timeouts += 1
        self._raise_error(EMCY_RPDO_TIMEOUT, ERR_REG_COMMUNICATION, bytes((number,)))
        self.control.abort_connection(EMCY_RPDO_TIMEOUT)
        self.control.refresh_statusword()

    # ==================================================================================================
    # routing
    # ==================================================================================================
    def _check_sync_cob(self, sub: int, value: int) -> None:
        if value & SYNC_COB_ID_GENERATE:
            raise SdoAbort(ABORT_VALUE_RANGE, OD_SYNC_COB_ID, 0, "this drive is a SYNC consumer; bit 30 must be 0")
        if value & (SYNC_COB_ID_GENERATE - 1) & ~COB_ID_MASK:  # bits 11-29: 3FFFF800h
            raise SdoAbort(ABORT_VALUE_RANGE, OD_SYNC_COB_ID, 0, "expected an 11-bit COB-ID")

    def _load_routing(self) -> None:
        st = self.store
        node = self.node_id
        self._sync_cob = (st.get(OD_SYNC_COB_ID) if st.has(OD_SYNC_COB_ID) else SYNC_COB_ID) & COB_ID_MASK
        self._sdo_rx_cob = (st.get(OD_SDO_SERVER, 1) if st.has(OD_SDO_SERVER, 1) else SDO_RX_BASE + node) & COB_ID_MASK
        self._sdo_tx_cob = (st.get(OD_SDO_SERVER, 2) if st.has(OD_SDO_SERVER, 2) else SDO_TX_BASE + node) & COB_ID_MASK
        ids = {NMT_COB_ID, self._sync_cob, self._sdo_rx_cob}
        ids.update(ch.cob_id for ch in self.pdo.rpdos if ch.valid)
        ids.update(HEARTBEAT_BASE + n for n in self.consumers.by_node)
        self._rx_ids = frozenset(ids)
        SimDrive.routes_generation = next(_ROUTE_GENERATIONS)  # atomic across the bus reader threads

    # ==================================================================================================
    # transmit
    # ==================================================================================================
    def _send_sdo(self, payload: bytes) -> None:
        self._tx(can.Message(arbitration_id=self._sdo_tx_cob, data=payload, is_extended_id=False, check=False))

    def _tx(self, msg: can.Message) -> None:
        try:
            self._send(msg)
        except can.CanError:
            self.counters.send_errors += 1


def _wrap_int32(value: int) -> int:
    return ((value - _INT32_MIN) & 0xFFFFFFFF) + _INT32_MIN


__all__ = ["DEFAULT_EDS_PATH", "DriveCounters", "DriveParams", "NmtState", "SimDrive"]
