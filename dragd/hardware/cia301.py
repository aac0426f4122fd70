"""CiA 301 communication constants: COB-ID bases, NMT commands and states (one owner for dragd and the sim)."""

from __future__ import annotations

from enum import IntEnum

NMT_COB_ID = 0x000
SYNC_COB_ID = 0x080
EMCY_BASE = 0x080  # + node id
TIME_COB_ID = 0x100  # TIME (time stamp object), the default COB-ID of 1012h
TPDO1_BASE, RPDO1_BASE = 0x180, 0x200  # + node id (TPDOn/RPDOn: + PDO_COB_STEP·(n − 1))
PDO_COB_STEP = 0x100  # the pre-defined connection set's PDOs 1-4: one COB-ID range apart
SDO_TX_BASE, SDO_RX_BASE = 0x580, 0x600  # + node id (server → client, client → server)
HEARTBEAT_BASE = 0x700  # + node id
NODE_ID_MIN, NODE_ID_MAX = 1, 127
COB_ID_MASK = 0x7FF  # an 11-bit CAN identifier (the COB-ID bits of a PDO/SYNC/EMCY COB-ID object)

# --- communication profile objects ------------------------------------------------------------------------
OD_DEVICE_TYPE = 0x1000
OD_ERROR_REGISTER = 0x1001
OD_ERROR_HISTORY = 0x1003  # pre-defined error field
OD_DEVICE_NAME = 0x1008  # manufacturer device name (VISIBLE_STRING)
OD_SYNC_COB_ID = 0x1005
OD_EMCY_COB_ID = 0x1014
OD_CONSUMER_HEARTBEAT = 0x1016
OD_PRODUCER_HEARTBEAT = 0x1017
OD_IDENTITY = 0x1018  # sub 1 vendor-ID, 2 product code, 3 revision, 4 serial number
OD_ERROR_BEHAVIOUR = 0x1029
OD_SDO_SERVER = 0x1200  # sub 1 COB-ID client -> server, sub 2 server -> client
OD_RPDO_COMM, OD_RPDO_MAP = 0x1400, 0x1600  # + n - 1 for RPDO n
OD_TPDO_COMM, OD_TPDO_MAP = 0x1800, 0x1A00  # + n - 1 for TPDO n
COB_ID_INVALID = 1 << 31  # PDO / EMCY COB-ID bit 31: not valid
COB_ID_NO_RTR = 1 << 30  # TPDO COB-ID bit 30: no remote frames
COB_ID_EXTENDED = 1 << 29  # bit 29: 29-bit identifier
SYNC_COB_ID_GENERATE = 1 << 30  # 1005h bit 30: this node produces the SYNC
# the object dictionary's areas (index ranges)
OD_COMMUNICATION_AREA = range(0x1000, 0x2000)
OD_MANUFACTURER_AREA = range(0x2000, 0x6000)
OD_DEVICE_PROFILE_AREA = range(0x6000, 0xA000)
PDO_TRANSMISSION_SYNC = 1  # PDO communication sub 2 (transmission type): sent/applied at every SYNC
PDO_TRANSMISSION_EVENT = 255  # ... event-driven (device-profile specific)
# data type indices usable as dummy mapping entries (a gap in a PDO) -> their width in bits
DT_INTEGER8, DT_INTEGER16, DT_INTEGER32 = 0x0002, 0x0003, 0x0004
DT_UNSIGNED8, DT_UNSIGNED16, DT_UNSIGNED32 = 0x0005, 0x0006, 0x0007
DUMMY_TYPES = {DT_INTEGER8: 8, DT_INTEGER16: 16, DT_INTEGER32: 32, DT_UNSIGNED8: 8, DT_UNSIGNED16: 16,
               DT_UNSIGNED32: 32}


class NmtCommand(IntEnum):
    """NMT node control command specifiers (first byte of COB-ID 0x000)."""

    START = 0x01
    STOP = 0x02
    PRE_OPERATIONAL = 0x80
    RESET_NODE = 0x81
    RESET_COMMUNICATION = 0x82


NMT_COMMANDS = {"start": NmtCommand.START, "stop": NmtCommand.STOP, "preop": NmtCommand.PRE_OPERATIONAL,
                "reset": NmtCommand.RESET_NODE, "reset-comm": NmtCommand.RESET_COMMUNICATION}  # `dragd nmt` names
SDO_TYPES: dict[str, str | None] = {  # `dragd sdo --type` -> struct format (None: bytes as text or hex)
    "u8": "<B", "u16": "<H", "u32": "<I", "u64": "<Q", "i8": "<b", "i16": "<h", "i32": "<i", "i64": "<q",
    "f32": "<f", "f64": "<d", "str": None, "hex": None,
}


class NmtState(IntEnum):
    """NMT states with their heartbeat codes."""

    INITIALISING = 0x00  # the boot-up message
    STOPPED = 0x04
    OPERATIONAL = 0x05
    PRE_OPERATIONAL = 0x7F
