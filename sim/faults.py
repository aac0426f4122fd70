"""Bus and node faults the simulated robot injects on command (control socket ``inject``; docs/SAFETY.md).

Every drive transmits through ``FaultInjector.sender(node_id)``; the network's reader thread asks ``rx_muted()``
before dispatching a frame. With no fault active a frame costs one attribute test and the bus's own ``send``.

Faults (``kind``):

- ``drive_silent``   node_id, seconds: the node transmits nothing (a cut cable; it still receives)
- ``burst_loss``     frames: the next N frames the drives transmit are lost
- ``duplicates``     frames: the next N frames are transmitted twice
- ``late_tpdo``      delay_ms, seconds: TPDOs leave ``delay_ms`` late (after the master's read deadline)
- ``emcy``           node_id, code: an EMCY (the error stays active; the drive keeps running)
- ``drive_fault``    node_id, code: a device fault (EMCY + the drive's fault reaction)
- ``switched_on``    node_id: the drive drops from operation enabled to switched on on its own (power off)
- ``node_reboot``    node_id: a power cycle of the node: objects back to defaults, boot-up, brake engaged
- ``bus_off``        seconds: the sim's link goes down (nothing in, nothing out), then comes back
- ``encoder_jump``   node_id, rad, seconds: the reported position jumps by ``rad`` (for ``seconds``; 0 = forever)
- ``garbage``        node_id: frames on the node's TPDO COB-ID a master must drop: short DLC, 29-bit id, RTR
- ``inputs_lost``    node_id, seconds: the node's TPDOs that carry its digital inputs (60FDh, or the object its
                     truth names) are lost — the rest of its frames pass (docs/HAND.md, docs/SAFETY.md)

Faults of the guiding device at the hand (a stuck or chattering contact, a cut cable) are the device's own:
sim/hand.py.
"""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable
from typing import Any

import can

from dragd.hardware.cia301 import (
    COB_ID_MASK,
    EMCY_BASE,
    HEARTBEAT_BASE,
    NODE_ID_MAX,
    PDO_COB_STEP,
    TPDO1_BASE,
)
from dragd.hardware.cia402 import EMCY_OVER_CURRENT, EMCY_TEMPERATURE_DEVICE, ERR_REG_GENERIC, State
from dragd.realtime import demote_current_thread

# 181h-4FFh: the pre-defined connection set's PDO COB-IDs from node 1's TPDO 1 to node 127's TPDO 4 (a 'late' fault
# delays these)
_PDO_COB_IDS = range(TPDO1_BASE + 1, TPDO1_BASE + 3 * PDO_COB_STEP + NODE_ID_MAX + 1)

KINDS = ("drive_silent", "burst_loss", "duplicates", "late_tpdo", "emcy", "drive_fault", "switched_on",
         "node_reboot", "bus_off", "encoder_jump", "garbage", "inputs_lost")


class FaultError(ValueError):
    """An inject request that names no known fault or carries a bad argument (the message says which)."""


class FaultInjector:
    """Faults on one bus: a gate on the drives' transmit path and on the reader's receive path."""

    def __init__(self, bus: can.BusABC, *, clock: Callable[[], float] = time.monotonic, lockstep: bool = False) -> None:
        """``clock``: the time fault windows are measured on (the simulated time on the lockstep clock, where
        delayed frames and timed ends are released by ``release_due`` at each period's end, not by threads)."""
        self.bus = bus
        self.clock = clock
        self.lockstep = lockstep
        self._due: list[tuple[float, Callable[[], None]]] = []  # lockstep: timed ends (encoder_jump seconds)
        self.active = False  # any transmit-side fault armed (the fast path tests only this)
        self.silent_until: dict[int, float] = {}
        self.silent_cobs: dict[int, float] = {}  # COB-ID -> until (inputs_lost)
        self.drop_frames = 0
        self.dup_frames = 0
        self.late_until = 0.0
        self.late_s = 0.0
        self.down_until = 0.0
        self.counters = collections.Counter[str]()
        self._late: collections.deque[tuple[float, can.Message]] = collections.deque()
        self._late_cv = threading.Condition()
        self._late_thread: threading.Thread | None = None

    # -------------------------------------------------------------------------------------- the gates

    def sender(self, node_id: int) -> Callable[[can.Message], None]:
        """The transmit function of one drive."""
        send = self.bus.send

        def tx(msg: can.Message) -> None:
            if self.active:
                self._tx_faulty(node_id, msg)
            else:
                send(msg)

        return tx

    def data_sender(self, node_id: int) -> Callable[[int, bytes, bool], None]:
        """The transmit function of one drive's plain data frames (its PDOs): without a ``can.Message`` where the bus
        has ``send_data`` and no fault is armed; otherwise through ``sender``'s path."""
        send_data = getattr(self.bus, "send_data", None)
        tx = self.sender(node_id)

        def tx_data(cob: int, data: bytes, fd: bool) -> None:
            if send_data is not None and not self.active:
                send_data(cob, data, fd)
            else:
                tx(can.Message(arbitration_id=cob, data=data, is_extended_id=False, is_fd=fd, bitrate_switch=fd,
                               check=False))

        return tx_data

    def rx_muted(self) -> bool:
        """True while the link is down (the reader drops what it receives)."""
        return self.down_until != 0.0 and self._down()

    def _down(self) -> bool:
        if self.clock() < self.down_until:
            return True
        self.down_until = 0.0
        self._rearm()
        return False

    def _tx_faulty(self, node_id: int, msg: can.Message) -> None:
        now = self.clock()
        c = self.counters
        if self.down_until and self._down():
            c["lost_link_down"] += 1
            return
        until = self.silent_until.get(node_id)
        if until is not None:
            if now < until:
                c["lost_silent"] += 1
                return
            del self.silent_until[node_id]
            self._rearm()
        if self.silent_cobs:
            until = self.silent_cobs.get(msg.arbitration_id)
            if until is not None:
                if now < until:
                    c["lost_inputs"] += 1
                    return
                del self.silent_cobs[msg.arbitration_id]
                self._rearm()
        if self.drop_frames > 0:
            self.drop_frames -= 1
            c["lost_burst"] += 1
            self._rearm()
            return
        if self.late_until:
            if now < self.late_until and msg.arbitration_id in _PDO_COB_IDS:
                c["late"] += 1
                with self._late_cv:
                    self._late.append((now + self.late_s, msg))
                    self._late_cv.notify()
                return
            if now >= self.late_until:
                self.late_until = 0.0
                self._rearm()
        self.bus.send(msg)
        if self.dup_frames > 0:
            self.dup_frames -= 1
            c["duplicated"] += 1
            self.bus.send(msg)
            self._rearm()

    def _rearm(self) -> None:
        self.active = bool(self.silent_until or self.drop_frames or self.dup_frames or self.late_until
                           or self.down_until or self.silent_cobs)

    def release_due(self, now: float) -> None:
        """Lockstep: at a period's end (sim time ``now``), send the delayed frames due by then and end what is due."""
        if self._late:
            batch = []
            with self._late_cv:
                while self._late and self._late[0][0] <= now + 1e-9:
                    batch.append(self._late.popleft()[1])
            for msg in batch:
                try:
                    self.bus.send(msg)
                except can.CanError:
                    self.counters["late_send_errors"] += 1
        if self._due:
            keep = []
            for due, fn in self._due:
                if due <= now + 1e-9:
                    fn()
                else:
                    keep.append((due, fn))
            self._due = keep

    def _late_sender(self) -> None:
        """Sends the delayed frames in batches (every frame due by now, then sleep until the next is due): one
        wake-up per millisecond at most, off the real-time policy, so the bus reader answering SYNCs never waits."""
        demote_current_thread()
        while True:
            with self._late_cv:
                while not self._late:
                    self._late_cv.wait()
                due = self._late[0][0]
            delay = due - time.monotonic()
            if delay > 0:
                time.sleep(max(delay, 0.0005))
            now = time.monotonic()
            batch = []
            with self._late_cv:
                while self._late and self._late[0][0] <= now:
                    batch.append(self._late.popleft()[1])
            for msg in batch:
                try:
                    self.bus.send(msg)
                except can.CanError:
                    self.counters["late_send_errors"] += 1

    # -------------------------------------------------------------------------------------- injection

    def inject(self, kind: str, drives: dict[int, Any], args: dict[str, Any], lock: threading.Lock) -> dict[str, Any]:
        """Arm one fault now; returns what was done with ``t_mono`` (CLOCK_MONOTONIC, s) of the injection."""
        if kind not in KINDS:
            raise FaultError(f"inject: kind: expected one of {', '.join(KINDS)}, got {kind!r}")
        now = self.clock()
        done: dict[str, Any] = {"kind": kind, "t_mono": now}  # (lockstep: the simulated time)

        def number(name: str, default: float | None, lo: float, hi: float) -> float:
            v = args.get(name, default)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not lo <= v <= hi:
                raise FaultError(f"inject {kind}: {name}: expected a number in [{lo:g}, {hi:g}], got {v!r}")
            done[name] = v
            return float(v)

        def node() -> Any:
            nid = args.get("node_id")
            if nid not in drives:
                raise FaultError(f"inject {kind}: node_id: expected one of {sorted(drives)}, got {nid!r}")
            done["node_id"] = nid
            return drives[nid]

        if kind == "drive_silent":
            d = node()
            self.silent_until[d.node_id] = now + number("seconds", 1.0, 0.001, 600.0)
        elif kind == "burst_loss":
            self.drop_frames += int(number("frames", 30, 1, 1e6))
        elif kind == "duplicates":
            self.dup_frames += int(number("frames", 30, 1, 1e6))
        elif kind == "late_tpdo":
            self.late_s = number("delay_ms", 3.0, 0.1, 1000.0) * 1e-3
            self.late_until = now + number("seconds", 0.2, 0.001, 600.0)
            if self._late_thread is None and not self.lockstep:
                self._late_thread = threading.Thread(target=self._late_sender, name="sim-late-tpdo", daemon=True)
                self._late_thread.start()
        elif kind == "bus_off":
            self.down_until = now + number("seconds", 1.0, 0.001, 600.0)
        elif kind == "inputs_lost":
            d = node()
            index = d.profile.bindings["digital_inputs"].index
            cobs = [ch.cob_id & COB_ID_MASK for ch in d.tpdos if ch.valid
                    and any((e.index, e.subindex) == (index, d.profile.bindings["digital_inputs"].subindex)
                            for e in ch.entries)]
            if not cobs:
                raise FaultError(f"inject inputs_lost: node {d.node_id} sends its digital inputs in no TPDO (is a "
                                 "master's layout mapping them?)")
            until = now + number("seconds", 1.0, 0.001, 600.0)
            for cob in cobs:
                self.silent_cobs[cob] = until
            done["cob_ids"] = [f"0x{c:03X}" for c in cobs]
        elif kind == "garbage":
            d = node()
            cob = TPDO1_BASE + d.node_id
            frames = [can.Message(arbitration_id=cob, data=b"\x01\x02", is_extended_id=False),  # short DLC
                      can.Message(arbitration_id=cob, data=bytes(8), is_extended_id=True),  # 29-bit id
                      can.Message(arbitration_id=HEARTBEAT_BASE + d.node_id, data=b"\x00",
                                  is_extended_id=True),  # "boot-up"
                      can.Message(arbitration_id=EMCY_BASE + d.node_id, data=b"\x10\x23\x01\x00\x00\x00\x00\x00",
                                  is_extended_id=True),  # "EMCY"
                      can.Message(arbitration_id=cob, is_remote_frame=True, dlc=8, is_extended_id=False)]  # RTR
            for msg in frames:
                self.bus.send(msg)
            done["frames"] = len(frames)
        else:
            d = node()
            with lock:
                if kind == "emcy":
                    d.raise_error(int(number("code", EMCY_TEMPERATURE_DEVICE, 1, 0xFFFF)), ERR_REG_GENERIC)
                elif kind == "drive_fault":
                    d.inject_fault(int(number("code", EMCY_OVER_CURRENT, 1, 0xFFFF)))
                elif kind == "switched_on":  # drops out on its own (power stage off, brake); a master's cyclic 0x0F
                    d.force_state(State.SWITCHED_ON)  # would enable it again on the next RPDO (transition 4)
                elif kind == "node_reboot":
                    d.reset_node()
                elif kind == "encoder_jump":
                    rad = number("rad", 0.2, -100.0, 100.0)
                    seconds = number("seconds", 0.0, 0.0, 600.0)
                    d.encoder_offset_counts = round(rad * d.params.encoder_counts_per_rev / (2.0 * 3.141592653589793))
                    if seconds > 0 and self.lockstep:
                        self._due.append((now + seconds, lambda: setattr(d, "encoder_offset_counts", 0)))
                    elif seconds > 0:
                        threading.Timer(seconds, lambda: setattr(d, "encoder_offset_counts", 0)).start()
        self._rearm()
        return done
