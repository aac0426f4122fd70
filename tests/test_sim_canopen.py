"""The simulated joint drives against a real CANopen master stack, across processes.

The simulated robot runs as its own process (`python -m sim run --bus udp_multicast:GROUP`, the seed
cobot truth: six drives, 4 kHz physics) on a multicast group unique to this module. The tests talk to it
with `canopen.Network` + `RemoteNode` (SDO, NMT, PDO configuration) and raw frames (SYNC, RPDOs,
heartbeats), and record every frame on the bus. The simulator runs on its lockstep clock (`--lockstep`): each
SYNC the test sends is one period (1 ms) of simulated time, ended by the simulator's TIME frame, so what a test
measures in time (a heartbeat's expiry, an RPDO deadline, a quick stop's ramp) is simulated time, exact to the period,
however busy the machine (docs/LOCKSTEP.md). Every test starts from NMT reset node of all drives; the
arm itself keeps its pose between tests, so tests that enable torque use the gravity-free joints
(node 1: base, vertical axis; node 6: flange).
"""

from __future__ import annotations

import math
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import can
import canopen
import pytest
from canopen.sdo.exceptions import SdoAbortedError

from dragd.clock import TIME_COB_ID, decode_time_of_day
from dragd.hardware.bus import UdpMulticastCanBus, open_bus, parse_bus
from dragd.hardware.cia402 import (
    CMD_DISABLE_VOLTAGE,
    CMD_ENABLE_OPERATION,
    CMD_FAULT_RESET,
    CMD_QUICK_STOP,
    CMD_SHUTDOWN,
    SW_TARGET_REACHED,
    State,
    decode_statusword,
    next_controlword,
)
from dragd.lab.rig import multicast_group
from sim.truth import load_truth

REPO = Path(__file__).resolve().parents[1]
EDS = REPO / "canopen_eds" / "joint_drive.eds"
TRUTH = load_truth(None)
DRIVES = {j.drive.node_id: j.drive for j in TRUTH.joints}
NODES = tuple(sorted(DRIVES))
MASTER_ID = 0x7F
T = TypeVar("T")

pytestmark = [pytest.mark.lockstep]
PERIOD_S = 0.001  # simulated time per SYNC (python -m sim run --lockstep's default --period-ms 1)
GUARD_S = 10.0  # wall time a period may take before the simulator counts as stalled (a hang guard, not a verdict)


def unique_group(name: str) -> str:
    """A multicast group of its own (dragd/lab/rig.py ``multicast_group``: claimed machine-wide, never the docs'
    239.74.163.x): no cross-talk with another test or another test run."""
    return multicast_group(name)


# ======================================================================================================
# the test side: the master, and the simulator's clock it steps
# ======================================================================================================
@dataclass
class Frame:
    t: float  # simulated time (s) when it was sent: the start of its period (the last TIME frame before it)
    cob: int
    data: bytes


class Periodic:
    """A frame the master sends every ``period_s`` of simulated time (before the SYNC of a period it falls due in)."""

    def __init__(self, log: FrameLog, msg: can.Message, period_s: float) -> None:
        self.log, self.msg, self.period_s = log, msg, period_s
        self.due_s = log.t_s
        self.last_s: float | None = None  # when it was last sent

    def stop(self) -> None:
        self.log.periodic.remove(self)


class FrameLog(can.Listener):
    """Every frame seen on the bus, and the simulator's lockstep clock as the master drives it
    (docs/LOCKSTEP.md, converting step 8): each SYNC this side sends runs one period of simulated time, which the
    simulator ends with a TIME frame (COB-ID 100h, the simulated time): after it, every frame of the period is here.
    Time passes only in ``step``; a wait looks at the log between periods, so its verdict is the same on a loaded
    machine; the wall clock is only the hang guard of one period (``GUARD_S``)."""

    def __init__(self, send: Callable[[can.Message], None] | None = None) -> None:
        self.frames: list[Frame] = []
        self.cond = threading.Condition()
        self.send = send
        self.t_s = 0.0  # simulated time at the last TIME frame
        self.periods = 0  # TIME frames received
        self.periodic: list[Periodic] = []

    def on_message_received(self, msg: can.Message) -> None:
        with self.cond:
            if msg.arbitration_id == TIME_COB_ID and not msg.is_extended_id:
                t = decode_time_of_day(msg.data)
                assert t is not None, msg
                self.t_s, self.periods = t, self.periods + 1
            self.frames.append(Frame(self.t_s, msg.arbitration_id, bytes(msg.data)))
            self.cond.notify_all()

    def mark(self) -> int:
        with self.cond:
            return len(self.frames)

    def since(self, mark: int, cob: int | None = None) -> list[Frame]:
        with self.cond:
            return [f for f in self.frames[mark:] if cob is None or f.cob == cob]

    def every(self, msg: can.Message, period_s: float) -> Periodic:
        task = Periodic(self, msg, period_s)
        self.periodic.append(task)
        return task

    def step(self, n: int = 1, before: Callable[[], None] | None = None) -> None:
        """Run ``n`` periods: per period the frames due (``every``; ``before``), a SYNC, then its TIME frame."""
        assert self.send is not None
        for _ in range(n):
            for task in self.periodic:
                if self.t_s >= task.due_s - 1e-9:
                    self.send(task.msg)
                    task.last_s, task.due_s = self.t_s, task.due_s + task.period_s
            if before is not None:
                before()
            with self.cond:
                target = self.periods + 1
            self.send(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False))
            end = time.monotonic() + GUARD_S
            with self.cond:
                while self.periods < target:
                    left = end - time.monotonic()
                    assert left > 0, (f"no TIME frame within {GUARD_S:g} s of wall time after the SYNC at "
                                      f"t = {self.t_s} s")
                    self.cond.wait(min(left, 0.05))  # (in slices: a QEMU guest's idle clock leaps to the next timer)

    def sleep(self, seconds: float) -> None:
        self.step(round(seconds / PERIOD_S))

    def until(self, cond: Callable[[], T | None | bool], timeout_s: float, what: str) -> T:
        """``cond()`` once it holds (looked at before every period), within ``timeout_s`` of simulated time."""
        end = self.t_s + timeout_s
        while not (value := cond()):
            assert self.t_s < end - 1e-9, f"no {what} within {timeout_s} s (simulated time)"
            self.step()
        return value  # type: ignore[return-value]

    def wait(self, pred: Callable[[Frame], bool], mark: int, timeout_s: float = 2.0, what: str = "frame") -> Frame:
        def found() -> Frame | None:
            return next((f for f in self.since(mark) if pred(f)), None)
        return self.until(found, timeout_s, what)

    def wait_emcy(self, node: int, code: int, mark: int, timeout_s: float = 2.0) -> Frame:
        return self.wait(lambda f: f.cob == 0x80 + node and struct.unpack_from("<H", f.data)[0] == code, mark,
                         timeout_s, f"EMCY 0x{code:04X} from node {node}")


@dataclass
class Rig:
    bus: UdpMulticastCanBus
    net: canopen.Network
    nodes: dict[int, canopen.RemoteNode]
    log: FrameLog
    boot_mark: int

    def send(self, cob: int, data: bytes = b"") -> None:
        self.bus.send(can.Message(arbitration_id=cob, data=data, is_extended_id=False))

    def sync(self) -> None:
        """A SYNC: one period of the simulator's time (its TIME frame awaited)."""
        self.log.step()

    def nmt(self, command: int, node: int = 0) -> None:
        self.send(0x000, bytes((command, node)))

    def raw_sdo(self, node: int, request: bytes, timeout_s: float = 0.01) -> bytes:
        """One SDO request frame, its response frame (bypassing canopen's client)."""
        mark = self.log.mark()
        self.send(0x600 + node, request)
        return self.log.wait(lambda f: f.cob == 0x580 + node, mark, timeout_s, f"SDO response of node {node}").data

    def wait_bootups(self, mark: int, nodes: tuple[int, ...] = NODES, timeout_s: float = 0.01) -> None:
        for n in nodes:
            self.log.wait(lambda f, n=n: f.cob == 0x700 + n and f.data == b"\x00", mark, timeout_s,
                          f"boot-up of node {n}")

    def reset_all(self) -> None:
        mark = self.log.mark()
        self.nmt(0x81)
        self.wait_bootups(mark)


def counts_per_rad(node_id: int) -> float:
    return DRIVES[node_id].encoder_counts_per_rev / (2.0 * math.pi)


def statusword_state(node: canopen.RemoteNode) -> State:
    return decode_statusword(node.sdo[0x6041].raw)


def wait_state(log: FrameLog, node: canopen.RemoteNode, state: State, timeout_s: float = 3.0) -> float:
    """Poll the statusword before every period until `state`; the simulated time it took."""
    t0 = log.t_s
    log.until(lambda: statusword_state(node) is state, timeout_s, f"node {node.id}: state {state.name}")
    return log.t_s - t0


def walk(log: FrameLog, node: canopen.RemoteNode, target: State, timeout_s: float = 0.1) -> None:
    """Drive the 402 state machine over SDO with next_controlword until `target` (a period between writes that did
    not get there)."""
    previous = 0

    def there() -> bool:
        nonlocal previous
        if (state := statusword_state(node)) is target:
            return True
        previous = next_controlword(state, target, previous)
        node.sdo[0x6040].raw = previous
        return statusword_state(node) is target
    log.until(there, timeout_s, f"node {node.id} on its way to {target.name}")


def abort_code(fn: Callable[[], object]) -> int:
    with pytest.raises(SdoAbortedError) as info:
        fn()
    return info.value.code


@pytest.fixture(scope="module")
def rig() -> Iterator[Rig]:
    group = unique_group(__name__)
    bus = open_bus(parse_bus(f"udp_multicast:{group}", fd=TRUTH.bus.fd))
    assert isinstance(bus, UdpMulticastCanBus)
    log = FrameLog(bus.send)
    net = canopen.Network(bus)
    net.connect()
    net.notifier.add_listener(log)
    nodes = {}
    for n in NODES:
        node = canopen.RemoteNode(n, str(EDS))
        node.sdo.RESPONSE_TIMEOUT = GUARD_S  # (answered at once, between periods: a hang guard)
        net.add_node(node)
        nodes[n] = node
    boot_mark = log.mark()
    try:
        with sim_process(["--bus", f"udp_multicast:{group}", "--lockstep"]):
            r = Rig(bus, net, nodes, log, boot_mark)
            r.wait_bootups(boot_mark)
            yield r
    finally:
        net.disconnect()


@contextmanager
def sim_process(args: list[str]) -> Iterator[list[str]]:
    """``python -m sim run ARGS`` as a child process, up once it said "sim: running"; yields what it wrote to stderr
    (kept drained), and ends it on exit."""
    proc = subprocess.Popen([sys.executable, "-m", "sim", "run", *args],
                            cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    said: list[str] = []
    try:
        assert proc.stderr is not None
        for line in proc.stderr:
            said.append(line)
            if line.startswith("sim: running"):
                break
        assert proc.poll() is None, f"the sim process exited ({proc.returncode}):\n{''.join(said)}"
        threading.Thread(target=lambda: said.extend(proc.stderr), daemon=True).start()  # keep the pipe drained
        yield said
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


@pytest.fixture
def r(rig: Rig) -> Rig:
    """The rig with every node freshly reset (NMT reset node, boot-ups awaited)."""
    rig.reset_all()
    return rig


# ======================================================================================================
# tests
# ======================================================================================================
def test_bootup_frames_of_all_nodes(rig: Rig) -> None:
    for n in NODES:
        ups = [f for f in rig.log.since(rig.boot_mark, 0x700 + n) if f.data == b"\x00"]
        assert ups, f"no boot-up frame from node {n}"
        assert all(len(f.data) == 1 for f in ups)


def test_sdo_expedited_and_segmented(r: Rig) -> None:
    node = r.nodes[2]
    assert node.sdo[0x1000].raw == 0x00020192
    assert node.sdo[0x1018][0].raw == 4
    assert node.sdo[0x6075].raw == round(DRIVES[2].rated_current_A * 1000)  # mA
    assert node.sdo[0x6076].raw == round(DRIVES[2].rated_torque_Nm * 1000)  # mN·m
    assert node.sdo[0x6502].raw & (1 << 9) and node.sdo[0x6502].raw & (1 << 7)
    assert node.sdo[0x1008].raw == "dragd-sim joint drive"  # segmented upload (21 bytes)
    label = "wrist joint, left arm, serial 0042 / revision C"
    node.sdo[0x2000].raw = label  # segmented download
    assert node.sdo[0x2000].raw == label
    node.sdo[0x2000].raw = "ab"  # expedited download of a string
    assert node.sdo[0x2000].raw == "ab"
    node.sdo[0x6072].raw = 1234
    assert node.sdo[0x6072].raw == 1234
    node.sdo[0x6071].raw = -321
    assert node.sdo[0x6071].raw == -321


def test_sdo_abort_codes(r: Rig) -> None:
    sdo = r.nodes[1].sdo
    assert abort_code(lambda: sdo.upload(0x1234, 0)) == 0x06020000
    assert abort_code(lambda: sdo.upload(0x1018, 9)) == 0x06090011
    assert abort_code(lambda: sdo.download(0x6041, 0, b"\x00\x00")) == 0x06010002
    # segmented download of a const object: refused at initiate. (A raw frame: canopen 2.4.1's client leaves a
    # half-built WritableStream behind on this abort whose finalizer sends a segment and blocks on a response.)
    assert r.raw_sdo(1, bytes.fromhex("2108100008000000")) == bytes.fromhex("8008100002000106")
    assert abort_code(lambda: sdo.download(0x6040, 0, b"\x06\x00\x00\x00")) == 0x06070010
    assert abort_code(lambda: sdo.download(0x1029, 1, b"\x07")) == 0x06090030  # above HighLimit 2
    assert abort_code(lambda: sdo.download(0x605A, 0, struct.pack("<h", 4))) == 0x06090030  # voltage limit
    assert sdo[0x1018][0].raw == 4  # the server still answers after aborts


def test_unsupported_mode_aborts_and_supported_mode_shows(r: Rig) -> None:
    sdo = r.nodes[3].sdo
    for mode in (1, 3, 6, 7, -1):  # PP, PV, HM, IP, manufacturer
        assert abort_code(lambda mode=mode: sdo.download(0x6060, 0, struct.pack("<b", mode))) == 0x06090030
    assert sdo[0x6061].raw == 0
    for mode in (10, 8, 4, 9):
        sdo[0x6060].raw = mode
        assert sdo[0x6061].raw == mode


def test_nmt_states_heartbeat_and_reset(r: Rig) -> None:
    node = r.nodes[1]
    hb = 0x701

    def next_heartbeat(mark: int) -> bytes:
        return r.log.wait(lambda f: f.cob == hb, mark, 1.0, "heartbeat of node 1").data

    node.sdo[0x1017].raw = 20
    node.sdo[0x2000].raw = "changed"
    assert next_heartbeat(r.log.mark()) == b"\x7f"
    r.nmt(0x01, 1)
    mark = r.log.mark()
    assert r.log.wait(lambda f: f.cob == hb and f.data == b"\x05", mark, 1.0, "operational heartbeat")
    r.nmt(0x02, 1)
    mark = r.log.mark()
    assert r.log.wait(lambda f: f.cob == hb and f.data == b"\x04", mark, 1.0, "stopped heartbeat")
    mark = r.log.mark()
    r.send(0x601, bytes.fromhex("4000100000000000"))  # no SDO in stopped: a period later, still no answer
    r.sync()
    assert not r.log.since(mark, 0x581)
    r.nmt(0x80, 1)
    mark = r.log.mark()
    assert r.log.wait(lambda f: f.cob == hb and f.data == b"\x7f", mark, 1.0, "pre-operational heartbeat")
    # reset communication: 1000h-1FFFh back to defaults, 2000h kept
    mark = r.log.mark()
    r.nmt(0x82, 1)
    r.wait_bootups(mark, (1,))
    assert node.sdo[0x1017].raw == 0
    assert node.sdo[0x2000].raw == "changed"
    # reset node: everything back to defaults
    node.sdo[0x1017].raw = 20
    mark = r.log.mark()
    r.nmt(0x81, 1)
    r.wait_bootups(mark, (1,))
    assert node.sdo[0x1017].raw == 0
    assert node.sdo[0x2000].raw == "joint"
    quiet_mark = r.log.mark()
    r.log.sleep(0.1)
    assert not r.log.since(quiet_mark, hb), "heartbeats after reset although 1017h = 0"


def _spin_up(log: FrameLog, node: canopen.RemoteNode, torque_permille: int, min_speed_rad_s: float,
             timeout_s: float = 3.0) -> float:
    """CST, operation enabled, torque until the joint turns faster than min_speed; the velocity (rad/s)."""
    node.sdo[0x6060].raw = 10
    walk(log, node, State.OPERATION_ENABLED)
    node.sdo[0x6071].raw = torque_permille

    def fast() -> float | None:
        velocity = node.sdo[0x606C].raw / counts_per_rad(node.id)
        return velocity if abs(velocity) >= min_speed_rad_s else None
    return log.until(fast, timeout_s, f"node {node.id}: {min_speed_rad_s} rad/s under {torque_permille} per mille")


@pytest.mark.parametrize("option", [2, 6, 0])
def test_402_walk_and_quick_stop(r: Rig, option: int) -> None:
    node = r.nodes[6]  # the flange: no gravity load
    assert statusword_state(node) is State.SWITCH_ON_DISABLED
    node.sdo[0x605A].raw = option
    decel_rad_s2 = 4.0
    node.sdo[0x6085].raw = round(decel_rad_s2 * counts_per_rad(6))
    # the walk passes every state on the way
    seen = []
    previous = 0
    while (state := statusword_state(node)) is not State.OPERATION_ENABLED:
        seen.append(state)
        previous = next_controlword(state, State.OPERATION_ENABLED, previous)
        node.sdo[0x6040].raw = previous
    assert seen == [State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON, State.SWITCHED_ON]
    assert node.sdo[0x6041].raw & 0x0610 == 0x0210  # voltage enabled, remote
    walk(r.log, node, State.SWITCH_ON_DISABLED)
    direction = -1 if node.sdo[0x6064].raw > 0 else 1  # stay clear of the hard stops over the runs
    velocity_rad_s = _spin_up(r.log, node, direction * 600, 2.5)
    node.sdo[0x6040].raw = CMD_QUICK_STOP
    if option == 0:
        assert statusword_state(node) is State.SWITCH_ON_DISABLED  # immediately, no ramp
        return
    assert statusword_state(node) is State.QUICK_STOP_ACTIVE
    assert direction * node.sdo[0x606C].raw > 0  # still decelerating under the drive's velocity loop
    if option == 2:
        took_s = wait_state(r.log, node, State.SWITCH_ON_DISABLED)
    else:
        t0 = r.log.t_s
        r.log.until(lambda: node.sdo[0x6041].raw & SW_TARGET_REACHED, 3.0, "standstill of the quick stop (605Ah = 6)")
        took_s = r.log.t_s - t0
        assert statusword_state(node) is State.QUICK_STOP_ACTIVE
    assert took_s > 0.3 * abs(velocity_rad_s) / decel_rad_s2, "stopped faster than the quick stop ramp allows"
    assert abs(node.sdo[0x606C].raw) < 0.05 * counts_per_rad(6)
    if option == 6:
        node.sdo[0x6040].raw = CMD_ENABLE_OPERATION  # transition 16
        assert statusword_state(node) is State.OPERATION_ENABLED


def _configure_master_heartbeat(r: Rig, node: canopen.RemoteNode, timeout_ms: int) -> Periodic:
    task = r.log.every(can.Message(arbitration_id=0x700 + MASTER_ID, data=b"\x05", is_extended_id=False), 0.01)
    node.sdo[0x1016][1].raw = (MASTER_ID << 16) | timeout_ms
    return task


def test_fault_reset_acts_on_rising_edge_only(r: Rig) -> None:
    node = r.nodes[1]
    node.sdo[0x6007].raw = 1  # fault on loss of communication
    task = _configure_master_heartbeat(r, node, 60)
    try:
        r.log.sleep(0.05)
        walk(r.log, node, State.READY_TO_SWITCH_ON)
        node.sdo[0x6040].raw = CMD_SHUTDOWN | CMD_FAULT_RESET  # bit 7 high before the fault: no command
        assert statusword_state(node) is State.READY_TO_SWITCH_ON
        mark = r.log.mark()
    finally:
        task.stop()
    emcy = r.log.wait_emcy(1, 0x8130, mark)
    assert emcy.data[2] & 0x11 == 0x11  # error register: generic + communication
    wait_state(r.log, node, State.FAULT)
    assert node.sdo[0x603F].raw == 0x8130
    node.sdo[0x6040].raw = CMD_FAULT_RESET  # bit 7 still high: no edge
    assert statusword_state(node) is State.FAULT
    node.sdo[0x6040].raw = CMD_DISABLE_VOLTAGE
    assert statusword_state(node) is State.FAULT
    mark = r.log.mark()
    node.sdo[0x6040].raw = CMD_FAULT_RESET  # rising edge
    assert statusword_state(node) is State.SWITCH_ON_DISABLED
    reset = r.log.wait_emcy(1, 0x0000, mark)
    assert reset.data[2] == 0
    assert node.sdo[0x603F].raw == 0 and node.sdo[0x1001].raw == 0


def test_master_heartbeat_loss_quick_stop_and_preoperational(r: Rig) -> None:
    node = r.nodes[1]
    node.sdo[0x6007].raw = 3  # quick stop
    node.sdo[0x1017].raw = 20
    task = _configure_master_heartbeat(r, node, 80)
    try:
        r.log.sleep(0.05)
        r.nmt(0x01, 1)
        node.sdo[0x6060].raw = 10
        walk(r.log, node, State.OPERATION_ENABLED)
        mark = r.log.mark()
    finally:
        task.stop()
    t_last = task.last_s
    assert t_last is not None
    emcy = r.log.wait_emcy(1, 0x8130, mark)
    # the consumer time (80 ms) after the last heartbeat, judged at a period's end: to the period
    assert abs(emcy.t - t_last - 0.080) <= PERIOD_S + 1e-9, emcy.t - t_last
    assert emcy.data[3] == MASTER_ID  # manufacturer byte: the silent node
    r.log.wait(lambda f: f.cob == 0x701 and f.data == b"\x7f" and f.t > emcy.t, mark, 1.0,
               "pre-operational heartbeat after the loss (1029h = 0)")
    state = statusword_state(node)
    assert state in (State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED)
    wait_state(r.log, node, State.SWITCH_ON_DISABLED)
    assert node.sdo[0x1001].raw & 0x10


def test_tpdo_remap_in_preoperational_and_sync(r: Rig) -> None:
    node = r.nodes[2]
    tpdo = node.tpdo[1]
    tpdo.read()
    assert [v.index for v in tpdo.map] == [0x6041, 0x6064, 0x6078]
    # mapping cannot change while the PDO is valid
    assert abort_code(lambda: node.sdo.download(0x1A00, 0, b"\x00")) == 0x08000022
    tpdo.clear()
    tpdo.add_variable(0x6064)
    tpdo.add_variable(0x606C)
    tpdo.trans_type = 2  # every 2nd SYNC
    tpdo.enabled = True
    tpdo.save()
    assert [node.sdo[0x1A00][i].raw for i in range(3)] == [2, 0x60640020, 0x606C0020]
    # invalid mappings are refused with the standard codes
    node.sdo[0x1801][1].raw = node.sdo[0x1801][1].raw | 0x80000000
    node.sdo[0x1A01][0].raw = 0
    assert abort_code(lambda: node.sdo.download(0x1A01, 1, struct.pack("<I", 0x10080008))) == 0x06040041
    assert abort_code(lambda: node.sdo.download(0x1A01, 1, struct.pack("<I", 0x12340010))) == 0x06020000
    assert abort_code(lambda: node.sdo.download(0x1A01, 1, struct.pack("<I", 0x00060010))) == 0x06040041  # dummy
    for sub in range(1, 18):
        node.sdo[0x1A01][sub].raw = 0x60640020  # the same object may be mapped repeatedly
    assert abort_code(lambda: node.sdo.download(0x1A01, 0, bytes((17,)))) == 0x06040042  # 68 bytes > 64 (FD)
    r.nmt(0x01, 2)
    assert abort_code(lambda: node.sdo.download(0x1A01, 0, b"\x00")) == 0x08000022  # operational
    r.log.sleep(0.02)
    mark = r.log.mark()
    sync_times = []
    for _ in range(10):
        sync_times.append(r.log.t_s)
        r.sync()
    frames = r.log.since(mark, 0x182)
    assert len(frames) == 5, [f.data.hex() for f in frames]
    position, velocity = struct.unpack("<ii", frames[-1].data)
    assert abs(position - node.sdo[0x6064].raw) < 0.01 * counts_per_rad(2)  # the shoulder rests on its brake
    assert abs(velocity - node.sdo[0x606C].raw) < 0.05 * counts_per_rad(2)
    # sent on SYNCs 2, 4, ...: in the period that SYNC began
    assert [f.t for f in frames] == [sync_times[2 * k + 1] for k in range(5)], (sync_times, [f.t for f in frames])


def test_event_tpdo_reports_statusword_changes(r: Rig) -> None:
    node = r.nodes[1]
    mark = r.log.mark()
    r.nmt(0x01, 1)
    first = r.log.wait(lambda f: f.cob == 0x281, mark, 1.0, "TPDO2 on start")
    assert decode_statusword(struct.unpack_from("<H", first.data)[0]) is State.SWITCH_ON_DISABLED
    mark = r.log.mark()
    node.sdo[0x6040].raw = CMD_SHUTDOWN
    frame = r.log.wait(lambda f: f.cob == 0x281, mark, 1.0, "TPDO2 after shutdown")
    statusword, mode = struct.unpack("<Hb", frame.data)
    assert decode_statusword(statusword) is State.READY_TO_SWITCH_ON and mode == 0


def _map_rpdo(node: canopen.RemoteNode, number: int, cob: int, words: list[int], trans_type: int = 1,
              event_timer_ms: int = 0) -> None:
    comm, mapping = 0x1400 + number - 1, 0x1600 + number - 1
    node.sdo[comm][1].raw = cob | 0x80000000
    node.sdo[comm][2].raw = trans_type
    node.sdo[comm][5].raw = event_timer_ms
    node.sdo[mapping][0].raw = 0
    for i, word in enumerate(words, start=1):
        node.sdo[mapping][i].raw = word
    node.sdo[mapping][0].raw = len(words)
    node.sdo[comm][1].raw = cob


def test_shared_rpdo_with_dummy_entries(r: Rig) -> None:
    n1, n2 = r.nodes[1], r.nodes[6]
    _map_rpdo(n1, 4, 0x200, [0x60710010, 0x00060010])
    _map_rpdo(n2, 4, 0x200, [0x00060010, 0x60710010])
    for node in (n1, n2):
        node.sdo[0x6060].raw = 10
    r.nmt(0x01)
    r.send(0x200, struct.pack("<hh", 150, -250))
    assert (n1.sdo[0x6071].raw, n2.sdo[0x6071].raw) == (0, 0), "synchronous RPDO applied before SYNC"
    r.sync()
    assert (n1.sdo[0x6071].raw, n2.sdo[0x6071].raw) == (150, -250), "shared RPDO not applied at SYNC"
    # the drives act on it: torque demand follows the target in CST once enabled
    for node in (n1, n2):
        walk(r.log, node, State.OPERATION_ENABLED)
    r.log.sleep(0.02)
    assert n1.sdo[0x6074].raw == 150 and n2.sdo[0x6074].raw == -250
    # a frame shorter than the mapping: EMCY 8210h, not processed
    mark = r.log.mark()
    r.send(0x200, struct.pack("<h", 999))
    r.sync()
    r.log.wait_emcy(1, 0x8210, mark)
    r.log.wait_emcy(6, 0x8210, mark)
    assert n1.sdo[0x6071].raw == 150
    for node in (n1, n2):
        walk(r.log, node, State.SWITCH_ON_DISABLED)


@pytest.mark.parametrize("option, final", [(3, State.SWITCH_ON_DISABLED), (1, State.FAULT)])
def test_rpdo_timeout_reaction(r: Rig, option: int, final: State) -> None:
    node = r.nodes[1]
    node.sdo[0x6007].raw = option
    _map_rpdo(node, 1, 0x201, [0x60400010, 0x60710010], trans_type=1, event_timer_ms=50)
    node.sdo[0x6060].raw = 10
    walk(r.log, node, State.OPERATION_ENABLED)
    r.nmt(0x01, 1)
    command = can.Message(arbitration_id=0x201, data=struct.pack("<Hh", CMD_ENABLE_OPERATION, 0), is_extended_id=False)
    task = r.log.every(command, 0.005)
    r.log.sleep(0.1)  # 100 ms of cyclic commands, every 5th period
    task.stop()
    assert statusword_state(node) is State.OPERATION_ENABLED
    mark = r.log.mark()
    t_last = task.last_s
    assert t_last is not None
    emcy = r.log.wait_emcy(1, 0x8250, mark)
    # the RPDO deadline (1400h sub 5: 50 ms) after the last RPDO, judged at a period's end: to the period
    assert abs(emcy.t - t_last - 0.050) <= PERIOD_S + 1e-9, emcy.t - t_last
    assert emcy.data[3] == 1  # manufacturer byte: RPDO number
    wait_state(r.log, node, final)
    if final is State.FAULT:
        assert node.sdo[0x603F].raw == 0x8250


# ======================================================================================================
# in-process: SDO server edge cases and the 402 walk between every pair of states
# ======================================================================================================
@dataclass
class LocalDrive:
    drive: object
    sent: list[can.Message]

    def sdo(self, request: str) -> str:
        """One SDO request (hex) straight into the drive; the response payload (hex)."""
        from sim.drive import SimDrive

        assert isinstance(self.drive, SimDrive)
        mark = len(self.sent)
        self.drive.on_message(can.Message(arbitration_id=0x600 + self.drive.node_id, data=bytes.fromhex(request),
                                          is_extended_id=False))
        responses = [bytes(m.data).hex() for m in self.sent[mark:] if m.arbitration_id == 0x580 + self.drive.node_id]
        assert len(responses) == 1, responses
        return responses[0]


@pytest.fixture
def local() -> LocalDrive:
    from sim.axis import AxisIO
    from sim.drive import SimDrive
    from sim.truth import drive_params

    sent: list[can.Message] = []
    drive = SimDrive(drive_params(TRUTH.joints[0], fd=False), AxisIO(), sent.append)
    drive.boot()
    return LocalDrive(drive, sent)


def test_sdo_server_edge_cases(local: LocalDrive) -> None:
    node = local.drive.node_id
    assert local.sent[0].arbitration_id == 0x700 + node and bytes(local.sent[0].data) == b"\x00"
    # read of a write-only object
    local.drive.store.var(0x2000, 0).access_type = "wo"
    assert local.sdo("4000200000000000") == "8000200001000106"
    local.drive.store.var(0x2000, 0).access_type = "rw"
    # empty string: segmented upload of 0 bytes
    assert local.sdo("2300200000000000") == "6000200000000000"  # expedited download, 4 bytes of NUL
    assert local.sdo("4000200000000000") == "4100200000000000"
    assert local.sdo("6000000000000000") == "0f00000000000000"
    # segments without an initiated transfer, toggle error, block transfer
    assert local.sdo("0000000000000000") == "8000000001000405"
    assert local.sdo("6000000000000000") == "8000000001000405"
    assert local.sdo("2100200009000000") == "6000200000000000"  # segmented download, 9 bytes announced
    assert local.sdo("1061626364656667") == "8000200000000305"  # toggle must start at 0
    assert local.sdo("a000200000000000") == "8000200001000405"  # block upload not offered
    # announced size differs from the bytes received
    assert local.sdo("2100200009000000") == "6000200000000000"
    assert local.sdo("0061626364656667") == "2000000000000000"
    assert local.sdo("1f68000000000000") == "8000200010000706"  # 8 bytes, 9 announced
    # a normal segmented round trip afterwards
    assert local.sdo("2100200009000000") == "6000200000000000"
    assert local.sdo("0061626364656667") == "2000000000000000"
    assert local.sdo("1b68690000000000") == "3000000000000000"
    assert local.drive.store.get(0x2000) == "abcdefghi"
    # an abort names the transfer's object (1A00h sub 1), also where another part of the dictionary refused it
    # TPDO1 invalid: its mapping may change
    assert local.sdo("23001801" + (0x80000180 + node).to_bytes(4, "little").hex()) == "6000180100000000"
    assert local.sdo("2f001a0000000000") == "60001a0000000000"
    assert local.sdo("23001a0108000810") == "80001a0141000406"  # 1008h (device name) cannot be mapped
    # frames that are not 8 bytes long are ignored
    mark = len(local.sent)
    local.drive.on_message(can.Message(arbitration_id=0x600 + node, data=b"\x40\x00\x10", is_extended_id=False))
    assert len(local.sent) == mark


COMMANDABLE = (State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON, State.SWITCHED_ON, State.OPERATION_ENABLED)


@pytest.mark.parametrize("start", COMMANDABLE)
@pytest.mark.parametrize("target", COMMANDABLE + (State.QUICK_STOP_ACTIVE,))
def test_next_controlword_walks_the_drive_between_states(local: LocalDrive, start: State, target: State) -> None:
    drive = local.drive
    store = drive.store
    store.sdo_write(0x605A, 0, struct.pack("<h", 6))  # quick stop: stay in quick stop active
    store.sdo_write(0x605B, 0, struct.pack("<h", 0))
    store.sdo_write(0x605C, 0, struct.pack("<h", 0))

    def go(to: State) -> None:
        previous = 0
        for step in range(8):
            state = decode_statusword(store.get(0x6041))
            if state is to:
                return
            previous = next_controlword(state, to, previous)
            store.sdo_write(0x6040, 0, struct.pack("<H", previous))
            drive.update(0.001 * step, 0.001)
        raise AssertionError(f"{start.name} -> {to.name}: stuck in {decode_statusword(store.get(0x6041)).name}")

    go(start)
    if target is State.QUICK_STOP_ACTIVE and start is not State.OPERATION_ENABLED:
        store.sdo_write(0x6040, 0, struct.pack("<H", next_controlword(start, target)))
        assert decode_statusword(store.get(0x6041)) is State.SWITCH_ON_DISABLED  # transitions 7 / 10
        return
    go(target)
