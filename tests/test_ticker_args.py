"""dragd.realtime without timing in the verdict: the Ticker's arguments and its close, set_realtime's argument checks
and what it does when nothing is requested, demoting a thread. The unit tier (the Ticker's periods, missed ticks and
the scheduling policy applied: tests/test_ticker.py, wall clock)."""

import asyncio
import os

import pytest

from dragd.realtime import Ticker, demote_current_thread, set_realtime

pytestmark = pytest.mark.unit


def run(coro):
    return asyncio.run(coro)


def test_close_is_idempotent_and_wait_after_close_fails():
    async def main():
        t = Ticker(0.002)
        await t.wait()
        fd = t.fileno
        t.close()
        t.close()
        with pytest.raises(OSError):
            os.fstat(fd)
        with pytest.raises(RuntimeError, match="closed"):
            await t.wait()

    run(main())



def test_invalid_period():
    with pytest.raises(ValueError, match="period"):
        Ticker(0)
    with pytest.raises(ValueError, match="10 us"):
        Ticker(1e-7)



def test_set_realtime_validates_arguments():
    with pytest.raises(ValueError, match="priority"):
        set_realtime(0, None)
    with pytest.raises(ValueError, match="cpus"):
        set_realtime(None, set())
    res = set_realtime(None, None)
    assert res["scheduler"]["reason"] == "not requested"
    assert res["affinity"]["reason"] == "not requested"



def test_demote_current_thread_is_safe():
    res = demote_current_thread(None)
    assert res["policy"] == "SCHED_OTHER"
    assert res["cpus"]
