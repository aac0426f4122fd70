"""The operator's CANopen tools on a bus no daemon drives: bus scan, SDO read/write, NMT (``dragd can|sdo|nmt``).

Each opens the bus itself (python-can + python canopen's SDO client) and first listens for a master: SYNC
(080h), the master's heartbeat (700h + its node id) or cyclic RPDO traffic (200h-57Fh) mean a daemon drives the
bus, and the tools refuse unless forced (`busy_reason`).
"""

from __future__ import annotations

import configparser
import struct
import time
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import can
import canopen

from dragd.hardware.cia301 import (
    HEARTBEAT_BASE,
    NMT_COB_ID,
    NMT_COMMANDS,
    OD_DEVICE_NAME,
    OD_IDENTITY,
    OD_PRODUCER_HEARTBEAT,
    RPDO1_BASE,
    SDO_RX_BASE,
    SDO_TX_BASE,
    SDO_TYPES,
    SYNC_COB_ID,
    NmtState,
)

__all__ = ["BusBusy", "NodeInfo", "busy_reason", "scan", "parse_address", "SDO_TYPES", "sdo_read", "sdo_write", "nmt",
           "NMT_COMMANDS", "eds_identity"]

_EDS_TYPES = {0x1: "u8", 0x2: "i8", 0x3: "i16", 0x4: "i32", 0x5: "u8", 0x6: "u16", 0x7: "u32", 0x8: "f32",
              0x9: "str", 0xA: "hex", 0xF: "hex", 0x11: "f64", 0x15: "i64", 0x1B: "u64"}
_STATES = {int(s): s.name.lower().replace("_", "-") for s in NmtState}
_STATES[int(NmtState.INITIALISING)] = "boot-up"


class BusBusy(RuntimeError):
    """A CANopen master (a running daemon) drives the bus."""


def busy_reason(bus: can.BusABC, master_node_id: int = 127, listen_s: float = 0.35) -> str | None:
    """Listen ``listen_s``: why a master seems to drive the bus (SYNC, its heartbeat, RPDOs), or None."""
    seen: dict[str, int] = {}
    end = time.monotonic() + listen_s
    while (left := end - time.monotonic()) > 0:
        m = bus.recv(left)
        if m is None or m.is_error_frame:
            continue
        cid = m.arbitration_id
        if cid == SYNC_COB_ID:
            seen["SYNC (080h)"] = seen.get("SYNC (080h)", 0) + 1
        elif cid == HEARTBEAT_BASE + master_node_id:
            key = f"the master's heartbeat ({HEARTBEAT_BASE + master_node_id:03X}h)"
            seen[key] = seen.get(key, 0) + 1
        elif RPDO1_BASE <= cid < SDO_TX_BASE and (cid & 0x7F) != 0:  # RPDO 1-4 of nodes 1-127
            seen["RPDOs (200h-57Fh)"] = seen.get("RPDOs (200h-57Fh)", 0) + 1
    if not seen:
        return None
    return ", ".join(f"{k} x{n}" for k, n in seen.items()) + f" within {listen_s:g} s"


@dataclass
class NodeInfo:
    node_id: int
    device_type: int
    profile: int  # low 16 bits of 1000h (402: CiA 402 drive)
    state: str | None = None  # from its heartbeat (None: no heartbeat heard)
    heartbeat_ms: int | None = None  # 1017h
    vendor_id: int | None = None  # 1018h:1..4
    product_code: int | None = None
    revision: int | None = None
    serial: int | None = None
    name: str | None = None  # 1008h
    eds: str | None = None  # the EDS file whose [DeviceInfo] matches the identity
    errors: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def eds_identity(path: Path) -> dict[str, int]:
    """[DeviceInfo] VendorNumber, ProductNumber, RevisionNumber of an EDS file (those that are numbers)."""
    cp = configparser.ConfigParser(strict=False, interpolation=None)
    try:
        cp.read(path, encoding="utf-8")
    except UnicodeDecodeError:
        cp = configparser.ConfigParser(strict=False, interpolation=None)
        cp.read(path, encoding="latin-1")
    info = cp["DeviceInfo"] if cp.has_section("DeviceInfo") else {}
    out = {}
    for key, name in (("VendorNumber", "vendor_id"), ("ProductNumber", "product_code"),
                      ("RevisionNumber", "revision")):
        if key in info:
            try:
                out[name] = int(str(info[key]).strip(), 0)
            except ValueError:
                continue
    return out


def _remote(network: canopen.Network, node_id: int, timeout_s: float) -> Any:
    """A RemoteNode without object dictionary (raw SDO upload/download), one SDO attempt of ``timeout_s``."""
    node: Any = network.nodes.get(node_id)
    if node is None:
        node = canopen.RemoteNode(node_id, canopen.ObjectDictionary())  # type: ignore[no-untyped-call]
        network.add_node(node)
    node.sdo.RESPONSE_TIMEOUT = timeout_s
    node.sdo.MAX_RETRIES = 1  # one request, no retry (python canopen counts the first try)
    return node


def scan(network: canopen.Network, bus: can.BusABC, *, timeout_s: float = 0.5, nodes: Iterable[int] = range(1, 128),
         eds_files: Iterable[Path] = ()) -> list[NodeInfo]:
    """Nodes answering an SDO upload of 1000h (device type), with heartbeat state, 1017h, identity, name, EDS."""
    wanted = list(nodes)
    heard: dict[int, int] = {}
    replies: dict[int, bytes] = {}

    def listen(msg: can.Message) -> None:
        cid = msg.arbitration_id
        if HEARTBEAT_BASE < cid <= HEARTBEAT_BASE + 127 and len(msg.data) >= 1:
            heard[cid - HEARTBEAT_BASE] = msg.data[0] & 0x7F
        elif SDO_TX_BASE < cid <= SDO_TX_BASE + 127 and len(msg.data) == 8 and bytes(msg.data[1:4]) == b"\x00\x10\x00":
            replies[cid - SDO_TX_BASE] = bytes(msg.data)

    ids = [SDO_TX_BASE + n for n in wanted] + [HEARTBEAT_BASE + n for n in wanted]
    for cid in ids:
        network.subscribe(cid, lambda cid, data, ts: listen(can.Message(arbitration_id=cid, data=data)))
    try:
        for n in wanted:
            network.send_message(SDO_RX_BASE + n, bytes([0x40, 0x00, 0x10, 0x00, 0, 0, 0, 0]))
            time.sleep(0.0002)  # ~127 frames in 25 ms: no burst that a receive buffer would drop
        time.sleep(timeout_s)
    finally:
        for cid in ids:
            network.unsubscribe(cid)
    eds = [(p, eds_identity(p)) for p in eds_files]
    found: list[NodeInfo] = []
    for n in sorted(replies):
        data = replies[n]
        if data[0] & 0xE0 == 0x80:  # abort: a node, but no device type
            info = NodeInfo(n, 0, 0, errors=[f"1000h aborted: {struct.unpack_from('<I', data, 4)[0]:08X}h"])
        else:
            dtype = struct.unpack_from("<I", data, 4)[0]
            info = NodeInfo(n, dtype, dtype & 0xFFFF)
        node = _remote(network, n, timeout_s)
        for attr, (index, sub) in (("heartbeat_ms", (OD_PRODUCER_HEARTBEAT, 0)), ("vendor_id", (OD_IDENTITY, 1)),
                                   ("product_code", (OD_IDENTITY, 2)), ("revision", (OD_IDENTITY, 3)),
                                   ("serial", (OD_IDENTITY, 4))):
            try:
                raw = node.sdo.upload(index, sub)
                setattr(info, attr, int.from_bytes(raw[:4], "little"))
            except (canopen.SdoAbortedError, canopen.SdoCommunicationError) as exc:
                info.errors.append(f"{index:04X}h:{sub}: {exc}")
        try:
            info.name = node.sdo.upload(OD_DEVICE_NAME, 0).rstrip(b"\x00").decode("utf-8", "replace")
        except (canopen.SdoAbortedError, canopen.SdoCommunicationError) as exc:
            info.errors.append(f"1008h: {exc}")
        if n in heard:
            info.state = _STATES.get(heard[n], f"0x{heard[n]:02X}")
        # vendor id and product code identify the drive (1018h:1, :2); a revision other than the EDS's is noted
        for path, ident in eds:
            key = {k: v for k, v in ident.items() if k != "revision"}
            if key and all(getattr(info, k) == v for k, v in key.items()):
                info.eds = path.name
                if "revision" in ident and info.revision is not None and ident["revision"] != info.revision:
                    info.eds += f" (EDS revision {ident['revision']:08X}h, the drive's {info.revision:08X}h)"
                break
        found.append(info)
    return found


def parse_address(text: str) -> tuple[int, int]:
    """``INDEX[:SUB]`` (hex with or without 0x, or decimal with a leading 'd'? no: hex like CANopen writes it)."""
    index_s, _, sub_s = text.partition(":")
    try:
        index = int(index_s, 16)
        sub = int(sub_s, 0) if sub_s else 0
    except ValueError:
        raise ValueError(f"address {text!r}: expected INDEX[:SUB] with INDEX in hex (e.g. 6041, 0x1018:2)") from None
    if not 0 <= index <= 0xFFFF or not 0 <= sub <= 0xFF:
        raise ValueError(f"address {text!r}: index must be 0000h..FFFFh and sub-index 0..255")
    return index, sub


def eds_type(index: int, sub: int, eds: Path | None) -> str | None:
    """The --type of an object from an EDS, or None when it does not describe it."""
    if eds is None:
        return None
    od = canopen.import_od(str(eds))
    try:
        obj = od[index]
        var = obj if isinstance(obj, canopen.objectdictionary.ODVariable) else obj[sub]
    except KeyError:
        return None
    return None if var.data_type is None else _EDS_TYPES.get(int(var.data_type))


def decode(raw: bytes, kind: str | None) -> Any:
    if kind is None:
        return int.from_bytes(raw, "little") if len(raw) in (1, 2, 4, 8) else raw.hex()
    fmt = SDO_TYPES[kind]
    if kind == "str":
        return raw.rstrip(b"\x00").decode("utf-8", "replace")
    if kind == "hex" or fmt is None:
        return raw.hex()
    size = struct.calcsize(fmt)
    if len(raw) < size:
        raise ValueError(f"{len(raw)} byte(s) received; --type {kind} needs {size}")
    return struct.unpack_from(fmt, raw)[0]


def encode(value: str, kind: str) -> bytes:
    fmt = SDO_TYPES.get(kind, "?")
    if fmt == "?":
        raise ValueError(f"--type {kind!r}: expected one of {', '.join(SDO_TYPES)}")
    if kind == "str":
        return value.encode("utf-8")
    if kind == "hex":
        try:
            return bytes.fromhex(value)
        except ValueError:
            raise ValueError(f"value {value!r}: expected hex bytes like 01ff for --type hex") from None
    assert fmt is not None
    try:
        number: int | float = float(value) if kind.startswith("f") else int(value, 0)
        return struct.pack(fmt, number)
    except (ValueError, struct.error) as exc:
        raise ValueError(f"value {value!r} does not fit --type {kind}: {exc}") from None


def sdo_read(network: canopen.Network, node_id: int, index: int, sub: int, kind: str | None,
             timeout_s: float = 0.5) -> dict[str, Any]:
    raw = _remote(network, node_id, timeout_s).sdo.upload(index, sub)
    return {"node": node_id, "index": f"{index:04X}", "sub": sub, "type": kind, "raw": raw.hex(),
            "value": decode(raw, kind)}


def sdo_write(network: canopen.Network, node_id: int, index: int, sub: int, value: str, kind: str,
              timeout_s: float = 0.5) -> dict[str, Any]:
    data = encode(value, kind)
    _remote(network, node_id, timeout_s).sdo.download(index, sub, data)
    return {"node": node_id, "index": f"{index:04X}", "sub": sub, "type": kind, "raw": data.hex(), "written": True}


def nmt(bus: can.BusABC, node_id: int, command: str) -> dict[str, Any]:
    """Send NMT ``command`` to ``node_id`` (0: all nodes)."""
    code = NMT_COMMANDS[command]
    bus.send(can.Message(arbitration_id=NMT_COB_ID, data=[int(code), node_id], is_extended_id=False))
    return {"node": node_id, "command": command, "sent": f"000#{int(code):02X}{node_id:02X}"}
