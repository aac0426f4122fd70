"""Reading a bus in the asyncio loop: every frame already queued in one go, the cycle's TPDOs without objects.

``DrainingNotifier`` is a ``can.Notifier`` (listeners, ``stop``, ``exception``, a reader thread for buses without
a file descriptor) whose loop callback takes every frame already waiting instead of one per wake-up: at 1 kHz the
six TPDOs of a cycle arrive in a burst, and one epoll wake-up + loop iteration per frame cost more than decoding.
A bus with ``drain`` (the host-local udp_multicast bus) hands plain data frames to ``on_data(cob_id, data)``
first; the frames it claims (the cyclic TPDOs, decoded straight into the feedback arrays) never become
``can.Message`` objects. Everything else reaches the listeners as before. ``after`` runs once the frames of a
wake-up are all delivered: the cycle's read step ends there (hardware/io.py ``BusIO.after_frames``), in the same
loop callback, without a future or a task wake-up.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable

import can

MAX_FRAMES_PER_WAKEUP = 64  # a flood cannot hold the loop: the rest waits for the next iteration


class DrainingNotifier(can.Notifier):
    """``can.Notifier`` that drains the bus on each wake-up; ``on_data`` claims frames before the listeners."""

    def __init__(self, bus: can.BusABC, listeners: list[can.Listener], *, timeout: float = 1.0,
                 loop: asyncio.AbstractEventLoop | None = None,
                 on_data: Callable[[int, bytes | bytearray], bool] | None = None,
                 after: Callable[[], None] | None = None, until: Callable[[], bool] | None = None) -> None:
        """``until()`` true: the wake-up has what it waited for; later frames wait for the next (the socket stays
        readable), which saves the read that would find the queue empty."""
        self._on_data = on_data or (lambda cob, data: False)
        self._after = after or (lambda: None)
        self._until = until or (lambda: False)
        super().__init__(bus, listeners, timeout=timeout, loop=loop)

    def _on_message_available(self, bus: can.BusABC) -> None:
        deliver = super()._on_message_received
        drain = getattr(bus, "drain", None)
        if drain is not None:
            drain(self._on_data, deliver, MAX_FRAMES_PER_WAKEUP, self._until)
        else:
            until = self._until
            for _ in range(MAX_FRAMES_PER_WAKEUP):
                msg = bus.recv(0)
                if msg is None:
                    break
                self._take(msg)
                if until():
                    break
        self._after()

    def _on_message_received(self, msg: can.Message) -> None:
        """One frame from the reader thread of a bus without a file descriptor (a loop callback per frame)."""
        self._take(msg)
        self._after()

    def _take(self, msg: can.Message) -> None:
        """``on_data`` first, the listeners for what it does not claim."""
        if msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame or not self._on_data(msg.arbitration_id,
                                                                                                 msg.data):
            super()._on_message_received(msg)
