"""CiA 301 communication constants: COB-ID bases, NMT commands and states (one owner for dragd and the sim)."""

from __future__ import annotations

from enum import IntEnum

NMT_COB_ID = 0x000
SYNC_COB_ID = 0x080
EMCY_BASE = 0x080  # + node id
TPDO1_BASE, RPDO1_BASE = 0x180, 0x200  # + node id (TPDOn/RPDOn: + 0x100·(n − 1))
SDO_TX_BASE, SDO_RX_BASE = 0x580, 0x600  # + node id (server → client, client → server)
HEARTBEAT_BASE = 0x700  # + node id


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
