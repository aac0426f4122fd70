"""CANopen master: boots the drives in the CiA 302 manner and configures them over SDO, as each joint's drive
profile (hardware/profile.py) plans it.

Sequence: listen for another master's SYNC or heartbeat (refuse if heard) → NMT reset node → wait for every
boot-up → per node, in pre-operational: check identity (CiA 402), supported modes (CST; CSP noted for the motions
that use it), rated current and torque (against the configuration and K_m) → configure (heartbeats, every PDO the
drive has disabled, the layout's PDOs written, RPDO deadline or the fallback protection, 6007h, 605Ah, 6072h,
torque command zero, mode 6060h confirmed on 6061h, controlword "disable voltage" with the statusword confirming
it) → read every PDO back (COB-IDs by the bits CiA 301 defines) → NMT start only when every node passed.

Required objects stop the node's boot when they fail; optional ones (6007h, 605Ah, 6072h, 1016h, 140xh sub 5) are
skipped where the EDS lacks them, and a status line per node names the protection in force. A node's failures are
collected into one report, every node's reports into one error; the drives are then left with controlword 0 (disable
voltage) in pre-operational. SDO runs only here and in the reconfiguration worker (``Master.sdo_worker``), never in
the cycle; every value is encoded with the EDS data type of its object.

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
from canopen.objectdictionary import ODVariable
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from dragd.config import Config, JointConfig
from dragd.hardware.cia301 import (
    HEARTBEAT_BASE,
    NMT_COB_ID,
    OD_CONSUMER_HEARTBEAT,
    OD_DEVICE_TYPE,
    OD_IDENTITY,
    OD_PRODUCER_HEARTBEAT,
    SYNC_COB_ID,
    NmtCommand,
)
from dragd.hardware.cia402 import (
    MODE_CSP,
    MODE_CST,
    OD_ABORT_CONNECTION_OPTION,
    OD_CONTROLWORD,
    OD_MAX_TORQUE,
    OD_MODES_OF_OPERATION,
    OD_MODES_OF_OPERATION_DISPLAY,
    OD_QUICK_STOP_OPTION,
    OD_STATUSWORD,
    OD_SUPPORTED_DRIVE_MODES,
    OD_TARGET_TORQUE,
    OD_TORQUE_OFFSET,
    VOLTAGE_ENABLED_STATES,
    decode_statusword,
)
from dragd.hardware.pdo import BusLayout, PdoSpec
from dragd.hardware.profile import CURRENT_UNITS_A, DEVICE_TYPE_402, TORQUE_UNITS_NM, DriveProfile, Profiles, address
from dragd.hardware.reader import BusReader
from dragd.realtime import demote_current_thread

COB_DEFINED_BITS = 0xA000_07FF  # CiA 301 PDO COB-ID: bit 31 valid, bit 29 frame (0: 11-bit), bits 10..0 the id
COB_NO_RTR = 0x4000_0000  # bit 30 (TPDO: no RTR allowed; RPDO: reserved): kept as the drive has it
DISABLE_VOLTAGE_WAIT_S = 0.5


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
    profile: DriveProfile
    booted_at: float | None = None
    device_type: int | None = None
    vendor_id: int | None = None
    product_code: int | None = None
    modes: int | None = None  # 6502h as read (None: the drive has none)
    status: list[str] = field(default_factory=list)  # the last boot's status lines (protection in force)

    @property
    def csp(self) -> bool | None:
        """CSP possible (607Ah mappable, 6502h lists CSP); None: unknown (no 6502h)."""
        if self.profile.target_position is None:
            return False
        modes = self.modes if self.modes is not None else self.profile.supported_modes
        return None if modes is None else bool(modes & (1 << (MODE_CSP - 1)))


class NodeReport:
    """One node's boot: its failures (each naming the object, its EDS name and the key to set) and status lines."""

    def __init__(self, where: str, profile: DriveProfile) -> None:
        self.where, self.profile = where, profile
        self.errors: list[str] = []
        self.status: list[str] = []
        self.silent = False  # no SDO answer: the rest of the node's steps are skipped

    def fail(self, index: int | None, sub: int, what: str, fix: str = "") -> None:
        obj = f"{self.profile.describe(index, sub)}: " if index is not None else ""
        self.errors.append(f"{obj}{what}{'; ' + fix if fix else ''}")

    def text(self) -> str:
        return f"{self.where}: {len(self.errors)} problem(s):\n" + "\n".join(f"  - {e}" for e in self.errors)


@dataclass
class BusRuntime:
    name: str
    bus: can.BusABC
    network: canopen.Network
    layout: BusLayout
    nodes: dict[int, NodeInfo] = field(default_factory=dict)
    notifier: BusReader | None = None  # the bus's reader (canopen's Network reads through it)
    own_reader: bool = False  # made by the master (stopped by it), not the cycle's I/O's


STRUCT_TYPES = ODVariable.STRUCT_TYPES


def _u(fmt: str, value: int) -> bytes:
    return struct.pack("<" + fmt, value)


class Master:
    """Boots and configures the drives of every bus; owns the canopen networks and the SDO worker thread."""

    def __init__(self, cfg: Config, buses: dict[str, can.BusABC], layouts: dict[str, BusLayout],
                 loop: asyncio.AbstractEventLoop, profiles: Profiles, readers: dict[str, BusReader] | None = None,
                 log: Callable[[str], None] = print) -> None:
        """``profiles``: every joint's drive profile (its EDS). ``readers``: the buses' readers of the cycle's I/O
        (``BusIO.open_readers``), which each bus's canopen network joins as listeners; a bus without one (tools,
        tests: no cycle) is read by a reader of the master's own."""
        self.cfg = cfg
        self.loop = loop
        self.log = log
        # started during boot, before the cycle thread turns SCHED_FIFO: set_realtime puts it at SCHED_FIFO 1 then
        # (dragd.realtime: a SCHED_OTHER helper preempted while holding the GIL stalls the cycle)
        self.sdo_worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="dragd-sdo",
                                             initializer=demote_current_thread,
                                             initargs=(set(cfg.loop.cpus or ()) or None,))
        self.runtimes: dict[str, BusRuntime] = {}
        # every drive heartbeat (bus, node, NMT state byte), in the loop's thread: the daemon's comms monitor
        self.on_heartbeat: Callable[[str, int, int], None] | None = None
        self.took_bus = False  # NMT sent: from then on this master owns the drives (and puts them down on exit)
        self.listening = False  # the window before boot: a SYNC or master heartbeat heard then is another master's
        self.foreign: str | None = None
        for name, bus in buses.items():
            net = canopen.Network(bus)
            rt = BusRuntime(name, bus, net, layouts[name])
            for i, j in enumerate(cfg.joints):
                if j.bus == name:
                    prof = profiles[i]
                    rt.nodes[j.node_id] = NodeInfo(j.node_id, j, name, prof)
                    node = canopen.RemoteNode(j.node_id, prof.od)
                    node.sdo.RESPONSE_TIMEOUT = cfg.master.sdo_timeout_s
                    node.sdo.MAX_RETRIES = 2
                    net.add_node(node)
                    net.subscribe(HEARTBEAT_BASE + j.node_id, self._heartbeat_cb(rt, j.node_id))
            net.subscribe(SYNC_COB_ID, self._foreign_cb(name, "SYNC"))
            net.subscribe(HEARTBEAT_BASE + cfg.master.node_id, self._foreign_cb(name, f"heartbeat of node "
                                                                                  f"{cfg.master.node_id}"))
            reader = (readers or {}).get(name)
            if reader is None:
                reader, rt.own_reader = BusReader(bus, [], timeout=0.5, loop=loop), True
            for listener in net.listeners:  # SDO answers, heartbeats, the foreign-master watch
                reader.add_listener(listener)
            rt.notifier = reader
            net.notifier = reader  # type: ignore[assignment]  # canopen calls stop() and reads exception
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
                rt.bus.send(can.Message(arbitration_id=NMT_COB_ID, data=bytes([command, node_id]),
                                        is_extended_id=False))

    async def boot(self) -> None:
        """Reset, check, configure and start every drive; DriveError with every node's failures (the drives left
        with controlword 0 in pre-operational)."""
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
        failed: list[str] = []
        for rt in self.runtimes.values():
            for node_id in rt.nodes:
                try:
                    await self.run_sdo(self.configure_node, rt, node_id)
                except DriveError as exc:
                    failed.append(str(exc))
        if failed:
            await self.run_sdo(self.put_down)
            raise DriveError("boot failed; every drive left in pre-operational with controlword 0000h (disable "
                             "voltage):\n" + "\n".join(failed))
        self.nmt(NmtCommand.START)

    def put_down(self) -> None:
        """Controlword 0000h (disable voltage) by SDO to every node that answers (worker thread; best effort)."""
        for rt in self.runtimes.values():
            for node_id, info in rt.nodes.items():
                var = info.profile.var(OD_CONTROLWORD)
                if var is None:
                    continue
                try:
                    rt.network[node_id].sdo.download(OD_CONTROLWORD, 0, var.encode_raw(0))
                except (SdoAbortedError, SdoCommunicationError):
                    pass

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
        var = rt.nodes[node_id].profile.var(index, sub)  # the EDS's data type where it has the object
        self._sdo(rt, node_id, index, sub, var.encode_raw(value) if var is not None and var.data_type in
                  STRUCT_TYPES else _u(fmt, value))

    def configure_node(self, rt: BusRuntime, node_id: int) -> NodeReport:
        """Check identity, write the configuration, read it back (worker thread; node in pre-operational); the
        node's report, or DriveError with every failure of the node."""
        info = rt.nodes[node_id]
        p = info.profile
        rep = NodeReport(f"bus '{rt.name}' node {node_id} ({info.joint.name}, {p.eds_path.name})", p)
        _Boot(self, rt, info, rep).run()
        info.status = rep.status
        notes = [line for line in rep.status if not line.startswith("warning:")]
        for line in rep.status:
            if line.startswith("warning:"):
                self.log(f"{rep.where}: {line}")
        if notes:
            self.log(f"{rep.where}: {' | '.join(notes)}")
        if rep.errors:
            raise DriveError(rep.text())
        return rep

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

    def csp_refusal(self) -> str | None:
        """Why the drives that follow motions in CSP (identify run, replay, track) cannot follow position targets, or
        None (drives whose profile follows motions in CST need none)."""
        reasons = []
        for rt in self.runtimes.values():
            csp = [info for info in rt.nodes.values() if info.profile.motion_mode == "csp"]
            if csp and not rt.layout.position_targets:
                reasons.append(f"bus '{rt.name}': layout '{rt.layout.kind}' carries no position targets")
                continue
            for info in csp:
                if info.csp is False:
                    reasons.append(f"node {info.node_id} ({info.joint.name}): "
                                   f"{info.profile.csp_reason() or '6502h lacks CSP'}")
        return "; ".join(reasons) or None

    async def shutdown(self) -> None:
        """NMT pre-operational (PDOs and their watchdogs stop), stop the readers the master made and the worker.

        A master that never took the bus (another master was heard) sends nothing."""
        if self.took_bus:
            self.nmt(NmtCommand.PRE_OPERATIONAL)
        for rt in self.runtimes.values():
            if rt.notifier is not None and rt.own_reader:
                rt.notifier.stop(timeout=0.5)
        self.sdo_worker.shutdown(wait=False, cancel_futures=True)


class _Boot:
    """One node's boot sequence (worker thread): every step runs, every failure lands in the report."""

    def __init__(self, master: Master, rt: BusRuntime, info: NodeInfo, rep: NodeReport) -> None:
        self.m, self.rt, self.info, self.rep = master, rt, info, rep
        self.p = info.profile
        self.node = rt.network[info.node_id]
        self.j = info.joint
        self.jkey = f"joints[{self.p.joint_index}]"

    # ---------------------------------------------------------------------------------------- SDO with the report

    def read(self, index: int, sub: int = 0, what: str = "", fix: str = "") -> int | None:
        """A number read by SDO and decoded by its EDS data type; None (and a failure) on an abort."""
        if self.rep.silent:
            return None
        var = self.p.var(index, sub)
        try:
            raw = self.node.sdo.upload(index, sub)
        except SdoAbortedError as exc:
            self.rep.fail(index, sub, f"{what + ': ' if what else ''}read aborted 0x{exc.code:08X} ({exc})", fix)
            return None
        except SdoCommunicationError as exc:
            self._silent(exc)
            return None
        if var is not None and var.data_type in STRUCT_TYPES and len(raw) * 8 >= len(var):
            value = var.decode_raw(raw[:len(var) // 8])
            return int(value) if not isinstance(value, float) else value  # type: ignore[return-value]
        return int.from_bytes(raw, "little", signed=False)

    def write(self, index: int, sub: int, value: int, what: str = "", fix: str = "") -> bool:
        """A number written by SDO in its EDS data type; False (and a failure) on an abort."""
        if self.rep.silent:
            return False
        var = self.p.var(index, sub)
        if var is None or var.data_type not in STRUCT_TYPES:
            self.rep.fail(index, sub, f"{what + ': ' if what else ''}not in the EDS, not written", fix)
            return False
        try:
            data = var.encode_raw(value)
        except (struct.error, ValueError, OverflowError):
            self.rep.fail(index, sub, f"{what + ': ' if what else ''}{value} does not fit its type", fix)
            return False
        try:
            self.node.sdo.download(index, sub, data)
        except SdoAbortedError as exc:
            self.rep.fail(index, sub, f"{what + ': ' if what else ''}write of {value} (0x{value & 0xFFFFFFFF:X}) "
                                      f"aborted 0x{exc.code:08X} ({exc})", fix)
            return False
        except SdoCommunicationError as exc:
            self._silent(exc)
            return False
        return True

    def _silent(self, exc: Exception) -> None:
        self.rep.silent = True
        self.rep.fail(None, 0, f"no SDO response ({exc}): the node's remaining steps skipped (check power, node id, "
                               "bitrate)")

    # ---------------------------------------------------------------------------------------- the sequence

    def run(self) -> None:
        self.identity()
        self.modes()
        self.rated_current()
        self.rated_torque()
        self.heartbeats()
        self.pdos()
        self.reactions()
        self.command_zero()
        self.mode_cst()
        self.disable_voltage()
        self.hand_inputs()
        for pdo in self.rt.layout.pdos[self.info.node_id]:
            self.verify_pdo(pdo)

    def identity(self) -> None:
        info, rep = self.info, self.rep
        info.device_type = self.read(OD_DEVICE_TYPE, 0, "device type")
        if info.device_type is not None and info.device_type & 0xFFFF != DEVICE_TYPE_402:
            rep.fail(OD_DEVICE_TYPE, 0, f"device type 0x{info.device_type:08X}, expected a CiA 402 drive (0x....0192)",
                     f"set {self.jkey}.node_id or {self.jkey}.drive")
        info.vendor_id = self.read(OD_IDENTITY, 1, "vendor id")
        if self.p.has(OD_IDENTITY, 2):
            info.product_code = self.read(OD_IDENTITY, 2, "product code")
        expect = self.p.var(OD_IDENTITY, 1)
        want = expect.default if expect is not None else None
        if isinstance(want, int) and want and info.vendor_id is not None and info.vendor_id != want:
            rep.status.append(f"warning: vendor id 0x{info.vendor_id:08X}, the EDS says 0x{want:08X}: is "
                              f"{self.p.eds_path.name} this drive's EDS?")

    def modes(self) -> None:
        if not self.p.has(OD_SUPPORTED_DRIVE_MODES):
            self.info.modes = None
            self.rep.status.append("6502h absent: CST confirmed by 6060h = 10 shown on 6061h; CSP by the same when a "
                                   "motion needs it")
            return
        modes = self.read(OD_SUPPORTED_DRIVE_MODES, 0, "supported drive modes")
        self.info.modes = modes
        if modes is None:
            return
        if not modes & (1 << (MODE_CST - 1)):
            self.rep.fail(OD_SUPPORTED_DRIVE_MODES, 0, f"supported modes 0x{modes:08X} lack CST (10): the drive "
                                                       "cannot do torque drag", "use a drive with CST")
        if not modes & (1 << (MODE_CSP - 1)):
            self.rep.status.append(f"6502h 0x{modes:08X} lacks CSP (8): identify run, replay and track refused")

    def rated_current(self) -> None:
        p, j, rep = self.p, self.j, self.rep
        obj = p.rated_current_object
        key = f"{self.jkey}.rated_current_A"
        if obj is None:
            rep.status.append(f"rated current {j.rated_current_A:g} A from {key}, unverified (the profile names no "
                              "object)")
            return
        raw = self.read(*obj, "rated current", f"set {p.key}.rated_current.object")
        if raw is None:
            return
        unit = p.drive.rated_current.unit
        got_A = raw * CURRENT_UNITS_A[unit]
        if abs(got_A - j.rated_current_A) > max(1e-3, 1e-3 * j.rated_current_A):
            rep.fail(*obj, f"rated current {raw} {unit} = {got_A:g} A, the configuration says {key} = "
                           f"{j.rated_current_A:g} A", f"set {key}: {got_A:g} (the drive's motor data) or correct "
                                                       "the drive")

    def rated_torque(self) -> None:
        p, j, rep = self.p, self.j, self.rep
        obj = p.rated_torque_object
        rt_cfg = p.drive.rated_torque
        unit = rt_cfg.unit
        km = j.km_Nm_per_A
        expected_Nm = j.rated_torque_motor_Nm
        basis = (f"{self.jkey}.rated_torque_Nm" if j.rated_torque_Nm is not None
                 else f"K_m {km:.4g} N·m/A × rated current {j.rated_current_A:g} A")
        if obj is None:
            rep.status.append(f"rated torque {expected_Nm:.4g} N·m ({basis}), unverified (the profile names no object)")
            return
        raw = self.read(*obj, "rated torque", f"set {p.key}.rated_torque.object")
        if raw is None:
            return
        if raw == 0:
            if rt_cfg.write:
                want = p.rated_torque_raw()
                if self.write(*obj, want, "rated torque") and self.read(*obj, "rated torque") == want:
                    rep.status.append(f"{address(*obj)} rated torque was 0: wrote {want} {unit} ({basis})")
                else:
                    rep.fail(*obj, f"rated torque 0 and the write of {want} {unit} did not read back")
            else:
                rep.fail(*obj, "rated torque 0: the drive cannot scale torque commands (6071h, 60B2h, 6077h are per "
                               "mille of it)", f"set {p.key}.rated_torque.write: true (dragd writes {basis}) or set "
                                               "it in the drive")
            return
        got_Nm = raw * TORQUE_UNITS_NM[unit]
        if j.rated_torque_Nm is not None:
            if abs(got_Nm - j.rated_torque_Nm) > rt_cfg.tolerance * j.rated_torque_Nm:
                rep.fail(*obj, f"rated torque {raw} {unit} = {got_Nm:.4g} N·m, the configuration says "
                               f"{self.jkey}.rated_torque_Nm = {j.rated_torque_Nm:.4g}",
                         f"set {self.jkey}.rated_torque_Nm: {got_Nm:.6g}, or {p.key}.rated_torque.unit if the "
                         "unit differs")
            return
        drive_km = got_Nm / j.rated_current_A
        if abs(drive_km - km) > rt_cfg.tolerance * km:
            rep.status.append(f"warning: {address(*obj)} rated torque {raw} {unit} / rated current "
                              f"{j.rated_current_A:g} A = K_m {drive_km:.4g} N·m/A, the configuration's K_m is "
                              f"{km:.4g} ({100 * (drive_km / km - 1):+.1f} %); torque commands stay per mille of the "
                              f"rated current (rated_torque_Nm unset); check the torque constant (dragd identify) or "
                              f"the unit ({p.key}.rated_torque.unit)")
        else:
            rep.status.append(f"{address(*obj)} rated torque {got_Nm:.4g} N·m agrees with K_m × rated current "
                              f"({100 * (drive_km / km - 1):+.1f} %)")

    def heartbeats(self) -> None:
        m = self.m.cfg.master
        self.write(OD_PRODUCER_HEARTBEAT, 0, m.drive_heartbeat_ms, "heartbeat producer time")
        if self.p.has(OD_CONSUMER_HEARTBEAT, 1):
            self.write(OD_CONSUMER_HEARTBEAT, 1, (m.node_id << 16) | m.heartbeat_consumer_ms, "heartbeat consumer")

    def pdos(self) -> None:
        """Every PDO the drive has disabled (its COB-ID bit 31), then the layout's written."""
        for ch in (*self.p.rpdos, *self.p.tpdos):
            if not ch.cob_writable:
                continue
            cob = self.read(ch.comm_index, 1, f"{ch.name} COB-ID")
            if cob is not None and not cob & 0x8000_0000:
                self.write(ch.comm_index, 1, cob | 0x8000_0000, f"{ch.name} COB-ID (disable)")
        deadline_on = None
        for pdo in self.rt.layout.pdos[self.info.node_id]:
            if self._write_pdo(pdo) and pdo.direction == "rpdo" and pdo.transmission_type <= 240 and 5 in pdo.comm_subs:
                deadline_on = pdo
        self._protection(deadline_on)

    def _write_pdo(self, pdo: PdoSpec) -> bool:
        comm, mapping = pdo.comm_index, pdo.map_index
        where = f"{pdo.name}"
        if pdo.cob_writable:
            have = self.read(comm, 1, f"{where} COB-ID") or 0
            keep = have & COB_NO_RTR
            if not self.write(comm, 1, pdo.cob_id | keep | 0x8000_0000, f"{where} COB-ID"):
                return False
        ok = self.write(comm, 2, pdo.transmission_type, f"{where} transmission type")
        if pdo.direction == "tpdo":
            if 3 in pdo.comm_subs:
                ok &= self.write(comm, 3, pdo.inhibit_100us, f"{where} inhibit time")
            if 5 in pdo.comm_subs:
                ok &= self.write(comm, 5, pdo.event_timer_ms, f"{where} event timer")
        elif 5 in pdo.comm_subs:  # RPDO deadline monitoring on the cyclic command (CiA 301 event timer of an RPDO)
            timeout = self.m.cfg.safety.rpdo_timeout_ms if pdo.transmission_type <= 240 else 0
            ok &= self.write(comm, 5, timeout, f"{where} deadline (event timer)")
        if not pdo.fixed_mapping:
            ok &= self.write(mapping, 0, 0, f"{where} mapping count")
            for i, e in enumerate(pdo.entries, start=1):
                ok &= self.write(mapping, i, e.word, f"{where} mapping entry {i} ({e.index:04X}h:{e.subindex})")
            ok &= self.write(mapping, 0, len(pdo.entries), f"{where} mapping count")
        if pdo.cob_writable and ok:
            keep = (self.read(comm, 1, f"{where} COB-ID") or 0) & COB_NO_RTR
            ok &= self.write(comm, 1, pdo.cob_id | keep, f"{where} COB-ID (enable)")
        return ok

    def _protection(self, deadline_on: PdoSpec | None) -> None:
        """The status line naming what stops the drive when dragd stops sending."""
        cfg = self.m.cfg
        parts = []
        if deadline_on is not None:
            parts.append(f"RPDO deadline {cfg.safety.rpdo_timeout_ms} ms on {deadline_on.name} "
                         f"({deadline_on.comm_index:04X}h:05)")
        else:
            parts.append("no RPDO deadline (140xh has no sub 5)")
        w = self.p.watchdog_object
        if w is not None:
            unit = self.p.drive.rpdo_watchdog.unit  # type: ignore[union-attr]
            per_ms = {"ms": 1.0, "us": 1000.0, "100us": 10.0, "s": 1e-3}[unit]
            value = max(1, round(cfg.safety.rpdo_timeout_ms * per_ms))
            if self.write(*w, value, "vendor watchdog", f"set {self.p.key}.rpdo_watchdog"):
                parts.append(f"vendor watchdog {address(*w)} = {value} {unit}")
        if self.p.has(OD_CONSUMER_HEARTBEAT, 1):
            parts.append(f"master heartbeat consumer 1016h {cfg.master.heartbeat_consumer_ms} ms")
        else:
            parts.append("no heartbeat consumer (1016h absent)")
        self.rep.status.append("protection: " + "; ".join(parts))

    def reactions(self) -> None:
        s, p, j = self.m.cfg.safety, self.p, self.j
        notes = []
        if p.has(OD_ABORT_CONNECTION_OPTION):
            self.write(OD_ABORT_CONNECTION_OPTION, 0, s.abort_connection_option, "abort connection option")
            notes.append(f"6007h = {s.abort_connection_option}")
        else:
            notes.append("6007h absent: the drive's own reaction to a lost connection")
        if p.has(OD_QUICK_STOP_OPTION):
            self.write(OD_QUICK_STOP_OPTION, 0, s.quick_stop_option, "quick stop option")
            notes.append(f"605Ah = {s.quick_stop_option}")
        else:
            notes.append("605Ah absent: the drive's own quick stop")
        if p.has(OD_MAX_TORQUE):
            if j.rated_torque_Nm is None:  # (per mille of the rated torque = of the rated current)
                permille = int(1000 * j.current_limit_A / j.rated_current_A + 0.5)
            else:
                permille = int(j.current_limit_A * p.command_per_A() + 0.5)
            var = p.var(OD_MAX_TORQUE)
            top = 0x7FFF if var is not None and var.data_type == 0x3 else 0xFFFF
            if var is not None and isinstance(var.max, int) and 0 < var.max < top:
                top = var.max  # the EDS's HighLimit
            value = min(top, permille)
            self.write(OD_MAX_TORQUE, 0, value, "max torque")
            notes.append(f"6072h = {value} per mille")
            if value < permille:
                self.rep.status.append(f"warning: 6072h capped at {value} per mille (its range): the drive limits the "
                                       f"current to {value / permille * j.current_limit_A:.3g} A, below "
                                       f"{self.jkey}.current_limit_A {j.current_limit_A:g} A")
        else:
            notes.append(f"6072h absent: the drive does not limit the torque to {self.jkey}.current_limit_A "
                         "(dragd's command clamp only)")
        self.rep.status.append("reactions: " + "; ".join(notes))

    def command_zero(self) -> None:
        if self.p.has(OD_TARGET_TORQUE):
            self.write(OD_TARGET_TORQUE, 0, 0, "target torque")
        if self.p.has(OD_TORQUE_OFFSET):
            self.write(OD_TORQUE_OFFSET, 0, 0, "torque offset")

    def mode_cst(self) -> None:
        if self.rep.silent or not self.write(OD_MODES_OF_OPERATION, 0, MODE_CST, "modes of operation (CST)"):
            return
        deadline = time.monotonic() + 0.5
        shown = None
        while time.monotonic() < deadline:
            shown = self.read(OD_MODES_OF_OPERATION_DISPLAY, 0, "modes of operation display")
            if shown is None or shown == MODE_CST:
                break
            time.sleep(0.005)
        if shown is not None and shown != MODE_CST:
            self.rep.fail(OD_MODES_OF_OPERATION_DISPLAY, 0, f"shows mode {shown} 0.5 s after 6060h = 10 (CST): the "
                                                            "drive does not do cyclic synchronous torque")

    def disable_voltage(self) -> None:
        """Controlword 0000h and the statusword confirming no voltage is enabled: the state the boot hands over."""
        if self.rep.silent or not self.write(OD_CONTROLWORD, 0, 0, "controlword (disable voltage)"):
            return
        deadline = time.monotonic() + DISABLE_VOLTAGE_WAIT_S
        state = None
        sw = None
        while True:
            sw = self.read(OD_STATUSWORD, 0, "statusword")
            if sw is None:
                return
            try:
                state = decode_statusword(sw)
            except ValueError:
                state = None
            if state is not None and state not in VOLTAGE_ENABLED_STATES:
                break
            if time.monotonic() > deadline:
                self.rep.fail(OD_STATUSWORD, 0, f"statusword 0x{sw:04X} "
                                                f"({state.name.lower() if state else 'no CiA 402 state'}) "
                                                f"{DISABLE_VOLTAGE_WAIT_S:g} s after controlword 0000h (disable "
                                                "voltage): the drive's state is not the one the boot hands over")
                return
            time.sleep(0.005)
        self.rep.status.append(f"statusword 0x{sw:04X} ({state.name.lower()}) after controlword 0000h")

    def hand_inputs(self) -> None:
        """The contacts wired to this drive's digital inputs (docs/HAND.md), read once before the arm may move: an
        enabling switch, mark or teach button reading active (pressed, stuck, or wired inverted), or an enabling
        switch whose two channels disagree, is a wiring fault; a stop reading active is reported (pressed, or its
        normally-closed wire open)."""
        obj = self.p.inputs
        if obj is None:
            return
        wired = [(k, inp) for k, inp in enumerate(self.m.cfg.hand.inputs) if inp.joint == self.j.name]
        word = self.read(obj.index, obj.sub, "the digital inputs (hand.inputs)")
        if word is None:
            return
        word = int(word) & ((1 << obj.bits) - 1)
        name = f"{obj.index:04X}h" + (f":{obj.sub}" if obj.sub else "")
        self.rep.status.append(f"hand inputs: {name} = 0x{word:0{max(2, obj.bits // 4)}X} at boot")

        def active(bit: int, low: bool) -> bool:
            return bool(word >> bit & 1) != low

        for k, inp in wired:
            low = inp.active == "low"
            chans = [(b, active(b, low)) for b in [inp.bit] + ([inp.second_bit] if inp.second_bit is not None else [])]
            key = f"hand.inputs[{k}] ({inp.label})"
            levels = ", ".join(f"bit {b} {'active' if a else 'inactive'}" for b, a in chans)
            if inp.function == "stop":
                if chans[0][1]:
                    self.rep.status.append(f"warning: {key} {self.j.name} {name} bit {inp.bit} reads active at boot: "
                                           "the stop is pressed, or its wire is open; nothing moves until it reads "
                                           "released")
                continue
            if len(chans) == 2 and chans[0][1] != chans[1][1]:
                self.rep.fail(obj.index, obj.sub, f"{key} on {self.j.name}: the enabling switch's channels disagree "
                              f"at boot ({levels}): one contact is stuck, broken or miswired",
                              f"check the wiring of {self.j.name}'s inputs {inp.bit} and {inp.second_bit}, or "
                              f"{key}.bit/.second_bit")
            elif any(a for _, a in chans):
                self.rep.fail(obj.index, obj.sub, f"{key} on {self.j.name}: {levels} at boot: the contact is pressed, "
                              "stuck, or wired inverted (nobody may hold it while dragd starts)",
                              f"release it; or set {key}.active: {'high' if low else 'low'} for a "
                              f"normally-{'open' if low else 'closed'} contact, or {key}.bit to the input it is "
                              "wired to")
            if inp.panic_bit is not None and word >> inp.panic_bit & 1:
                self.rep.fail(obj.index, obj.sub, f"{key} on {self.j.name}: the panic contact (bit {inp.panic_bit}) "
                              "reads active at boot: the switch is squeezed, stuck or miswired",
                              f"release it, or set {key}.panic_bit to the input it is wired to")

    def verify_pdo(self, pdo: PdoSpec) -> None:
        where = pdo.name
        cob = self.read(pdo.comm_index, 1, f"{where} COB-ID")
        if cob is not None and cob & COB_DEFINED_BITS != pdo.cob_id & COB_DEFINED_BITS:
            self.rep.fail(pdo.comm_index, 1, f"{where} COB-ID read back 0x{cob:08X}, wrote 0x{pdo.cob_id:03X} (CiA "
                                             "301 bits 31, 29, 10..0 compared)")
        ttype = self.read(pdo.comm_index, 2, f"{where} transmission type")
        if ttype is not None and ttype != pdo.transmission_type:
            self.rep.fail(pdo.comm_index, 2, f"{where} transmission type read back {ttype}, wrote "
                                             f"{pdo.transmission_type}")
        count = self.read(pdo.map_index, 0, f"{where} mapping count")
        if count is None:
            return
        words = [self.read(pdo.map_index, i, f"{where} mapping entry {i}") for i in range(1, count + 1)]
        want = [e.word for e in pdo.entries]
        if words != want:
            self.rep.fail(pdo.map_index, 0, f"{where} mapping read back "
                                            f"[{', '.join(f'{w:08X}h' if w is not None else '?' for w in words)}], "
                                            f"expected [{', '.join(f'{w:08X}h' for w in want)}]")
