"""CAN buses from "INTERFACE:CHANNEL" strings, shared by the daemon and the simulated robot.

Interfaces: ``socketcan:can0`` / ``socketcan:vcan0`` (Linux SocketCAN), ``udp_multicast:239.74.163.2``
(CAN frames as UDP datagrams between processes on this host) and ``virtual:NAME`` (in-process).

udp_multicast uses python-can's wire format (a msgpack map per frame, as ``can.interfaces.udp_multicast``
packs it) but its own socket, because python-can's would join the group on the default-route interface
and send frames onto the LAN. Here the socket is host-local: group joined on the loopback interface
only, multicast TTL 0, bound to the group address with IP_MULTICAST_ALL off (so tests on different
groups sharing a port stay apart), and a large receive buffer. On top of that the bus

- drops its own frames (multicast loopback echoes every datagram to its sender): in the kernel, by a socket filter
  (classic BPF) that matches the sender's stamp, so an echo never wakes the process; frames that get past it (a
  kernel without socket filters) are recognised by the same stamp before they are decoded,
- drops duplicated datagrams,
- counts frames lost between sender and receiver.

For this each sender stamps the msgpack ``channel`` field (the map's first key, so a receiver recognises
its own echoes by their first bytes) with a 64-bit integer: a random 32-bit sender
token (per bus instance) in the high half and a 32-bit sequence number in the low half (the receiver
replaces the field with its own channel name). Python-can's ``channel`` field accepts any msgpack value,
so the frames stay readable by python-can. python-can opens this bus by name: it is registered as the
``can.interface`` entry point ``dragd_udp`` (``can.Bus(interface="dragd_udp", channel=GROUP)``, ``python -m can.logger
-i dragd_udp -c GROUP``; tests/test_python_can_tools.py). python-can's own udp_multicast bus talks to it too once the
group is routed to the loopback interface (``ip route add 239.74.0.0/16 dev lo``: then both join on ``lo``;
docs/TOOLS.md, tests/test_python_can_interop.py). A receiver tracks, per sender token, the highest sequence
seen plus a 64-frame window: repeats in the window are duplicates, numbers skipped are gaps (a frame that
arrives late fills its gap again and counts as reordered). Losses the kernel itself counts (receive
buffer overflow, SO_RXQ_OVFL) are reported as well. Not detectable: frames from senders that do not
stamp the field (plain python-can peers; these are passed through and counted as foreign), losses after
a sender's last frame, and the first frames of a sender before its first frame that arrived.

Batching (opt-in, ``batch_frames=True``): frames a thread sends inside ``with bus.batch():`` leave as one datagram
(at most ``DATAGRAM_MAX`` bytes; more: several) — their msgpack maps back to back, each with its own stamp — when
the block ends. The simulated drives answer a SYNC that way (six TPDOs, one datagram: one send and one receiver
wake-up instead of six). Every bus of this module decodes such datagrams, and ``drain`` hands out all their frames
at once; ``recv`` returns them one per call, so a reader that waits on the socket between calls (python-can's
asyncio ``Notifier``, which calls ``recv(0)`` once per wake-up) would leave the rest of a batch queued until the next
datagram — dragd's daemon reads with ``BusReader`` (hardware/reader.py) and its tools with a thread that calls
``recv(timeout)`` in a loop. python-can's own udp_multicast bus cannot read batches at all (it expects exactly one
map), so a bus that talks to python-can's tools leaves batching off (the default).
"""

from __future__ import annotations

import ctypes
import ipaddress
import os
import re
import secrets
import select
import socket
import struct
import threading
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import can
import msgpack

INTERFACES = ("socketcan", "udp_multicast", "virtual")  # handled here; any other python-can interface goes to can.Bus
DEFAULT_UDP_PORT = 43113
DEFAULT_RCVBUF_BYTES = 4 * 1024 * 1024
_IFNAME = re.compile(r"^[A-Za-z0-9_.\-]{1,15}$")
_LOOPBACK = "127.0.0.1"
_IP_MULTICAST_ALL = getattr(socket, "IP_MULTICAST_ALL", 49)  # Linux value; absent from Python's socket module
_SO_RXQ_OVFL = getattr(socket, "SO_RXQ_OVFL", 40)
_SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)
_MSG_TRUNC = int(socket.MSG_TRUNC)  # (a plain int: ``&`` with the IntFlag costs an enum call per datagram)
_SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)
_SO_ATTACH_FILTER = getattr(socket, "SO_ATTACH_FILTER", 26)
_UDP_HEADER = 8  # a UDP socket's filter sees the datagram from its UDP header on
_TIMESPEC = struct.Struct("@ll")
_U32 = struct.Struct("@I")
_WINDOW = 64
DATAGRAM_MAX = 4096  # bytes read per datagram; a batch longer than this leaves in several datagrams
_STAMP = slice(10, 18)  # a packed frame's sender stamp (after the map header, "channel" and the uint64 marker)
_WINDOW_MASK = (1 << _WINDOW) - 1
_STAMP_CODEC = struct.Struct(">II")  # the stamp as (token, sequence)
_U64_BE = struct.Struct(">Q")  # the stamp as one number (token << 32 | sequence)
_MAP_HEAD = b"\x8b\xa7channel\xcf"  # how each of our packed frames starts: an 11-entry map, "channel", a uint64


@dataclass(frozen=True)
class BusSpec:
    """Where a bus is: python-can interface and channel, plus bit timing (used where the interface has it)."""

    interface: str
    channel: str
    bitrate: int = 1_000_000
    fd: bool = False
    data_bitrate: int | None = None

    def __str__(self) -> str:
        return f"{self.interface}:{self.channel}"


def parse_bus(text: str, *, bitrate: int = 1_000_000, fd: bool = False, data_bitrate: int | None = None) -> BusSpec:
    """Parse "INTERFACE:CHANNEL" (e.g. ``socketcan:can0``, ``udp_multicast:239.74.163.2``, ``virtual:arm``)."""
    expected = (f"expected INTERFACE:CHANNEL with INTERFACE one of {', '.join(INTERFACES)} "
                "(e.g. socketcan:can0, udp_multicast:239.74.163.2, virtual:arm)")
    interface, sep, channel = text.strip().partition(":")
    if not sep or not channel:
        raise ValueError(f"bus {text!r}: missing channel; {expected}")
    if interface not in INTERFACES and interface not in can.interfaces.VALID_INTERFACES:
        raise ValueError(f"bus {text!r}: unknown interface {interface!r}; {expected}, or another python-can interface "
                         f"({', '.join(sorted(set(can.interfaces.VALID_INTERFACES) - set(INTERFACES)))})")
    if interface == "socketcan" and not _IFNAME.match(channel):
        raise ValueError(f"bus {text!r}: {channel!r} is not a network interface name "
                         "(expected 1-15 characters of letters, digits, '_', '.', '-', e.g. can0 or vcan0)")
    if interface == "udp_multicast":
        _check_multicast_group(text, channel)
    if data_bitrate is not None and not fd:
        raise ValueError(f"bus {text!r}: data_bitrate={data_bitrate} is only meaningful with fd=True")
    return BusSpec(interface, channel, bitrate, fd, data_bitrate)


def _check_multicast_group(text: str, channel: str) -> None:
    try:
        address = ipaddress.ip_address(channel)
    except ValueError:
        address = None
    if address is None or address.version != 4 or not address.is_multicast \
            or address in ipaddress.ip_network("224.0.0.0/24"):
        raise ValueError(f"bus {text!r}: {channel!r} is not a usable multicast group; expected an IPv4 "
                         "multicast address outside 224.0.0.0/24, e.g. 239.74.163.2")


def socketcan_available(channel: str | None = None) -> tuple[bool, str]:
    """Whether SocketCAN works here (and `channel` exists and binds); the reason if not."""
    if not hasattr(socket, "AF_CAN"):
        return False, "this Python has no AF_CAN support"
    try:
        sock = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    except OSError as exc:
        return False, f"the kernel refuses AF_CAN sockets (errno {exc.errno}: {exc.strerror})"
    try:
        if channel is None:
            return True, "AF_CAN sockets available"
        if not os.path.exists(f"/sys/class/net/{channel}"):
            return False, (f"no network interface {channel!r} (create one with: ip link add dev {channel} type vcan; "
                           f"ip link set up {channel})")
        try:
            sock.bind((channel,))
        except OSError as exc:
            return False, f"cannot bind a CAN socket to {channel!r} (errno {exc.errno}: {exc.strerror})"
        return True, f"{channel} is available"
    finally:
        sock.close()


def open_bus(spec: BusSpec, *, receive_own_messages: bool = False, udp_port: int = DEFAULT_UDP_PORT,
             rcvbuf_bytes: int = DEFAULT_RCVBUF_BYTES, batch_frames: bool = False) -> can.BusABC:
    """Open the python-can bus of a spec (udp_multicast: the filtering host-local bus of this module).

    ``batch_frames``: udp_multicast only, ``batch()`` blocks send one datagram (see the module docstring).
    """
    if spec.interface == "udp_multicast":
        return UdpMulticastCanBus(spec.channel, port=udp_port, fd=spec.fd, rcvbuf_bytes=rcvbuf_bytes,
                                  receive_own_messages=receive_own_messages, batch_frames=batch_frames)
    if spec.interface == "virtual":
        protocol = can.CanProtocol.CAN_FD if spec.fd else can.CanProtocol.CAN_20
        return can.Bus(interface="virtual", channel=spec.channel, receive_own_messages=receive_own_messages,
                       protocol=protocol)
    if spec.interface == "socketcan":
        ok, reason = socketcan_available(spec.channel)
        if not ok:
            raise can.CanInitializationError(f"bus {spec}: SocketCAN unavailable: {reason}")
        return can.Bus(interface="socketcan", channel=spec.channel, fd=spec.fd,
                       receive_own_messages=receive_own_messages)
    if spec.interface in can.interfaces.VALID_INTERFACES:  # pcan, kvaser, vector, slcan, ...: python-can's plugin
        kwargs: dict[str, Any] = {"bitrate": spec.bitrate, "receive_own_messages": receive_own_messages}
        if spec.fd:
            kwargs.update(fd=True, data_bitrate=spec.data_bitrate)
        return can.Bus(interface=spec.interface, channel=spec.channel, **kwargs)
    raise ValueError(f"bus {spec}: unknown interface {spec.interface!r}; expected one of {', '.join(INTERFACES)} "
                     "or another python-can interface")


@dataclass(frozen=True)
class UdpBusCounters:
    """A snapshot of a UdpMulticastCanBus's counters."""

    frames_sent: int
    frames_received: int  # delivered to the caller
    own_echoes_dropped: int  # our own frames looped back (by the kernel's socket filter, or after recvmsg)
    duplicates_dropped: int
    gaps: int  # frames missing in senders' sequences (not refilled by a late arrival)
    reordered: int  # frames that arrived after a later one of the same sender
    too_late_dropped: int  # arrived more than 64 frames behind its sender's newest: dropped
    kernel_drops: int  # datagrams the kernel dropped for a full receive buffer (SO_RXQ_OVFL, less our filtered echoes)
    foreign_frames: int  # frames without a sender stamp (passed through, not checked)
    fd_frames_dropped: int  # CAN FD frames received on a classic-CAN bus
    undecodable: int
    datagrams_sent: int  # fewer than frames_sent when frames were batched
    template_datagrams: int  # datagrams of expected frames only, read by their templates (``expect``)
    rcvbuf_bytes: int  # receive buffer the kernel granted


@dataclass
class PreparedBatch:
    """Plain data frames that always leave together, as one datagram packed once (``UdpMulticastCanBus.prepare``):
    the caller writes each frame's payload into ``data[i]``; ``send_prepared`` stamps the frames and sends."""

    datagram: bytearray
    stamps: list[int]  # offset of each frame's stamp in the datagram
    data: list[memoryview]  # each frame's payload bytes, in the datagram


class UdpMulticastCanBus(can.BusABC):
    """Host-local CAN-over-UDP-multicast bus with echo and duplicate suppression and loss counters."""

    def __init__(self, channel: str, port: int = DEFAULT_UDP_PORT, fd: bool = False,
                 rcvbuf_bytes: int = DEFAULT_RCVBUF_BYTES, receive_own_messages: bool = False,
                 can_filters: Any = None, batch_frames: bool = False, **kwargs: Any) -> None:
        _check_multicast_group(f"udp_multicast:{channel}", channel)
        self.group = channel
        self.port = port
        self.receive_own_messages = receive_own_messages
        self._can_protocol = can.CanProtocol.CAN_FD if fd else can.CanProtocol.CAN_20
        self._token = secrets.randbits(32) or 1
        self._seq = 0
        self._packer = msgpack.Packer(use_bin_type=True)  # reused: packb would build one per frame
        # how our own datagrams start (an 11-entry map whose first key is "channel", a uint64 with our token on
        # top): the echo of a frame we sent is recognised by its first 14 bytes, without unpacking it
        self._own_prefix = _MAP_HEAD + self._token.to_bytes(4, "big")
        self._tx_lock = threading.Lock()
        self._rx_lock = threading.Lock()
        self._senders: dict[int, list[int]] = {}
        self.batch_frames = batch_frames
        self._local = threading.local()  # .held: this thread's open batch() block (other threads' frames go at once)
        self._pending: deque[can.Message] = deque()  # recv(): the rest of a batched datagram
        self.rx_timestamp = 0.0  # drain(): the kernel's reception time of the datagram whose frames it hands over
        self._templates: dict[tuple[int, int, bool], tuple[bytes, bytes]] = {}  # send_data(): packed map around data
        # expect(): frames read without msgpack — their packed map after the stamp up to the data → per kind of frame
        # with that head (classic, FD): (arbitration id, length, the map after the data, the decoded fields for the
        # rare can.Message); the head lengths in use
        self._expected: dict[bytes, tuple[tuple[int, int, bytes, dict[str, Any]], ...]] = {}
        self._expected_heads: tuple[int, ...] = ()
        self._c = dict(frames_sent=0, frames_received=0, own_echoes_dropped=0, duplicates_dropped=0, gaps=0,
                       reordered=0, too_late_dropped=0, kernel_drops=0, foreign_frames=0, fd_frames_dropped=0,
                       undecodable=0, datagrams_sent=0, template_datagrams=0)
        self._sock = self._open_socket(rcvbuf_bytes)
        # own echoes dropped in the kernel: each datagram we send is filtered once on our socket, and the kernel
        # counts filtered datagrams with its overflow drops (SO_RXQ_OVFL): ``_filtered`` is subtracted from those
        self._kernel_filter = not receive_own_messages and self._attach_echo_filter()
        self._filtered = 0
        self.rcvbuf_bytes = self._sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        self._dest = (self.group, self.port)
        self._ancillary_size = socket.CMSG_SPACE(_TIMESPEC.size) + socket.CMSG_SPACE(_U32.size)
        self.channel = channel
        self.channel_info = f"udp_multicast {channel}:{port} (host-local, rcvbuf {self.rcvbuf_bytes} B)"
        super().__init__(channel=channel, can_filters=can_filters, **kwargs)

    def _open_socket(self, rcvbuf_bytes: int) -> socket.socket:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(_LOOPBACK))
            sock.setsockopt(socket.IPPROTO_IP, _IP_MULTICAST_ALL, 0)
            sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
            sock.setsockopt(socket.SOL_SOCKET, _SO_RXQ_OVFL, 1)
            try:
                sock.setsockopt(socket.SOL_SOCKET, _SO_RCVBUFFORCE, rcvbuf_bytes)
            except PermissionError:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf_bytes)
            sock.bind((self.group, self.port))
            membership = socket.inet_aton(self.group) + socket.inet_aton(_LOOPBACK)
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, membership)
        except OSError as exc:
            sock.close()
            raise can.CanInitializationError(
                f"udp_multicast:{self.group} port {self.port}: cannot set up the host-local multicast socket: "
                f"{exc}") from exc
        return sock

    def _attach_echo_filter(self) -> bool:
        """A socket filter that drops datagrams starting with our stamp (our echoes); False where refused."""
        prefix = self._own_prefix  # 14 bytes: three words and a half-word, compared as the kernel loads them
        words = [int.from_bytes(prefix[i:i + 4], "big") for i in (0, 4, 8)]
        half = int.from_bytes(prefix[12:14], "big")
        ld_len, ld_w, ld_h, jge, jeq, ret = 0x80, 0x20, 0x28, 0x35, 0x15, 0x06
        accept = 11  # the last instruction; a jump's offset counts from the instruction after it
        prog = [(ld_len, 0, 0, 0), (jge, 0, accept - 2, _UDP_HEADER + len(prefix)),  # shorter: not ours
                (ld_w, 0, 0, _UDP_HEADER), (jeq, 0, accept - 4, words[0]),
                (ld_w, 0, 0, _UDP_HEADER + 4), (jeq, 0, accept - 6, words[1]),
                (ld_w, 0, 0, _UDP_HEADER + 8), (jeq, 0, accept - 8, words[2]),
                (ld_h, 0, 0, _UDP_HEADER + 12), (jeq, 0, accept - 10, half),
                (ret, 0, 0, 0),  # ours: dropped
                (ret, 0, 0, 0xFFFFFFFF)]  # anything else: the whole datagram
        code = ctypes.create_string_buffer(b"".join(struct.pack("HBBI", *insn) for insn in prog))
        fprog = struct.pack("HL", len(prog), ctypes.addressof(code))
        try:
            self._sock.setsockopt(socket.SOL_SOCKET, _SO_ATTACH_FILTER, fprog)
        except OSError:
            return False  # the echoes are then dropped after recvmsg, by the same stamp
        return True

    # --- send --------------------------------------------------------------------------------------------
    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._check_fd(msg.is_fd)
        self._emit(self._pack(msg))  # packed now (the caller may reuse msg)

    def send_data(self, arbitration_id: int, data: bytes | bytearray, fd: bool = False) -> None:
        """``send`` of a plain data frame (11-bit id, not remote, not an error frame; CAN FD with bit-rate switch when
        ``fd``) without a ``can.Message``: the same bytes on the wire, from a template per id and length."""
        self._check_fd(fd)
        parts = self._parts(arbitration_id, len(data), fd)
        packed = bytearray(parts[0])
        packed += data
        packed += parts[1]
        self._emit(packed)

    def prepare(self, frames: list[tuple[int, int, bool]]) -> PreparedBatch:
        """A datagram of plain data frames ``(arbitration_id, length, fd)``, in order, packed once: the 1 kHz path
        sends it with ``send_prepared`` and neither packs a map nor makes an object per frame (the same bytes on
        the wire as ``send`` of each frame inside ``batch()``)."""
        datagram, stamps, spans = bytearray(), [], []
        for arbitration_id, length, fd in frames:
            self._check_fd(fd)
            parts = self._parts(arbitration_id, length, fd)
            stamps.append(len(datagram) + _STAMP.start)
            datagram += parts[0]
            spans.append((len(datagram), length))
            datagram += bytes(length)
            datagram += parts[1]
        if not frames or len(datagram) > DATAGRAM_MAX:
            raise ValueError(f"{self.channel_info}: a prepared batch must hold at least one frame and fit one datagram "
                             f"({DATAGRAM_MAX} bytes); got {len(frames)} frames, {len(datagram)} bytes")
        view = memoryview(datagram)
        return PreparedBatch(datagram, stamps, [view[at:at + n] for at, n in spans])

    def send_prepared(self, batch: PreparedBatch) -> None:
        """Send a prepared datagram with the payloads its ``data`` holds now (each frame stamped in turn)."""
        buf, token, pack_into = batch.datagram, self._token, _STAMP_CODEC.pack_into
        with self._tx_lock:
            seq = self._seq
            for at in batch.stamps:
                seq = (seq + 1) & 0xFFFFFFFF
                pack_into(buf, at, token, seq)
            self._seq = seq
            self._sendto(buf, len(batch.stamps))

    def _check_fd(self, fd: bool) -> None:
        if fd and self._can_protocol is not can.CanProtocol.CAN_FD:
            raise can.CanOperationError(f"{self.channel_info}: cannot send a CAN FD frame on a classic-CAN bus")

    def _emit(self, packed: bytearray) -> None:
        """A packed frame leaves now, or with this thread's open ``batch()`` (stamped when it leaves)."""
        held = getattr(self._local, "held", None)
        if held is not None:
            held.append(packed)
            return
        with self._tx_lock:
            self._sendto(self._stamp(packed), 1)

    def _parts(self, arbitration_id: int, length: int, fd: bool) -> tuple[bytes, bytes]:
        """``_template``, made once per id, length and kind."""
        key = (arbitration_id, length, fd)
        parts = self._templates.get(key)
        if parts is None:
            parts = self._templates[key] = self._template(arbitration_id, length, fd)
        return parts

    def _template(self, arbitration_id: int, length: int, fd: bool) -> tuple[bytes, bytes]:
        """The packed map of such a frame before and after its data bytes (as ``_pack`` writes it for a fresh
        ``can.Message``): found by packing one with marker data."""
        marker = bytes(range(1, length + 1))
        packed = bytes(self._pack(can.Message(arbitration_id=arbitration_id, data=marker, is_extended_id=False,
                                              is_fd=fd, bitrate_switch=fd, check=False)))
        field = self._packer.pack("data") + self._packer.pack(marker)  # the key, the bin header, the marker
        data_at = packed.index(field) + len(field) - length
        return packed[:data_at], packed[data_at + length:]

    def expect(self, frames: Iterable[tuple[int, int, bool]]) -> None:
        """Plain data frames ``(arbitration_id, length, fd)`` this bus receives every cycle (the TPDOs of a master,
        the SYNC and RPDOs of a drive): ``drain`` reads a datagram made only of such frames, as dragd's senders pack
        them (``send_data``/``prepare``: the same template), by comparing bytes instead of unpacking maps — the
        same frames, counters and sequence checks as the msgpack path, which takes every other datagram."""
        if self.receive_own_messages:
            return  # (own frames need can.Message objects: every datagram takes the msgpack path)
        # copied, then replaced: a reader in another thread sees the old table or the new one, never one mid-update
        # (the simulator calls this from its reader, inside drain's callbacks; entries are only ever added)
        expected = dict(self._expected)
        for arbitration_id, length, fd in frames:
            if fd and self._can_protocol is not can.CanProtocol.CAN_FD:
                continue  # (such a frame is dropped on this bus: the msgpack path counts it)
            before, after = self._parts(arbitration_id, length, fd)
            head = before[_STAMP.stop:]
            kinds = expected.get(head, ())
            if any(k[2] == after for k in kinds):
                continue
            fields = msgpack.unpackb(before + bytes(length) + after, raw=False)
            fields.pop("data")
            expected[head] = (*kinds, (arbitration_id, length, after, fields))
        self._expected = expected
        self._expected_heads = tuple(sorted({len(head) for head in expected}))

    def _expected_frames(self, raw: bytes) -> list[tuple[int, int, bytes, dict[str, Any]]] | None:
        """``(stamp, arbitration_id, data, fields)`` of each frame when ``raw`` holds expected frames only, else
        None."""
        expected, heads, stamp_at, head_at = self._expected, self._expected_heads, _STAMP.start, _STAMP.stop
        out = []
        frame, end = 0, len(raw)
        while frame < end:
            if not raw.startswith(_MAP_HEAD, frame):
                return None
            at = frame + head_at
            for n in heads:
                kinds = expected.get(raw[at:at + n])
                if kinds is not None:
                    break
            else:
                return None
            at += n
            for kind in kinds:  # (arbitration id, length, the map after the data, fields)
                stop = at + kind[1]
                if raw.startswith(kind[2], stop):
                    break
            else:
                return None
            out.append((_U64_BE.unpack_from(raw, frame + stamp_at)[0], kind[0], raw[at:stop], kind[3]))
            frame = stop + len(kind[2])
        return out

    @contextmanager
    def batch(self) -> Iterator[None]:
        """Frames this thread sends inside the block leave together, as one datagram, when it ends.

        Without ``batch_frames`` (and when nested) the block changes nothing: every frame leaves at once.
        """
        if not self.batch_frames or getattr(self._local, "held", None) is not None:
            yield
            return
        held: list[bytearray] = []
        self._local.held = held
        try:
            yield
        finally:
            self._local.held = None
            if held:
                self._flush(held)

    def _flush(self, held: list[bytearray]) -> None:
        with self._tx_lock:
            parts: list[bytearray] = []
            size = 0
            for data in held:
                if parts and size + len(data) > DATAGRAM_MAX:
                    self._sendto(b"".join(parts), len(parts))
                    parts, size = [], 0
                parts.append(self._stamp(data))
                size += len(data)
            self._sendto(b"".join(parts), len(parts))

    def _stamp(self, data: bytearray) -> bytearray:
        """Put the next sequence number into a packed frame's stamp (caller holds the tx lock)."""
        self._seq = (self._seq + 1) & 0xFFFFFFFF
        data[_STAMP] = (self._token << 32 | self._seq).to_bytes(8, "big")
        return data

    def _pack(self, msg: can.Message) -> bytearray:
        """One frame's msgpack map; its stamp carries the sender token and sequence 0 until ``_stamp``."""
        packed = bytearray(self._packer.pack({
            "channel": self._token << 32,  # first: the datagram starts with the sender's stamp (a uint64)
            "timestamp": msg.timestamp,
            "arbitration_id": msg.arbitration_id,
            "is_extended_id": msg.is_extended_id,
            "is_remote_frame": msg.is_remote_frame,
            "is_error_frame": msg.is_error_frame,
            "dlc": msg.dlc,
            "data": bytes(msg.data),
            "is_fd": msg.is_fd,
            "bitrate_switch": msg.bitrate_switch,
            "error_state_indicator": msg.error_state_indicator,
        }))
        return packed

    def _sendto(self, datagram: bytes | bytearray, frames: int) -> None:
        if self._kernel_filter:  # counted before the kernel filters the echo: the overflow count never runs ahead
            self._filtered += 1
        try:
            self._sock.sendto(datagram, self._dest)
        except OSError as exc:
            if self._kernel_filter:
                self._filtered -= 1
            raise can.CanOperationError(f"{self.channel_info}: send failed: {exc}") from exc
        c = self._c
        c["frames_sent"] += frames
        c["datagrams_sent"] += 1
        if self._kernel_filter:
            c["own_echoes_dropped"] += frames

    # --- receive -----------------------------------------------------------------------------------------
    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self._pending:  # the rest of a batched datagram
            return self._pending.popleft(), False
        # a datagram already queued is taken without a select() first (one syscall per frame, not two)
        try:
            raw, ancillary, flags, _ = self._sock.recvmsg(DATAGRAM_MAX, self._ancillary_size, socket.MSG_DONTWAIT)
        except BlockingIOError:
            if timeout == 0:
                return None, False
            try:
                ready, _, _ = select.select([self._sock], [], [], timeout)
            except (OSError, ValueError) as exc:
                raise can.CanOperationError(f"{self.channel_info}: wait for data failed: {exc}") from exc
            if not ready:
                return None, False
            try:
                raw, ancillary, flags, _ = self._sock.recvmsg(DATAGRAM_MAX, self._ancillary_size, socket.MSG_DONTWAIT)
            except BlockingIOError:
                return None, False  # another reader took it
            except OSError as exc:
                raise can.CanOperationError(f"{self.channel_info}: receive failed: {exc}") from exc
        except OSError as exc:
            raise can.CanOperationError(f"{self.channel_info}: receive failed: {exc}") from exc
        with self._rx_lock:
            frames, timestamp = self._frames(raw, ancillary, flags)
            first: can.Message | None = None
            for fields, own in frames:
                msg = self._message(fields, timestamp, own)
                if msg is None:
                    continue
                if first is None:
                    first = msg
                else:
                    self._pending.append(msg)
            return first, False

    def _message(self, fields: dict[str, Any], timestamp: float, own: bool) -> can.Message | None:
        try:
            msg = can.Message(timestamp=timestamp, arbitration_id=fields["arbitration_id"],
                              is_extended_id=fields["is_extended_id"], is_remote_frame=fields["is_remote_frame"],
                              is_error_frame=fields["is_error_frame"], channel=self.channel, dlc=fields["dlc"],
                              data=fields["data"], is_fd=fields["is_fd"], bitrate_switch=fields["bitrate_switch"],
                              error_state_indicator=fields["error_state_indicator"], is_rx=not own, check=False)
        except (ValueError, TypeError, KeyError):
            self._c["undecodable"] += 1
            return None
        self._c["frames_received"] += 1
        return msg

    def _frames(self, raw: bytes, ancillary: list[tuple[int, int, bytes]], flags: int = 0
                ) -> tuple[list[tuple[dict[str, Any], bool]], float]:
        """A datagram's accepted frames (fields, whether our own echo) and its reception time.

        A datagram holds one frame, or several back to back (a batch); own echoes, duplicates and broken frames
        are dropped and counted.
        """
        timestamp, readable = self._receipt(raw, ancillary, flags)
        return (self._unpacked(raw) if readable else []), timestamp

    def _receipt(self, raw: bytes, ancillary: list[tuple[int, int, bytes]], flags: int) -> tuple[float, bool]:
        """A datagram's reception time (and the kernel's drop count), and whether it holds frames to decode: not
        cut short, not empty, not our own looped back."""
        c = self._c
        timestamp = 0.0
        for level, kind, payload in ancillary:
            if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS and len(payload) >= _TIMESPEC.size:
                sec, nsec = _TIMESPEC.unpack_from(payload)
                timestamp = sec + nsec * 1e-9
            elif level == socket.SOL_SOCKET and kind == _SO_RXQ_OVFL and len(payload) >= _U32.size:
                # the kernel's drops include the echoes our filter took
                c["kernel_drops"] = max(0, _U32.unpack_from(payload)[0] - self._filtered)
        if flags & _MSG_TRUNC or not raw:  # longer than DATAGRAM_MAX (cut: nobody of ours sends that), or empty
            c["undecodable"] += 1
            return timestamp, False
        if not self.receive_own_messages and raw.startswith(self._own_prefix):
            c["own_echoes_dropped"] += raw.count(self._own_prefix)  # our own datagram, looped back: not decoded
            return timestamp, False
        return timestamp, True

    def _unpacked(self, raw: bytes) -> list[tuple[dict[str, Any], bool]]:
        """The frames of a datagram (maps back to back) with the sender checks: (fields, whether our own echo)."""
        c = self._c
        frames: list[tuple[dict[str, Any], bool]] = []
        unpacker = msgpack.Unpacker(raw=False, max_buffer_size=DATAGRAM_MAX)  # a batch: maps back to back
        unpacker.feed(raw)
        end = 0
        while True:
            try:
                fields = unpacker.unpack()
            except msgpack.OutOfData:
                if end < len(raw):  # a map cut short
                    c["undecodable"] += 1
                break
            except (ValueError, TypeError, msgpack.UnpackException):
                c["undecodable"] += 1  # nothing after a broken map can be read
                break
            end = unpacker.tell()
            if not isinstance(fields, dict):  # not a frame: the rest of the datagram is not ours to guess at
                c["undecodable"] += 1
                break
            try:
                stamp = fields.get("channel")
                own = False
                if isinstance(stamp, int) and stamp >> 32:
                    token = stamp >> 32
                    if token == self._token:
                        c["own_echoes_dropped"] += 1
                        if not self.receive_own_messages:
                            continue
                        own = True
                    elif not self._accept(token, stamp & 0xFFFFFFFF):
                        continue
                else:
                    c["foreign_frames"] += 1
                if fields["is_fd"] and self._can_protocol is not can.CanProtocol.CAN_FD:
                    c["fd_frames_dropped"] += 1
                    continue
            except (TypeError, KeyError, AttributeError):
                c["undecodable"] += 1
                continue
            frames.append((fields, own))
        return frames

    def drain(self, on_data: Callable[[int, bytes | bytearray], bool], on_message: Callable[[can.Message], None],
              limit: int = 64, until: Callable[[], bool] | None = None) -> int:
        """Take every datagram already queued (at most ``limit``; none after one that makes ``until()`` true) without
        waiting; returns how many were read.

        A plain data frame (standard id, not remote, not an error frame) is first offered to ``on_data(cob_id,
        data)``; when that returns True it is consumed without a ``can.Message`` (the 1 kHz cycle's TPDOs).
        Every other accepted frame that passes the bus's filters (``set_filters``: e.g. no 29-bit ids) goes to
        ``on_message`` as a ``can.Message``. Echo, duplicate and loss handling and the counters are those of ``recv``.
        Inside the callbacks ``rx_timestamp`` is the kernel's reception time of the frame's datagram (wall clock).
        """
        recvmsg, size, anc_size, c = self._sock.recvmsg, DATAGRAM_MAX, self._ancillary_size, self._c
        pending = self._pending
        while pending:  # left by recv() in the middle of a batch
            msg = pending.popleft()
            if self._matches_filters(msg):
                on_message(msg)
        n = 0
        while n < limit:
            try:
                raw, ancillary, flags, _ = recvmsg(size, anc_size, socket.MSG_DONTWAIT)
            except BlockingIOError:
                break
            except OSError as exc:
                raise can.CanOperationError(f"{self.channel_info}: receive failed: {exc}") from exc
            n += 1
            messages: list[can.Message] = []
            with self._rx_lock:
                timestamp, readable = self._receipt(raw, ancillary, flags)
                self.rx_timestamp = timestamp
                expected = self._expected_frames(raw) if readable and self._expected else None
                if expected is not None:
                    c["template_datagrams"] += 1
                    self._take_expected(expected, timestamp, on_data, messages)
                for fields, own in (self._unpacked(raw) if readable and expected is None else ()):
                    try:
                        plain = not (own or fields["is_extended_id"] or fields["is_remote_frame"]
                                     or fields["is_error_frame"])
                        if plain and on_data(fields["arbitration_id"], fields["data"]):
                            c["frames_received"] += 1
                            continue
                    except (TypeError, KeyError):
                        c["undecodable"] += 1
                        continue
                    decoded = self._message(fields, timestamp, own)
                    if decoded is not None:
                        messages.append(decoded)
            for msg in messages:
                if self._matches_filters(msg):  # the bus's can_filters, as recv() applies them
                    on_message(msg)
            if until is not None and until():
                break  # (what is still queued keeps the socket readable: the loop calls again)
        return n

    def _take_expected(self, frames: list[tuple[int, int, bytes, dict[str, Any]]], timestamp: float,
                       on_data: Callable[[int, bytes | bytearray], bool], messages: list[can.Message]) -> None:
        """``drain`` of expected frames: the sender checks and delivery of ``_unpacked`` and ``drain``'s loop, by the
        stamp and the template's fields instead of a map per frame (plain data frames: ``on_data`` first)."""
        c, own, senders = self._c, self._token, self._senders
        accepted = []
        for frame in frames:  # every frame's sender checks before any delivery (as _unpacked before drain's loop)
            stamp = frame[0]
            token = stamp >> 32
            if token:
                if token == own:
                    c["own_echoes_dropped"] += 1
                    continue  # (``expect`` is off with receive_own_messages)
                seq = stamp & 0xFFFFFFFF
                state = senders.get(token)
                if state is not None and seq == (state[0] + 1) & 0xFFFFFFFF:  # the next in sequence: as _accept does
                    state[0] = seq
                    state[1] = ((state[1] << 1) | 1) & _WINDOW_MASK
                elif not self._accept(token, seq):
                    continue
            else:
                c["foreign_frames"] += 1
            accepted.append(frame)
        for stamp, arbitration_id, data, fields in accepted:
            try:
                if on_data(arbitration_id, data):
                    c["frames_received"] += 1
                    continue
            except (TypeError, KeyError):
                c["undecodable"] += 1  # (as drain's loop counts what on_data could not take)
                continue
            decoded = self._message({**fields, "channel": stamp, "data": data}, timestamp, False)
            if decoded is not None:
                messages.append(decoded)

    def _accept(self, token: int, seq: int) -> bool:
        """Sequence bookkeeping for one sender; False for a duplicate or a hopelessly late frame."""
        c = self._c
        state = self._senders.get(token)
        if state is None:
            self._senders[token] = [seq, 1]
            return True
        newest, window = state
        ahead = (seq - newest) & 0xFFFFFFFF
        if ahead and ahead < 0x80000000:
            if ahead > 1:
                c["gaps"] += ahead - 1
            state[0] = seq
            state[1] = ((window << ahead) | 1) & _WINDOW_MASK if ahead < _WINDOW else 1
            return True
        behind = (newest - seq) & 0xFFFFFFFF
        if behind >= _WINDOW:
            c["too_late_dropped"] += 1
            return False
        bit = 1 << behind
        if window & bit:
            c["duplicates_dropped"] += 1
            return False
        state[1] = window | bit
        c["gaps"] -= 1
        c["reordered"] += 1
        return True

    # --- misc --------------------------------------------------------------------------------------------
    def counters(self) -> UdpBusCounters:
        """Current counter values."""
        with self._rx_lock:
            return UdpBusCounters(rcvbuf_bytes=self.rcvbuf_bytes, **self._c)

    def fileno(self) -> int:
        return self._sock.fileno()

    def shutdown(self) -> None:
        if self._is_shutdown:
            return
        super().shutdown()
        self._sock.close()
