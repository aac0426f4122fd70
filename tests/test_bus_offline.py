"""dragd.bus without the host's sockets: ``INTERFACE:CHANNEL`` spec parsing (what is accepted, what is refused and how
it is said), the SocketCAN probe's reason, python-can's in-process virtual bus (a frame is in the peer's queue when
``send`` returns). The unit tier (the buses on real sockets: tests/test_bus.py)."""

from __future__ import annotations

import can
import pytest

from dragd.hardware.bus import BusSpec, open_bus, parse_bus, socketcan_available

pytestmark = pytest.mark.unit


# --- parsing ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("text, interface, channel", [
    ("socketcan:can0", "socketcan", "can0"),
    ("socketcan:vcan0", "socketcan", "vcan0"),
    ("udp_multicast:239.74.163.2", "udp_multicast", "239.74.163.2"),
    ("virtual:arm", "virtual", "arm"),
    (" virtual:my bus ", "virtual", "my bus"),
])
def test_parse_bus_accepts(text: str, interface: str, channel: str) -> None:
    spec = parse_bus(text)
    assert spec == BusSpec(interface, channel)
    assert spec.bitrate == 1_000_000 and spec.fd is False and spec.data_bitrate is None
    assert str(spec) == f"{interface}:{channel}"


def test_parse_bus_keeps_timing() -> None:
    spec = parse_bus("socketcan:can1", bitrate=500_000, fd=True, data_bitrate=5_000_000)
    assert (spec.bitrate, spec.fd, spec.data_bitrate) == (500_000, True, 5_000_000)


def test_other_python_can_interfaces_parse():
    spec = parse_bus("pcan:PCAN_USBBUS1", fd=True, data_bitrate=5_000_000)
    assert (spec.interface, spec.channel, spec.fd) == ("pcan", "PCAN_USBBUS1", True)


@pytest.mark.parametrize("text, words", [
    ("can0", ["'can0'", "missing channel", "INTERFACE:CHANNEL"]),
    ("socketcan:", ["missing channel"]),
    ("nosuchbus:x", ["unknown interface 'nosuchbus'", "socketcan, udp_multicast, virtual", "pcan"]),
    ("socketcan:this-name-is-too-long", ["not a network interface name"]),
    ("udp_multicast:10.0.0.1", ["'10.0.0.1' is not a usable multicast group", "IPv4 multicast"]),
    ("udp_multicast:239.74.163", ["not a usable multicast group"]),
    ("udp_multicast:224.0.0.5", ["not a usable multicast group", "224.0.0.0/24"]),
    ("udp_multicast:ff15::1", ["not a usable multicast group", "IPv4"]),
])
def test_parse_bus_rejects_with_clear_message(text: str, words: list[str]) -> None:
    with pytest.raises(ValueError) as info:
        parse_bus(text)
    message = str(info.value)
    assert repr(text) in message or text.strip() in message
    for word in words:
        assert word in message


def test_data_bitrate_needs_fd() -> None:
    with pytest.raises(ValueError, match="only meaningful with fd=True"):
        parse_bus("socketcan:can0", data_bitrate=2_000_000)


def test_socketcan_probe_reports_a_reason() -> None:
    ok, reason = socketcan_available()
    assert isinstance(ok, bool) and reason
    ok_ch, reason_ch = socketcan_available("vcan-absent9")
    assert not ok_ch and reason_ch
    if not ok:
        with pytest.raises(can.CanInitializationError, match="SocketCAN unavailable"):
            open_bus(parse_bus("socketcan:vcan0"))


def test_virtual_bus_in_process(request: pytest.FixtureRequest) -> None:
    spec = parse_bus(f"virtual:{request.node.name}")
    a, b = open_bus(spec), open_bus(spec)
    try:
        a.send(can.Message(arbitration_id=0x181, data=b"\x01\x02", is_extended_id=False))
        msg = b.recv(1.0)
        assert msg is not None and msg.arbitration_id == 0x181 and bytes(msg.data) == b"\x01\x02"
        assert a.recv(0.05) is None, "own frame echoed"
    finally:
        a.shutdown()
        b.shutdown()
