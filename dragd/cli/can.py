"""``dragd can scan``, ``dragd sdo read|write``, ``dragd nmt``: the operator's CANopen tools (docs/TOOLS.md).

They open the bus themselves and refuse while a master (a running daemon) drives it, unless ``--force``.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from dragd.cli.common import CliError, add_config, emit, table


@contextlib.contextmanager
def _network(args: argparse.Namespace) -> Iterator[tuple[Any, Any, Any]]:
    """(bus, canopen network, config) of ``--bus`` or the config's first bus, after the busy check."""
    import logging

    import can
    import canopen

    from dragd.config import load_config

    logging.getLogger("canopen").addHandler(logging.NullHandler())  # its warnings: ours say it in one line
    from dragd.hardware.bus import open_bus, parse_bus
    from dragd.hardware.operator import busy_reason

    cfg = load_config(args.config)
    try:
        if args.bus:
            spec = parse_bus(args.bus, fd=True, data_bitrate=None)
        else:
            b = cfg.buses[0]
            spec = parse_bus(f"{b.interface}:{b.channel}", bitrate=b.bitrate, fd=b.fd, data_bitrate=b.data_bitrate)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    try:
        bus = open_bus(spec)
    except (can.CanError, OSError) as exc:
        raise CliError(f"bus {spec}: {exc}", status=1) from None
    try:
        reason = busy_reason(bus, cfg.master.node_id)
        if reason is not None and not args.force:
            raise CliError(f"bus {spec}: a CANopen master drives it ({reason}): is dragd running? stop it first "
                           "(dragd stop; systemctl stop dragd) or pass --force to act beside it", status=1)
        if reason is not None:
            print(f"dragd: warning: bus {spec}: a master drives it ({reason}); acting beside it (--force)",
                  file=sys.stderr)
        net = canopen.Network(bus)
        net.connect()
        try:
            yield bus, net, cfg
        finally:
            net.disconnect()
    finally:
        with contextlib.suppress(Exception):
            bus.shutdown()


def _sdo_errors(fn: Any) -> Any:
    import canopen

    try:
        return fn()
    except canopen.SdoAbortedError as exc:
        raise CliError(f"SDO aborted by the node: {exc}", status=1) from None
    except canopen.SdoCommunicationError as exc:
        raise CliError(f"no SDO answer: {exc} (node absent, or not in pre-operational/operational?)",
                       status=1) from None
    except ValueError as exc:
        raise CliError(str(exc)) from None


def _node(text: str, allow_all: bool = False) -> int:
    if allow_all and text == "all":
        return 0
    try:
        n = int(text, 0)
    except ValueError:
        n = -1
    if not 1 <= n <= 127:
        raise CliError(f"NODE: expected a node id 1..127{' or all' if allow_all else ''}, got {text!r}")
    return n


def _eds_files(cfg: Any, eds_dir: Path | None = None) -> list[Path]:
    """The EDS files a scan matches nodes against: the configuration's drives', ``--eds-dir``'s, dragd's own."""
    from dragd.resources import eds_path

    files = [cfg.eds_of(i) for i in range(len(cfg.joints))]
    if eds_dir is not None:
        if not eds_dir.is_dir():
            raise CliError(f"--eds-dir {eds_dir}: not a directory")
        files += sorted(p for p in eds_dir.iterdir() if p.suffix.lower() in (".eds", ".dcf"))
    files.append(Path(eds_path()))
    return list(dict.fromkeys(files))


def _node_eds(cfg: Any, node: int) -> Path:
    """The EDS of the configured drive at ``node`` (dragd's own where no joint has that node id)."""
    from dragd.resources import eds_path

    for i, j in enumerate(cfg.joints):
        if j.node_id == node:
            return Path(cfg.eds_of(i))
    return Path(eds_path())


def cmd_scan(args: argparse.Namespace) -> int:
    from dragd.hardware.operator import scan

    with _network(args) as (bus, net, cfg):
        nodes = scan(net, bus, timeout_s=args.timeout, eds_files=_eds_files(cfg, args.eds_dir))
    data = {"nodes": [n.as_dict() for n in nodes]}

    def text(d: dict[str, Any]) -> str:
        if not d["nodes"]:
            return "no node answered an SDO upload of 1000h"
        rows = [(n["node_id"], f"{n['device_type']:08X}h", n["profile"], n["state"] or "no heartbeat",
                 n["heartbeat_ms"] if n["heartbeat_ms"] is not None else "-",
                 f"{n['vendor_id']:08X}h" if n["vendor_id"] is not None else "-",
                 f"{n['product_code']:08X}h" if n["product_code"] is not None else "-",
                 f"{n['revision']:08X}h" if n["revision"] is not None else "-",
                 n["serial"] if n["serial"] is not None else "-", n["name"] or "-", n["eds"] or "-")
                for n in d["nodes"]]
        return table(["node", "device type", "profile", "state", "hb ms", "vendor", "product", "revision", "serial",
                      "name", "EDS"], rows)

    emit(args, data, text)
    return 0


def cmd_sdo(args: argparse.Namespace) -> int:
    from dragd.hardware.operator import eds_type, parse_address, sdo_read, sdo_write

    node = _node(args.node)
    try:
        index, sub = parse_address(args.address)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    if args.type is None:
        from dragd.config import load_config

        kind = eds_type(index, sub, _node_eds(load_config(args.config), node))
    else:
        kind = args.type
    value: str | None = args.value
    if args.action == "write":
        if value is None:
            raise CliError("sdo write: missing VALUE")
        if kind is None:
            raise CliError(f"sdo write {index:04X}h:{sub}: the EDS does not describe it; give --type")
        write_value, write_kind = value, kind  # (narrowed for the call below)
    elif value is not None:
        raise CliError("sdo read takes no VALUE")
    with _network(args) as (_bus, net, _cfg):
        if args.action == "read":
            data = _sdo_errors(lambda: sdo_read(net, node, index, sub, kind, args.timeout))
        else:
            data = _sdo_errors(lambda: sdo_write(net, node, index, sub, write_value, write_kind, args.timeout))
    emit(args, data, lambda d: (f"node {d['node']} {d['index']}h:{d['sub']} = {d['value']!r}  (raw {d['raw']})"
                                if "value" in d else f"node {d['node']} {d['index']}h:{d['sub']} <- {d['raw']}"))
    return 0


def cmd_nmt(args: argparse.Namespace) -> int:
    from dragd.hardware.operator import nmt

    node = _node(args.node, allow_all=True)
    with _network(args) as (bus, _net, _cfg):
        data = nmt(bus, node, args.command)
    emit(args, data, lambda d: f"NMT {d['command']} -> {'all nodes' if d['node'] == 0 else 'node ' + str(d['node'])}"
                               f" ({d['sent']})")
    return 0


def _common(p: argparse.ArgumentParser, timeout: float = 0.5) -> None:
    p.add_argument("--bus", default=None, help="INTERFACE:CHANNEL (default: the config's first bus), e.g. "
                   "socketcan:can0, udp_multicast:239.74.163.2")
    p.add_argument("--force", action="store_true", help="act even though a master (a running daemon) drives the bus")
    p.add_argument("--timeout", type=float, default=timeout,
                   help=f"SDO answer timeout in seconds (default {timeout:g})")
    add_config(p, params=False)
    p.add_argument("--json", action="store_true", help="print JSON")


def register(sub: Any) -> None:
    from dragd.hardware.cia301 import NMT_COMMANDS, SDO_TYPES

    c = sub.add_parser("can", help="CAN bus tools: scan for CANopen nodes")
    csub = c.add_subparsers(dest="can_command", metavar="ACTION")
    csub.required = True
    s = csub.add_parser("scan", help="nodes on the bus: boot state, device type, identity, matching EDS")
    _common(s)
    s.add_argument("--eds-dir", type=Path, default=None, metavar="DIR",
                   help="match the nodes' identity (1018h vendor id, product code) against these EDS files too "
                        "(the configuration's drives' and dragd's own are always tried)")
    s.set_defaults(func=cmd_scan)

    p = sub.add_parser("sdo", help="read or write one object of a node over SDO")
    p.add_argument("action", choices=["read", "write"])
    p.add_argument("node", metavar="NODE", help="node id 1..127")
    p.add_argument("address", metavar="INDEX[:SUB]", help="object index in hex, sub-index (default "
                                                          "0), e.g. 6041, 1018:2")
    p.add_argument("value", metavar="VALUE", nargs="?", help="write: the value (numbers: decimal or 0x hex)")
    p.add_argument("--type", choices=list(SDO_TYPES), default=None,
                   help="data type (default: the type in the EDS of the configured drive at NODE; read: unsigned by "
                        "length)")
    _common(p)
    p.set_defaults(func=cmd_sdo)

    n = sub.add_parser("nmt", help="NMT command to a node or all nodes: " + ", ".join(NMT_COMMANDS))
    n.add_argument("command", choices=list(NMT_COMMANDS))
    n.add_argument("node", metavar="NODE", help="node id 1..127, or all")
    _common(n)
    n.set_defaults(func=cmd_nmt)
