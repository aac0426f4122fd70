"""Reading a bus in the asyncio loop: every frame already queued in one go, the cycle's TPDOs without objects.

``BusReader`` does for the daemon what ``can.Notifier`` does (hands each frame to ``can.Listener``s, ``stop``,
``exception``; a reader thread for buses without a file descriptor), through python-can's public API only:
``bus.fileno()`` watched with ``loop.add_reader``, ``bus.recv``, ``Listener.on_message_received`` / ``on_error`` /
``stop``. What it does differently is why it exists: its loop callback takes every frame already waiting instead of
one per wake-up — at 1 kHz the six TPDOs of a cycle arrive in a burst, and one epoll wake-up + loop iteration per
frame cost more than decoding. dragd's own udp_multicast bus (``UdpMulticastCanBus.drain``) hands plain data frames
to ``on_data(cob_id, data)`` first; the frames it claims (the cyclic TPDOs, decoded straight into the feedback
arrays) never become ``can.Message`` objects. Everything else reaches the listeners. ``after`` runs once the frames
of a wake-up are all delivered: the cycle's read step ends there (hardware/io.py ``BusIO.after_frames``), in the same
loop callback, without a future or a task wake-up. The daemon's readers are the cycle's I/O's (``BusIO.open_readers``);
the SDO master's canopen ``Network`` joins one as listeners and takes it as its ``notifier`` (it calls ``stop`` and
reads ``exception``).
"""

from __future__ import annotations

import asyncio
import logging
import threading
from collections.abc import Callable

import can

from dragd.hardware.bus import UdpMulticastCanBus

MAX_FRAMES_PER_WAKEUP = 64  # a flood cannot hold the loop: the rest waits for the next iteration

log = logging.getLogger(__name__)


class BusReader:
    """Reads one bus in ``loop``: ``on_data`` claims plain data frames first, the listeners get the rest."""

    def __init__(self, bus: can.BusABC, listeners: list[can.Listener], *, timeout: float = 1.0,
                 loop: asyncio.AbstractEventLoop,
                 on_data: Callable[[int, bytes | bytearray], bool] | None = None,
                 after: Callable[[], None] | None = None, until: Callable[[], bool] | None = None) -> None:
        """``until()`` true: the wake-up has what it waited for; later frames wait for the next (the socket stays
        readable), which saves the read that would find the queue empty. ``timeout``: the reader thread's ``recv``
        wait (buses without a file descriptor), which bounds how long ``stop`` waits for it."""
        self.bus = bus
        self.listeners = list(listeners)
        self.timeout = timeout
        self.exception: Exception | None = None  # what the reader thread died of (as ``can.Notifier.exception``)
        self._loop = loop
        self._on_data = on_data or (lambda cob, data: False)
        self._after = after or (lambda: None)
        self._until = until or (lambda: False)
        self._stopped = False
        self._fd = -1
        self._thread: threading.Thread | None = None
        try:
            self._fd = bus.fileno()
        except NotImplementedError:
            pass
        if self._fd >= 0:
            readable = self._drain if isinstance(bus, UdpMulticastCanBus) else self._read_queued
            loop.add_reader(self._fd, readable)
        else:
            self._thread = threading.Thread(target=self._rx_thread, name=f"dragd-reader {bus.channel_info}",
                                            daemon=True)
            self._thread.start()

    def add_listener(self, listener: can.Listener) -> None:
        self.listeners.append(listener)

    def stop(self, timeout: float = 5.0) -> None:
        """No more frames to the listeners; each listener's ``stop``; the reader thread joined (up to ``timeout``)."""
        self._stopped = True
        if self._fd >= 0:
            self._loop.remove_reader(self._fd)
            self._fd = -1
        if self._thread is not None:
            self._thread.join(timeout)
        for listener in self.listeners:
            listener.stop()

    # --- the loop's callbacks --------------------------------------------------------------------------
    def _drain(self) -> None:
        """dragd's udp_multicast bus: every queued datagram, plain data frames to ``on_data`` without a Message."""
        bus = self.bus
        assert isinstance(bus, UdpMulticastCanBus)
        bus.drain(self._on_data, self._deliver, MAX_FRAMES_PER_WAKEUP, self._until)
        self._after()

    def _read_queued(self) -> None:
        """Any other bus with a file descriptor (socketcan): ``recv(0)`` until the queue is empty (or ``until``)."""
        recv, until = self.bus.recv, self._until
        for _ in range(MAX_FRAMES_PER_WAKEUP):
            msg = recv(0)
            if msg is None:
                break
            self._take(msg)
            if until():
                break
        self._after()

    def _received(self, msg: can.Message) -> None:
        """One frame from the reader thread (a loop callback per frame)."""
        if self._stopped:
            return
        self._take(msg)
        self._after()

    def _take(self, msg: can.Message) -> None:
        """``on_data`` first, the listeners for what it does not claim."""
        if (msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame
                or not self._on_data(msg.arbitration_id, msg.data)):
            self._deliver(msg)

    def _deliver(self, msg: can.Message) -> None:
        for listener in self.listeners:
            listener.on_message_received(msg)

    # --- buses without a file descriptor -----------------------------------------------------------------
    def _rx_thread(self) -> None:
        recv, timeout = self.bus.recv, self.timeout
        call_soon = self._loop.call_soon_threadsafe
        while not self._stopped:
            try:
                msg = recv(timeout)
            except Exception as exc:  # the bus failed: the listeners hear it, canopen's Network.check raises it
                self.exception = exc
                if not self._stopped:
                    call_soon(self._error, exc)
                return
            if msg is not None:
                call_soon(self._received, msg)

    def _error(self, exc: Exception) -> None:
        handled = False
        for listener in self.listeners:
            try:
                listener.on_error(exc)
            except NotImplementedError:
                continue
            handled = True
        if not handled:
            log.error("bus %s: receive failed, no more frames are read: %s", self.bus.channel_info, exc)
