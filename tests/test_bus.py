"""dragd.bus on real sockets: the host-local udp_multicast bus across processes, virtual and SocketCAN buses.

The wall-clock tier: these read real sockets until a quiet period (``drain``, ``recv`` timeouts: a frame later than
that counts as absent) and start peer processes — delivery timing on the host. The parsing of bus specs, the
SocketCAN probe and python-can's in-process virtual bus are not: tests/test_bus_offline.py (unit tier)."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time

import can
import canopen
import msgpack
import pytest

from dragd.hardware.bus import (
    DEFAULT_UDP_PORT,
    UdpMulticastCanBus,
    open_bus,
    parse_bus,
    socketcan_available,
)
from dragd.lab.rig import multicast_group

pytestmark = [pytest.mark.rig, pytest.mark.timeout(60)]


def unique_group(name: str) -> str:
    """A multicast group of its own (dragd/lab/rig.py ``multicast_group``: claimed machine-wide, never the docs'
    239.74.163.x): no cross-talk with another test or another test run."""
    return multicast_group(name)


def raw_sender() -> socket.socket:
    """A plain UDP socket that sends to the host-local groups (loopback interface, TTL 0): crafted datagrams."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton("127.0.0.1"))
    return sock


def drain(bus: can.BusABC, quiet_s: float = 0.2) -> list[can.Message]:
    out = []
    while (msg := bus.recv(quiet_s)) is not None:
        out.append(msg)
    return out


# --- udp_multicast across processes ------------------------------------------------------------------------------
_PEER = r"""
import json, sys, can
from dragd.hardware.bus import open_bus, parse_bus
group, n = sys.argv[1], int(sys.argv[2])
bus = open_bus(parse_bus("udp_multicast:" + group))
bus.send(can.Message(arbitration_id=0x7E0, data=b"ready", is_extended_id=False))
got = []
while len(got) < n:
    msg = bus.recv(5.0)
    if msg is None:
        break
    if msg.arbitration_id == 0x7E1 and msg.data == b"hello":
        bus.send(can.Message(arbitration_id=0x7E0, data=b"ready", is_extended_id=False))
        continue
    got.append((msg.arbitration_id, bytes(msg.data).hex()))
for i in range(n):
    bus.send(can.Message(arbitration_id=0x300 + i % 8, data=i.to_bytes(4, "little"), is_extended_id=False))
while bus.recv(0.3) is not None:  # read the loopback echoes of its own frames (dropped, counted)
    pass
c = bus.counters()
bus.shutdown()
print(json.dumps({"got": got, "counters": c.__dict__}))
"""


def test_udp_multicast_between_processes_no_echo_no_duplicates(request: pytest.FixtureRequest) -> None:
    group = unique_group(request.node.name)
    n = 300
    bus = open_bus(parse_bus(f"udp_multicast:{group}"))
    assert isinstance(bus, UdpMulticastCanBus)
    assert bus.rcvbuf_bytes >= 4 * 1024 * 1024, f"receive buffer only {bus.rcvbuf_bytes} B"
    peer = subprocess.Popen([sys.executable, "-c", _PEER, group, str(n)], stdout=subprocess.PIPE, text=True)
    try:
        ready = None
        deadline = time.monotonic() + 15
        while ready is None and time.monotonic() < deadline:
            bus.send(can.Message(arbitration_id=0x7E1, data=b"hello", is_extended_id=False))
            ready = bus.recv(0.2)
        assert ready is not None and ready.arbitration_id == 0x7E0, "peer process did not come up"
        drain(bus, 0.05)  # further 'ready' answers to repeated hellos
        sent = []
        for i in range(n):
            msg = can.Message(arbitration_id=0x100 + i % 16, data=i.to_bytes(4, "little"), is_extended_id=False)
            bus.send(msg)
            sent.append((msg.arbitration_id, bytes(msg.data).hex()))
            if i % 50 == 49:
                time.sleep(0.001)
        received = [m for m in drain(bus, 1.0) if m.arbitration_id != 0x7E0]
        out, _ = peer.communicate(timeout=15)
    finally:
        if peer.poll() is None:
            peer.kill()
    report = json.loads(out)
    got = [tuple(x) for x in report["got"]]
    assert got == sent, "the peer must see every frame once, in order"
    assert [(m.arbitration_id, int.from_bytes(m.data, "little")) for m in received] == \
        [(0x300 + i % 8, i) for i in range(n)], "own frames or duplicates leaked, or frames were lost"
    assert all(m.is_rx and m.channel == group for m in received)
    mine = bus.counters()
    bus.shutdown()
    assert mine.own_echoes_dropped == mine.frames_sent >= n
    assert mine.duplicates_dropped == 0 and mine.gaps == 0 and mine.kernel_drops == 0
    assert mine.frames_received >= n + 1  # the peer's frames and at least one 'ready'
    theirs = report["counters"]
    assert theirs["own_echoes_dropped"] == theirs["frames_sent"]
    assert theirs["duplicates_dropped"] == 0 and theirs["gaps"] == 0 and theirs["foreign_frames"] == 0


def _raw_datagram(arbitration_id: int, stamp: object, data: bytes = b"\x01") -> bytes:
    return msgpack.packb({
        "timestamp": 0.0, "arbitration_id": arbitration_id, "is_extended_id": False, "is_remote_frame": False,
        "is_error_frame": False, "channel": stamp, "dlc": len(data), "data": data, "is_fd": False,
        "bitrate_switch": False, "error_state_indicator": False}, use_bin_type=True)


def test_udp_multicast_drops_duplicates_and_counts_gaps(request: pytest.FixtureRequest) -> None:
    """Datagrams crafted in python-can's wire format, sent from a plain socket on the loopback interface."""
    group = unique_group(request.node.name)
    bus = open_bus(parse_bus(f"udp_multicast:{group}"))
    raw = raw_sender()
    token = 0x5EED0001
    try:
        for seq, cob in ((1, 0x101), (1, 0x101), (2, 0x102), (4, 0x104), (3, 0x103), (3, 0x103), (9, 0x109)):
            raw.sendto(_raw_datagram(cob, token << 32 | seq), (group, DEFAULT_UDP_PORT))
        raw.sendto(_raw_datagram(0x555, None), (group, DEFAULT_UDP_PORT))  # a plain python-can peer
        received = [m.arbitration_id for m in drain(bus, 0.3)]
        counters = bus.counters()
    finally:
        raw.close()
        bus.shutdown()
    assert received == [0x101, 0x102, 0x104, 0x103, 0x109, 0x555]
    assert counters.duplicates_dropped == 2
    assert counters.reordered == 1
    assert counters.gaps == 4  # 5..8 never arrived; 3 arrived late and refilled its gap
    assert counters.foreign_frames == 1
    assert counters.frames_received == 6


def test_udp_multicast_groups_are_isolated(request: pytest.FixtureRequest) -> None:
    group_a = unique_group(request.node.name + "a")
    group_b = unique_group(request.node.name + "b")
    assert group_a != group_b
    a1, a2 = open_bus(parse_bus(f"udp_multicast:{group_a}")), open_bus(parse_bus(f"udp_multicast:{group_a}"))
    b1 = open_bus(parse_bus(f"udp_multicast:{group_b}"))
    try:
        a1.send(can.Message(arbitration_id=0x123, data=b"a", is_extended_id=False))
        got = drain(a2, 0.2)
        assert [m.arbitration_id for m in got] == [0x123]
        assert drain(b1, 0.1) == [] and drain(a1, 0.05) == []
    finally:
        for bus in (a1, a2, b1):
            bus.shutdown()


def test_udp_multicast_fd_frames(request: pytest.FixtureRequest) -> None:
    group = unique_group(request.node.name)
    fd_tx = open_bus(parse_bus(f"udp_multicast:{group}", fd=True))
    fd_rx = open_bus(parse_bus(f"udp_multicast:{group}", fd=True))
    classic = open_bus(parse_bus(f"udp_multicast:{group}"))
    try:
        payload = bytes(range(64))
        fd_tx.send(can.Message(arbitration_id=0x200, data=payload, is_fd=True, bitrate_switch=True,
                               is_extended_id=False))
        (msg,) = drain(fd_rx, 0.2)
        assert msg.is_fd and msg.bitrate_switch and bytes(msg.data) == payload
        assert drain(classic, 0.05) == []
        assert classic.counters().fd_frames_dropped == 1
        with pytest.raises(can.CanOperationError, match="CAN FD frame on a classic-CAN bus"):
            classic.send(can.Message(arbitration_id=0x200, data=payload, is_fd=True, is_extended_id=False))
    finally:
        for bus in (fd_tx, fd_rx, classic):
            bus.shutdown()


def test_udp_multicast_works_under_canopen_network_and_notifier(request: pytest.FixtureRequest) -> None:
    group = unique_group(request.node.name)
    bus = open_bus(parse_bus(f"udp_multicast:{group}"))
    peer = open_bus(parse_bus(f"udp_multicast:{group}"))
    net = canopen.Network(bus)
    net.connect()
    try:
        seen = []
        net.subscribe(0x701, lambda cob, data, t: seen.append(bytes(data)))
        peer.send(can.Message(arbitration_id=0x701, data=b"\x05", is_extended_id=False))
        net.send_message(0x000, b"\x01\x00")
        deadline = time.monotonic() + 2.0
        while not seen and time.monotonic() < deadline:
            time.sleep(0.01)
        assert seen == [b"\x05"]
        assert [m.data for m in drain(peer, 0.2)] == [bytearray(b"\x01\x00")]
    finally:
        net.disconnect()
        peer.shutdown()


def test_udp_multicast_own_echo_dropped_before_decoding(request: pytest.FixtureRequest,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """The echo of our own frame is recognised by its first bytes (sender stamp): it is never unpacked."""
    import dragd.hardware.bus as dbus

    bus = open_bus(parse_bus(f"udp_multicast:{unique_group(request.node.name)}"))
    try:
        def no_unpack(*a: object, **k: object) -> None:
            raise AssertionError("an own echo was msgpack-decoded")

        monkeypatch.setattr(dbus.msgpack, "unpackb", no_unpack)
        for i in range(3):
            bus.send(can.Message(arbitration_id=0x444, data=bytes([i]), is_extended_id=False))
        assert bus.recv(0.2) is None
        c = bus.counters()
        assert c.own_echoes_dropped == 3 and c.undecodable == 0
    finally:
        bus.shutdown()


def test_udp_multicast_own_echo_is_dropped_in_the_kernel(request: pytest.FixtureRequest) -> None:
    """The socket filter drops our echoes before they are queued: the socket never becomes readable for them, the
    kernel's drop counter (which counts filtered datagrams) does not report them as losses, and a peer's frames —
    also one that merely starts like a frame of ours up to the sender token — still arrive."""
    import select as _select

    group = unique_group(request.node.name)
    spec = parse_bus(f"udp_multicast:{group}")
    bus, peer = open_bus(spec, batch_frames=True), open_bus(spec)
    try:
        for i in range(20):
            bus.send(can.Message(arbitration_id=0x444, data=bytes([i]), is_extended_id=False))
        with bus.batch():
            for msg in _frames(6):
                bus.send(msg)
        ready, _, _ = _select.select([bus.fileno()], [], [], 0.2)
        assert ready == [], "an own echo reached the socket's queue"
        assert len(drain(peer, 0.3)) == 26
        # our layout with the token's last bit flipped, and a datagram shorter than the stamp: both get through
        fields = msgpack.unpackb(_raw_datagram(0x555, None, b"\x09"))
        fields["channel"] = ((bus._token ^ 1) << 32) | 7
        lookalike = msgpack.packb({"channel": fields.pop("channel"), **fields}, use_bin_type=True)
        assert lookalike[:13] == bus._own_prefix[:13] and lookalike[13] != bus._own_prefix[13]
        raw = raw_sender()
        try:
            raw.sendto(lookalike, (group, DEFAULT_UDP_PORT))
            raw.sendto(bus._own_prefix[:9], (group, DEFAULT_UDP_PORT))
        finally:
            raw.close()
        peer.send(can.Message(arbitration_id=0x321, data=b"\x01", is_extended_id=False))
        got = drain(bus, 0.3)
        assert sorted(m.arbitration_id for m in got) == [0x321, 0x555]
        c = bus.counters()
        assert c.own_echoes_dropped == c.frames_sent == 26 and c.datagrams_sent == 21
        assert c.undecodable == 1, "the short datagram must reach the bus (and be counted), not be filtered"
        assert c.kernel_drops == 0, "filtered echoes counted as losses"
    finally:
        bus.shutdown()
        peer.shutdown()


def test_udp_multicast_receive_own_messages_returns_the_echo(request: pytest.FixtureRequest) -> None:
    """With receive_own_messages the echo comes back (marked not rx) instead of being dropped before decoding."""
    group = unique_group(request.node.name)
    spec = parse_bus(f"udp_multicast:{group}")
    own, plain = open_bus(spec, receive_own_messages=True), open_bus(spec)
    try:
        own.send(can.Message(arbitration_id=0x222, data=b"\x05\x06", is_extended_id=False))
        echo = own.recv(1.0)
        assert echo is not None and echo.arbitration_id == 0x222 and bytes(echo.data) == b"\x05\x06"
        assert echo.is_rx is False
        got = plain.recv(1.0)
        assert got is not None and got.arbitration_id == 0x222 and got.is_rx
        plain.send(can.Message(arbitration_id=0x333, data=b"\x07", is_extended_id=False))
        assert plain.recv(0.2) is None, "own frame echoed on the bus without receive_own_messages"
        assert plain.counters().own_echoes_dropped == 1
    finally:
        own.shutdown()
        plain.shutdown()


# --- batched datagrams (the simulated drives' SYNC answers) -----------------------------------------------
def _frames(n: int, base: int = 0x181) -> list[can.Message]:
    return [can.Message(arbitration_id=base + i, data=bytes([i, 0xA5, i]), is_extended_id=False) for i in range(n)]


def test_udp_multicast_batch_leaves_as_one_datagram_and_arrives_as_frames(request: pytest.FixtureRequest) -> None:
    """Six frames sent in a batch: one datagram; a peer gets six frames in order (recv and drain), none lost."""
    spec = parse_bus(f"udp_multicast:{unique_group(request.node.name)}")
    tx, rx, rx2 = open_bus(spec, batch_frames=True), open_bus(spec), open_bus(spec)
    try:
        with tx.batch():
            for msg in _frames(6):
                tx.send(msg)
            assert rx.recv(0.1) is None, "a frame left before the batch ended"
        got = drain(rx, 0.3)
        assert [(m.arbitration_id, bytes(m.data)) for m in got] == [(m.arbitration_id, bytes(m.data))
                                                                    for m in _frames(6)]
        assert all(m.is_rx and m.timestamp > 0 for m in got)
        time.sleep(0.05)
        data, others = [], []
        assert rx2.drain(lambda cob, d: cob < 0x184 and not data.append((cob, bytes(d))), others.append) == 1
        assert [c for c, _ in data] == [0x181, 0x182, 0x183] and [m.arbitration_id for m in others] == [0x184, 0x185,
                                                                                                           0x186]
        c = tx.counters()
        assert c.frames_sent == 6 and c.datagrams_sent == 1
        assert tx.recv(0.1) is None and tx.counters().own_echoes_dropped == 6, "own batch must be dropped whole"
        for r in (rx, rx2):
            rc = r.counters()
            assert rc.frames_received == 6 and rc.gaps == 0 and rc.reordered == 0 and rc.undecodable == 0
    finally:
        for b in (tx, rx, rx2):
            b.shutdown()


def test_udp_multicast_prepared_batch_is_the_batch_on_the_wire(request: pytest.FixtureRequest) -> None:
    """A prepared datagram (the daemon's command frames + SYNC) carries what ``send`` inside ``batch()`` would: the
    same bytes but the stamps, which go on counting (no gap, no duplicate at the receiver); payloads as written
    before each send; a batch larger than one datagram is refused."""
    from dragd.hardware.bus import DATAGRAM_MAX

    spec = parse_bus(f"udp_multicast:{unique_group(request.node.name)}")
    tx, rx = open_bus(spec, batch_frames=True), open_bus(spec)
    try:
        frames = [can.Message(arbitration_id=0x201 + i, data=bytes([i, 2 * i, 0xA5]), is_extended_id=False)
                  for i in range(3)] + [can.Message(arbitration_id=0x080, data=b"", is_extended_id=False)]
        prepared = tx.prepare([(m.arbitration_id, len(m.data), False) for m in frames])
        assert [len(v) for v in prepared.data] == [3, 3, 3, 0]
        with tx.batch():
            for m in frames:
                tx.send(m)
        for k in range(2):
            for i in range(3):
                prepared.data[i][:] = bytes([i, 2 * i + k, 0xA5])
            tx.send_prepared(prepared)
        got = drain(rx, 0.3)
        sent = [(m.arbitration_id, bytes(m.data)) for m in frames]
        again = [(0x201 + i, bytes([i, 2 * i + 1, 0xA5])) for i in range(3)] + [(0x080, b"")]
        assert [(m.arbitration_id, bytes(m.data)) for m in got] == sent + sent + again
        c = rx.counters()
        assert c.frames_received == 12 and c.gaps == 0 and c.duplicates_dropped == 0 and c.undecodable == 0
        assert tx.counters().frames_sent == 12 and tx.counters().datagrams_sent == 3
        # byte for byte, the sequence numbers aside: the datagram ``batch()`` packs
        for i in range(3):
            prepared.data[i][:] = frames[i].data
        with tx.batch():
            for m in frames:
                tx.send(m)
            held = b"".join(tx._local.held)  # packed, stamped only when the block ends

        def without_seq(datagram: bytes | bytearray) -> bytes:
            out = bytearray(datagram)
            for at in prepared.stamps:
                out[at + 4:at + 8] = bytes(4)  # (the token, the high half, stays)
            return bytes(out)

        assert without_seq(prepared.datagram) == without_seq(held)
        with pytest.raises(ValueError, match="fit one datagram"):
            tx.prepare([(0x201, 64, False)] * (DATAGRAM_MAX // 64 + 1))
    finally:
        tx.shutdown()
        rx.shutdown()


def test_udp_multicast_batch_is_off_by_default_and_per_thread(request: pytest.FixtureRequest) -> None:
    """Without batch_frames a batch block changes nothing (python-can's tools read every datagram); with it,
    a frame another thread sends during the block leaves at once, before the batch."""
    import threading

    spec = parse_bus(f"udp_multicast:{unique_group(request.node.name)}")
    plain, batching, rx = open_bus(spec), open_bus(spec, batch_frames=True), open_bus(spec)
    try:
        with plain.batch():
            for msg in _frames(3):
                plain.send(msg)
        assert plain.counters().datagrams_sent == 3
        assert [m.arbitration_id for m in drain(rx, 0.3)] == [0x181, 0x182, 0x183]
        with batching.batch():
            batching.send(_frames(1, 0x201)[0])
            t = threading.Thread(target=batching.send, args=(_frames(1, 0x301)[0],))
            t.start()
            t.join()
            with batching.batch():  # nested: part of the outer batch
                batching.send(_frames(1, 0x202)[0])
        assert [m.arbitration_id for m in drain(rx, 0.3)] == [0x301, 0x201, 0x202]
        c, rc = batching.counters(), rx.counters()
        assert c.frames_sent == 3 and c.datagrams_sent == 2
        assert rc.gaps == 0 and rc.reordered == 0, "sequence numbers must follow the order frames leave in"
    finally:
        for b in (plain, batching, rx):
            b.shutdown()


def test_udp_multicast_broken_frame_in_a_batch_is_counted(request: pytest.FixtureRequest) -> None:
    """A datagram whose second map is cut short: the first frame is delivered, the break counted, nothing hangs."""
    group = unique_group(request.node.name)
    rx = open_bus(parse_bus(f"udp_multicast:{group}"))
    sock = raw_sender()
    try:
        frame = {"channel": 7 << 32 | 1, "timestamp": 0.0, "arbitration_id": 0x181, "is_extended_id": False,
                 "is_remote_frame": False, "is_error_frame": False, "dlc": 1, "data": b"\x01", "is_fd": False,
                 "bitrate_switch": False, "error_state_indicator": False}
        second = msgpack.packb({**frame, "channel": 7 << 32 | 2, "arbitration_id": 0x182}, use_bin_type=True)
        not_a_map = msgpack.packb({**frame, "channel": 7 << 32 | 3}, use_bin_type=True) + msgpack.packb([1, 2])
        sock.sendto(msgpack.packb(frame, use_bin_type=True) + second[:-3], (group, DEFAULT_UDP_PORT))
        sock.sendto(not_a_map, (group, DEFAULT_UDP_PORT))
        got = drain(rx, 0.3)
        assert [(m.arbitration_id, bytes(m.data)) for m in got] == [(0x181, b"\x01"), (0x181, b"\x01")]
        c = rx.counters()
        assert c.undecodable == 2 and c.frames_received == 2
    finally:
        sock.close()
        rx.shutdown()


def test_udp_multicast_batch_takes_each_frame_as_sent_and_oversize_datagrams_are_counted(
        request: pytest.FixtureRequest) -> None:
    """A frame object reused inside a batch (a caller's preallocated buffer) leaves as it was at each send; a datagram
    longer than the bus reads (DATAGRAM_MAX) is counted, not half-decoded in silence."""
    from dragd.hardware.bus import DATAGRAM_MAX

    group = unique_group(request.node.name)
    spec = parse_bus(f"udp_multicast:{group}")
    tx, rx = open_bus(spec, batch_frames=True), open_bus(spec)
    sock = raw_sender()
    try:
        msg = can.Message(arbitration_id=0x201, data=bytearray(b"\x01\x02"), is_extended_id=False)
        with tx.batch():
            tx.send(msg)
            msg.data[0] = 0x7F
            tx.send(msg)
        assert [bytes(m.data) for m in drain(rx, 0.3)] == [b"\x01\x02", b"\x7f\x02"]
        sock.sendto(b"\x00" * (DATAGRAM_MAX + 100), (group, DEFAULT_UDP_PORT))
        sock.sendto(b"", (group, DEFAULT_UDP_PORT))
        assert drain(rx, 0.3) == []
        assert rx.counters().undecodable == 2
    finally:
        sock.close()
        tx.shutdown()
        rx.shutdown()


# --- virtual and SocketCAN ---------------------------------------------------------------------------------
def test_socketcan_vcan_roundtrip() -> None:
    ok, reason = socketcan_available("vcan0")
    if not ok:
        pytest.skip(f"SocketCAN vcan0 unavailable: {reason}")
    a, b = open_bus(parse_bus("socketcan:vcan0")), open_bus(parse_bus("socketcan:vcan0"))
    try:
        a.send(can.Message(arbitration_id=0x123, data=b"\x42", is_extended_id=False))
        msg = b.recv(1.0)
        assert msg is not None and msg.arbitration_id == 0x123
    finally:
        a.shutdown()
        b.shutdown()


def test_udp_multicast_send_data_is_send_without_a_message(request: pytest.FixtureRequest) -> None:
    """``send_data`` (the simulated drives' PDOs) puts the same bytes on the wire as ``send`` of the equivalent
    ``can.Message`` — classic and FD, empty to 64 bytes, alone and inside a batch — and a classic bus refuses FD."""
    spec = parse_bus(f"udp_multicast:{unique_group(request.node.name)}", fd=True)
    tx, rx = open_bus(spec, batch_frames=True), open_bus(spec)
    try:
        for cob, n, fd in ((0x181, 8, False), (0x281, 0, False), (0x381, 12, True), (0x481, 64, True)):
            data = bytes((7 * i + cob) & 0xFF for i in range(n))
            msg = can.Message(arbitration_id=cob, data=data, is_extended_id=False, is_fd=fd, bitrate_switch=fd)
            head, tail = tx._template(cob, n, fd)
            assert head + data + tail == bytes(tx._pack(msg)), (cob, n, fd)
        frames = [(0x181 + i, bytes([i] * 8)) for i in range(6)]
        with tx.batch():
            for cob, data in frames:
                tx.send_data(cob, data)
        tx.send_data(0x381, bytes(range(12)), fd=True)
        got = drain(rx, 0.3)
        assert [(m.arbitration_id, bytes(m.data), m.is_fd) for m in got] == \
            [(c, d, False) for c, d in frames] + [(0x381, bytes(range(12)), True)]
        assert all(not m.is_extended_id and not m.is_remote_frame and m.bitrate_switch == m.is_fd for m in got)
        c = tx.counters()
        assert c.frames_sent == 7 and c.datagrams_sent == 2 and rx.counters().gaps == 0
    finally:
        tx.shutdown()
        rx.shutdown()
    classic = open_bus(parse_bus(f"udp_multicast:{unique_group(request.node.name + 'c')}"))
    try:
        with pytest.raises(can.CanOperationError, match="CAN FD"):
            classic.send_data(0x181, bytes(8), fd=True)
    finally:
        classic.shutdown()


def test_udp_multicast_expected_frames_are_read_as_the_msgpack_path_reads_them(request: pytest.FixtureRequest) -> None:
    """``expect``: a datagram of expected frames is read by comparing bytes with the frames' templates, anything
    else by unpacking maps — a bus that expects and one that does not, on the same datagrams (prepared batches,
    single frames, wrong lengths, mixed and foreign datagrams, duplicates, reordering, gaps, a cut-short and a
    broken datagram, FD on a classic bus, another sender's gap, reorder and duplicate, a frame without a sender token,
    our own frame inside another sender's datagram, a decoder that raises), hand over the same frames and count
    the same."""
    import random

    group = unique_group(request.node.name)
    spec = parse_bus(f"udp_multicast:{group}")
    tx, tx2 = open_bus(spec, batch_frames=True), open_bus(spec, batch_frames=True)
    fd_tx = open_bus(parse_bus(f"udp_multicast:{group}", fd=True))
    fast, plain = open_bus(spec), open_bus(spec)
    plain._token, plain._own_prefix = fast._token, fast._own_prefix  # (one token: our own echo inside a datagram)
    fd_spec = parse_bus(f"udp_multicast:{group}", fd=True)
    fast_fd, plain_fd = open_bus(fd_spec), open_bus(fd_spec)  # (an FD bus: both kinds of a TPDO expected)
    raw = raw_sender()
    tpdos = [(0x181 + i, 8) for i in range(6)]
    others = [(0x80, 0, False), (0x201, 6, False), (0x381, 12, True)]
    fast.expect([(cob, n, False) for cob, n in tpdos] + others)
    fast_fd.expect([(cob, n, kind) for cob, n in tpdos for kind in (True, False)] + others)
    rng = random.Random(7)
    sent: list[bytes] = []  # every datagram the senders' sockets put on the wire, as it left (replayed below)
    try:
        for bus in (tx, tx2, fd_tx):
            real = bus._sock.sendto
            bus._sock = _Tap(bus._sock, sent)
            assert bus._sock.sendto is not real
        batch = tx.prepare([(cob, n, False) for cob, n in tpdos] + [(0x80, 0, False)])
        for k in range(40):
            for view in batch.data:
                view[:] = bytes(rng.randrange(256) for _ in range(len(view)))
            tx.send_prepared(batch)  # the expected datagram
            tx2.send_data(0x201, bytes(rng.randrange(256) for _ in range(6)))  # another sender, expected
            if k % 5 == 0:
                tx.send_data(0x181, bytes(7))  # an expected id with another length: msgpack path
                tx2.send(can.Message(arbitration_id=0x182, data=bytes(8), is_extended_id=False, timestamp=1.5))
                with tx.batch():  # mixed: one expected and one other frame (0x701 heartbeat) in one datagram
                    tx.send_data(0x183, bytes(8))
                    tx.send_data(0x701, b"\x05")
                fd_tx.send_data(0x381, bytes(range(12)), fd=True)  # FD on the classic receivers: dropped, counted
                fd_tx.send_data(0x181, bytes(8), fd=True)  # ... also where it differs from a template after the data
                tx.send(can.Message(arbitration_id=0x1ABCDEF, data=b"\x01", is_extended_id=True))
        for d in (sent[3], sent[3], sent[10], sent[2]):  # replays (duplicates, too late by now)
            raw.sendto(d, (group, DEFAULT_UDP_PORT))
        raw.sendto(sent[0][:-3], (group, DEFAULT_UDP_PORT))  # cut short (a duplicate by its stamps, if whole)
        raw.sendto(b"\x8b\xa7channel\xcf" + bytes(20), (group, DEFAULT_UDP_PORT))  # broken
        raw.sendto(_raw_datagram(0x181, None, bytes(8)), (group, DEFAULT_UDP_PORT))  # a plain python-can peer

        def framed(stamp: int, cob: int = 0x201, data: bytes = bytes(6)) -> bytes:  # a frame as our senders pack it
            before, after = tx._parts(cob, len(data), False)
            return before[:10] + stamp.to_bytes(8, "big") + before[18:] + data + after

        z = 0x5EED0002 << 32
        for seq in (1, 2, 4, 3, 3, 9, 30):  # another sender within the window: a gap, a reorder, a duplicate
            raw.sendto(framed(z | seq, data=bytes([seq] * 6)), (group, DEFAULT_UDP_PORT))
        raw.sendto(framed(0, 0x182, bytes(8)), (group, DEFAULT_UDP_PORT))  # no sender token: a foreign frame
        # our own frame after another sender's in one datagram: dropped as our echo, the other delivered
        raw.sendto(framed(z | 31) + framed(fast._token << 32 | 77), (group, DEFAULT_UDP_PORT))
        fast._sock.sendto(sent[1], (group, DEFAULT_UDP_PORT))  # a datagram of another sender sent by us (not echo)
        time.sleep(0.3)

        def read(bus: UdpMulticastCanBus) -> tuple[list[tuple[int, bytes]], list[tuple], dict]:
            data, msgs = [], []

            def on_data(cob: int, payload: bytes | bytearray) -> bool:
                if cob in (0x183, 0x201):
                    return False  # not claimed: becomes a can.Message
                if cob == 0x185:
                    raise TypeError("a decoder that cannot take it")  # counted as undecodable, the rest goes on
                data.append((cob, bytes(payload)))
                return True

            def on_message(m: can.Message) -> None:
                msgs.append((m.arbitration_id, bytes(m.data), m.dlc, m.is_extended_id, m.is_remote_frame,
                             m.is_error_frame, m.is_fd, m.bitrate_switch, m.error_state_indicator, m.is_rx,
                             m.channel))

            while bus.drain(on_data, on_message, limit=7):
                pass
            return data, msgs, bus.counters().__dict__

        got_fast, got_plain = read(fast), read(plain)
        got_fast_fd, got_plain_fd = read(fast_fd), read(plain_fd)
    finally:
        raw.close()
        for bus in (tx, tx2, fd_tx, fast, plain, fast_fd, plain_fd):
            bus.shutdown()
    templated = got_fast[2].pop("template_datagrams"), got_plain[2].pop("template_datagrams")
    templated_fd = got_fast_fd[2].pop("template_datagrams"), got_plain_fd[2].pop("template_datagrams")
    # 40 batches, 40 frames 0x201, the batch and the 0x201 replayed, the 9 crafted datagrams; on the FD bus also 8 FD
    # 0x381 and 8 FD 0x181
    assert templated == (91, 0) and templated_fd == (107, 0)
    assert got_fast_fd == got_plain_fd
    assert got_fast_fd[2]["fd_frames_dropped"] == 0 and (0x181, bytes(8)) in got_fast_fd[0]
    assert got_fast == got_plain
    data, msgs, counters = got_fast
    assert len(data) > 40 * 5 and {cob for cob, _ in data} >= {0x80, 0x182, 0x701} and {m[0] for m in msgs} == \
        {0x183, 0x201, 0x1ABCDEF}  # (0x183, 0x201 not claimed by on_data; the 29-bit frame never offered to it)
    assert counters["duplicates_dropped"] >= 3 and counters["fd_frames_dropped"] == 16
    assert counters["reordered"] == 1 and counters["gaps"] == 4 + 20  # (5..8 and 10..29 of the crafted sender)
    assert counters["undecodable"] >= 2 + 40 and counters["foreign_frames"] == 2
    assert counters["own_echoes_dropped"] == 1 and (0x201, bytes([31] * 6)) not in data


class _Tap:
    """A socket whose sendto also keeps a copy of each datagram (what left, to replay it)."""

    def __init__(self, sock: socket.socket, out: list[bytes]) -> None:
        self._sock, self._out = sock, out

    def sendto(self, data: bytes | bytearray, dest: tuple[str, int]) -> int:
        self._out.append(bytes(data))
        return self._sock.sendto(data, dest)

    def __getattr__(self, name: str):  # noqa: ANN204
        return getattr(self._sock, name)
