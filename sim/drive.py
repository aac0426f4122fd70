"""One simulated CiA 301 / CiA 402 joint drive: NMT, SDO server, PDOs, 402 state machine, watchdogs, EMCY.

Threads: `on_message` / `on_data` / `on_sync` run in the network's reader thread, `update` in the physics thread.
All take the drive's re-entrant lock for their (short) work. Only `update` writes the AxisIO outputs. Reception
deadlines are judged against the time up to which the reader has handed frames over.

Clocks: communication timing (heartbeats, RPDO deadlines, inhibit times, event timers) uses
`time.monotonic()` because it concerns the real bus; motion timing (brake release, stop ramps, torque
slope) uses the physics time `t` handed to `update`.

Drive-specific behaviour, beyond what CiA 301/402 fix:
- 6007h (abort connection option) reacts to: master heartbeat loss (1016h), RPDO deadline expiry (event
  timer, 140xh sub 5), NMT stop and reset communication. It acts in ready to switch on, switched on,
  operation enabled and quick stop active. Heartbeat loss also applies 1029h sub 1 to the NMT state.
- Quick stop / fault reaction / slow-down stops run the drive's own PI velocity loop toward rest
  (ramp 6084h or 6085h, or a current-limit stop); at rest the brake engages and the power stage switches
  off. Quick stop option codes 0-3, 5-7 and fault reaction codes 0-3 are supported (voltage-limit codes
  are refused with abort 0x06090030).
- 6075h is stored in mA and 6076h in mN·m (CiA 402 units); both are read-only hardware facts.
"""

from __future__ import annotations

import itertools
import math
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from enum import IntEnum
from pathlib import Path
from typing import Any

import can

from dragd.hardware.cia402 import (
    EMCY_COMMUNICATION,
    EMCY_HEARTBEAT,
    EMCY_NO_ERROR,
    EMCY_PDO_LENGTH,
    EMCY_RPDO_TIMEOUT,
    ERR_REG_COMMUNICATION,
    ERR_REG_GENERIC,
    STATE_STATUSWORD_BITS,
    SW_CYCLIC_FOLLOWING,
    SW_INTERNAL_LIMIT_ACTIVE,
    SW_REMOTE,
    SW_TARGET_REACHED,
    SW_VOLTAGE_ENABLED,
    SW_WARNING,
    VOLTAGE_ENABLED_STATES,
    AbortConnectionOption,
    Command,
    FaultReactionOption,
    Mode,
    QuickStopOption,
    ShutdownOption,
    State,
    decode_command,
    is_fault_reset_edge,
    modes_from_supported_bits,
)
from dragd.hardware.cia301 import HEARTBEAT_BASE, NmtCommand, NmtState
from dragd.resources import eds_path
from sim.axis import AxisIO
from sim.od import (
    ABORT_DEVICE_STATE,
    ABORT_PARAMETER_INCOMPATIBLE,
    ABORT_VALUE_RANGE,
    COMM_RANGE,
    ObjectStore,
    SdoAbort,
)
from sim.pdo import (
    CLASSIC_MAX_BYTES,
    COB_EXTENDED,
    COB_INVALID,
    FD_MAX_BYTES,
    PdoChannel,
    check_transmission_type,
    validate_entry,
    validate_mapping,
)
from sim.sdo_server import SdoServer

DEFAULT_EDS_PATH = eds_path()
COMM_TICK_S = 0.001  # period of the communication watchdog / heartbeat / event-TPDO checks
_EMCY = struct.Struct("<HB5s")
_INT32_MIN, _INT32_MAX = -(1 << 31), (1 << 31) - 1
_CYCLIC_MODES = frozenset({Mode.CYCLIC_SYNC_POSITION, Mode.CYCLIC_SYNC_VELOCITY, Mode.CYCLIC_SYNC_TORQUE})
_SWITCHED_ON_STATES = frozenset(
    {State.READY_TO_SWITCH_ON, State.SWITCHED_ON, State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE}
)




@dataclass(frozen=True)
class DriveParams:
    """Hardware facts of one joint drive (from the sim's truth config). Currents are motor currents."""

    node_id: int
    rated_current_A: float  # 6075h
    rated_torque_Nm: float  # 6076h, motor side
    max_current_A: float  # 6073h
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
    fd: bool = False  # PDOs up to 64 bytes (CAN FD bus)
    vendor_id: int = 0x00000000
    product_code: int = 0x00000001
    revision_number: int = 0x00010000
    serial_number: int = 0

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


class _Regime(IntEnum):
    OFF = 0  # power stage off, brake engaged
    COMMAND = 1  # operation enabled: the mode's control law
    STOPPING = 2  # the drive's own velocity loop brings the joint to rest


@dataclass
class _Stop:
    """An active deceleration to rest."""

    decel_rad_s2: float | None  # None: current-limit stop
    then: State | None  # state after the stop; None: stay (quick stop active, codes 5-7)
    v_ref_rad_s: float
    integral_A: float
    started_s: float
    still_since_s: float | None = None


@dataclass
class _Consumer:
    """Heartbeat consumer entry (1016h)."""

    timeout_s: float
    last_rx_s: float | None = None
    expired: bool = False


_ROUTE_GENERATIONS = itertools.count(1)


class SimDrive:
    """A CANopen joint drive node backed by an EDS, exchanging signals with the physics through AxisIO."""

    routes_generation = 0  # renewed by every drive whose COB-ID routing changes (SimNetwork rebuilds its tables)

    def __init__(self, params: DriveParams, io: AxisIO, send: Callable[[can.Message], None],
                 eds_path: str | Path = DEFAULT_EDS_PATH,
                 send_data: Callable[[int, bytes, bool], None] | None = None) -> None:
        """``send`` transmits a frame; ``send_data(cob_id, data, fd)``, when given, the PDOs (no ``can.Message``)."""
        self.params = params
        self.io = io
        self.node_id = params.node_id
        self._send = send
        self._send_data = send_data
        self.counters = DriveCounters()
        self._lock = threading.RLock()
        self.store = ObjectStore.from_eds(eds_path, params.node_id)
        self._counts_per_rad = params.encoder_counts_per_rev / (2.0 * math.pi)
        self._A_per_permille = params.rated_current_A / 1000.0
        self._apply_hardware_defaults()
        self._bind_slots()
        self._supported_modes = modes_from_supported_bits(self.store.get(0x6502))
        self.sdo = SdoServer(self.store, self._send_sdo)
        self.rpdos = [PdoChannel(n, True, 0x1400 + n - 1, 0x1600 + n - 1) for n in range(1, 5)]
        self.tpdos = [PdoChannel(n, False, 0x1800 + n - 1, 0x1A00 + n - 1) for n in range(1, 5)]
        self._install_hooks()
        self.store.written = self._unsteady
        self._consumers: dict[int, _Consumer] = {}
        # set by the SimNetwork: the time (monotonic) up to which every frame that reached this process has been
        # handed to the drives, given now — the reception watchdogs judge against it: a stall of the simulator's
        # reader is not a silent bus
        self.rx_caught_up: Callable[[float], float] | None = None
        self.nmt_state = NmtState.INITIALISING
        self._sim_t = 0.0
        self._steady = False  # the last update's outputs hold until something reaches the drive (see ``update``)
        self.encoder_offset_counts = 0  # an injected encoder jump (sim/faults.py), added to 6064h
        self._reset_application_state()
        self._reset_communication_state()

    # ==================================================================================================
    # construction helpers
    # ==================================================================================================
    def _apply_hardware_defaults(self) -> None:
        p, st = self.params, self.store
        st.set_default(0x6075, 0, round(p.rated_current_A * 1000.0))
        st.set_default(0x6076, 0, round(p.rated_torque_Nm * 1000.0))
        st.set_default(0x6073, 0, round(1000.0 * p.max_current_A / p.rated_current_A))
        st.set_default(0x6072, 0, p.max_torque_permille)
        st.set_default(0x6084, 0, max(1, round(p.slowdown_decel_rad_s2 * self._counts_per_rad)))
        st.set_default(0x6085, 0, max(1, round(p.quickstop_decel_rad_s2 * self._counts_per_rad)))
        st.set_default(0x1018, 1, p.vendor_id)
        st.set_default(0x1018, 2, p.product_code)
        st.set_default(0x1018, 3, p.revision_number)
        st.set_default(0x1018, 4, p.serial_number or p.node_id)

    def _bind_slots(self) -> None:
        s = self.store.slot
        self._s_err_reg = s(0x1001)
        self._s_abort_option = s(0x6007)
        self._s_error_code = s(0x603F)
        self._s_controlword = s(0x6040)
        self._s_statusword = s(0x6041)
        self._s_qs_option = s(0x605A)
        self._s_shutdown_option = s(0x605B)
        self._s_disable_op_option = s(0x605C)
        self._s_fault_option = s(0x605E)
        self._s_mode = s(0x6060)
        self._s_mode_display = s(0x6061)
        self._s_position = s(0x6064)
        self._s_velocity = s(0x606C)
        self._s_target_torque = s(0x6071)
        self._s_max_torque = s(0x6072)
        self._s_max_current = s(0x6073)
        self._s_torque_demand = s(0x6074)
        self._s_torque_actual = s(0x6077)
        self._s_current_actual = s(0x6078)
        self._s_target_position = s(0x607A)
        self._s_profile_decel = s(0x6084)
        self._s_quickstop_decel = s(0x6085)
        self._s_torque_slope = s(0x6087)
        self._s_velocity_offset = s(0x60B1)
        self._s_torque_offset = s(0x60B2)
        self._s_following_error = s(0x60F4)
        self._s_target_velocity = s(0x60FF)
        self._rpdo_hooks: dict[int, Callable[[int], None]] = {
            self._s_mode: self._rpdo_mode,
            self._s_controlword: self._on_controlword,
        }

    def _install_hooks(self) -> None:
        before, after = self.store.before_write, self.store.after_write
        for ch in self.rpdos + self.tpdos:
            before[ch.comm_index] = self._make_comm_check(ch)
            after[ch.comm_index] = self._make_comm_apply(ch)
            before[ch.map_index] = self._make_map_check(ch)
        before[0x1003] = self._check_error_history
        after[0x1003] = self._clear_error_history
        before[0x1005] = self._check_sync_cob
        after[0x1005] = self._after_routing_change
        before[0x1014] = self._check_emcy_cob
        before[0x1016] = self._check_consumer
        after[0x1016] = lambda sub, value: self._load_consumers()
        after[0x1017] = lambda sub, value: self._schedule_heartbeat(time.monotonic())
        before[0x605A] = self._check_quick_stop_option
        before[0x6060] = self._check_mode
        after[0x6060] = lambda sub, value: self._set_mode(value)
        after[0x6040] = lambda sub, value: self._on_controlword(value)

    def _reset_application_state(self) -> None:
        """402 side back to power-on: no torque, brake engaged, no errors."""
        self.state = State.NOT_READY_TO_SWITCH_ON
        self._regime = _Regime.OFF
        self._stop: _Stop | None = None
        self._brake_released = False
        self._enabled_at_s = 0.0
        self._prev_controlword = 0
        self._mode = 0
        self._pt_ref_permille = 0.0
        self._csp_last_target = 0
        self._csp_last_change_s = 0.0
        self._csp_interval_s = 0.0
        self._csp_v_ff_rad_s = 0.0
        self._csp_integral_A = 0.0
        self._internal_limit = False
        self._target_reached = False
        self._active_errors: dict[int, int] = {}

    def _reset_communication_state(self) -> None:
        """Communication side from the current store values (after a store reset or at construction)."""
        self.sdo.reset()
        for ch in self.rpdos + self.tpdos:
            self._load_channel(ch)
        self._load_consumers()  # also reloads the routing (COB-IDs consumed)
        self._schedule_heartbeat(time.monotonic())
        self._next_comm_s = 0.0

    # ==================================================================================================
    # public API
    # ==================================================================================================
    def boot(self) -> None:
        """Power-on: initialisation, boot-up frame, NMT pre-operational, 402 switch on disabled."""
        with self._lock:
            self._steady = False
            self._enter_state(State.SWITCH_ON_DISABLED)
            self._send_bootup()

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
            self._fault(code, error_register_bits, manufacturer)

    def on_message(self, msg: can.Message) -> None:
        """Handle one received frame (NMT, SYNC, SDO request, RPDO, heartbeat); ignores the rest."""
        if msg.is_extended_id or msg.is_error_frame or msg.is_remote_frame:
            return
        self.on_data(msg.arbitration_id, msg.data)

    def on_data(self, cob: int, data: bytes | bytearray) -> None:
        """`on_message` for a plain data frame (11-bit id, not remote): its COB-ID and payload."""
        now = time.monotonic()
        with self._lock:
            self._steady = False  # (whatever the frame changes, the next physics step computes the outputs afresh)
            if cob == 0x000:
                self._on_nmt(data)
                return
            nmt = self.nmt_state
            if nmt is NmtState.INITIALISING:
                return
            if cob == self._sync_cob:
                self.on_sync(now)
                return
            if cob == self._sdo_rx_cob:
                if nmt is not NmtState.STOPPED:
                    self._sample(self.io)  # an upload of an actual value reads it now
                    self.sdo.on_request(data)
                return
            channels = self._rpdo_by_cob.get(cob)
            if channels is not None:
                if nmt is NmtState.OPERATIONAL:
                    for ch in channels:
                        self._receive_rpdo(ch, data, now)
                return
            consumer = self._consumers.get(cob - HEARTBEAT_BASE)
            if consumer is not None and 0x701 <= cob <= 0x77F:
                self._heartbeat_received(cob - HEARTBEAT_BASE, consumer, now)

    def on_sync(self, t: float | None = None) -> None:
        """SYNC: send the synchronous TPDOs with the latest sampled values, then apply latched RPDOs.

        `t` is the SYNC's reception time on the `time.monotonic()` clock (default: now); it times the
        event-driven TPDOs that a controlword applied here may trigger.
        """
        if self.nmt_state is not NmtState.OPERATIONAL:
            return
        with self._lock:
            self._steady = False
            self.counters.syncs += 1
            self._sample(self.io)  # the actual values as of this SYNC
            cells = self.store.cells
            for ch in self._sync_tpdos:
                ch.sync_count += 1
                if ch.trans_type == 0:
                    data = ch.sample(cells)
                    if data != ch.last_data:
                        self._send_pdo(ch, data)
                elif ch.sync_count >= ch.trans_type:
                    ch.sync_count = 0
                    self._send_pdo(ch, ch.sample(cells))
            applied = False
            for ch in self._sync_rpdos:
                data = ch.latched
                if data is not None:
                    ch.latched = None
                    self._apply_rpdo(ch, data)
                    applied = True
            if applied and self._event_tpdos:
                self._poll_event_tpdos(time.monotonic() if t is None else t, sampled=True)

    def update(self, t: float, dt: float) -> None:
        """One physics step: sample io, run the 402 timers and control law, write the io outputs.

        A drive whose outputs cannot change by themselves (power stage off, or cyclic synchronous torque with the
        brake released: the demand is the last applied command) skips the steps until something reaches it — a
        frame, a SYNC, a fault, a watchdog (``_steady``). Actual values are sampled where they are read: a SYNC's
        TPDOs, an SDO upload, an event TPDO, and each computed step (the CSP following error).
        """
        if self._steady:
            self._sim_t = t
            return
        io = self.io
        with self._lock:
            self._sim_t = t
            self._sample(io)
            regime = self._regime
            if regime is _Regime.COMMAND:
                demand_A = self._command_current(t, dt)
                if not self._brake_released and t - self._enabled_at_s >= self.params.brake_release_delay_s:
                    self._brake_released = True
            elif regime is _Regime.STOPPING:
                demand_A = self._stop_current(t, dt)
            else:
                demand_A = 0.0
            if self._regime is _Regime.OFF:
                io.current_demand_A = 0.0
                io.power_stage_on = False
                io.brake_engaged = True
            else:
                io.current_demand_A = demand_A
                io.power_stage_on = True
                io.brake_engaged = not self._brake_released
            self._refresh_statusword()
            self._steady = self._regime is _Regime.OFF or (
                self._regime is _Regime.COMMAND and self._mode == Mode.CYCLIC_SYNC_TORQUE and self._brake_released)

    def _unsteady(self) -> None:
        self._steady = False

    def comm(self, now: float) -> None:
        """The communication side's timers (watchdogs, heartbeat, event TPDOs), due every ``COMM_TICK_S``; ``now`` on
        the ``time.monotonic()`` clock. Called once per millisecond tick by the simulator's loop."""
        if now >= self._next_comm_s:
            self._comm_tick(now)

    # ==================================================================================================
    # sampling, control laws, stops
    # ==================================================================================================
    def _sample(self, io: AxisIO) -> None:
        cells = self.store.cells
        cells[self._s_position] = _wrap_int32(round(io.position_rad * self._counts_per_rad) + self.encoder_offset_counts)
        cells[self._s_velocity] = _clamp_int32(round(io.velocity_rad_s * self._counts_per_rad))
        current_permille = _clamp_int16(round(io.current_measured_A / self._A_per_permille))
        cells[self._s_current_actual] = current_permille
        cells[self._s_torque_actual] = current_permille  # K_m = 6076h/6075h: torque and current per mille agree

    def _limit_A(self) -> float:
        cells = self.store.cells
        return min(cells[self._s_max_torque], cells[self._s_max_current]) * self._A_per_permille

    def _command_current(self, t: float, dt: float) -> float:
        cells = self.store.cells
        mode = self._mode
        offset_A = cells[self._s_torque_offset] * self._A_per_permille
        if mode == Mode.CYCLIC_SYNC_TORQUE:
            demand_A = cells[self._s_target_torque] * self._A_per_permille + offset_A
        elif mode == Mode.CYCLIC_SYNC_POSITION:
            demand_A = self._csp_current(t, dt, cells) + offset_A
        elif mode == Mode.CYCLIC_SYNC_VELOCITY:
            v_ref = (cells[self._s_target_velocity] + cells[self._s_velocity_offset]) / self._counts_per_rad
            demand_A = self.params.csp_kd_A_s_per_rad * (v_ref - self.io.velocity_rad_s) + offset_A
        elif mode == Mode.PROFILE_TORQUE:
            demand_A = self._pt_step(cells, dt) * self._A_per_permille + offset_A
        else:
            demand_A = 0.0
        return self._clamp_demand(demand_A)

    def _clamp_demand(self, demand_A: float) -> float:
        limit_A = self._limit_A()
        if demand_A > limit_A:
            demand_A, self._internal_limit = limit_A, True
        elif demand_A < -limit_A:
            demand_A, self._internal_limit = -limit_A, True
        else:
            self._internal_limit = False
        self.store.cells[self._s_torque_demand] = _clamp_int16(round(demand_A / self._A_per_permille))
        return demand_A

    def _csp_current(self, t: float, dt: float, cells: list[Any]) -> float:
        target = cells[self._s_target_position]
        if target != self._csp_last_target:
            interval = t - self._csp_last_change_s
            if 0.0 < interval < 0.1:
                self._csp_v_ff_rad_s = (target - self._csp_last_target) / self._counts_per_rad / interval
                self._csp_interval_s = interval
            else:
                self._csp_v_ff_rad_s = 0.0
            self._csp_last_target = target
            self._csp_last_change_s = t
        elif t - self._csp_last_change_s > 3.0 * self._csp_interval_s:
            self._csp_v_ff_rad_s = 0.0
        cells[self._s_following_error] = _clamp_int32(target - cells[self._s_position])
        p = self.params
        error_rad = target / self._counts_per_rad - self.io.position_rad
        if p.csp_ki_A_per_rad_s:
            limit_A = self._limit_A()
            self._csp_integral_A = max(-limit_A, min(limit_A, self._csp_integral_A + p.csp_ki_A_per_rad_s * error_rad * dt))
        return (p.csp_kp_A_per_rad * error_rad + p.csp_kd_A_s_per_rad * (self._csp_v_ff_rad_s - self.io.velocity_rad_s)
                + self._csp_integral_A)

    def _pt_step(self, cells: list[Any], dt: float) -> float:
        target = float(cells[self._s_target_torque])
        step = cells[self._s_torque_slope] * dt
        ref = self._pt_ref_permille
        if ref < target:
            ref = min(target, ref + step)
        elif ref > target:
            ref = max(target, ref - step)
        self._pt_ref_permille = ref
        self._target_reached = ref == target
        return ref

    def _start_stop(self, decel_rad_s2: float | None, then: State | None) -> None:
        """Begin a deceleration to rest with the drive's velocity loop (bumpless from the last demand)."""
        self._stop = _Stop(decel_rad_s2=decel_rad_s2, then=then, v_ref_rad_s=self.io.velocity_rad_s,
                           integral_A=self.io.current_demand_A, started_s=self._sim_t)
        self._regime = _Regime.STOPPING
        self._target_reached = False

    def _stop_current(self, t: float, dt: float) -> float:
        st = self._stop
        assert st is not None
        p = self.params
        v = self.io.velocity_rad_s
        limit_A = self._limit_A()
        if st.decel_rad_s2 is None:
            st.v_ref_rad_s = 0.0
        elif st.v_ref_rad_s > 0.0:
            st.v_ref_rad_s = max(0.0, st.v_ref_rad_s - st.decel_rad_s2 * dt)
        elif st.v_ref_rad_s < 0.0:
            st.v_ref_rad_s = min(0.0, st.v_ref_rad_s + st.decel_rad_s2 * dt)
        error = st.v_ref_rad_s - v
        st.integral_A = max(-limit_A, min(limit_A, st.integral_A + p.quickstop_ki_A_per_rad * error * dt))
        if st.decel_rad_s2 is None and abs(v) > 4.0 * p.standstill_velocity_rad_s:
            demand_A = -limit_A if v > 0.0 else limit_A
        else:
            demand_A = p.quickstop_kd_A_s_per_rad * error + st.integral_A
        demand_A = self._clamp_demand(demand_A)
        if st.v_ref_rad_s == 0.0 and abs(v) < p.standstill_velocity_rad_s:
            if st.still_since_s is None:
                st.still_since_s = t
            elif t - st.still_since_s >= p.standstill_time_s:
                self._finish_stop()
        else:
            st.still_since_s = None
            if t - st.started_s > p.stop_timeout_s:
                self.counters.stop_timeouts += 1
                self._finish_stop()
        return demand_A

    def _finish_stop(self) -> None:
        st = self._stop
        assert st is not None
        self._stop = None
        self._power_off()
        if self.state is State.FAULT_REACTION_ACTIVE:
            self._enter_state(State.FAULT)
        elif st.then is None:
            self._target_reached = True  # quick stop active, at rest (option codes 5-7)
            self._refresh_statusword()
        else:
            self._enter_state(st.then)

    def _power_off(self) -> None:
        self._steady = False
        self._regime = _Regime.OFF
        self._brake_released = False
        self._internal_limit = False
        self.store.cells[self._s_torque_demand] = 0

    # ==================================================================================================
    # CiA 402 state machine
    # ==================================================================================================
    def _enter_state(self, state: State) -> None:
        self._steady = False
        self.state = state
        if state is not State.OPERATION_ENABLED and state not in (State.QUICK_STOP_ACTIVE,
                                                                  State.FAULT_REACTION_ACTIVE):
            self._stop = None
            self._power_off()
        self._target_reached = False
        self._refresh_statusword()

    def _enter_operation_enabled(self) -> None:
        self._stop = None
        self._regime = _Regime.COMMAND
        self._enabled_at_s = self._sim_t
        self._pt_ref_permille = 0.0
        self._csp_last_target = self.store.cells[self._s_target_position]
        self._csp_last_change_s = self._sim_t
        self._csp_v_ff_rad_s = 0.0
        self._csp_integral_A = 0.0
        self.state = State.OPERATION_ENABLED
        self._target_reached = False
        self._refresh_statusword()

    def _refresh_statusword(self) -> None:
        state = self.state
        sw = STATE_STATUSWORD_BITS[state] | SW_REMOTE
        if state in VOLTAGE_ENABLED_STATES:
            sw |= SW_VOLTAGE_ENABLED
        if self._active_errors and state is not State.FAULT and state is not State.FAULT_REACTION_ACTIVE:
            sw |= SW_WARNING
        if self._target_reached:
            sw |= SW_TARGET_REACHED
        if self._internal_limit:
            sw |= SW_INTERNAL_LIMIT_ACTIVE
        if self._regime is _Regime.COMMAND and self._mode in _CYCLIC_MODES:
            sw |= SW_CYCLIC_FOLLOWING
        self.store.cells[self._s_statusword] = sw

    def _on_controlword(self, controlword: int) -> None:
        previous = self._prev_controlword
        self._prev_controlword = controlword
        if self.state is State.FAULT:
            if is_fault_reset_edge(previous, controlword):
                self._fault_reset()
            return
        command = decode_command(controlword)
        if command is not None:
            self._apply_command(command)

    def _apply_command(self, command: Command) -> None:
        state = self.state
        if state is State.SWITCH_ON_DISABLED:
            if command is Command.SHUTDOWN:
                self._enter_state(State.READY_TO_SWITCH_ON)  # 2
        elif state is State.READY_TO_SWITCH_ON:
            if command is Command.SWITCH_ON:
                self._enter_state(State.SWITCHED_ON)  # 3
            elif command is Command.ENABLE_OPERATION:
                self._enter_state(State.SWITCHED_ON)  # 3 + 4
                self._enter_operation_enabled()
            elif command in (Command.DISABLE_VOLTAGE, Command.QUICK_STOP):
                self._enter_state(State.SWITCH_ON_DISABLED)  # 7
        elif state is State.SWITCHED_ON:
            if command is Command.ENABLE_OPERATION:
                self._enter_operation_enabled()  # 4
            elif command is Command.SHUTDOWN:
                self._enter_state(State.READY_TO_SWITCH_ON)  # 6
            elif command in (Command.DISABLE_VOLTAGE, Command.QUICK_STOP):
                self._enter_state(State.SWITCH_ON_DISABLED)  # 10
        elif state is State.OPERATION_ENABLED:
            self._command_in_operation_enabled(command)
        elif state is State.QUICK_STOP_ACTIVE:
            if command is Command.DISABLE_VOLTAGE:
                self._enter_state(State.SWITCH_ON_DISABLED)  # 12
            elif command is Command.ENABLE_OPERATION and self.store.cells[self._s_qs_option] >= 5:
                self._enter_operation_enabled()  # 16

    def _command_in_operation_enabled(self, command: Command) -> None:
        cells = self.store.cells
        if command is Command.ENABLE_OPERATION:
            if self._stop is not None:  # cancel a slow-down toward switched on / ready to switch on
                self._enter_operation_enabled()
        elif command is Command.SWITCH_ON:  # 5: disable operation
            self._leave_operation(State.SWITCHED_ON, cells[self._s_disable_op_option])
        elif command is Command.SHUTDOWN:  # 8
            self._leave_operation(State.READY_TO_SWITCH_ON, cells[self._s_shutdown_option])
        elif command is Command.DISABLE_VOLTAGE:  # 9
            self._enter_state(State.SWITCH_ON_DISABLED)
        else:  # 11
            self._quick_stop()

    def _leave_operation(self, then: State, option: int) -> None:
        if self._stop is not None:  # already slowing down (a repeated or changed command)
            self._stop.then = then
            return
        if option == ShutdownOption.SLOW_DOWN_THEN_DISABLE and self._regime is not _Regime.OFF:
            self._start_stop(self._decel_rad_s2(self._s_profile_decel), then)
        else:
            self._enter_state(then)

    def _quick_stop(self) -> None:
        option = self.store.cells[self._s_qs_option]
        self.state = State.QUICK_STOP_ACTIVE
        if option == QuickStopOption.DISABLE_DRIVE:
            self._enter_state(State.SWITCH_ON_DISABLED)  # 11 then 12
            return
        then = State.SWITCH_ON_DISABLED if option <= QuickStopOption.VOLTAGE_LIMIT else None
        self._start_stop(self._stop_decel(option), then)
        self._refresh_statusword()

    def _stop_decel(self, option: int) -> float | None:
        """Deceleration (rad/s²) of a quick-stop / fault-reaction code; None for a current-limit stop."""
        base = option - 4 if option >= QuickStopOption.SLOW_DOWN_RAMP_STAY else option
        if base == QuickStopOption.SLOW_DOWN_RAMP:
            return self._decel_rad_s2(self._s_profile_decel)
        if base == QuickStopOption.QUICK_STOP_RAMP:
            return self._decel_rad_s2(self._s_quickstop_decel)
        return None

    def _decel_rad_s2(self, slot: int) -> float:
        return self.store.cells[slot] / self._counts_per_rad

    def _fault(self, code: int, register_bits: int, manufacturer: bytes = b"", emcy: bool = True) -> None:
        self._steady = False
        if emcy:
            self._raise_error(code, register_bits, manufacturer)
        else:
            self._active_errors[code] = register_bits
            self._update_error_register()
        if self.state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
            return
        self.store.cells[self._s_error_code] = code
        reaction = self.store.cells[self._s_fault_option]
        was_powered = self._regime is not _Regime.OFF
        self.state = State.FAULT_REACTION_ACTIVE
        if not was_powered or reaction == FaultReactionOption.DISABLE_DRIVE:
            self._enter_state(State.FAULT)
            return
        self._start_stop(self._stop_decel(reaction), State.FAULT)
        self._refresh_statusword()

    def _fault_reset(self) -> None:
        self._active_errors.clear()
        self.store.cells[self._s_error_code] = 0
        self._update_error_register()
        self._enter_state(State.SWITCH_ON_DISABLED)  # 15
        self._send_emcy(EMCY_NO_ERROR, b"")

    def _set_mode(self, mode: int) -> None:
        self._steady = False
        if self._mode == mode:
            return
        self._mode = mode
        self.store.cells[self._s_mode_display] = mode
        self._pt_ref_permille = self.store.cells[self._s_torque_demand] if self._regime is _Regime.COMMAND else 0.0
        self._csp_last_target = self.store.cells[self._s_target_position]
        self._csp_v_ff_rad_s = 0.0
        self._csp_integral_A = 0.0
        self._target_reached = False
        self._refresh_statusword()

    def _rpdo_mode(self, mode: int) -> None:
        if mode == 0 or mode in self._supported_modes:
            self._set_mode(mode)
        else:
            self.counters.rpdo_invalid_mode += 1
            self.store.cells[self._s_mode] = self._mode

    def _abort_connection(self, error_code: int) -> None:
        """Apply 6007h after a loss of communication."""
        if self.state not in _SWITCHED_ON_STATES:
            return
        option = self.store.cells[self._s_abort_option]
        if option == AbortConnectionOption.FAULT:
            self._fault(error_code, ERR_REG_COMMUNICATION, emcy=False)
        elif option == AbortConnectionOption.DISABLE_VOLTAGE:
            self._apply_command(Command.DISABLE_VOLTAGE)
        elif option == AbortConnectionOption.QUICK_STOP:
            self._apply_command(Command.QUICK_STOP)

    # ==================================================================================================
    # errors and EMCY
    # ==================================================================================================
    def _raise_error(self, code: int, register_bits: int, manufacturer: bytes = b"") -> None:
        self._steady = False
        self._active_errors[code] = register_bits
        self._update_error_register()
        self._push_error_history(code, manufacturer)
        self._send_emcy(code, manufacturer)

    def _clear_error(self, code: int) -> None:
        """A non-latched error condition went away; EMCY 0000h once no error remains."""
        self._steady = False
        if code not in self._active_errors or self.state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
            return
        del self._active_errors[code]
        self._update_error_register()
        if not self._active_errors:
            self._send_emcy(EMCY_NO_ERROR, b"")
        self._refresh_statusword()

    def _update_error_register(self) -> None:
        register = 0
        for bits in self._active_errors.values():
            register |= bits | ERR_REG_GENERIC
        self.store.cells[self._s_err_reg] = register

    def _push_error_history(self, code: int, manufacturer: bytes) -> None:
        st = self.store
        extra = int.from_bytes(manufacturer[:2].ljust(2, b"\x00"), "little")
        for sub in range(8, 1, -1):
            st.set(0x1003, sub, st.get(0x1003, sub - 1))
        st.set(0x1003, 1, code | extra << 16)
        st.set(0x1003, 0, min(8, st.get(0x1003, 0) + 1))

    def _send_emcy(self, code: int, manufacturer: bytes) -> None:
        if self.nmt_state not in (NmtState.PRE_OPERATIONAL, NmtState.OPERATIONAL):
            return
        cob = self.store.get(0x1014)
        if cob & COB_INVALID:
            return
        data = _EMCY.pack(code, self.store.cells[self._s_err_reg], manufacturer[:5].ljust(5, b"\x00"))
        self.counters.emcys_sent += 1
        self._tx(can.Message(arbitration_id=cob & 0x7FF, data=data, is_extended_id=False, check=False))

    # ==================================================================================================
    # NMT
    # ==================================================================================================
    def _on_nmt(self, data: bytes) -> None:
        if len(data) < 2 or data[1] not in (0, self.node_id) or self.nmt_state is NmtState.INITIALISING:
            return
        self.counters.nmt_commands += 1
        command = data[0]
        if command == NmtCommand.START:
            self._set_nmt(NmtState.OPERATIONAL)
        elif command == NmtCommand.STOP:
            self._set_nmt(NmtState.STOPPED)
            self._abort_connection(EMCY_COMMUNICATION)
        elif command == NmtCommand.PRE_OPERATIONAL:
            self._set_nmt(NmtState.PRE_OPERATIONAL)
        elif command == NmtCommand.RESET_NODE:
            self.reset_node()
        elif command == NmtCommand.RESET_COMMUNICATION:
            self.reset_communication()

    def _set_nmt(self, state: NmtState) -> None:
        self._steady = False
        previous = self.nmt_state
        if state is previous:
            return
        self.nmt_state = state
        if previous is NmtState.OPERATIONAL:
            for ch in self.rpdos:
                ch.latched = None
                ch.last_rx_s = None
                ch.timed_out = False
        if state is NmtState.OPERATIONAL:
            for ch in self.tpdos:
                ch.sync_count = 0
                ch.last_data = None
                ch.pending = ch.valid and not ch.synchronous  # event TPDOs report once on start
            self._next_comm_s = 0.0

    def reset_node(self) -> None:
        """NMT reset node: application and communication objects back to defaults, boot-up."""
        with self._lock:
            self._steady = False
            self.nmt_state = NmtState.INITIALISING
            self.store.reset()
            self._reset_application_state()
            self._reset_communication_state()
            self._enter_state(State.SWITCH_ON_DISABLED)
            self._send_bootup()

    def reset_communication(self) -> None:
        """NMT reset communication: 1000h-1FFFh back to defaults, boot-up (6007h reaction first)."""
        with self._lock:
            self._steady = False
            self._abort_connection(EMCY_COMMUNICATION)
            self.nmt_state = NmtState.INITIALISING
            self.store.reset(COMM_RANGE)
            self._update_error_register()
            self._reset_communication_state()
            self._send_bootup()

    def _send_bootup(self) -> None:
        self.nmt_state = NmtState.PRE_OPERATIONAL
        self._tx(can.Message(arbitration_id=HEARTBEAT_BASE + self.node_id, data=b"\x00", is_extended_id=False, check=False))
        self._schedule_heartbeat(time.monotonic())

    # ==================================================================================================
    # PDOs
    # ==================================================================================================
    def _mapping_raws(self, ch: PdoChannel) -> list[int]:
        st = self.store
        return [st.get(ch.map_index, sub) for sub in range(1, st.get(ch.map_index, 0) + 1)]

    def _max_pdo_bytes(self) -> int:
        return FD_MAX_BYTES if self.params.fd else CLASSIC_MAX_BYTES

    def _load_channel(self, ch: PdoChannel) -> None:
        """(Re)compile one PDO from the store (called when its parameters change or on reset)."""
        st = self.store
        cob = st.get(ch.comm_index, 1)
        ch.valid = not cob & COB_INVALID
        ch.cob_id = cob & 0x7FF
        ch.trans_type = st.get(ch.comm_index, 2)
        ch.inhibit_s = 0.0 if ch.receive else st.get(ch.comm_index, 3) * 1e-4
        ch.event_s = st.get(ch.comm_index, 5) * 1e-3
        entries = validate_mapping(st, ch.map_index, self._mapping_raws(ch), ch.receive, self._max_pdo_bytes()) \
            if ch.valid else []
        ch.compile(entries, self.params.fd)
        ch.hooked_slots = tuple(slot for slot in self._rpdo_hooks if ch.receive and slot in ch.slots)
        self._index_channels()

    def _index_channels(self) -> None:
        valid_rpdos = [ch for ch in self.rpdos if ch.valid]
        by_cob: dict[int, list[PdoChannel]] = {}
        for ch in valid_rpdos:
            by_cob.setdefault(ch.cob_id, []).append(ch)
        self._rpdo_by_cob = by_cob
        self._sync_rpdos = [ch for ch in valid_rpdos if ch.synchronous]
        valid_tpdos = [ch for ch in self.tpdos if ch.valid and ch.layout.size > 0]
        self._sync_tpdos = [ch for ch in valid_tpdos if ch.synchronous]
        self._event_tpdos = [ch for ch in valid_tpdos if not ch.synchronous]
        self._deadline_rpdos = [ch for ch in valid_rpdos if ch.event_s > 0.0]

    def _make_comm_check(self, ch: PdoChannel) -> Callable[[int, Any], None]:
        def check(sub: int, value: int) -> None:
            if sub == 1:
                self._check_pdo_cob(ch, value)
            elif sub == 2:
                check_transmission_type(ch.comm_index, value, ch.receive)
            elif sub == 3 and ch.valid:
                raise SdoAbort(ABORT_DEVICE_STATE, ch.comm_index, sub,
                               "inhibit time cannot change while the PDO is valid (set COB-ID bit 31 first)")
        return check

    def _make_comm_apply(self, ch: PdoChannel) -> Callable[[int, Any], None]:
        def apply(sub: int, value: int) -> None:
            self._load_channel(ch)
            if sub == 1:
                self._after_routing_change(sub, value)
        return apply

    def _check_pdo_cob(self, ch: PdoChannel, value: int) -> None:
        index = ch.comm_index
        if value & COB_EXTENDED:
            raise SdoAbort(ABORT_VALUE_RANGE, index, 1, "29-bit COB-IDs are not supported; expected bit 29 = 0")
        can_id = value & 0x1FFFFFFF
        if not 0 < can_id <= 0x7FF:
            raise SdoAbort(ABORT_VALUE_RANGE, index, 1, f"COB-ID 0x{can_id:X} outside 0x001..0x7FF")
        new_valid = not value & COB_INVALID
        if ch.valid and new_valid and can_id != ch.cob_id:
            raise SdoAbort(ABORT_VALUE_RANGE, index, 1,
                           "COB-ID cannot change while the PDO is valid (set bit 31 first)")
        if new_valid and not ch.valid:
            validate_mapping(self.store, ch.map_index, self._mapping_raws(ch), ch.receive, self._max_pdo_bytes())

    def _make_map_check(self, ch: PdoChannel) -> Callable[[int, Any], None]:
        def check(sub: int, value: int) -> None:
            index = ch.map_index
            if self.nmt_state is not NmtState.PRE_OPERATIONAL:
                raise SdoAbort(ABORT_DEVICE_STATE, index, sub,
                               f"PDO mapping can only change in NMT pre-operational (now {self.nmt_state.name})")
            if ch.valid:
                raise SdoAbort(ABORT_DEVICE_STATE, index, sub,
                               f"PDO is valid; set bit 31 of 0x{ch.comm_index:04X}:01 first")
            if sub == 0:
                raws = [self.store.get(index, s) for s in range(1, value + 1)]
                validate_mapping(self.store, index, raws, ch.receive, self._max_pdo_bytes())
                return
            if self.store.get(index, 0) != 0:
                raise SdoAbort(ABORT_DEVICE_STATE, index, sub,
                               "mapping entries can only be written while sub-index 0 is 0")
            if value != 0:
                validate_entry(self.store, index, value, ch.receive)
        return check

    def _receive_rpdo(self, ch: PdoChannel, data: bytes, now: float) -> None:
        self.counters.rpdos_received += 1
        if len(data) < ch.layout.size:
            self.counters.rpdo_length_errors += 1
            if not ch.length_error:
                ch.length_error = True
                self._raise_error(EMCY_PDO_LENGTH, ERR_REG_COMMUNICATION, bytes((ch.number,)))
                self._refresh_statusword()
            return
        if ch.length_error:
            ch.length_error = False
            self._clear_error(EMCY_PDO_LENGTH)
        ch.last_rx_s = now
        if ch.timed_out:
            ch.timed_out = False
            self._clear_error(EMCY_RPDO_TIMEOUT)
        if ch.synchronous:
            ch.latched = bytes(data)
        else:
            self._apply_rpdo(ch, data)
            if self._event_tpdos:
                self._poll_event_tpdos(now)

    def _apply_rpdo(self, ch: PdoChannel, data: bytes) -> None:
        cells = self.store.cells
        for slot, value in zip(ch.slots, ch.layout.unpack_from(data)):
            cells[slot] = value
        for slot in ch.hooked_slots:  # mode before controlword
            self._rpdo_hooks[slot](cells[slot])
        self.counters.rpdos_applied += 1

    def _send_pdo(self, ch: PdoChannel, data: bytes) -> None:
        ch.last_data = data
        self.counters.tpdos_sent += 1
        if self._send_data is None:
            self._tx(can.Message(arbitration_id=ch.cob_id, data=data, is_extended_id=False, is_fd=ch.is_fd,
                                 bitrate_switch=ch.is_fd, check=False))
            return
        try:
            self._send_data(ch.cob_id, data, ch.is_fd)
        except can.CanError:
            self.counters.send_errors += 1

    def _poll_event_tpdos(self, now: float, sampled: bool = False) -> None:
        """Send the event-driven TPDOs whose data changed (inhibit time kept); ``sampled``: actual values are current."""
        if not sampled:
            self._sample(self.io)
        cells = self.store.cells
        for ch in self._event_tpdos:
            data = ch.sample(cells)
            if data != ch.last_data or ch.pending:
                if now - ch.last_tx_s >= ch.inhibit_s:
                    ch.pending = False
                    ch.last_tx_s = now
                    self._send_pdo(ch, data)
                else:
                    ch.pending = True
            elif ch.event_s > 0.0 and now - ch.last_tx_s >= ch.event_s:
                ch.last_tx_s = now
                self._send_pdo(ch, data)

    # ==================================================================================================
    # communication watchdogs, heartbeat
    # ==================================================================================================
    def _comm_tick(self, now: float) -> None:
        with self._lock:
            # on a COMM_TICK_S grid: called once per tick by the simulator's loop, a tick that comes a little early
            # must not push the next one a whole period further (at most one period is made up after a stall)
            self._next_comm_s = max(self._next_comm_s + COMM_TICK_S, now - COMM_TICK_S)
            nmt = self.nmt_state
            if nmt is NmtState.INITIALISING:
                return
            if self._hb_period_s > 0.0 and now >= self._next_hb_s:
                self._send_heartbeat(now)
            for node, consumer in self._consumers.items():
                if consumer.last_rx_s is not None and not consumer.expired \
                        and self._deadline_passed(consumer.last_rx_s, consumer.timeout_s, now):
                    consumer.expired = True
                    self._heartbeat_lost(node)
            if self.nmt_state is not NmtState.OPERATIONAL:
                return
            for ch in self._deadline_rpdos:
                if ch.last_rx_s is not None and not ch.timed_out and self._deadline_passed(ch.last_rx_s, ch.event_s, now):
                    ch.timed_out = True
                    self._rpdo_timeout(ch)
            if self._event_tpdos:
                self._poll_event_tpdos(now)

    def _deadline_passed(self, last_rx_s: float, timeout_s: float, now: float) -> bool:
        """Whether a reception deadline has passed — by the clock, and by what the reader has handed over: a real
        drive's controller takes each frame off the wire as it comes, this process may not have been scheduled to
        read them yet (counted in ``watchdog_waits``)."""
        if now - last_rx_s <= timeout_s:
            return False
        caught_up = self.rx_caught_up
        if caught_up is None or min(now, caught_up(now)) - last_rx_s > timeout_s:
            return True
        self.counters.watchdog_waits += 1
        return False

    def _schedule_heartbeat(self, now: float) -> None:
        self._hb_period_s = self.store.get(0x1017) * 1e-3
        self._next_hb_s = now + self._hb_period_s

    def _send_heartbeat(self, now: float) -> None:
        self._next_hb_s = max(self._next_hb_s + self._hb_period_s, now)
        self.counters.heartbeats_sent += 1
        self._tx(can.Message(arbitration_id=HEARTBEAT_BASE + self.node_id, data=bytes((int(self.nmt_state),)),
                             is_extended_id=False, check=False))

    def _heartbeat_received(self, node: int, consumer: _Consumer, now: float) -> None:
        consumer.last_rx_s = now
        if consumer.expired:
            consumer.expired = False
            self._clear_error(EMCY_HEARTBEAT)

    def _heartbeat_lost(self, node: int) -> None:
        self._steady = False
        self.counters.heartbeat_losses += 1
        self._raise_error(EMCY_HEARTBEAT, ERR_REG_COMMUNICATION, bytes((node,)))
        self._abort_connection(EMCY_HEARTBEAT)
        behaviour = self.store.get(0x1029, 1)
        if behaviour == 0 and self.nmt_state is NmtState.OPERATIONAL:
            self._set_nmt(NmtState.PRE_OPERATIONAL)
        elif behaviour == 2:
            self._set_nmt(NmtState.STOPPED)
        self._refresh_statusword()

    def _rpdo_timeout(self, ch: PdoChannel) -> None:
        self._steady = False
        self.counters.rpdo_timeouts += 1
        self._raise_error(EMCY_RPDO_TIMEOUT, ERR_REG_COMMUNICATION, bytes((ch.number,)))
        self._abort_connection(EMCY_RPDO_TIMEOUT)
        self._refresh_statusword()

    def _load_consumers(self) -> None:
        consumers: dict[int, _Consumer] = {}
        st = self.store
        for sub in range(1, st.get(0x1016, 0) + 1):
            value = st.get(0x1016, sub)
            node, time_ms = (value >> 16) & 0xFF, value & 0xFFFF
            if node and time_ms:
                consumers[node] = _Consumer(timeout_s=time_ms * 1e-3)
        self._consumers = consumers
        self._load_routing()

    def _check_consumer(self, sub: int, value: int) -> None:
        if sub == 0:
            return
        node, time_ms = (value >> 16) & 0xFF, value & 0xFFFF
        if value >> 24:
            raise SdoAbort(ABORT_VALUE_RANGE, 0x1016, sub, "bits 24..31 must be 0")
        if not node or not time_ms:
            return
        if node > 127:
            raise SdoAbort(ABORT_VALUE_RANGE, 0x1016, sub, f"node-ID {node} outside 1..127")
        for other in range(1, self.store.get(0x1016, 0) + 1):
            existing = self.store.get(0x1016, other)
            if other != sub and (existing >> 16) & 0xFF == node and existing & 0xFFFF:
                raise SdoAbort(ABORT_PARAMETER_INCOMPATIBLE, 0x1016, sub,
                               f"node {node} is already monitored by sub-index {other}")

    # ==================================================================================================
    # other object hooks and routing
    # ==================================================================================================
    def _check_error_history(self, sub: int, value: int) -> None:
        if sub != 0 or value != 0:
            raise SdoAbort(ABORT_VALUE_RANGE, 0x1003, sub, "only 0 may be written to sub-index 0 (clear history)")

    def _clear_error_history(self, sub: int, value: int) -> None:
        for s in range(1, 9):
            self.store.set(0x1003, s, 0)

    def _check_sync_cob(self, sub: int, value: int) -> None:
        if value & 0x40000000:
            raise SdoAbort(ABORT_VALUE_RANGE, 0x1005, 0, "this drive is a SYNC consumer; bit 30 must be 0")
        if value & 0x3FFFF800:
            raise SdoAbort(ABORT_VALUE_RANGE, 0x1005, 0, "expected an 11-bit COB-ID")

    def _check_emcy_cob(self, sub: int, value: int) -> None:
        if value & 0x7FFFF800:
            raise SdoAbort(ABORT_VALUE_RANGE, 0x1014, 0, "expected an 11-bit COB-ID (bit 31 = EMCY disabled)")

    def _check_quick_stop_option(self, sub: int, value: int) -> None:
        if value in (QuickStopOption.VOLTAGE_LIMIT, QuickStopOption.VOLTAGE_LIMIT_STAY):
            raise SdoAbort(ABORT_VALUE_RANGE, 0x605A, 0, "voltage-limit quick stop is not supported; use 0-3, 5-7")

    def _check_mode(self, sub: int, value: int) -> None:
        if value != 0 and value not in self._supported_modes:
            raise SdoAbort(ABORT_VALUE_RANGE, 0x6060, 0,
                           f"mode {value} not supported; expected 0 or one of {sorted(self._supported_modes)}")

    def _after_routing_change(self, sub: int, value: Any) -> None:
        self._load_routing()

    def _load_routing(self) -> None:
        st = self.store
        self._sync_cob = st.get(0x1005) & 0x7FF
        self._sdo_rx_cob = st.get(0x1200, 1) & 0x7FF
        self._sdo_tx_cob = st.get(0x1200, 2) & 0x7FF
        ids = {0x000, self._sync_cob, self._sdo_rx_cob}
        ids.update(ch.cob_id for ch in self.rpdos if ch.valid)
        ids.update(HEARTBEAT_BASE + node for node in self._consumers)
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


def _clamp_int32(value: int) -> int:
    return _INT32_MIN if value < _INT32_MIN else _INT32_MAX if value > _INT32_MAX else value


def _clamp_int16(value: int) -> int:
    return -32768 if value < -32768 else 32767 if value > 32767 else value


__all__ = ["DEFAULT_EDS_PATH", "DriveCounters", "DriveParams", "NmtState", "SimDrive"]
