"""The simulated drives on real SocketCAN against a real CANopen master stack (python-can socketcan + canopen).

The protocol tests are tests/test_sim_canopen.py's own, imported unchanged: here their ``rig`` fixture is a
python-can ``SocketcanBus`` on ``DRAGD_VCAN_BUS`` (CAN_RAW socket, CAN FD frames enabled) and the simulator
process (``python -m sim run --bus socketcan:vcan0 --lockstep``) runs on ``DRAGD_VCAN_SIM_BUS``, its clock stepped by
the test's SYNCs as on the host (test_sim_canopen.FrameLog: the TIME frame of each period crosses the kernel too).
Covered: boot-up, SDO (expedited, segmented, aborts), NMT and heartbeats, the 402 walk and quick stop, master heartbeat
loss, TPDO remap in pre-operational and TPDOs on SYNC, event TPDOs, the shared RPDO with dummy entries, the RPDO-timeout
reaction. Plus SocketCAN specifics: kernel CAN_RAW filters, error frames, CAN FD frames on the wire.
"""

from __future__ import annotations

import struct
import threading
import time
from collections.abc import Iterator

import can
import canopen
import pytest
import test_sim_canopen as base
from can.interfaces.socketcan import SocketcanBus
from test_sim_canopen import (  # noqa: F401  (pytest collects the imported tests here, with this module's rig)
    r,
    test_402_walk_and_quick_stop,
    test_bootup_frames_of_all_nodes,
    test_event_tpdo_reports_statusword_changes,
    test_fault_reset_acts_on_rising_edge_only,
    test_master_heartbeat_loss_quick_stop_and_preoperational,
    test_nmt_states_heartbeat_and_reset,
    test_rpdo_timeout_reaction,
    test_sdo_abort_codes,
    test_sdo_expedited_and_segmented,
    test_shared_rpdo_with_dummy_entries,
    test_tpdo_remap_in_preoperational_and_sync,
    test_unsupported_mode_aborts_and_supported_mode_shows,
)

from dragd.hardware.bus import open_bus, parse_bus
from dragd.lab.rig import Rig as Processes

from .conftest import BUS, PHYSICS_HZ, SIM_BUS, START_TIMEOUT_S, channel, net_stat, vcan_only

pytestmark = pytest.mark.timeout(600)


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[base.Rig]:
    """test_sim_canopen's Rig on SocketCAN: the client's bus, canopen network, frame log; the sim process."""
    bus = open_bus(parse_bus(BUS, fd=base.TRUTH.bus.fd))
    assert isinstance(bus, SocketcanBus), type(bus)
    log = base.FrameLog(bus.send)
    net = canopen.Network(bus)
    net.connect()
    net.notifier.add_listener(log)
    nodes = {}
    for n in base.NODES:
        node = canopen.RemoteNode(n, str(base.EDS))
        node.sdo.RESPONSE_TIMEOUT = base.GUARD_S
        net.add_node(node)
        nodes[n] = node
    boot_mark = log.mark()
    sim = Processes("vcan-canopen", workdir=tmp_path_factory.mktemp("canopen"), bus=SIM_BUS,
                    sim_args=["--physics-rate-Hz", str(PHYSICS_HZ)], lockstep=True)
    try:
        sim.start_sim(timeout_s=START_TIMEOUT_S)
        r = base.Rig(bus, net, nodes, log, boot_mark)
        r.wait_bootups(boot_mark)
        yield r
    finally:
        sim.close()
        net.disconnect()


def test_the_client_bus_is_socketcan_with_fd(rig: base.Rig) -> None:
    assert isinstance(rig.bus, SocketcanBus)
    assert rig.bus.protocol is can.CanProtocol.CAN_FD
    assert rig.bus.channel == channel(BUS)
    chan = channel(BUS)
    tx0 = net_stat(chan, "tx_packets")
    rig.nodes[1].sdo[0x1000].raw  # noqa: B018 - one SDO round trip
    if chan.startswith("vcan"):
        assert net_stat(chan, "tx_packets") - tx0 >= 2  # request + response went through the interface


def test_fd_frames_cross_the_bus(rig: base.Rig) -> None:
    """A 64-byte CAN FD frame (BRS) sent on one SocketCAN socket arrives intact on another."""
    other = open_bus(parse_bus(SIM_BUS, fd=True))
    try:
        payload = bytes(range(64))
        rig.bus.send(can.Message(arbitration_id=0x4F0, data=payload, is_fd=True, bitrate_switch=True,
                                 is_extended_id=False))
        end = time.monotonic() + 5.0
        while time.monotonic() < end:
            msg = other.recv(0.5)
            if msg is not None and msg.arbitration_id == 0x4F0:
                assert msg.is_fd and msg.dlc == 64 and bytes(msg.data) == payload
                return
        raise AssertionError("the CAN FD frame did not arrive")
    finally:
        other.shutdown()


def test_kernel_can_raw_filters(rig: base.Rig) -> None:
    """CAN_RAW filters are applied by the kernel: a socket filtered to node 3's heartbeat gets only that."""
    filtered = can.Bus(interface="socketcan", channel=channel(BUS), fd=True,
                       can_filters=[{"can_id": 0x703, "can_mask": 0x7FF, "extended": False}])
    try:
        assert filtered._is_filtered  # noqa: SLF001 - set only when the kernel accepted CAN_RAW_FILTER
        rig.nodes[3].sdo[0x1017].raw = 10  # node 3: heartbeat every 10 ms
        rig.nodes[2].sdo[0x1017].raw = 10
        seen: set[int] = set()
        rig.log.sleep(0.1)  # 100 periods: ten heartbeats of each, and the SYNCs and TIME frames
        while (msg := filtered.recv(0.1)) is not None:
            seen.add(msg.arbitration_id)
        assert seen == {0x703}, sorted(hex(c) for c in seen)
    finally:
        rig.nodes[3].sdo[0x1017].raw = 0
        rig.nodes[2].sdo[0x1017].raw = 0
        filtered.shutdown()


@vcan_only
def test_error_frames_reach_sockets_and_canopen_ignores_them(rig: base.Rig) -> None:
    """An error frame (CAN_ERR_FLAG) is delivered to python-can's sockets (error filter: all classes) and is
    not taken for a CANopen frame by canopen's listener, even where its class bits equal a COB-ID."""
    listener = open_bus(parse_bus(BUS, fd=True))
    got: list[can.Message] = []
    stop = threading.Event()

    def pump() -> None:
        while not stop.is_set():
            msg = listener.recv(0.05)
            if msg is not None and msg.is_error_frame:
                got.append(msg)

    thread = threading.Thread(target=pump, daemon=True)
    thread.start()
    try:
        mark = rig.log.mark()
        # class bits 0x080 (bus error) | 0x001 (TX timeout) = 0x081, node 1's EMCY COB-ID
        rig.bus.send(can.Message(arbitration_id=0x081, is_error_frame=True,
                                 data=bytes([0x10, 0x23, 0x11, 0, 0, 0, 0, 0]),
                                 is_extended_id=False))
        end = time.monotonic() + 3.0
        while not got and time.monotonic() < end:
            time.sleep(0.01)
        assert got, "the error frame did not reach a second SocketCAN socket"
        assert got[0].is_error_frame and got[0].arbitration_id == 0x081
        time.sleep(0.1)
        assert not [f for f in rig.log.since(mark) if f.cob == 0x081], "canopen's notifier passed an error frame on"
        assert rig.nodes[1].sdo[0x1000].raw == 0x00020192  # the client still works
    finally:
        stop.set()
        thread.join(2)
        listener.shutdown()


def test_sync_tpdo_round_trip_through_the_kernel(rig: base.Rig) -> None:
    """All six drives answer one SYNC with their TPDO1 (statusword, position, current) via vcan0."""
    rig.reset_all()
    rig.nmt(0x01)
    rig.log.sleep(0.05)
    mark = rig.log.mark()
    rig.sync()
    for n in base.NODES:
        frame = rig.log.wait(lambda f, n=n: f.cob == 0x180 + n, mark, 2.0, f"TPDO1 of node {n}")
        statusword, position, _current = struct.unpack("<Hih", frame.data[:8])
        assert base.decode_statusword(statusword) is base.State.SWITCH_ON_DISABLED
        assert abs(position - rig.nodes[n].sdo[0x6064].raw) < 0.01 * base.counts_per_rad(n)
    rig.nmt(0x80)
