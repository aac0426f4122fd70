"""The cycle's clock (dragd/clock.py) without processes: the lockstep clock's grants, waits, timers, off-cycle jobs,
gates, its guard against a silent peer and its check of the peer's period; TIME_OF_DAY frames."""

from __future__ import annotations

import asyncio
import threading
import time

import pytest

from dragd.clock import LockstepClock, LockstepError, WallClock, decode_time_of_day, encode_time_of_day

pytestmark = pytest.mark.unit


class Peer:
    """A stand-in for the simulator: ends each period (TIME frame) a few loop iterations after the tick."""

    def __init__(self, clock: LockstepClock, period_s: float | None = None, silent_after: int | None = None) -> None:
        self.clock = clock
        self.period_s = clock.period_s if period_s is None else period_s
        self.silent_after = silent_after
        self.ticks: list[float] = []

    def on_tick(self, n: int) -> None:
        k = self.clock.ticks
        self.ticks.append(self.clock.now())
        if self.silent_after is not None and k > self.silent_after:
            return
        loop = asyncio.get_running_loop()
        data = encode_time_of_day(k * self.period_s)
        loop.call_soon(lambda: loop.call_soon(self.clock.peer_time, "arm", data))


def run(coro_fn, clock: LockstepClock, peer: Peer):  # type: ignore[no-untyped-def]
    async def main():  # type: ignore[no-untyped-def]
        loop = asyncio.get_running_loop()
        errors: list[BaseException] = []
        clock.call_each(loop, peer.on_tick, errors.append)
        try:
            return await coro_fn(loop, errors)
        finally:
            clock.close()

    return asyncio.run(main())


def test_time_of_day_round_trip() -> None:
    for t in (0.0, 0.001, 12.345, 86_399.999, 86_400.0, 3 * 86_400 + 0.5):
        assert decode_time_of_day(encode_time_of_day(t)) == pytest.approx(t, abs=5e-4)
    assert len(encode_time_of_day(1.0)) == 6 and decode_time_of_day(b"\x00" * 5) is None


def test_grants_run_exactly_their_periods_and_time_stands_still_between() -> None:
    clock = LockstepClock(0.001, ["arm"])
    peer = Peer(clock)

    async def body(loop, errors):  # type: ignore[no-untyped-def]
        assert await clock.grant(0.25) == 250
        await asyncio.sleep(0.05)  # wall time passes: the arm's does not
        assert clock.ticks == 250 and clock.now() == pytest.approx(0.25)
        a, b = clock.grant(0.1), clock.grant(0.0004)  # a second grant adds to the first; 0.4 ms rounds to none
        assert await a == 350 and await b == 350
        assert clock.stamp_ns() == 350_000_000
        return errors

    assert run(body, clock, peer) == []
    assert len(peer.ticks) == 350


def test_waits_ask_for_time_and_sleeps_do_not() -> None:
    clock = LockstepClock(0.001, ["arm"])
    peer = Peer(clock)

    async def body(loop, errors):  # type: ignore[no-untyped-def]
        woke: list[int] = []

        async def background() -> None:
            await clock.sleep(0.01)
            woke.append(clock.ticks)

        task = loop.create_task(background())
        await asyncio.sleep(0.02)
        assert clock.ticks == 0 and not woke  # a sleep asks for no time
        assert await clock.wait_for(lambda: clock.ticks >= 37, 1.0) is True
        assert clock.ticks == 37  # looked at between every two ticks: it stops at the first that holds
        assert woke == [10]  # the sleeper woke on its tick, on the way
        assert await clock.wait_for(lambda: False, 0.05) is False and clock.ticks == 87  # a timeout on the clock
        await task
        return errors

    assert run(body, clock, peer) == []


def test_executor_jobs_hold_the_clock_and_warm_ups_need_not() -> None:
    clock = LockstepClock(0.001, ["arm"])
    peer = Peer(clock)

    async def body(loop, errors):  # type: ignore[no-untyped-def]
        grant = clock.grant(1.0)
        await clock.wait_for(lambda: clock.ticks >= 100, 1.0)
        at: list[int] = []

        def job() -> None:
            time.sleep(0.2)  # wall time: an SDO transfer, a file
            at.append(clock.ticks)

        await loop.run_in_executor(None, job)
        assert at == [clock.ticks]  # nothing ticked while the job ran: its result lands at this very tick
        with clock.untracked():
            free = loop.run_in_executor(None, time.sleep, 0.2)
        t0 = clock.ticks
        await free
        assert clock.ticks > t0  # a warm-up does not hold the arm's time
        assert await grant == 1000
        return errors

    assert run(body, clock, peer) == []


def test_gates_hold_the_next_tick() -> None:
    clock = LockstepClock(0.001, ["arm"])
    peer = Peer(clock)
    room = threading.Event()
    clock.gates.append(room.is_set)

    async def body(loop, errors):  # type: ignore[no-untyped-def]
        grant = clock.grant(0.01)
        await asyncio.sleep(0.05)
        assert clock.ticks == 0 and clock.gate_waits > 0
        room.set()
        assert await grant == 10
        return errors

    assert run(body, clock, peer) == []


def test_a_silent_peer_is_an_error_after_the_guard_not_a_hang() -> None:
    clock = LockstepClock(0.001, ["arm"], guard_s=0.3)
    peer = Peer(clock, silent_after=5)

    async def body(loop, errors):  # type: ignore[no-untyped-def]
        with pytest.raises(LockstepError, match="no TIME frame from the simulator for SYNC 6 .* on bus 'arm'"):
            await asyncio.wait_for(clock.grant(1.0), 10.0)
        return errors

    errors = run(body, clock, peer)
    assert len(errors) == 1 and isinstance(errors[0], LockstepError)


def test_a_peer_on_another_period_is_named() -> None:
    clock = LockstepClock(0.002, ["arm"])  # the daemon at 500 Hz, the simulator still at 1 ms per SYNC
    peer = Peer(clock, period_s=0.001)

    async def body(loop, errors):  # type: ignore[no-untyped-def]
        with pytest.raises(LockstepError, match="--period-ms 2"):
            await asyncio.wait_for(clock.grant(0.1), 10.0)
        return errors

    run(body, clock, peer)


def test_wall_clock_waits_on_the_wall() -> None:
    clock = WallClock(0.001)

    async def body() -> tuple[bool, bool]:
        t0 = time.monotonic()
        ok = await clock.wait_for(lambda: time.monotonic() - t0 > 0.03, 2.0)
        return ok, await clock.wait_for(lambda: False, 0.02)

    assert asyncio.run(body()) == (True, False)
    assert clock.lockstep is False and clock.stamp_ns() is None


def test_the_cli_default_guard_is_the_clocks() -> None:
    from dragd.cli.daemon import LOCKSTEP_GUARD_S
    from dragd.clock import GUARD_S

    assert LOCKSTEP_GUARD_S == GUARD_S


def test_free_run_until_paused_and_close_fails_what_it_cannot_serve() -> None:
    clock = LockstepClock(0.001, ["arm"])
    peer = Peer(clock)

    async def body(loop, errors):  # type: ignore[no-untyped-def]
        clock.set_free_run(True)  # `clock run`: time goes on without a grant
        await clock.wait_for(lambda: clock.ticks >= 50, 10.0)
        clock.set_free_run(False)  # `clock pause`: it stops at the next settled tick
        await asyncio.sleep(0.02)
        at = clock.ticks
        await asyncio.sleep(0.05)
        assert clock.ticks == at >= 50
        grant = clock.grant(10.0)
        await asyncio.sleep(0.01)
        clock.close()  # (the cycle stopped: the rest of the grant can never run)
        with pytest.raises(LockstepError, match="the cycle stopped"):
            await grant
        return errors

    assert run(body, clock, peer) == []
