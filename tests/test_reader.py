"""dragd.hardware.reader: the draining notifier hands the cycle's TPDOs over without can.Message objects.

In-process (two udp_multicast buses or a virtual bus, one asyncio loop); no wall-clock assertions.
"""

from __future__ import annotations

import asyncio
import os
import socket
import struct

import can
import pytest

from dragd.hardware.bus import open_bus, parse_bus
from dragd.hardware.reader import BusReader
from dragd.lab.rig import multicast_group

pytestmark = pytest.mark.unit


def _group(name: str) -> str:
    """A private group per call (pid- and time-derived, never one given before in this process): two runs of this
    module at once (two checkouts, xdist workers) do not share a group."""
    return multicast_group(f"reader:{name}")


def test_groups_of_the_same_test_differ() -> None:
    """The same test name twice (as two concurrent runs of it would ask) gives two groups, each a valid private one."""
    groups = [_group("test_x") for _ in range(200)]
    assert len(set(groups)) == len(groups)
    for g in groups:
        parse_bus(f"udp_multicast:{g}")  # (an address dragd's bus takes)
        a, b, c, d = map(int, g.split("."))
        assert (a, b) == (239, 74) and 0 <= c <= 255 and 1 <= d <= 254


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("", 0))
        return int(s.getsockname()[1])


class _Collect(can.Listener):
    def __init__(self) -> None:
        self.got: list[tuple[int, bytes, bool, bool]] = []

    def on_message_received(self, msg: can.Message) -> None:
        self.got.append((msg.arbitration_id, bytes(msg.data), msg.is_extended_id, msg.is_remote_frame))


FRAMES = [
    can.Message(arbitration_id=0x181, data=b"\x01\x02\x03\x04", is_extended_id=False),  # claimed
    can.Message(arbitration_id=0x701, data=b"\x05", is_extended_id=False),  # offered, refused
    can.Message(arbitration_id=0x181, data=b"\x09", is_extended_id=True),  # extended: never offered
    can.Message(arbitration_id=0x182, is_remote_frame=True, dlc=0, is_extended_id=False),  # remote: never offered
    can.Message(arbitration_id=0x182, data=b"\xAA\xBB", is_extended_id=False),  # claimed
]


async def _run(bus: can.BusABC, peer: can.BusABC) -> tuple[list, list, int]:
    offered: list[tuple[int, bytes]] = []

    def on_data(cob: int, data: bytes) -> bool:
        offered.append((cob, bytes(data)))
        return cob in (0x181, 0x182)

    rest = _Collect()
    notifier = BusReader(bus, [rest], loop=asyncio.get_running_loop(), on_data=on_data, timeout=0.1)
    try:
        for msg in FRAMES:
            peer.send(msg)
        for _ in range(400):  # until everything arrived (bounded: 4 s)
            if len(offered) + len(rest.got) >= 6:
                break
            await asyncio.sleep(0.01)
        await asyncio.sleep(0.05)
    finally:
        notifier.stop()
    return offered, rest.got, int(notifier._thread is not None)


def _check(offered: list, rest: list) -> None:
    assert offered == [(0x181, b"\x01\x02\x03\x04"), (0x701, b"\x05"), (0x182, b"\xAA\xBB")]
    assert rest == [(0x701, b"\x05", False, False), (0x181, b"\x09", True, False), (0x182, b"", False, True)]


def test_udp_bus_drain_claims_plain_frames_and_delivers_the_rest(request: pytest.FixtureRequest) -> None:
    spec = parse_bus(f"udp_multicast:{_group(request.node.name)}")
    bus, peer = open_bus(spec), open_bus(spec)
    try:
        offered, rest, threaded = asyncio.run(_run(bus, peer))
        c = bus.counters()
    finally:
        bus.shutdown()
        peer.shutdown()
    _check(offered, rest)
    assert threaded == 0  # read by the loop's callback on the socket, no thread
    assert c.frames_received == 5 and c.undecodable == 0 and c.duplicates_dropped == 0


def test_udp_bus_drain_takes_a_burst_in_one_call(request: pytest.FixtureRequest) -> None:
    """Everything queued is read by one drain() (bounded by its limit), echoes and duplicates filtered as recv does."""
    spec = parse_bus(f"udp_multicast:{_group(request.node.name)}")
    bus, peer = open_bus(spec), open_bus(spec)
    try:
        bus.send(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False))  # own echo: dropped
        for i in range(10):
            peer.send(can.Message(arbitration_id=0x181 + i % 6, data=bytes([i]), is_extended_id=False))
        assert bus.recv(2.0) is not None  # wait for the first; the rest is queued behind it
        import time
        time.sleep(0.1)
        seen: list[int] = []
        n = bus.drain(lambda cob, data: seen.append(data[0]) is None, lambda m: seen.append(-1), limit=4)
        n += bus.drain(lambda cob, data: seen.append(data[0]) is None, lambda m: seen.append(-1))
        assert bus.drain(lambda cob, data: True, lambda m: None) == 0
        c = bus.counters()
    finally:
        bus.shutdown()
        peer.shutdown()
    assert n == 9 and seen == list(range(1, 10))
    assert c.own_echoes_dropped == 1 and c.frames_received == 10


@pytest.mark.parametrize("interface, threaded", [("virtual", 1), ("udp_multicast", 0)])
def test_bus_without_drain_is_read_with_the_same_split(interface: str, threaded: int,
                                                        request: pytest.FixtureRequest) -> None:
    """A bus without dragd's drain() splits frames the same way: without a file descriptor (python-can's virtual) in
    the reader's thread; with one (socketcan on a robot; python-can's own udp_multicast here) in the loop, every
    queued frame by recv(0) (BusReader._read_queued)."""
    if interface == "virtual":
        channel, kw = f"reader-{request.node.name}-{os.getpid()}", {}
    else:  # python-can's socket is bound to its port on every address, so it hears every group sent to that port
        # (another test's rig on dragd's default port): a port of its own, the kernel's pick of a free one
        channel, kw = _group(request.node.name), {"fd": True, "port": _free_udp_port()}
    bus = can.Bus(interface=interface, channel=channel, **kw)
    peer = can.Bus(interface=interface, channel=channel, **kw)
    try:
        offered, rest, in_thread = asyncio.run(_run(bus, peer))
    finally:
        bus.shutdown()
        peer.shutdown()
    _check(offered, rest)
    assert in_thread == threaded


@pytest.mark.parametrize("config", ["default.yaml", "two_buses.yaml"])
def test_tpdo_decoder_fills_the_feedback_as_the_listener_does(config: str) -> None:
    """The frames the reader hands over without can.Message decode into the same feedback as through the listener
    (the path the golden traces replay), TPDOs claimed, everything else (EMCY, heartbeat) refused."""
    import numpy as np

    from dragd.config import load_config

    from conftest import REPO
    from inproc import InProcess

    cfg = load_config(REPO / "config" / config)
    a, b = InProcess(cfg).d.io, InProcess(cfg).d.io
    emcys: list[tuple[int, int, int]] = []
    a.on_emcy = lambda j, code, reg: emcys.append((j, code, reg))
    rng = np.random.default_rng(7)
    frames = []
    for name, layout in a.layouts.items():
        for fr in layout.frames:
            if fr.direction == "tpdo":
                size = struct.Struct(fr.slots[0].fmt).size
                frames += [(name, fr.cob_id, bytes(rng.integers(0, 256, size, dtype=np.uint8))) for _ in range(2)]
                frames.append((name, fr.cob_id, b"\x01"))  # too short: ignored by both
    frames += [(next(iter(a.layouts)), 0x081, b"\x10\x32\x01\x00\x00\x00\x00\x00"),
               (next(iter(a.layouts)), 0x701, b"\x05")]
    for io in (a, b):
        io.begin_cycle()
    claimed = {}
    listeners = {name: a.listener(name) for name in a.layouts}
    decoders = {name: b.tpdo_decoder(name) for name in b.layouts}
    for name, cob, data in frames:
        listeners[name].on_message_received(can.Message(arbitration_id=cob, data=data, is_extended_id=False))
        claimed[cob] = decoders[name](cob, data)
    assert claimed.pop(0x081) is False and claimed.pop(0x701) is False and all(claimed.values())
    assert emcys == [(0, 0x3210, 1)]
    for field in ("counts", "statusword", "current_permille", "rx"):
        assert np.array_equal(getattr(a.feedback, field), getattr(b.feedback, field)), field
    assert a.feedback.rx_count == b.feedback.rx_count == a.n and a.end_read() and b.end_read()


def test_lockstep_time_frame_is_taken_by_the_decoder_as_by_the_listener() -> None:
    """On the lockstep clock the reader's decoder takes the simulator's TIME frame (no can.Message), as the listener
    does, and the bus's reader then looks for no more frames in that period (``until``); a 29-bit frame with the
    same id is not a TIME frame."""
    from dragd.clock import TIME_COB_ID, encode_time_of_day
    from dragd.config import load_config

    from conftest import REPO
    from inproc import InProcess

    cfg = load_config(REPO / "config" / "two_buses.yaml")
    a, b = InProcess(cfg).d.io, InProcess(cfg).d.io
    got: dict[str, list[tuple[str, bytes]]] = {"a": [], "b": []}
    a.on_time = lambda bus, data: got["a"].append((bus, bytes(data)))
    b.on_time = lambda bus, data: got["b"].append((bus, bytes(data)))
    first, second = list(b.layouts)
    decoders = {name: b.tpdo_decoder(name) for name in b.layouts}
    untils = {name: b._time_until(name) for name in b.layouts}
    for io in (a, b):
        io.begin_cycle()
    data = encode_time_of_day(12.345)
    assert not untils[first]() and not untils[second]()
    a.listener(first).on_message_received(can.Message(arbitration_id=TIME_COB_ID, data=data, is_extended_id=False))
    a.listener(first).on_message_received(can.Message(arbitration_id=TIME_COB_ID, data=data, is_extended_id=True))
    assert decoders[first](TIME_COB_ID, data) is True
    assert got["a"] == got["b"] == [(first, data)] and a.rejected_frames == 1
    assert untils[first]() and not untils[second]()
    b.begin_cycle()  # the next SYNC: the period is open again
    assert not untils[first]()
