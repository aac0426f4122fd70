"""CiA 402 (drives and motion control) constants, controlword commands and statusword decoding.

Pure functions and constants, no I/O; shared by the daemon's master and the simulated drives.
Bit numbers, masks and option codes follow CiA 402-2 (device control, 6040h/6041h/605xh/6060h).
"""

from __future__ import annotations

from enum import IntEnum

DEVICE_TYPE_402 = 0x0192  # 1000h bits 0-15: the device profile number (CiA 402)
DEVICE_TYPE_SERVO = 0x02 << 16  # 1000h bits 16-23, CiA 402's additional information: a servo drive

# --- object indices used by the device control function ---------------------------------------------
OD_ABORT_CONNECTION_OPTION = 0x6007
OD_ERROR_CODE = 0x603F
OD_CONTROLWORD = 0x6040
OD_STATUSWORD = 0x6041
OD_QUICK_STOP_OPTION = 0x605A
OD_SHUTDOWN_OPTION = 0x605B
OD_DISABLE_OPERATION_OPTION = 0x605C
OD_FAULT_REACTION_OPTION = 0x605E
OD_MODES_OF_OPERATION = 0x6060
OD_MODES_OF_OPERATION_DISPLAY = 0x6061
OD_POSITION_ACTUAL = 0x6064
OD_VELOCITY_ACTUAL = 0x606C
OD_TARGET_TORQUE = 0x6071
OD_MAX_TORQUE = 0x6072
OD_MAX_CURRENT = 0x6073
OD_TORQUE_DEMAND = 0x6074
OD_MOTOR_RATED_CURRENT = 0x6075
OD_MOTOR_RATED_TORQUE = 0x6076
OD_TORQUE_ACTUAL = 0x6077
OD_CURRENT_ACTUAL = 0x6078
OD_TARGET_POSITION = 0x607A
OD_PROFILE_DECELERATION = 0x6084
OD_QUICK_STOP_DECELERATION = 0x6085
OD_TORQUE_SLOPE = 0x6087
OD_VELOCITY_OFFSET = 0x60B1
OD_TORQUE_OFFSET = 0x60B2
OD_FOLLOWING_ERROR_ACTUAL = 0x60F4
OD_DIGITAL_INPUTS = 0x60FD  # bits 0-3: limit switches, home, interlock; 4-15 reserved; 16-31 the manufacturer's
OD_TARGET_VELOCITY = 0x60FF
OD_SUPPORTED_DRIVE_MODES = 0x6502

# --- controlword (6040h) bits ------------------------------------------------------------------------
CW_SWITCH_ON = 1 << 0
CW_ENABLE_VOLTAGE = 1 << 1
CW_QUICK_STOP = 1 << 2  # active low: 0 requests a quick stop
CW_ENABLE_OPERATION = 1 << 3
CW_OMS_4 = 1 << 4  # operation-mode specific
CW_OMS_5 = 1 << 5
CW_OMS_6 = 1 << 6
CW_FAULT_RESET = 1 << 7  # acts on the rising edge only
CW_HALT = 1 << 8
CW_OMS_9 = 1 << 9

# standard commands (the state-relevant bits; bits 4..6, 8, 9 left 0)
CMD_DISABLE_VOLTAGE = 0x0000
CMD_QUICK_STOP = 0x0002
CMD_SHUTDOWN = 0x0006
CMD_SWITCH_ON = 0x0007
CMD_DISABLE_OPERATION = 0x0007
CMD_ENABLE_OPERATION = 0x000F
CMD_FAULT_RESET = 0x0080  # must follow a word with bit 7 clear to form the rising edge

# --- statusword (6041h) bits ---------------------------------------------------------------------------
SW_READY_TO_SWITCH_ON = 1 << 0
SW_SWITCHED_ON = 1 << 1
SW_OPERATION_ENABLED = 1 << 2
SW_FAULT = 1 << 3
SW_VOLTAGE_ENABLED = 1 << 4
SW_QUICK_STOP = 1 << 5  # active low: 0 while a quick stop is active
SW_SWITCH_ON_DISABLED = 1 << 6
SW_WARNING = 1 << 7
SW_MANUFACTURER_8 = 1 << 8
SW_REMOTE = 1 << 9
SW_TARGET_REACHED = 1 << 10
SW_INTERNAL_LIMIT_ACTIVE = 1 << 11
SW_OMS_12 = 1 << 12  # CSP/CSV/CST: 1 = drive follows the command value
SW_OMS_13 = 1 << 13  # CSP: following error
SW_MANUFACTURER_14 = 1 << 14
SW_MANUFACTURER_15 = 1 << 15

# aliases of the mode-specific bits in the cyclic synchronous modes
SW_CYCLIC_FOLLOWING = SW_OMS_12
SW_FOLLOWING_ERROR = SW_OMS_13


class State(IntEnum):
    """The CiA 402 power drive system states."""

    NOT_READY_TO_SWITCH_ON = 0
    SWITCH_ON_DISABLED = 1
    READY_TO_SWITCH_ON = 2
    SWITCHED_ON = 3
    OPERATION_ENABLED = 4
    QUICK_STOP_ACTIVE = 5
    FAULT_REACTION_ACTIVE = 6
    FAULT = 7


# (mask, value) of the statusword per state, as tabulated in CiA 402-2
STATE_PATTERNS: tuple[tuple[State, int, int], ...] = (
    (State.NOT_READY_TO_SWITCH_ON, 0x004F, 0x0000),
    (State.SWITCH_ON_DISABLED, 0x004F, 0x0040),
    (State.READY_TO_SWITCH_ON, 0x006F, 0x0021),
    (State.SWITCHED_ON, 0x006F, 0x0023),
    (State.OPERATION_ENABLED, 0x006F, 0x0027),
    (State.QUICK_STOP_ACTIVE, 0x006F, 0x0007),
    (State.FAULT_REACTION_ACTIVE, 0x004F, 0x000F),
    (State.FAULT, 0x004F, 0x0008),
)

# the state bits (0..3, 5, 6) a drive reports in each state
STATE_STATUSWORD_BITS: dict[State, int] = {
    State.NOT_READY_TO_SWITCH_ON: 0x0000,
    State.SWITCH_ON_DISABLED: 0x0040,
    State.READY_TO_SWITCH_ON: 0x0021,
    State.SWITCHED_ON: 0x0023,
    State.OPERATION_ENABLED: 0x0027,
    State.QUICK_STOP_ACTIVE: 0x0007,
    State.FAULT_REACTION_ACTIVE: 0x000F,
    State.FAULT: 0x0008,
}

# states in which high voltage is applied (statusword bit 4 "voltage enabled")
VOLTAGE_ENABLED_STATES = frozenset(
    {
        State.READY_TO_SWITCH_ON,
        State.SWITCHED_ON,
        State.OPERATION_ENABLED,
        State.QUICK_STOP_ACTIVE,
        State.FAULT_REACTION_ACTIVE,
    }
)


def decode_statusword(statusword: int) -> State:
    """Return the 402 state encoded in a statusword; ValueError if the bits match no state."""
    for state, mask, value in STATE_PATTERNS:
        if statusword & mask == value:
            return state
    raise ValueError(f"statusword 0x{statusword:04X} encodes no CiA 402 state (bits 0-3, 5, 6 invalid)")


class Command(IntEnum):
    """Device control commands decoded from the controlword (fault reset is edge-triggered, separate)."""

    DISABLE_VOLTAGE = 0
    QUICK_STOP = 1
    SHUTDOWN = 2
    SWITCH_ON = 3  # also "disable operation" (same bit pattern)
    ENABLE_OPERATION = 4


def decode_command(controlword: int) -> Command | None:
    """Return the state command in a controlword, or None while bit 7 (fault reset) is set."""
    if controlword & CW_FAULT_RESET:
        return None
    if not controlword & CW_ENABLE_VOLTAGE:
        return Command.DISABLE_VOLTAGE
    if not controlword & CW_QUICK_STOP:
        return Command.QUICK_STOP
    if not controlword & CW_SWITCH_ON:
        return Command.SHUTDOWN
    if not controlword & CW_ENABLE_OPERATION:
        return Command.SWITCH_ON
    return Command.ENABLE_OPERATION


def is_fault_reset_edge(previous_controlword: int, controlword: int) -> bool:
    """True on the 0 -> 1 transition of controlword bit 7."""
    return bool(controlword & CW_FAULT_RESET) and not previous_controlword & CW_FAULT_RESET


# the controlword that holds each commandable state
_HOLD_WORD: dict[State, int] = {
    State.SWITCH_ON_DISABLED: CMD_DISABLE_VOLTAGE,
    State.READY_TO_SWITCH_ON: CMD_SHUTDOWN,
    State.SWITCHED_ON: CMD_SWITCH_ON,
    State.OPERATION_ENABLED: CMD_ENABLE_OPERATION,
    State.QUICK_STOP_ACTIVE: CMD_QUICK_STOP,
}
_RANK: dict[State, int] = {
    State.SWITCH_ON_DISABLED: 0,
    State.READY_TO_SWITCH_ON: 1,
    State.SWITCHED_ON: 2,
    State.OPERATION_ENABLED: 3,
}
_UP_WORD: dict[State, int] = {
    State.SWITCH_ON_DISABLED: CMD_SHUTDOWN,  # transition 2
    State.READY_TO_SWITCH_ON: CMD_SWITCH_ON,  # transition 3
    State.SWITCHED_ON: CMD_ENABLE_OPERATION,  # transition 4
}
COMMANDABLE_TARGETS = frozenset(_HOLD_WORD)


def next_controlword(state: State, target: State, previous_controlword: int = 0) -> int:
    """The controlword that moves a drive from `state` one transition toward `target`.

    Targets are the commandable states (switch on disabled, ready to switch on, switched on, operation
    enabled, quick stop active). In Fault the result is the fault reset word, preceded by a word with bit 7
    clear when `previous_controlword` already had bit 7 set (the reset acts on the rising edge only).
    Quick stop active is reached by the quick stop command (from operation enabled; from ready to switch on
    or switched on the same command leads to switch on disabled). Leaving quick stop active goes through
    switch on disabled (transition 12).
    """
    if target not in COMMANDABLE_TARGETS:
        raise ValueError(f"target state {target.name} cannot be commanded; expected one of "
                         f"{sorted(s.name for s in COMMANDABLE_TARGETS)}")
    if state is State.FAULT:
        return CMD_DISABLE_VOLTAGE if previous_controlword & CW_FAULT_RESET else CMD_FAULT_RESET
    if state in (State.NOT_READY_TO_SWITCH_ON, State.FAULT_REACTION_ACTIVE):
        return CMD_DISABLE_VOLTAGE  # nothing to command; bit 7 clear prepares a later reset edge
    if target is State.QUICK_STOP_ACTIVE:
        return CMD_QUICK_STOP
    if state is State.QUICK_STOP_ACTIVE:
        return CMD_DISABLE_VOLTAGE  # transition 12
    if state is target:
        return _HOLD_WORD[target]
    if _RANK[target] > _RANK[state]:
        return _UP_WORD[state]
    return _HOLD_WORD[target]  # transitions 5, 6, 7, 8, 9, 10 go straight down


class Mode(IntEnum):
    """Modes of operation (6060h / 6061h)."""

    NO_MODE = 0
    PROFILE_POSITION = 1
    VELOCITY = 2
    PROFILE_VELOCITY = 3
    PROFILE_TORQUE = 4
    HOMING = 6
    INTERPOLATED_POSITION = 7
    CYCLIC_SYNC_POSITION = 8
    CYCLIC_SYNC_VELOCITY = 9
    CYCLIC_SYNC_TORQUE = 10


MODE_PP = Mode.PROFILE_POSITION
MODE_PV = Mode.PROFILE_VELOCITY
MODE_PT = Mode.PROFILE_TORQUE
MODE_HM = Mode.HOMING
MODE_CSP = Mode.CYCLIC_SYNC_POSITION
MODE_CSV = Mode.CYCLIC_SYNC_VELOCITY
MODE_CST = Mode.CYCLIC_SYNC_TORQUE


def supported_modes_bits(modes: tuple[Mode, ...] | list[Mode] | frozenset[Mode]) -> int:
    """6502h value for a set of modes: bit (mode - 1) per supported mode."""
    bits = 0
    for mode in modes:
        if mode <= 0:
            raise ValueError(f"mode {mode!r} has no bit in 6502h; expected a mode >= 1")
        bits |= 1 << (int(mode) - 1)
    return bits


def modes_from_supported_bits(bits: int) -> frozenset[int]:
    """The mode numbers whose bits are set in a 6502h value (bits 0..15, standard modes)."""
    return frozenset(bit + 1 for bit in range(16) if bits >> bit & 1)


# --- option codes --------------------------------------------------------------------------------------
class QuickStopOption(IntEnum):
    """605Ah quick stop option code."""

    DISABLE_DRIVE = 0
    SLOW_DOWN_RAMP = 1
    QUICK_STOP_RAMP = 2
    CURRENT_LIMIT = 3
    VOLTAGE_LIMIT = 4
    SLOW_DOWN_RAMP_STAY = 5
    QUICK_STOP_RAMP_STAY = 6
    CURRENT_LIMIT_STAY = 7
    VOLTAGE_LIMIT_STAY = 8


class FaultReactionOption(IntEnum):
    """605Eh fault reaction option code."""

    DISABLE_DRIVE = 0
    SLOW_DOWN_RAMP = 1
    QUICK_STOP_RAMP = 2
    CURRENT_LIMIT = 3
    VOLTAGE_LIMIT = 4


class AbortConnectionOption(IntEnum):
    """6007h abort connection option code."""

    NO_ACTION = 0
    FAULT = 1
    DISABLE_VOLTAGE = 2
    QUICK_STOP = 3


class ShutdownOption(IntEnum):
    """605Bh shutdown option code (transition 8) and 605Ch disable operation option code (transition 5)."""

    DISABLE_DRIVE = 0
    SLOW_DOWN_THEN_DISABLE = 1


# --- emergency error codes used by the joint drives (CiA 301 / CiA 402) -------------------------------------
EMCY_NO_ERROR = 0x0000
EMCY_GENERIC = 0x1000
EMCY_CURRENT = 0x2300
EMCY_OVER_CURRENT = 0x2310  # continuous over-current (current, device output side)
EMCY_TEMPERATURE_DEVICE = 0x4210  # excess temperature, device
EMCY_COMMUNICATION = 0x8100
EMCY_HEARTBEAT = 0x8130
EMCY_PDO_LENGTH = 0x8210
EMCY_PDO_LENGTH_EXCEEDED = 0x8220
EMCY_RPDO_TIMEOUT = 0x8250
EMCY_FOLLOWING_ERROR = 0x8611
EMCY_NAMES: dict[int, str] = {
    EMCY_NO_ERROR: "error reset or no error",
    EMCY_GENERIC: "generic error",
    EMCY_CURRENT: "current",
    EMCY_OVER_CURRENT: "continuous over-current",
    EMCY_TEMPERATURE_DEVICE: "excess temperature, device",
    EMCY_COMMUNICATION: "communication",
    EMCY_HEARTBEAT: "life guard or heartbeat error",
    EMCY_PDO_LENGTH: "PDO not processed due to length error",
    EMCY_PDO_LENGTH_EXCEEDED: "PDO length exceeded",
    EMCY_RPDO_TIMEOUT: "RPDO timeout",
    EMCY_FOLLOWING_ERROR: "following error",
}


def emcy_name(code: int) -> str:
    """What an EMCY error code means: its name above, else its CiA 301 class (python-canopen's table)."""
    name = EMCY_NAMES.get(code)
    if name is not None:
        return name
    from canopen.emcy import EmcyError  # (only where an unnamed code is reported: not on the cycle's import path)

    for base, mask, text in EmcyError.DESCRIPTIONS:
        if code & mask == base:
            return f"{text.lower()} (class)"
    return "no CiA 301 class"

# error register (1001h) bits
ERR_REG_GENERIC = 1 << 0
ERR_REG_CURRENT = 1 << 1
ERR_REG_VOLTAGE = 1 << 2
ERR_REG_TEMPERATURE = 1 << 3
ERR_REG_COMMUNICATION = 1 << 4
ERR_REG_DEVICE_PROFILE = 1 << 5
ERR_REG_MANUFACTURER = 1 << 7
