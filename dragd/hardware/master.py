"""CANopen master: boots the drives in the CiA 302 manner and configures them over SDO.

Sequence (per bus, all nodes): listen for another master's SYNC or heartbeat (refuse if heard) → NMT reset node → wait for every boot-up → check device type (CiA 402),
supported modes and rated current → configure in pre-operational (heartbeat producer/consumer, PDO
mappings and transmission types, RPDO deadline, 6007h, 605Ah, 6072h, torque command zero, mode 6060h
confirmed on 6061h) → read the mappings back and verify → NMT start. SDO runs only here and in the
reconfiguration worker (``Master.sdo_worker``), never in the cycle.

All frames are read by one ``can.Notifier`` per bus whose callbacks run in the asyncio loop's thread
(``loop.add_reader`` on the bus's fileno): the cycle's TPDO listener and canopen's SDO/NMT machinery.
SDO calls block their (worker) thread while the loop delivers the responses.
"""

from __future__ import annotations

import asyncio
import struct
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import can
import canopen
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from dragd.hardware.cia301 import HEARTBEAT_BASE, NMT_COB_ID, SYNC_COB_ID, NmtCommand
from dragd.hardware.reader import DrainingNotifier
from dragd.hardware.cia402 import (MODE_CSP, MODE_CST, OD_ABORT_CONNECTION_OPTION, OD_MAX_TORQUE, OD_MODES_OF_OPERATION, OD_MODES_OF_OPERATION_DISPLAY,
                     OD_MOTOR_RATED_CURRENT, OD_QUICK_STOP_OPTION, OD_SUPPORTED_DRIVE_MODES, OD_TARGET_TORQUE,
                     OD_TORQUE_OFFSET)
from dragd.config import Config, JointConfig
from dragd.hardware.pdo import BusLayout, PdoSpec
from dragd.realtime import demote_current_thread
from dragd.resources import eds_path

DEVICE_TYPE_402 = 0x0192


class DriveError(RuntimeError):
    """A drive that does not answer or behave as configured; the message names bus, node and object."""


class MasterConflict(DriveError):
    """Another CANopen master is active on a bus: this one must not touch the drives."""


LISTEN_S = 0.3  # before any NMT: how long to listen for another master's SYNC or heartbeat


@dataclass
class NodeInfo:
    node_id: int
    joint: JointConfig
    bus: str
    booted_at: float | None = None
    device_type: int | None = None
    vendor_id: int | None = None
    product_code: int | None = None


@dataclass
class BusRuntime:
    name: str
    bus: can.BusABC
    network: canopen.Network
    layout: BusLayout
    nodes: dict[int, NodeInfo] = field(default_factory=dict)
    notifier: can.Notifier | None = None


def _u(fmt: str, value: int) -> bytes:
    return struct.pack("<" + fmt, value)


class Master:
    """Boots and configures the drives of every bus; owns the canopen networks and the SDO worker thread."""

    def __init__(self, cfg: Config, buses: dict[str, can.BusABC], layouts: dict[str, BusLayout],
                 loop: asyncio.AbstractEventLoop, listeners: dict[str, list[can.Listener]],
                 log: Callable[[str], None] = print,
                 on_data: dict[str, Callable[[int, bytes | bytearray], bool]] | None = None,
                 after_frames: Callable[[], None] | None = None, read_done: Callable[[], bool] | None = None) -> None:
        """``on_data`` (per bus) claims the cyclic TPDOs before any ``can.Message``; ``after_frames`` runs after each
        wake-up's frames of any bus (the cycle's read step ends there); ``read_done()`` true ends a wake-up's
        reading early (the cycle has every TPDO it waits for)."""
        self.cfg = cfg
        self.loop = loop
        self.log = log
        # started during boot, before the cycle thread turns SCHED_FIFO; demoted anyway should it start later
        self.sdo_worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="dragd-sdo",
                                             initializer=demote_current_thread, initargs=(set(cfg.loop.cpus or ()) or None,))
        self.runtimes: dict[str, BusRuntime] = {}
        # every drive heartbeat (bus, node, NMT state byte), in the loop's thread: the daemon's comms monitor
        self.on_heartbeat: Callable[[str, int, int], None] | None = None
        self.took_bus = False  # NMT sent: from then on this master owns the drives (and puts them down on exit)
        self.listening = False  # the window before boot: a SYNC or master heartbeat heard then is another master's
        self.foreign: str | None = None
        for name, bus in buses.items():
            net = canopen.Network(bus)
            rt = BusRuntime(name, bus, net, layouts[name])
            for j in cfg.joints:
                if j.bus == name:
                    rt.nodes[j.node_id] = NodeInfo(j.node_id, j, name)
                    node = canopen.RemoteNode(j.node_id, str(eds_path()))
                    node.sdo.RESPONSE_TIMEOUT = cfg.master.sdo_timeout_s
                    node.sdo.MAX_RETRIES = 2
                    net.add_node(node)
                    net.subscribe(HEARTBEAT_BASE + j.node_id, self._heartbeat_cb(rt, j.node_id))
            net.subscribe(SYNC_COB_ID, self._foreign_cb(name, "SYNC"))
            net.subscribe(HEARTBEAT_BASE + cfg.master.node_id, self._foreign_cb(name, f"heartbeat of node "
                                                                                  f"{cfg.master.node_id}"))
            rt.notifier = DrainingNotifier(bus, [*net.listeners, *listeners.get(name, [])], timeout=0.5, loop=loop,
                                           on_data=(on_data or {}).get(name), after=after_frames,
                                           until=read_done)
            net.notifier = rt.notifier
            self.runtimes[name] = rt

    # ------------------------------------------------------------------------------------------ NMT

    def _heartbeat_cb(self, rt: BusRuntime, node_id: int) -> Callable[[int, bytearray, float], None]:
        def cb(can_id: int, data: bytearray, timestamp: float) -> None:
            if len(data) >= 1 and data[0] == 0x00:
                rt.nodes[node_id].booted_at = time.monotonic()
            if len(data) >= 1 and self.on_heartbeat is not None:
                self.on_heartbeat(rt.name, node_id, data[0] & 0x7F)

        return cb

    def _foreign_cb(self, bus: str, what: str) -> Callable[[int, bytearray, float], None]:
        def cb(can_id: int, data: bytearray, timestamp: float) -> None:
            if self.listening and self.foreign is None:
                self.foreign = f"{what} (COB-ID 0x{can_id:03X}) on bus '{bus}'"

        return cb

    async def listen_for_other_master(self, seconds: float = LISTEN_S) -> None:
        """Before any NMT: refuse (MasterConflict) when another master's SYNC or heartbeat is on a bus."""
        self.listening = True
        try:
            end = time.monotonic() + seconds
            while time.monotonic() < end and self.foreign is None:
                await asyncio.sleep(0.01)
        finally:
            self.listening = False
        if self.foreign is not None:
            raise MasterConflict(f"another CANopen master is running: heard its {self.foreign} before any NMT; "
                                 "refusing to reset or configure the drives (is another dragd running on this bus?)")

    def nmt(self, command: int, node_id: int = 0, bus: str | None = None) -> None:
        """Send an NMT command (node 0 = all nodes) on one bus or all."""
        for rt in self.runtimes.values():
            if bus is None or rt.name == bus:
                rt.bus.send(can.Message(arbitration_id=NMT_COB_ID, data=bytes([command, node_id]), is_extended_id=False))

    async def boot(self) -> None:
        """Reset, check, configure and start every drive; raise DriveError naming what failed."""
        await self.listen_for_other_master()
        self.took_bus = True
        for rt in self.runtimes.values():
            for info in rt.nodes.values():
                info.booted_at = None
        t0 = time.monotonic()
        self.nmt(NmtCommand.RESET_NODE)
        deadline = t0 + self.cfg.master.boot_timeout_s
        while time.monotonic() < deadline:
            if all(i.booted_at is not None for rt in self.runtimes.values() for i in rt.nodes.values()):
                break
            await asyncio.sleep(0.01)
        missing = [f"node {i.node_id} on bus '{rt.name}'" for rt in self.runtimes.values() for i in rt.nodes.values()
                   if i.booted_at is None]
        if missing:
            raise DriveError(f"no boot-up from {', '.join(missing)} within {self.cfg.master.boot_timeout_s:.1f} s "
                             "after NMT reset node (check wiring, node ids, bitrate, power)")
        self.log(f"all {sum(len(rt.nodes) for rt in self.runtimes.values())} drives booted in "
                 f"{(time.monotonic() - t0) * 1e3:.0f} ms")
        for rt in self.runtimes.values():
            for node_id in rt.nodes:
                await self.run_sdo(self.configure_node, rt, node_id)
        self.nmt(NmtCommand.START)

    async def run_sdo(self, fn: Callable[..., object], *args: object) -> object:
        """Run a blocking SDO sequence on the worker thread (never on the loop or in the cycle)."""
        return await self.loop.run_in_executor(self.sdo_worker, fn, *args)

    # ------------------------------------------------------------------------------------------ SDO

    def _sdo(self, rt: BusRuntime, node_id: int, index: int, sub: int, data: bytes | None = None) -> bytes:
        node = rt.network[node_id]
        what = f"bus '{rt.name}' node {node_id}: {'write' if data is not None else 'read'} {index:04X}h sub {sub}"
        try:
            if data is None:
                return node.sdo.upload(index, sub)
            node.sdo.download(index, sub, data)
            return data
        except SdoAbortedError as exc:
            raise DriveError(f"{what}: SDO abort 0x{exc.code:08X} ({exc})") from None
        except SdoCommunicationError as exc:
            raise DriveError(f"{what}: no SDO response ({exc})") from None

    def read_u(self, rt: BusRuntime, node_id: int, index: int, sub: int = 0) -> int:
        raw = self._sdo(rt, node_id, index, sub)
        return int.from_bytes(raw, "little", signed=False)

    def write(self, rt: BusRuntime, node_id: int, index: int, sub: int, fmt: str, value: int) -> None:
        self._sdo(rt, node_id, index, sub, _u(fmt, value))

    def configure_node(self, rt: BusRuntime, node_id: int) -> None:
        """Check identity, write the configuration, read it back (worker thread; node in pre-operational)."""
        info = rt.nodes[node_id]
        j = info.joint
        where = f"bus '{rt.name}' node {node_id} ({j.name})"
        info.device_type = self.read_u(rt, node_id, 0x1000)
        if info.device_type & 0xFFFF != DEVICE_TYPE_402:
            raise DriveError(f"{where}: device type 1000h = 0x{info.device_type:08X}, expected a CiA 402 drive (0x....0192)")
        info.vendor_id = self.read_u(rt, node_id, 0x1018, 1)
        info.product_code = self.read_u(rt, node_id, 0x1018, 2)
        modes = self.read_u(rt, node_id, OD_SUPPORTED_DRIVE_MODES)
        for mode, name in ((MODE_CST, "CST (10)"), (MODE_CSP, "CSP (8)")):
            if not modes & (1 << (mode - 1)):
                raise DriveError(f"{where}: 6502h supported modes 0x{modes:08X} lack {name}")
        rated_mA = self.read_u(rt, node_id, OD_MOTOR_RATED_CURRENT)
        want_mA = round(j.rated_current_A * 1000)
        if abs(rated_mA - want_mA) > 1:
            raise DriveError(f"{where}: 6075h rated current is {rated_mA} mA, the configuration says "
                             f"rated_current_A = {j.rated_current_A} ({want_mA} mA)")
        safety, master = self.cfg.safety, self.cfg.master
        self.write(rt, node_id, 0x1017, 0, "H", master.drive_heartbeat_ms)
        self.write(rt, node_id, 0x1016, 1, "I", (master.node_id << 16) | master.heartbeat_consumer_ms)
        # PDOs: disable all, then write each of the layout's
        for base in (0x1400, 0x1800):
            for k in range(4):
                cob = self.read_u(rt, node_id, base + k, 1)
                self.write(rt, node_id, base + k, 1, "I", cob | 0x8000_0000)
        for pdo in rt.layout.pdos[node_id]:
            self._write_pdo(rt, node_id, pdo)
        self.write(rt, node_id, OD_ABORT_CONNECTION_OPTION, 0, "h", safety.abort_connection_option)
        self.write(rt, node_id, OD_QUICK_STOP_OPTION, 0, "h", safety.quick_stop_option)
        max_permille = min(0xFFFF, int(1000 * j.current_limit_A / j.rated_current_A + 0.5))
        self.write(rt, node_id, OD_MAX_TORQUE, 0, "H", max_permille)
        self.write(rt, node_id, OD_TARGET_TORQUE, 0, "h", 0)
        self.write(rt, node_id, OD_TORQUE_OFFSET, 0, "h", 0)
        self.set_mode(rt, node_id, MODE_CST)
        for pdo in rt.layout.pdos[node_id]:
            self._verify_pdo(rt, node_id, pdo)

    def set_mode(self, rt: BusRuntime, node_id: int, mode: int, timeout_s: float = 0.5) -> None:
        """Write 6060h and wait until 6061h confirms it."""
        self.write(rt, node_id, OD_MODES_OF_OPERATION, 0, "b", mode)
        deadline = time.monotonic() + timeout_s
        while True:
            shown = int.from_bytes(self._sdo(rt, node_id, OD_MODES_OF_OPERATION_DISPLAY, 0), "little", signed=True)
            if shown == mode:
                return
            if time.monotonic() > deadline:
                raise DriveError(f"bus '{rt.name}' node {node_id}: 6061h shows mode {shown} {timeout_s:.1f} s after "
                                 f"6060h = {mode}")
            time.sleep(0.005)

    def _write_pdo(self, rt: BusRuntime, node_id: int, pdo: PdoSpec) -> None:
        comm, mapping = pdo.comm_index, pdo.map_index
        self.write(rt, node_id, comm, 1, "I", pdo.cob_id | 0x8000_0000)
        self.write(rt, node_id, comm, 2, "B", pdo.transmission_type)
        if pdo.direction == "tpdo":
            self.write(rt, node_id, comm, 3, "H", pdo.inhibit_100us)
            self.write(rt, node_id, comm, 5, "H", pdo.event_timer_ms)
        else:  # RPDO deadline monitoring on the cyclic command (CiA 301 event timer of an RPDO)
            timeout = self.cfg.safety.rpdo_timeout_ms if pdo.transmission_type <= 240 else 0
            self.write(rt, node_id, comm, 5, "H", timeout)
        self.write(rt, node_id, mapping, 0, "B", 0)
        for i, e in enumerate(pdo.entries, start=1):
            self.write(rt, node_id, mapping, i, "I", e.word)
        self.write(rt, node_id, mapping, 0, "B", len(pdo.entries))
        self.write(rt, node_id, comm, 1, "I", pdo.cob_id)

    def _verify_pdo(self, rt: BusRuntime, node_id: int, pdo: PdoSpec) -> None:
        where = f"bus '{rt.name}' node {node_id}: {pdo.direction.upper()}{pdo.number}"
        cob = self.read_u(rt, node_id, pdo.comm_index, 1)
        if cob != pdo.cob_id:
            raise DriveError(f"{where}: COB-ID read back 0x{cob:08X}, wrote 0x{pdo.cob_id:03X}")
        ttype = self.read_u(rt, node_id, pdo.comm_index, 2)
        if ttype != pdo.transmission_type:
            raise DriveError(f"{where}: transmission type read back {ttype}, wrote {pdo.transmission_type}")
        count = self.read_u(rt, node_id, pdo.map_index, 0)
        words = [self.read_u(rt, node_id, pdo.map_index, i) for i in range(1, count + 1)]
        want = [e.word for e in pdo.entries]
        if words != want:
            raise DriveError(f"{where}: mapping read back {[hex(w) for w in words]}, wrote {[hex(w) for w in want]}")

    async def shutdown(self) -> None:
        """NMT pre-operational (PDOs and their watchdogs stop), stop the notifiers and the worker.

        A master that never took the bus (another master was heard) sends nothing."""
        if self.took_bus:
            self.nmt(NmtCommand.PRE_OPERATIONAL)
        for rt in self.runtimes.values():
            if rt.notifier is not None:
                rt.notifier.stop(timeout=0.5)
        self.sdo_worker.shutdown(wait=False, cancel_futures=True)
