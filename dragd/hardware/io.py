"""The cycle's process data on the buses: SYNC out, TPDOs in (decoded into arrays), command RPDOs out, heartbeat.

``BusIO`` owns the buses' readers (``open_readers``: a ``BusReader`` per bus, hardware/reader.py, in the asyncio
loop's thread; the SDO master's canopen networks join them as listeners). The cycle makes one call per period,
``cycle``: the SYNC leaves (on a batching bus together with the command frames the previous step wrote), and the
period's feedback comes back decoded into the preallocated ``Feedback`` arrays, handed over by a plain call
(``on_feedback(complete)``): no future, no task wake-up. A frame's way, by calls: the socket is readable →
``BusReader._drain`` (or ``_read_queued``) → ``UdpMulticastCanBus.drain`` → the bus's ``tpdo_decoder`` →
``BusIO._tpdo`` (``struct`` codecs straight into the arrays; anything else becomes a ``can.Message`` for
``listener``: EMCYs to ``on_emcy``, SDO and heartbeats to canopen) → ``BusReader`` calls ``after_frames`` once the
wake-up's frames are decoded → ``end_read_step`` when every joint's position TPDO arrived (or the deadline timer,
or the simulator's TIME frame on the lockstep clock) → ``on_feedback``. ``write`` packs the controlwords, target
positions and torque commands into each command frame's preallocated buffer. The frames' fields, offsets and struct
codes come from the bus's layout (planned from each drive's EDS: hardware/pdo.py), precompiled once.
"""

from __future__ import annotations

import asyncio
import struct
from collections.abc import Callable

import can
import numpy as np

from dragd.clock import TIME_COB_ID
from dragd.hardware.bus import PreparedBatch, UdpMulticastCanBus
from dragd.hardware.cia301 import EMCY_BASE, HEARTBEAT_BASE, SYNC_COB_ID
from dragd.hardware.pdo import BusLayout, RpdoEncoder
from dragd.hardware.reader import BusReader

# joint, codec, and where the codec's values hold the position, the statusword, the current and the digital inputs
# (-1: not in the frame)
Decoder = tuple[int, struct.Struct, int, int, int, int]
# a batching bus's prepared datagram, each command frame's (datagram view, encoder buffer), the frames themselves
_Batch = tuple[PreparedBatch, list[tuple[memoryview, bytearray]], list[can.Message]]


class Feedback:
    """What the drives reported, in drive units (filled by the read step)."""

    def __init__(self, n: int) -> None:
        self.counts = np.zeros(n, dtype=np.int64)  # 6064h
        self.statusword = np.zeros(n, dtype=np.int64)  # 6041h
        self.current_permille = np.zeros(n)  # the current object (6078h: per mille of rated current), the drive's sign
        self.rx = np.zeros(n, dtype=bool)  # the position TPDO arrived this cycle
        self.stale = np.zeros(n, dtype=np.int64)  # cycles since each joint's last position TPDO
        self.rx_count = 0  # joints whose position TPDO arrived this cycle
        self.inputs = np.zeros(n, dtype=np.int64)  # the digital inputs word (60FDh) where a TPDO carries it
        self.inputs_age = np.full(n, 1 << 40, dtype=np.int64)  # cycles since that TPDO arrived (none yet: ages)

    def worst_stale(self) -> tuple[int, int]:
        """(cycles, joint) of the stalest joint; (0, 0) when every TPDO arrived this cycle."""
        if self.rx_count >= self.rx.shape[0]:
            return 0, 0
        return int(self.stale.max()), int(self.stale.argmax())


class BusIO:
    """SYNC, TPDO decoding, command RPDOs and the master heartbeat of every bus of one arm."""

    def __init__(self, layouts: dict[str, BusLayout], buses: dict[str, can.BusABC], node_ids: list[int],
                 master_node_id: int, on_emcy: Callable[[int, int, int], None]) -> None:
        """A bus opened with ``batch_frames`` (udp_multicast) carries a cycle's cyclic command frames in one datagram
        with the next SYNC (see ``write``)."""
        n = self.n = len(node_ids)
        self.feedback = Feedback(n)
        self.layouts = layouts
        self.on_emcy = on_emcy
        self.tx_errors = 0
        self.error_frames = 0
        self.rejected_frames = 0  # 29-bit ids, RTR, TPDOs shorter than their mapping: dropped, never decoded
        self.duplicate_tpdos = 0  # a joint's position TPDO a second time within one cycle
        # a statusword the step has not seen yet, and one that arrived after it, different, before the step (a late
        # TPDO merged with the next): the step sees every reported state in order (``statuswords_seen``)
        self._sw_unseen = np.zeros(n, dtype=bool)
        self._sw_later = np.zeros(n, dtype=np.int64)
        self._sw_held = np.zeros(n, dtype=bool)
        self._sw_holding = False
        self.deferred_statuswords = 0  # such statuswords, shown to the step one cycle later
        self.reading = False  # a read step is open: SYNC sent, waiting for TPDOs or the deadline
        # the lockstep clock's TIME frames (bus name, data); set before the listeners are made (dragd/clock.py). On
        # that clock the read step ends only when the simulator ended its period (every bus's TIME frame: then every
        # frame of the period was decoded, whichever bus's datagram came first), never on the TPDOs alone
        self.on_time: Callable[[str, bytes | bytearray], None] | None = None
        self._period_ended = {name: False for name in layouts}  # (lockstep) the bus's TIME frame since the SYNC
        self._on_read: Callable[[bool], None] = lambda complete: None
        self._deadline_handle: asyncio.TimerHandle | None = None
        self._decoders: dict[str, dict[int, Decoder]] = {}
        # (bus, frame, encoder, whether the frame waits for the next SYNC: cyclic on a batching bus)
        self._commands: list[tuple[can.BusABC, can.Message, RpdoEncoder, bool]] = []
        self._sync: list[tuple[can.BusABC, can.Message]] = []
        self._heartbeat: list[tuple[can.BusABC, can.Message]] = []
        # per batching bus: its cyclic command frames and SYNC as one prepared datagram (each frame's payload copied
        # from its encoder's buffer when it leaves), and the frames themselves (``flush``)
        self._batched: dict[can.BusABC, _Batch] = {}
        self._commands_wait = False  # write() left cyclic command frames for the next SYNC
        for name, layout in layouts.items():
            bus = buses[name]
            fd = layout.fd
            table = self._decoders.setdefault(name, {})
            for fr in layout.frames:
                if fr.direction == "tpdo":
                    (slot,) = fr.slots
                    at = {f: i for i, f in enumerate(slot.fields)}
                    table[fr.cob_id] = (slot.joint, struct.Struct(slot.fmt), at.get("position", -1),
                                        at.get("statusword", -1), at.get("current", -1), at.get("inputs", -1))
                else:
                    enc = RpdoEncoder(fr, fd, min_interval_s=1.0 / fr.max_rate_Hz)
                    msg = can.Message(arbitration_id=fr.cob_id, data=enc.buffer, is_extended_id=False,
                                      is_fd=fd, bitrate_switch=fd, dlc=len(enc.buffer))
                    with_sync = enc.cyclic and isinstance(bus, UdpMulticastCanBus) and bus.batch_frames
                    self._commands.append((bus, msg, enc, with_sync))
            self._sync.append((bus, can.Message(arbitration_id=SYNC_COB_ID, data=b"", is_extended_id=False)))
            synced = [(msg, enc) for b, msg, enc, with_sync in self._commands if b is bus and with_sync]
            if synced:
                frames = [(msg.arbitration_id, len(enc.buffer), fd) for msg, enc in synced] + [(SYNC_COB_ID, 0, False)]
                assert isinstance(bus, UdpMulticastCanBus)
                batch = bus.prepare(frames)
                views = [(view, enc.buffer) for view, (_, enc) in zip(batch.data, synced, strict=False)]  # (+ SYNC)
                self._batched[bus] = (batch, views, [msg for msg, _ in synced])
            self._heartbeat.append((bus, can.Message(arbitration_id=HEARTBEAT_BASE + master_node_id, data=b"\x05",
                                                     is_extended_id=False)))
            if isinstance(bus, UdpMulticastCanBus):  # the TPDOs read by their template, without unpacking maps
                tpdos = [fr for fr in layout.frames if fr.direction == "tpdo"]  # (on an FD bus: FD or classic)
                bus.expect([(fr.cob_id, fr.data_bytes, kind) for fr in tpdos for kind in {fd, False}])
        self._emcy = {EMCY_BASE + node: i for i, node in enumerate(node_ids)}
        self._node_ids = list(node_ids)
        self._buses = [buses[name] for name in layouts]
        self._bus_by_name = {name: buses[name] for name in layouts}
        self.readers: dict[str, BusReader] = {}  # (open_readers)
        self._loop: asyncio.AbstractEventLoop | None = None

    def open_readers(self, loop: asyncio.AbstractEventLoop) -> dict[str, BusReader]:
        """Start reading every bus in ``loop``: its cyclic TPDOs decoded without a ``can.Message``
        (``tpdo_decoder``), the rest to ``listener`` (and to whatever joins the reader: the SDO master's canopen
        network), the read step judged after each wake-up's frames (``after_frames``, ``read_done``)."""
        self._loop = loop
        for name, bus in self._bus_by_name.items():
            self.readers[name] = BusReader(bus, [self.listener(name)], timeout=0.5, loop=loop,
                                           on_data=self.tpdo_decoder(name), after=self.after_frames,
                                           until=self.read_done if self.on_time is None else self._time_until(name))
        return self.readers

    def _time_until(self, bus_name: str) -> Callable[[], bool]:
        """The lockstep clock's ``until`` for one bus's reader: that bus's TIME frame ended the period (its datagram
        was the period's last: the reader need not look for more, which saves the read that finds the queue empty;
        anything queued later keeps the socket readable and is read before the next tick)."""
        ended = self._period_ended

        def period_ended() -> bool:
            return ended[bus_name]

        return period_ended

    def close_readers(self) -> None:
        """Stop reading the buses (each reader's listeners stopped)."""
        for reader in self.readers.values():
            reader.stop(timeout=0.5)
        self.readers = {}

    def expect_lockstep(self) -> None:
        """The lockstep clock: the simulator's datagram per period also carries its TIME frame and, when due, the
        drives' heartbeats; a bus that reads by template (udp_multicast ``expect``) learns them too."""
        for bus in self._buses:
            if isinstance(bus, UdpMulticastCanBus):
                bus.expect([(TIME_COB_ID, 6, False)] + [(HEARTBEAT_BASE + node, 1, False) for node in self._node_ids])

    # ------------------------------------------------------------------------------------------ read

    def listener(self, bus_name: str) -> can.Listener:
        """The Notifier listener of one bus (runs in the loop's thread)."""
        on_frame, table = self.on_frame, self._decoders.setdefault(bus_name, {})
        time_frame = self.tpdo_decoder(bus_name)

        class _Rx(can.Listener):
            def on_message_received(self, msg: can.Message) -> None:
                on_frame(msg, table)

        if self.on_time is None:
            return _Rx()

        class _RxTime(can.Listener):  # the lockstep clock: the simulator's TIME frame ends its period
            def on_message_received(self, msg: can.Message) -> None:  # (a reader's on_data takes it first)
                if msg.arbitration_id == TIME_COB_ID and not (msg.is_extended_id or msg.is_remote_frame
                                                              or msg.is_error_frame):
                    time_frame(TIME_COB_ID, msg.data)
                    return
                on_frame(msg, table)

        return _RxTime()

    def on_frame(self, msg: can.Message, table: dict[int, Decoder]) -> None:
        """Decode a TPDO into the feedback arrays, or report an EMCY.

        Error frames are counted, never decoded: their class bits can equal a COB-ID (0x081 = a node 1 EMCY);
        29-bit, RTR and too-short frames are counted as rejected; a second position TPDO of a joint within one
        cycle (a duplicate) is counted and decoded (the same sample).
        """
        if msg.is_error_frame:
            self.error_frames += 1
            return
        if msg.is_extended_id or msg.is_remote_frame:  # a 29-bit id can equal a COB-ID; an RTR carries no data
            self.rejected_frames += 1
            return
        if self._tpdo(msg.arbitration_id, msg.data, table):
            return
        emcy_joint = self._emcy.get(msg.arbitration_id)
        if emcy_joint is not None and len(msg.data) >= 3:
            code = msg.data[0] | (msg.data[1] << 8)
            if code != 0:
                self.on_emcy(emcy_joint, code, msg.data[2])

    def tpdo_decoder(self, bus_name: str) -> Callable[[int, bytes | bytearray], bool]:
        """``on_data`` for the bus's reader: decodes a (plain data) frame that is a TPDO, True if it was one. On the
        lockstep clock (``on_time`` set) it also takes the simulator's TIME frame (without a ``can.Message``)."""
        table, tpdo, on_time = self._decoders.setdefault(bus_name, {}), self._tpdo, self.on_time

        def decode_tpdo(cob: int, data: bytes | bytearray) -> bool:
            return tpdo(cob, data, table)

        if on_time is None:
            return decode_tpdo
        ended = self._period_ended

        def decode_lockstep(cob: int, data: bytes | bytearray) -> bool:
            if cob == TIME_COB_ID:
                ended[bus_name] = True
                on_time(bus_name, data)
                return True
            return tpdo(cob, data, table)

        return decode_lockstep

    def _tpdo(self, cob: int, data: bytes | bytearray, table: dict[int, Decoder]) -> bool:
        entry = table.get(cob)
        if entry is None:
            return False
        j, codec, at_position, at_statusword, at_current, at_inputs = entry
        if len(data) < codec.size:
            self.rejected_frames += 1
            return True
        fb = self.feedback
        values = codec.unpack_from(data)
        if at_position >= 0:
            if fb.rx[j]:
                self.duplicate_tpdos += 1
            fb.counts[j] = values[at_position]
        if at_current >= 0:
            fb.current_permille[j] = values[at_current]
        if at_inputs >= 0:
            fb.inputs[j] = values[at_inputs]
            fb.inputs_age[j] = 0
        if at_statusword >= 0:
            v = values[at_statusword]
            if self._sw_unseen[j] and v != fb.statusword[j]:
                # a second, different statusword before the step saw the first (the first came late): the first
                # stays for this step (a drive that left operation enabled for one sample is not overwritten by its
                # re-enabled next one); this one is the next step's
                self._sw_later[j] = v
                self._sw_held[j] = True
                self._sw_holding = True
                self.deferred_statuswords += 1
            else:
                fb.statusword[j] = v
                self._sw_unseen[j] = True
        if at_position >= 0 and not fb.rx[j]:
            fb.rx[j] = True
            fb.rx_count += 1
        return True

    def statuswords_seen(self) -> None:
        """The step has judged the statuswords: a deferred one becomes the next step's (the rare path)."""
        unseen = self._sw_unseen
        unseen.fill(False)
        if self._sw_holding:
            held = self._sw_held
            np.copyto(self.feedback.statusword, self._sw_later, where=held)
            np.copyto(unseen, held)
            held.fill(False)
            self._sw_holding = False

    def begin_cycle(self) -> None:
        """Before the SYNC: nothing has arrived for this cycle yet."""
        self.feedback.rx.fill(False)
        self.feedback.rx_count = 0
        self.feedback.inputs_age += 1
        if self.on_time is not None:
            ended = self._period_ended
            for name in ended:
                ended[name] = False

    def end_read(self) -> bool:
        """After the read step: age the joints that did not report; True when every joint reported."""
        fb = self.feedback
        if fb.rx_count >= self.n:  # (the usual cycle: every joint reported)
            fb.stale.fill(0)
            return True
        np.add(fb.stale, 1, out=fb.stale)
        np.copyto(fb.stale, 0, where=fb.rx)  # (a boolean-mask assignment would allocate)
        return False

    def cycle(self, deadline_s: float | None, on_feedback: Callable[[bool], None],
              loop: asyncio.AbstractEventLoop | None = None) -> None:
        """The period's exchange, one call: SYNC out (on a batching bus with the command frames ``write`` left for
        it, in one datagram), the period's TPDOs decoded into ``feedback`` as they arrive, then
        ``on_feedback(complete)`` once, in the loop's thread: True when every joint's position TPDO arrived, False
        when ``deadline_s`` passed first. Without a deadline (the lockstep clock) the read step ends when the
        TPDOs are complete or someone calls ``end_read_step`` (the simulator's TIME frame). ``loop``: the readers'
        (``open_readers``) unless given."""
        loop = loop if loop is not None else self._loop
        assert loop is not None, "BusIO.cycle: open_readers(loop) first, or give the loop"
        self.begin_cycle()
        self._on_read = on_feedback
        self.reading = True
        if self._commands_wait:
            self._send_with_sync()
        else:
            self._send(self._sync)
        if deadline_s is not None:
            self._deadline_handle = loop.call_at(loop.time() + deadline_s, self.end_read_step)

    def read_done(self) -> bool:
        """The open read step has every joint's position TPDO (the reader need not look for more now)."""
        return self.reading and self.feedback.rx_count >= self.n and self.on_time is None

    def after_frames(self) -> None:
        """A wake-up's frames are all decoded: the read step ends if every joint has reported."""
        if self.read_done():
            self.end_read_step()

    def end_read_step(self) -> None:
        """End the open read step now (the deadline; a tick that finds it still open): ``on_read`` runs."""
        if not self.reading:
            return
        self.abandon_read()
        self._on_read(self.end_read())

    def abandon_read(self) -> None:
        """Close an open read step without ``on_read`` (the cycle is stopping)."""
        self.reading = False
        if self._deadline_handle is not None:
            self._deadline_handle.cancel()
            self._deadline_handle = None

    async def read(self, loop: asyncio.AbstractEventLoop, deadline_s: float) -> bool:
        """``cycle`` awaited: True when every joint's position TPDO arrived, False at the deadline."""
        done: asyncio.Future[bool] = loop.create_future()
        self.cycle(deadline_s, done.set_result, loop)
        try:
            return await done
        finally:
            self.abandon_read()

    # ------------------------------------------------------------------------------------------ write

    def write(self, cw_array: np.ndarray, counts_array: np.ndarray, permille_array: np.ndarray, t: float) -> None:
        """Pack every command frame and send the ones due (cyclic frames always; event frames on change).

        On a bus that batches (udp_multicast with ``batch_frames``) the cyclic frames leave with the next cycle's
        SYNC, in one datagram ahead of it: a synchronous RPDO is applied at the next SYNC wherever it arrives in the
        cycle (CiA 301; no synchronous window, 1007h, is configured), so the drives apply the same command at the same
        SYNC, and the cycle makes one send (and wakes the drives once) instead of two. Event-driven frames leave at
        once, as on any other bus."""
        # one conversion per array (numpy scalars per element cost ~18 object creations a cycle)
        cw, target_counts, torque_permille = cw_array.tolist(), counts_array.tolist(), permille_array.tolist()
        for bus, msg, enc, with_sync in self._commands:
            buf = enc.buffer
            for j, off, codec, kind in enc.slots:  # (kinds: pdo.RpdoEncoder.KINDS)
                if kind == 0:
                    codec.pack_into(buf, off, int(cw[j]), int(target_counts[j]), int(torque_permille[j]))
                elif kind == 1:
                    codec.pack_into(buf, off, int(torque_permille[j]))
                elif kind == 2:
                    codec.pack_into(buf, off, int(cw[j]))
                elif kind == 3:
                    codec.pack_into(buf, off, int(target_counts[j]), int(torque_permille[j]))
                elif kind == 4:
                    codec.pack_into(buf, off, int(cw[j]), int(torque_permille[j]))
            for j, off, codec, f in enc.loose:  # a drive's fixed mapping in an order of its own: field by field
                codec.pack_into(buf, off, int(cw[j] if f == "controlword" else target_counts[j]
                                              if f == "target_position" else torque_permille[j]))
            if not enc.due(t):
                continue
            if with_sync:
                self._commands_wait = True  # (its buffer is packed again only after the next read)
                enc.sent(t)
                continue
            try:
                bus.send(msg, timeout=0)
                enc.sent(t)
            except can.CanError:
                self.tx_errors += 1

    def flush(self) -> None:
        """Send command frames still waiting for a SYNC (the cycle stops: they must not be lost)."""
        if not self._commands_wait:
            return
        self._commands_wait = False
        self._send([(bus, msg) for bus, (_, _, msgs) in self._batched.items() for msg in msgs])

    def _send_with_sync(self) -> None:
        """Each bus's waiting command frames and its SYNC, in that order, as one (prepared) datagram."""
        self._commands_wait = False
        for bus, sync in self._sync:
            entry = self._batched.get(bus)
            try:
                if entry is None:
                    bus.send(sync, timeout=0)
                    continue
                batch, payloads, _ = entry
                for view, buffer in payloads:
                    view[:] = buffer
                bus.send_prepared(batch)  # type: ignore[attr-defined]
            except can.CanError:
                self.tx_errors += 1

    def heartbeat(self) -> None:
        self._send(self._heartbeat)

    def _send(self, frames: list[tuple[can.BusABC, can.Message]]) -> None:
        for bus, msg in frames:
            try:
                bus.send(msg, timeout=0)
            except can.CanError:
                self.tx_errors += 1

    @property
    def compact_buses(self) -> list[str]:
        """Buses whose layout carries no position targets (no CSP: drag, hold and idle only)."""
        return [name for name, lay in self.layouts.items() if not lay.position_targets]
