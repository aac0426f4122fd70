"""CiA 402 device control of one simulated drive: the state machine, controlword (6040h) and statusword (6041h),
modes of operation (6060h / 6061h against 6502h), the option codes (605Ah-605Eh, 6007h) and the fault reaction.

Quick stop / fault reaction / slow-down stops hand over to the power stage's stop loop (sim/motion.py, sim/stops.py);
at rest it calls back ``stopped``. Quick stop option codes 0-3, 5-7 and fault reaction codes 0-3 are supported
(voltage-limit codes are refused with abort 0x06090030). Option objects the EDS lacks act with the values of
docs/SIM_DRIVES.md (CiA 402's defaults).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from dragd.hardware.cia402 import (
    ERR_REG_COMMUNICATION,
    OD_MODES_OF_OPERATION,
    OD_QUICK_STOP_OPTION,
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
from sim.motion import Motion, Regime
from sim.od import ABORT_VALUE_RANGE, SdoAbort

if TYPE_CHECKING:
    from sim.emcy import Errors

CYCLIC_MODES = frozenset({Mode.CYCLIC_SYNC_POSITION, Mode.CYCLIC_SYNC_VELOCITY, Mode.CYCLIC_SYNC_TORQUE})
SWITCHED_ON_STATES = frozenset(
    {State.READY_TO_SWITCH_ON, State.SWITCHED_ON, State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE}
)
_FAULT_STATES = (State.FAULT, State.FAULT_REACTION_ACTIVE)


class DeviceControl:
    """The 402 state machine of one drive, acting on its power stage (``motion``) and error state (``errors``)."""

    def __init__(self, cells: list[Any], slots: Any, motion: Motion, errors: Errors, supported_modes: int) -> None:
        self.cells = cells
        self.s = slots
        self.motion = motion
        self.errors = errors
        self.supported_modes = modes_from_supported_bits(supported_modes)
        self.reset()

    def reset(self) -> None:
        """Power-on: not ready to switch on (``boot`` moves on to switch on disabled)."""
        self.state = State.NOT_READY_TO_SWITCH_ON
        self.prev_controlword = 0

    # --- states ------------------------------------------------------------------------------------------
    def enter(self, state: State) -> None:
        self.state = state
        motion = self.motion
        if state is not State.OPERATION_ENABLED and state not in (State.QUICK_STOP_ACTIVE, State.FAULT_REACTION_ACTIVE):
            motion.stop = None
            motion.power_off()
        motion.target_reached = False
        self.refresh_statusword()

    def enter_operation_enabled(self) -> None:
        self.motion.enable()
        self.state = State.OPERATION_ENABLED
        self.refresh_statusword()

    def refresh_statusword(self) -> None:
        state = self.state
        motion = self.motion
        sw = STATE_STATUSWORD_BITS[state] | SW_REMOTE
        if state in VOLTAGE_ENABLED_STATES:
            sw |= SW_VOLTAGE_ENABLED
        if self.errors.active and state is not State.FAULT and state is not State.FAULT_REACTION_ACTIVE:
            sw |= SW_WARNING
        if motion.target_reached:
            sw |= SW_TARGET_REACHED
        if motion.internal_limit:
            sw |= SW_INTERNAL_LIMIT_ACTIVE
        if motion.regime is Regime.COMMAND and motion.mode in CYCLIC_MODES:
            sw |= SW_CYCLIC_FOLLOWING
        self.cells[self.s.statusword] = sw

    def stopped(self, then: State | None) -> None:
        """The power stage's stop ended (brake engaged, power off): where the state machine goes from there."""
        if self.state is State.FAULT_REACTION_ACTIVE:
            self.enter(State.FAULT)
        elif then is None:
            self.motion.target_reached = True  # quick stop active, at rest (option codes 5-7)
            self.refresh_statusword()
        else:
            self.enter(then)

    # --- controlword ---------------------------------------------------------------------------------------
    def on_controlword(self, controlword: int) -> None:
        previous = self.prev_controlword
        self.prev_controlword = controlword
        if self.state is State.FAULT:
            if is_fault_reset_edge(previous, controlword):
                self.fault_reset()
            return
        command = decode_command(controlword)
        if command is not None:
            self.apply(command)

    def apply(self, command: Command) -> None:
        state = self.state
        if state is State.SWITCH_ON_DISABLED:
            if command is Command.SHUTDOWN:
                self.enter(State.READY_TO_SWITCH_ON)  # 2
        elif state is State.READY_TO_SWITCH_ON:
            if command is Command.SWITCH_ON:
                self.enter(State.SWITCHED_ON)  # 3
            elif command is Command.ENABLE_OPERATION:
                self.enter(State.SWITCHED_ON)  # 3 + 4
                self.enter_operation_enabled()
            elif command in (Command.DISABLE_VOLTAGE, Command.QUICK_STOP):
                self.enter(State.SWITCH_ON_DISABLED)  # 7
        elif state is State.SWITCHED_ON:
            if command is Command.ENABLE_OPERATION:
                self.enter_operation_enabled()  # 4
            elif command is Command.SHUTDOWN:
                self.enter(State.READY_TO_SWITCH_ON)  # 6
            elif command in (Command.DISABLE_VOLTAGE, Command.QUICK_STOP):
                self.enter(State.SWITCH_ON_DISABLED)  # 10
        elif state is State.OPERATION_ENABLED:
            self._in_operation_enabled(command)
        elif state is State.QUICK_STOP_ACTIVE:
            if command is Command.DISABLE_VOLTAGE:
                self.enter(State.SWITCH_ON_DISABLED)  # 12
            elif command is Command.ENABLE_OPERATION and self.cells[self.s.qs_option] >= 5:
                self.enter_operation_enabled()  # 16

    def _in_operation_enabled(self, command: Command) -> None:
        cells = self.cells
        if command is Command.ENABLE_OPERATION:
            if self.motion.stop is not None:  # cancel a slow-down toward switched on / ready to switch on
                self.enter_operation_enabled()
        elif command is Command.SWITCH_ON:  # 5: disable operation
            self._leave_operation(State.SWITCHED_ON, cells[self.s.disable_op_option])
        elif command is Command.SHUTDOWN:  # 8
            self._leave_operation(State.READY_TO_SWITCH_ON, cells[self.s.shutdown_option])
        elif command is Command.DISABLE_VOLTAGE:  # 9
            self.enter(State.SWITCH_ON_DISABLED)
        else:  # 11
            self._quick_stop()

    def _leave_operation(self, then: State, option: int) -> None:
        motion = self.motion
        if motion.stop is not None:  # already slowing down (a repeated or changed command)
            motion.stop.then = then
            return
        if option == ShutdownOption.SLOW_DOWN_THEN_DISABLE and motion.regime is not Regime.OFF:
            motion.start_stop(self._decel_rad_s2(self.s.profile_decel), then)
        else:
            self.enter(then)

    def _quick_stop(self) -> None:
        option = self.cells[self.s.qs_option]
        self.state = State.QUICK_STOP_ACTIVE
        if option == QuickStopOption.DISABLE_DRIVE:
            self.enter(State.SWITCH_ON_DISABLED)  # 11 then 12
            return
        then = State.SWITCH_ON_DISABLED if option <= QuickStopOption.VOLTAGE_LIMIT else None
        self.motion.start_stop(self._stop_decel(option), then)
        self.refresh_statusword()

    def _stop_decel(self, option: int) -> float | None:
        """Deceleration (rad/s²) of a quick-stop / fault-reaction code; None for a current-limit stop."""
        base = option - 4 if option >= QuickStopOption.SLOW_DOWN_RAMP_STAY else option
        if base == QuickStopOption.SLOW_DOWN_RAMP:
            return self._decel_rad_s2(self.s.profile_decel)
        if base == QuickStopOption.QUICK_STOP_RAMP:
            return self._decel_rad_s2(self.s.quickstop_decel)
        return None

    def _decel_rad_s2(self, slot: int) -> float:
        return self.cells[slot] / self.motion.counts_per_rad

    # --- faults ----------------------------------------------------------------------------------------------
    def fault(self, code: int, register_bits: int, manufacturer: bytes = b"", emcy: bool = True) -> None:
        """A device fault: the error (EMCY unless ``emcy`` is False), then the fault reaction (605Eh)."""
        if emcy:
            self.errors.raise_error(code, register_bits, manufacturer)
        else:
            self.errors.note(code, register_bits)
        if self.state in _FAULT_STATES:
            return
        cells = self.cells
        cells[self.errors.s_error_code] = code
        reaction = cells[self.s.fault_option]
        motion = self.motion
        was_powered = motion.regime is not Regime.OFF
        self.state = State.FAULT_REACTION_ACTIVE
        if not was_powered or reaction == FaultReactionOption.DISABLE_DRIVE:
            self.enter(State.FAULT)
            return
        motion.start_stop(self._stop_decel(reaction), State.FAULT)
        self.refresh_statusword()

    def fault_reset(self) -> None:
        self.errors.active.clear()
        self.cells[self.errors.s_error_code] = 0
        self.errors.update_register()
        self.enter(State.SWITCH_ON_DISABLED)  # 15
        self.errors.send(0, b"")

    def clear_error(self, code: int) -> None:
        """A non-latched error condition went away (kept while in fault)."""
        if self.state in _FAULT_STATES:
            return
        if self.errors.clear(code):
            self.refresh_statusword()

    def abort_connection(self, error_code: int) -> None:
        """Apply 6007h after a loss of communication."""
        if self.state not in SWITCHED_ON_STATES:
            return
        option = self.cells[self.s.abort_option]
        if option == AbortConnectionOption.FAULT:
            self.fault(error_code, ERR_REG_COMMUNICATION, emcy=False)
        elif option == AbortConnectionOption.DISABLE_VOLTAGE:
            self.apply(Command.DISABLE_VOLTAGE)
        elif option == AbortConnectionOption.QUICK_STOP:
            self.apply(Command.QUICK_STOP)

    # --- modes -----------------------------------------------------------------------------------------------
    def set_mode(self, mode: int) -> None:
        motion = self.motion
        if motion.mode == mode:
            return
        motion.set_mode(mode)
        self.cells[self.s.mode_display] = mode
        self.refresh_statusword()

    def rpdo_mode(self, mode: int) -> bool:
        """A mode written by an RPDO (no abort possible): applied if supported, else the old one kept (False)."""
        if mode == 0 or mode in self.supported_modes:
            self.set_mode(mode)
            return True
        self.cells[self.s.mode] = self.motion.mode
        return False

    def check_mode(self, sub: int, value: int) -> None:
        if value != 0 and value not in self.supported_modes:
            raise SdoAbort(ABORT_VALUE_RANGE, OD_MODES_OF_OPERATION, 0,
                           f"mode {value} not supported; expected 0 or one of {sorted(self.supported_modes)}")

    def check_quick_stop_option(self, sub: int, value: int) -> None:
        if value in (QuickStopOption.VOLTAGE_LIMIT, QuickStopOption.VOLTAGE_LIMIT_STAY):
            raise SdoAbort(ABORT_VALUE_RANGE, OD_QUICK_STOP_OPTION, 0,
                           "voltage-limit quick stop is not supported; use 0-3, 5-7")
