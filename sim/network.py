"""The simulated drives' side of one CAN bus: a reader thread that dispatches frames to the drives.

SYNC frames take a fast path: every drive's `on_sync` runs right away, so that all synchronous TPDOs leave within a
few hundred microseconds of the SYNC. Other frames go to the drives that consume their COB-ID (NMT to all; SDO requests,
RPDOs — also a COB-ID shared by several drives — and consumed heartbeats by routing table). The routing table is
rebuilt whenever a drive's COB-IDs change. On dragd's udp_multicast bus the reader drains whole datagrams and hands
plain data frames over as (COB-ID, payload), without a ``can.Message`` each. It keeps the time up to which it has
handed over everything that arrived (`caught_up`): the drives' reception watchdogs judge against it. Its times are on
the drives' clock (``clock``: in the simulator's process CLOCK_MONOTONIC read through sim/runner.py's OwnStalls, which
notes when the process did not run).

On the lockstep clock (sim/lockstep.py) a SYNC's reception time is the simulated time; the drives answer it as always,
then, in the same batch, the period runs (``LockstepSync.on_sync``) and its TIME frame ends the answer — also while
an injected link-down mutes the bus (the fault is the drives' frames, not the clock); the reader is caught up by
construction: a period runs only after its SYNC, and whatever the master sent before the SYNC came before it.

The network does not own the bus: the caller opens it before and shuts it down after `stop()`.
"""

from __future__ import annotations

import logging
import select
import sys
import threading
import time
from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass
from typing import TYPE_CHECKING

import can

from dragd.hardware.bus import UdpMulticastCanBus
from dragd.hardware.cia301 import SYNC_COB_ID
from sim.drive import SimDrive

if TYPE_CHECKING:
    from sim.lockstep import LockstepSync

log = logging.getLogger(__name__)

# the reader thread must win the GIL quickly from the physics thread when a SYNC arrives
SWITCH_INTERVAL_S = 0.0005
DRAIN_LIMIT = 64  # datagrams per drain (a flood cannot hold the reader from its stop flag)


@dataclass
class NetworkCounters:
    """What the reader thread handled."""

    frames: int = 0
    syncs: int = 0
    unrouted: int = 0
    late_responses: int = 0  # SYNCs whose TPDOs all left later than late_threshold_s after reception
    max_sync_latency_s: float = 0.0
    handler_errors: int = 0
    error_frames: int = 0  # CAN error frames received (dropped)


class SimNetwork:
    """Reader thread for a set of drives sharing one bus."""

    def __init__(self, bus: can.BusABC, drives: list[SimDrive], *, late_threshold_s: float = 0.0005,
                 recv_timeout_s: float = 0.05, lockstep: LockstepSync | None = None, bus_index: int = 0,
                 clock: Callable[[], float] | None = None) -> None:
        """``clock``: the drives' communication clock (default: CLOCK_MONOTONIC; the lockstep clock's with
        ``lockstep``)."""
        ids = [d.node_id for d in drives]
        if len(set(ids)) != len(ids):
            raise ValueError(f"SimNetwork: node ids must be unique on one bus, got {ids}")
        self.bus = bus
        self.drives = list(drives)
        self.late_threshold_s = late_threshold_s
        self.recv_timeout_s = recv_timeout_s
        self.counters = NetworkCounters()
        self.lockstep = lockstep
        self.bus_index = bus_index
        self._now: Callable[[], float] = (clock if clock is not None
                                          else time.monotonic if lockstep is None else lockstep.clock.now)
        self._sync_cob = SYNC_COB_ID  # (lockstep: a SYNC counts toward the period even while the link is muted)
        self.rx_muted: Callable[[], bool] | None = None  # an injected link-down (sim/faults.py): drop what arrives
        # the TPDOs a SYNC triggers leave in one datagram where the bus batches (udp_multicast, batch_frames)
        self._batch: Callable[[], AbstractContextManager[None]] = (bus.batch if isinstance(bus, UdpMulticastCanBus)
                                                                   else nullcontext)
        self._routes: dict[int, tuple[SimDrive, ...]] = {}
        self._sync_routes: dict[int, tuple[SimDrive, ...]] = {}
        self._epoch = -1
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        # what the reader has read: every frame that reached the socket before _caught_up_s has been handed to the
        # drives; while _idle it waits on an empty socket (caught up as of now); a reader not _running reads nothing
        self._caught_up_s = 0.0
        self._idle = False
        self._running = False
        self.cpu_ns = 0  # CPU time of the reader thread (on the lockstep clock it also runs the periods)
        for drive in self.drives:
            drive.rx_caught_up = self.caught_up

    def start(self, boot: bool = True) -> None:
        """Start the reader thread, then (by default) boot every drive (boot-up frames)."""
        if self._thread is not None:
            raise RuntimeError("SimNetwork.start(): already running")
        if sys.getswitchinterval() > SWITCH_INTERVAL_S:
            sys.setswitchinterval(SWITCH_INTERVAL_S)
        self._stop.clear()
        self._rebuild_routes()
        self._thread = threading.Thread(target=self._run, name="sim-can-reader", daemon=True)
        self._thread.start()
        if boot:
            for drive in self.drives:
                drive.boot()

    def stop(self, timeout_s: float = 2.0) -> None:
        """Stop the reader thread (the bus stays open)."""
        thread, self._thread = self._thread, None
        if thread is None:
            return
        self._stop.set()
        thread.join(timeout_s)
        if thread.is_alive():
            raise RuntimeError(f"SimNetwork.stop(): reader thread still running after {timeout_s} s")

    def __enter__(self) -> SimNetwork:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def caught_up(self, now: float) -> float:
        """The time (on ``clock``) up to which every frame that reached this process has been handed to the drives:
        ``now`` while the reader waits on an empty socket (or is not running: then nothing will be read), else when
        it last found the socket empty. The drives' reception watchdogs judge against it (only once a deadline has
        passed by the clock: the rare path). A reader waiting while frames are queued has been woken but not run yet
        (another thread of this process holds the GIL, e.g. physics catching up): not caught up."""
        if not self._running or self.lockstep is not None:
            return now
        if self._idle and not self._frames_waiting():
            return now
        return self._caught_up_s

    def _frames_waiting(self) -> bool:
        """Whether the bus's socket holds frames the reader has not taken (False for a bus without a descriptor)."""
        try:
            fd = self.bus.fileno()
            if fd < 0:
                return False
            ready, _, _ = select.select([fd], [], [], 0)
        except (NotImplementedError, OSError, ValueError):
            return False
        return bool(ready)

    def _run(self) -> None:
        self._caught_up_s, self._running = self._now(), True
        cpu0 = time.thread_time_ns()
        try:
            if isinstance(self.bus, UdpMulticastCanBus):
                self._run_draining(self.bus.drain)
            else:
                self._run_receiving()
        finally:
            self._running = False
            self.cpu_ns += time.thread_time_ns() - cpu0

    def _run_receiving(self) -> None:
        """The reader on any other python-can bus (socketcan, virtual): frame by frame."""
        recv, timeout, clock = self.bus.recv, self.recv_timeout_s, self._now
        while not self._stop.is_set():
            t0 = clock()
            try:
                msg = recv(0.0)
                if msg is None:  # nothing queued at t0: everything before it has been handed over
                    self._caught_up_s, self._idle = t0, True
                    try:
                        msg = recv(timeout)
                    finally:
                        self._idle = False
            except can.CanError as exc:
                if getattr(self.bus, "_is_shutdown", False):
                    return
                log.error("sim bus receive failed: %s", exc)
                self.counters.handler_errors += 1
                time.sleep(timeout)
                continue
            if msg is not None:
                self._on_message(msg)

    def _run_draining(self, drain: Callable[..., int]) -> None:
        """The reader on a bus with ``drain`` (dragd's udp_multicast): every datagram already queued in one go, plain
        data frames (SYNC, RPDOs, SDO requests, NMT) handed over without a ``can.Message`` each."""
        fd, timeout, bus, clock = self.bus.fileno(), self.recv_timeout_s, self.bus, self._now
        while not self._stop.is_set():
            t0 = clock()
            try:
                n = drain(self._on_data, self._on_message, DRAIN_LIMIT)
            except can.CanError as exc:
                if getattr(bus, "_is_shutdown", False):
                    return
                log.error("sim bus receive failed: %s", exc)
                self.counters.handler_errors += 1
                time.sleep(timeout)
                continue
            if n == 0:  # the socket was empty at t0: everything before it has been handed over
                self._caught_up_s, self._idle = t0, True
                try:
                    select.select([fd], [], [], timeout)
                except (OSError, ValueError):  # the bus was shut down under us
                    if getattr(bus, "_is_shutdown", False):
                        return
                    raise
                finally:
                    self._idle = False

    def _on_data(self, cob: int, data: bytes | bytearray) -> bool:
        if self.rx_muted is None or not self.rx_muted():
            self.dispatch_data(cob, data, self.bus.rx_timestamp if isinstance(self.bus, UdpMulticastCanBus) else 0.0)
        elif self.lockstep is not None and cob == self._sync_cob:
            self._on_sync(0.0, ())  # (muted: the drives hear nothing; the period still runs)
        return True

    def _on_message(self, msg: can.Message) -> None:
        if self.rx_muted is None or not self.rx_muted():
            self.dispatch(msg)
        elif self.lockstep is not None and msg.arbitration_id == self._sync_cob and not msg.is_extended_id:
            self._on_sync(0.0, ())

    def dispatch(self, msg: can.Message) -> None:
        """Hand one frame to the drives that consume it (also usable without the thread); error frames are dropped."""
        if msg.is_error_frame:  # class bits 0x080 would otherwise act as a SYNC
            self.counters.error_frames += 1
            return
        if msg.is_extended_id or msg.is_remote_frame:  # (no drive consumes them)
            self.counters.frames += 1
            self.counters.unrouted += 1
            return
        self.dispatch_data(msg.arbitration_id, msg.data, msg.timestamp)

    def dispatch_data(self, cob: int, data: bytes | bytearray, timestamp: float = 0.0) -> None:
        """`dispatch` for a plain data frame: its COB-ID, payload and reception time (wall clock; 0: unknown)."""
        counters = self.counters
        counters.frames += 1
        if SimDrive.routes_generation != self._epoch:
            self._rebuild_routes()
        try:
            sync_drives = self._sync_routes.get(cob)
            if sync_drives is None and cob == self._sync_cob and self.lockstep is not None:
                sync_drives = ()  # (no drive consumes it here: the period still runs)
            if sync_drives is not None:
                self._on_sync(timestamp, sync_drives)
                others = self._routes.get(cob)
                if others is None:
                    return
            else:
                others = self._routes.get(cob)
                if others is None:
                    counters.unrouted += 1
                    return
            for drive in others:
                drive.on_data(cob, data)
        except Exception:
            counters.handler_errors += 1
            log.exception("sim drive failed on frame 0x%03X %s", cob, bytes(data).hex())

    def _on_sync(self, timestamp: float, drives: tuple[SimDrive, ...]) -> None:
        now = self._now()
        lockstep = self.lockstep
        with self._batch():
            try:
                for drive in drives:
                    drive.on_sync(now)
            finally:
                if lockstep is not None:  # the period, then its TIME frame: in the same datagram as the answer
                    lockstep.on_sync(self.bus_index)
        counters = self.counters
        counters.syncs += 1
        if timestamp:
            latency = time.time() - timestamp
            if latency > counters.max_sync_latency_s:
                counters.max_sync_latency_s = latency
            if latency > self.late_threshold_s:
                counters.late_responses += 1

    def _rebuild_routes(self) -> None:
        epoch = SimDrive.routes_generation
        routes: dict[int, list[SimDrive]] = {}
        syncs: dict[int, list[SimDrive]] = {}
        for drive in self.drives:
            sync_cob = drive.sync_cob_id()
            syncs.setdefault(sync_cob, []).append(drive)
            for cob in drive.rx_cob_ids():
                if cob != sync_cob:
                    routes.setdefault(cob, []).append(drive)
        self._routes = {cob: tuple(ds) for cob, ds in routes.items()}
        self._sync_routes = {cob: tuple(ds) for cob, ds in syncs.items()}
        self._epoch = epoch
        expect = getattr(self.bus, "expect", None)
        if expect is not None:  # (dragd's udp_multicast: SYNC and the RPDOs read by their template, without msgpack)
            try:
                expect([(cob, 0, False) for cob in syncs]
                       + [(ch.cob_id, ch.frame_len, kind) for drive in self.drives for ch in drive.rpdos if ch.valid
                          for kind in {ch.is_fd, False}])
            except (ValueError, can.CanError):  # (a speed-up only: without it every datagram is unpacked)
                log.exception("sim bus: the drives' frames could not be registered for reading by template")
