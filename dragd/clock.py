"""The cycle's clock: its tick and ``now()``, and every wait the daemon measures in the arm's time.

    WallClock      production: ticks from the timerfd ``Ticker`` (dragd/realtime.py) on CLOCK_MONOTONIC's absolute
                   grid; ``now()`` is CLOCK_MONOTONIC; sleeps, timers and waits are asyncio's.
    LockstepClock  simulated time: the simulated robot (``dragd sim --lockstep``) advances one period for each SYNC
                   and ends the period with a CANopen TIME frame (COB-ID 100h, CiA 301 TIME_OF_DAY of its sim time);
                   the daemon ticks again once every bus's TIME frame for its last SYNC arrived. Time runs only while
                   someone needs it: a grant (the ``clock`` command: ``Rig.sleep``, ``dragd clock advance``), or a
                   command of the daemon waiting for the arm (``wait_for``: ``start`` until the drives are enabled).
                   No sleeps, no wall clock: the same processes, bus and frames run as fast as both can.

Determinism (lockstep): whatever can change what a cycle does happens between two ticks, at a tick the run itself
decides: a tick waits until (a) the simulator ended the previous period (its TIME frame arrived on every bus: every
frame of that period was read before it), (b) no job the loop handed to a thread is in flight (SDO transfers, the
planner, telemetry files: ``run_in_executor`` is counted), (c) every timer and waiter due by now has run and what it
woke has settled (the loop has nothing else ready), (d) the telemetry rings have room (a row is never dropped).
A peer that stops answering is an error after ``guard_s`` of wall time (``LockstepError``), never a silent hang.

Wall-time diagnostics (compute µs, period histograms, status latencies) stay on the wall clock in either mode; what
a lockstep run records (telemetry rows and their log times) carries the clock's values.
"""

from __future__ import annotations

import asyncio
import contextlib
import heapq
import itertools
import math
import struct
import time
from collections.abc import Callable, Iterator
from typing import Any, TypeVar

from dragd.hardware.cia301 import TIME_COB_ID
from dragd.realtime import Ticker

__all__ = ["Clock", "WallClock", "LockstepClock", "LockstepError", "TIME_COB_ID", "encode_time_of_day",
           "decode_time_of_day", "GUARD_S"]

T = TypeVar("T")

GUARD_S = 10.0  # lockstep: wall seconds without an answer from the simulator before it is an error
POLL_S = 0.01  # WallClock.wait_for: how often a condition is looked at
_DAY_MS = 86_400_000
_TOD = struct.Struct("<IH")


def encode_time_of_day(t_s: float) -> bytes:
    """``t_s`` seconds after the epoch as CiA 301 TIME_OF_DAY: ms after midnight (28 bits), days (16 bits)."""
    ms = int(round(t_s * 1000.0))
    days, ms = divmod(ms, _DAY_MS)
    return _TOD.pack(ms & 0x0FFF_FFFF, days & 0xFFFF)


def decode_time_of_day(data: bytes | bytearray) -> float | None:
    """Seconds after the epoch from a TIME frame's 6 bytes (None for a shorter frame)."""
    if len(data) < 6:
        return None
    ms, days = _TOD.unpack_from(data)
    return (days * _DAY_MS + (ms & 0x0FFF_FFFF)) * 1e-3


class LockstepError(RuntimeError):
    """The lockstep clock cannot go on: a silent peer, a period that disagrees, a wait on the wall clock."""


class Clock:
    """What the cycle and the daemon's waits read. Subclasses: `WallClock` (production), `LockstepClock`."""

    lockstep = False

    def __init__(self, period_s: float) -> None:
        if not (period_s > 0 and math.isfinite(period_s)):
            raise ValueError(f"clock period_s: expected a positive number of seconds, got {period_s!r}")
        self.period_s = float(period_s)

    def now(self) -> float:
        """Seconds on this clock (CLOCK_MONOTONIC, or simulated time)."""
        raise NotImplementedError

    def stamp_ns(self) -> int | None:
        """A telemetry log time for now: None (the writer stamps CLOCK_REALTIME) or the clock's own, in ns."""
        return None

    def attach(self, loop: asyncio.AbstractEventLoop) -> None:
        """Bind the clock to the daemon's loop (before anything waits on it)."""

    def call_each(self, loop: asyncio.AbstractEventLoop, on_tick: Callable[[int], None]) -> None:
        """Call ``on_tick(n)`` from ``loop`` once per period (n: periods since the last call), until `close`."""
        raise NotImplementedError

    def close(self) -> None:
        """Stop ticking."""

    async def sleep(self, seconds: float) -> None:
        """Wait ``seconds`` on this clock without asking for time (a background check's pace)."""
        raise NotImplementedError

    async def wait_for(self, cond: Callable[[], bool], timeout_s: float) -> bool:
        """Run the arm until ``cond()`` holds or ``timeout_s`` passed on this clock; ``cond()`` at the end."""
        raise NotImplementedError

    @contextlib.contextmanager
    def untracked(self) -> Iterator[None]:
        """Executor jobs started inside do not hold the clock (a warm-up nothing waits for)."""
        yield

    def status(self) -> dict[str, Any]:
        return {"lockstep": self.lockstep, "t_s": self.now(), "period_s": self.period_s}


class WallClock(Clock):
    """Production: the timerfd Ticker's absolute CLOCK_MONOTONIC grid; asyncio's sleeps."""

    def __init__(self, period_s: float) -> None:
        super().__init__(period_s)
        self._ticker: Ticker | None = None

    def now(self) -> float:
        return time.monotonic()

    def call_each(self, loop: asyncio.AbstractEventLoop, on_tick: Callable[[int], None]) -> None:
        self._ticker = Ticker(self.period_s, loop)
        self._ticker.call_each(loop, on_tick)

    def close(self) -> None:
        if self._ticker is not None:
            self._ticker.close()
            self._ticker = None

    async def sleep(self, seconds: float) -> None:
        await asyncio.sleep(seconds)

    async def wait_for(self, cond: Callable[[], bool], timeout_s: float) -> bool:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if cond():
                return True
            await asyncio.sleep(POLL_S)
        return cond()


class _Waiter:
    __slots__ = ("cond", "due", "future")

    def __init__(self, cond: Callable[[], bool], due: int, future: asyncio.Future[bool]) -> None:
        self.cond, self.due, self.future = cond, due, future


class LockstepClock(Clock):
    """Simulated time, ticked by the simulator's periods and advanced only through grants and waits (module doc)."""

    lockstep = True

    def __init__(self, period_s: float, buses: list[str], *, guard_s: float = GUARD_S,
                 free_run: bool = False) -> None:
        super().__init__(period_s)
        if not buses:
            raise ValueError("LockstepClock: expected at least one bus")
        if not guard_s > 0:
            raise ValueError(f"LockstepClock guard_s: expected a positive number of seconds, got {guard_s!r}")
        self.buses = list(buses)
        self.guard_s = float(guard_s)
        self.ticks = 0  # periods elapsed (the SYNCs sent)
        self.free_run = free_run  # ``clock run``: no grant needed
        self._granted = 0  # the tick up to which time is granted
        self._grants: list[tuple[int, int, asyncio.Future[int]]] = []  # (target tick, seq, future) heap
        self._waiters: list[_Waiter] = []  # active waits: they ask for time
        self._timers: list[tuple[int, int, Callable[[], None]]] = []  # (due tick, seq, callback) heap
        self._seq = itertools.count()
        self._offcycle = 0  # executor jobs in flight
        self._untracked = False
        self.gates: list[Callable[[], bool]] = []  # all must hold for a tick (e.g. telemetry rings with room)
        self._peer = {name: 0 for name in self.buses}  # TIME frames received per bus (one per SYNC)
        self._peer_base: tuple[int, float] | None = None  # (tick, sim time) of the first TIME frame: the period check
        self.peer_time_s: float | None = None  # the simulator's time from its last TIME frame
        self.on_peer_done: Callable[[], None] = lambda: None  # the cycle: end a read step still open
        self._loop: asyncio.AbstractEventLoop | None = None
        self._on_tick: Callable[[int], None] | None = None
        self._on_error: Callable[[BaseException], None] | None = None
        self._scheduled = False
        self._closed = False
        self._tick_wall = 0.0  # when the last tick went out (the guard's reference)
        self._guard_handle: asyncio.TimerHandle | None = None
        self._gate_handle: asyncio.TimerHandle | None = None
        self.error: BaseException | None = None
        # wall-time bookkeeping for the real-time factor (status)
        self._wall0: float | None = None
        self._wall_run = 0.0
        self.offcycle_jobs = 0  # executor jobs counted so far
        self.gate_waits = 0  # times a tick waited for a gate

    # ------------------------------------------------------------------------------------------ reading

    def now(self) -> float:
        return self.ticks * self.period_s

    def stamp_ns(self) -> int | None:
        return round(self.ticks * self.period_s * 1e9)

    def ticks_for(self, seconds: float) -> int:
        """Whole periods in ``seconds`` (rounded to the nearest; a wait of 0.3 s at 1 kHz is 300 ticks)."""
        if not (seconds >= 0 and math.isfinite(seconds)):
            raise ValueError(f"expected a finite number of seconds >= 0, got {seconds!r}")
        return int(round(seconds / self.period_s))

    def status(self) -> dict[str, Any]:
        wall = self._wall_run
        return {"lockstep": True, "t_s": self.now(), "ticks": self.ticks, "period_s": self.period_s,
                "granted_s": self._granted * self.period_s, "free_run": self.free_run,
                "waiters": len(self._waiters), "offcycle": self._offcycle, "offcycle_jobs": self.offcycle_jobs,
                "gate_waits": self.gate_waits, "peer_time_s": self.peer_time_s,
                "wall_running_s": round(wall, 6), "rtf": round(self.now() / wall, 4) if wall > 0 else None}

    # ------------------------------------------------------------------------------------------ binding

    def attach(self, loop: asyncio.AbstractEventLoop) -> None:
        """Bind to the daemon's loop: its ``run_in_executor`` (and so ``asyncio.to_thread``) is counted."""
        if self._loop is loop:
            return
        self._loop = loop
        inner = loop.run_in_executor

        def run_in_executor(executor: Any, func: Callable[..., T], *args: Any) -> asyncio.Future[T]:
            fut = inner(executor, func, *args)
            if not self._untracked:
                self._offcycle += 1
                self.offcycle_jobs += 1
                fut.add_done_callback(self._offcycle_done)
            return fut

        loop.run_in_executor = run_in_executor  # type: ignore[method-assign,assignment]

    @contextlib.contextmanager
    def untracked(self) -> Iterator[None]:
        self._untracked = True
        try:
            yield
        finally:
            self._untracked = False

    def _offcycle_done(self, _fut: object) -> None:
        self._offcycle -= 1
        self.kick()

    def call_each(self, loop: asyncio.AbstractEventLoop, on_tick: Callable[[int], None],
                  on_error: Callable[[BaseException], None] | None = None) -> None:
        self.attach(loop)
        self._on_tick = on_tick
        self._on_error = on_error
        self._closed = False
        self._tick_wall = time.monotonic()
        self._guard_handle = loop.call_later(1.0, self._guard)
        self.kick()

    def close(self) -> None:
        """Stop ticking; a grant or a wait still open can no longer be served: it fails (LockstepError)."""
        self._closed = True
        self._on_tick = None
        for h in (self._guard_handle, self._gate_handle):
            if h is not None:
                h.cancel()
        self._guard_handle = self._gate_handle = None
        self._stop_wall()
        stopped = LockstepError(f"lockstep: the cycle stopped at t = {self.now():.3f} s")
        for fut in [g[2] for g in self._grants] + [w.future for w in self._waiters]:
            if not fut.done():
                fut.set_exception(stopped)
        self._grants.clear()
        self._waiters.clear()

    # ------------------------------------------------------------------------------------------ asking for time

    def grant(self, seconds: float) -> asyncio.Future[int]:
        """Let the arm run ``seconds`` more (after what was granted before); the future resolves with the tick
        reached, once that tick's cycle and everything it woke are done."""
        assert self._loop is not None, "LockstepClock.grant before attach"
        fut: asyncio.Future[int] = self._loop.create_future()
        self._granted = max(self._granted, self.ticks) + self.ticks_for(seconds)
        heapq.heappush(self._grants, (self._granted, next(self._seq), fut))
        self.kick()
        return fut

    def set_free_run(self, on: bool) -> None:
        """``clock run`` / ``clock pause``: time runs without grants (as fast as both processes can)."""
        self.free_run = bool(on)
        if not on:
            self._granted = max(self._granted, self.ticks)
        self.kick()

    async def sleep(self, seconds: float) -> None:
        """Wake once ``seconds`` of simulated time passed (asking for none: a background task's pace)."""
        assert self._loop is not None, "LockstepClock.sleep before attach"
        fut: asyncio.Future[None] = self._loop.create_future()

        def wake() -> None:
            if not fut.done():
                fut.set_result(None)

        self.call_later(seconds, wake)
        await fut

    def call_later(self, seconds: float, callback: Callable[[], None]) -> None:
        """``callback()`` between two ticks once ``seconds`` of simulated time passed (at least one tick)."""
        due = self.ticks + max(1, self.ticks_for(seconds))
        heapq.heappush(self._timers, (due, next(self._seq), callback))

    async def wait_for(self, cond: Callable[[], bool], timeout_s: float) -> bool:
        """Ask for time until ``cond()`` holds (looked at between every two ticks) or ``timeout_s`` passed."""
        assert self._loop is not None, "LockstepClock.wait_for before attach"
        if cond():
            return True
        fut: asyncio.Future[bool] = self._loop.create_future()
        self._waiters.append(_Waiter(cond, self.ticks + max(1, self.ticks_for(timeout_s)), fut))
        self.kick()
        return await fut

    # ------------------------------------------------------------------------------------------ the peer

    def peer_time(self, bus: str, data: bytes | bytearray) -> None:
        """A TIME frame on ``bus``: the simulator ended the period of one SYNC sent there."""
        n = self._peer.get(bus)
        if n is None:
            return
        self._peer[bus] = n + 1
        t = decode_time_of_day(data)
        if t is not None:
            self.peer_time_s = t
        if self.peer_done():
            if t is not None:
                self._check_period(t)
            self.on_peer_done()
            self.kick()

    def peer_done(self) -> bool:
        """The simulator ended the period of every SYNC sent so far (on every bus)."""
        return min(self._peer.values()) >= self.ticks

    def _check_period(self, t: float) -> None:
        if self._peer_base is None:
            self._peer_base = (self.ticks, t)
            return
        k0, t0 = self._peer_base
        expect = t0 + (self.ticks - k0) * self.period_s
        if abs(t - expect) > 1.0e-3 + 1e-9:  # (TIME_OF_DAY has 1 ms resolution)
            self._fail(LockstepError(
                f"lockstep: the simulator's time went {t - t0:.3f} s in {self.ticks - k0} SYNCs, this daemon's period "
                f"is {self.period_s * 1e3:g} ms ({(self.ticks - k0) * self.period_s:.3f} s): start the simulator with "
                f"--lockstep --period-ms {self.period_s * 1e3:g} (the daemon's loop.rate_Hz)"))

    def _guard(self) -> None:
        """Once a second (wall): a SYNC unanswered for ``guard_s`` is an error, never a silent hang."""
        loop = self._loop
        if self._closed or loop is None:
            return
        self._guard_handle = loop.call_later(1.0, self._guard)
        if self.ticks > 0 and not self.peer_done() and time.monotonic() - self._tick_wall > self.guard_s:
            silent = [b for b, n in self._peer.items() if n < self.ticks]
            self._fail(LockstepError(
                f"lockstep: no TIME frame from the simulator for SYNC {self.ticks} (t = {self.now():.3f} s) on "
                f"bus {', '.join(repr(b) for b in silent)} within {self.guard_s:g} s of wall time: is the simulator "
                "running with --lockstep on this bus, and still alive?"))

    def _fail(self, exc: BaseException) -> None:
        if self.error is not None:
            return
        self.error = exc
        for _, _, fut in self._grants:
            if not fut.done():
                fut.set_exception(exc)
        self._grants.clear()
        for w in self._waiters:
            if not w.future.done():
                w.future.set_exception(exc)
        self._waiters.clear()
        if self._on_error is not None:
            self._on_error(exc)

    # ------------------------------------------------------------------------------------------ ticking

    def kick(self) -> None:
        """Something changed that may let the next tick go: look (once) when the loop gets to it."""
        if not self._scheduled and self._loop is not None and not self._closed:
            self._scheduled = True
            self._loop.call_soon(self._try_tick)

    def _busy_loop(self) -> bool:
        """The loop has other callbacks ready (what a timer, a frame or a finished job woke has not settled)."""
        ready = getattr(self._loop, "_ready", None)  # (asyncio's run queue; CPython's BaseEventLoop)
        return bool(ready)

    def _try_tick(self) -> None:
        self._scheduled = False
        if self._closed or self.error is not None:
            return
        loop = self._loop
        assert loop is not None
        if self._busy_loop():
            self.kick()
            return
        if not self.peer_done() or self._offcycle:
            return  # (the TIME frame, or the job's end, kicks again)
        # everything due by now: timers, then the waits (each may wake tasks: they settle before anything else)
        woke = False
        timers, now = self._timers, self.ticks
        while timers and timers[0][0] <= now:
            _, _, cb = heapq.heappop(timers)
            cb()
            woke = True
        if self._waiters:
            keep = []
            for w in self._waiters:
                if w.future.done():
                    continue
                try:
                    ok = w.cond()
                except Exception as exc:  # noqa: BLE001 - raised where the wait was
                    w.future.set_exception(exc)
                    woke = True
                    continue
                if ok or now >= w.due:
                    w.future.set_result(ok)
                    woke = True
                else:
                    keep.append(w)
            self._waiters = keep
        grants = self._grants
        while grants and grants[0][0] <= now:
            _, _, fut = heapq.heappop(grants)
            if not fut.done():
                fut.set_result(now)
                woke = True
        if woke:
            self.kick()
            return
        if not (self.free_run or now < self._granted or self._waiters):
            self._stop_wall()
            return  # paused: nothing asks for time
        for gate in self.gates:
            if not gate():
                self.gate_waits += 1
                if self._gate_handle is None:
                    self._gate_handle = loop.call_later(0.001, self._gate_retry)
                return
        on_tick = self._on_tick
        if on_tick is None:
            return
        self._start_wall()
        self.ticks += 1
        self._tick_wall = time.monotonic()
        on_tick(1)

    def _gate_retry(self) -> None:
        self._gate_handle = None
        self.kick()

    def _start_wall(self) -> None:
        if self._wall0 is None:
            self._wall0 = time.perf_counter()

    def _stop_wall(self) -> None:
        if self._wall0 is not None:
            self._wall_run += time.perf_counter() - self._wall0
            self._wall0 = None

