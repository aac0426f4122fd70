"""python-can opens dragd's udp_multicast bus by name (the ``can.interface`` entry point ``dragd_udp``).

python-can's own command-line tools, in processes of their own, talk to dragd's bus over the host-local group:
``can.logger`` hears what dragd's bus sends (single frames and a batched datagram), ``can.player`` replays a log file
written by python-can's own writer into dragd's bus. No namespace or multicast route is needed: both sides use
dragd's host-local socket.
"""

from __future__ import annotations

import hashlib
import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import can
import pytest

from dragd.hardware.bus import UdpMulticastCanBus, open_bus, parse_bus

pytestmark = pytest.mark.unit

INTERFACE = "dragd_udp"
FRAMES = [
    can.Message(arbitration_id=0x181, data=b"\x01\x02\x03\x04", is_extended_id=False),
    can.Message(arbitration_id=0x701, data=b"\x05", is_extended_id=False),
    can.Message(arbitration_id=0x1ABCDE, data=b"\x09\x08", is_extended_id=True),
    can.Message(arbitration_id=0x080, data=b"", is_extended_id=False),
]


def _group(name: str) -> str:
    h = int.from_bytes(hashlib.sha256(f"tools:{name}:{os.getpid()}".encode()).digest()[:4], "big")
    return f"239.74.{150 + h % 50}.{1 + (h >> 8) % 254}"


def _frames(msgs: list[can.Message]) -> list[tuple[int, bool, bytes]]:
    return [(m.arbitration_id, m.is_extended_id, bytes(m.data)) for m in msgs]


def _lines_until(proc: subprocess.Popen[bytes], done, timeout_s: float) -> list[str]:
    """The process's stdout lines until ``done(lines)`` (or its end, or the timeout: then what came). Read from the
    pipe's descriptor itself: a buffered reader would hold lines that ``select`` no longer reports."""
    assert proc.stdout is not None
    fd = proc.stdout.fileno()
    lines: list[str] = []
    rest = b""
    end = time.monotonic() + timeout_s
    while not done(lines) and time.monotonic() < end:
        ready, _, _ = select.select([fd], [], [], max(0.0, end - time.monotonic()))
        if not ready:
            break
        chunk = os.read(fd, 65536)
        if not chunk:
            break
        *complete, rest = (rest + chunk).split(b"\n")
        lines += [line.decode() for line in complete]
    return lines


def test_python_can_opens_dragds_bus_by_interface_name(request: pytest.FixtureRequest) -> None:
    """``can.Bus(interface="dragd_udp")`` is dragd's bus (python-can found it by its entry point), and it talks to a
    bus dragd opened itself."""
    assert INTERFACE in can.interfaces.VALID_INTERFACES
    group = _group(request.node.name)
    theirs = can.Bus(interface=INTERFACE, channel=group)
    ours = open_bus(parse_bus(f"udp_multicast:{group}"))
    try:
        assert isinstance(theirs, UdpMulticastCanBus)
        theirs.send(FRAMES[0])
        got = ours.recv(5.0)
        assert got is not None and _frames([got]) == _frames(FRAMES[:1])
    finally:
        theirs.shutdown()
        ours.shutdown()


def test_python_can_logger_hears_dragds_bus(request: pytest.FixtureRequest) -> None:
    """``python -m can.logger -i dragd_udp`` (another process) prints every frame dragd's bus sends, a batched
    datagram's frames included."""
    group = _group(request.node.name)
    logger = subprocess.Popen([sys.executable, "-m", "can.logger", "-i", INTERFACE, "-c", group],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, bufsize=0,
                              env={**os.environ, "PYTHONUNBUFFERED": "1"},
                              preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # (SIGINT ends it
    # even where this run's SIGINT is ignored, as in a shell script's background job: tests/test_python_can_interop.py)
    ours = open_bus(parse_bus(f"udp_multicast:{group}"), batch_frames=True)
    try:
        head = _lines_until(logger, lambda lines: any(line.startswith("Connected to") for line in lines), 60)
        assert any(f"Connected to {UdpMulticastCanBus.__name__}" in line for line in head), head
        ours.send(FRAMES[0])  # alone
        with ours.batch():  # one datagram of three frames
            for msg in FRAMES[1:]:
                ours.send(msg)
        printed = [line for line in _lines_until(
            logger, lambda lines: sum("ID:" in line for line in lines) >= len(FRAMES), 30) if "ID:" in line]
    finally:
        ours.shutdown()
        logger.send_signal(signal.SIGINT)
        try:
            logger.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            logger.kill()
            logger.communicate()
    ids = [int(line.split("ID:")[1].split()[0], 16) for line in printed]
    assert ids == [m.arbitration_id for m in FRAMES], printed
    assert ["01 02 03 04" in printed[0], "05" in printed[1].split("DL:")[1], "09 08" in printed[2]] == [True] * 3


def test_python_can_player_replays_a_log_into_dragds_bus(request: pytest.FixtureRequest, tmp_path: Path) -> None:
    """A log written by python-can's own writer, replayed by ``python -m can.player -i dragd_udp`` (another
    process), arrives at dragd's bus frame for frame."""
    group = _group(request.node.name)
    path = tmp_path / "frames.log"
    with can.Logger(str(path)) as writer:
        for i, msg in enumerate(FRAMES):
            writer.on_message_received(can.Message(timestamp=1.0 + 0.001 * i, arbitration_id=msg.arbitration_id,
                                                   is_extended_id=msg.is_extended_id, data=msg.data))
    ours = open_bus(parse_bus(f"udp_multicast:{group}"))
    try:
        played = subprocess.run([sys.executable, "-m", "can.player", "-i", INTERFACE, "-c", group,
                                 "--ignore-timestamps", str(path)], capture_output=True, text=True, timeout=60)
        assert played.returncode == 0, played.stderr
        got: list[can.Message] = []
        while len(got) < len(FRAMES):
            msg = ours.recv(5.0)
            if msg is None:
                break
            got.append(msg)
        assert ours.recv(0.05) is None  # nothing more (no duplicates)
    finally:
        ours.shutdown()
    assert _frames(got) == _frames(FRAMES)
