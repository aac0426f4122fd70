"""The simulated drives' reception watchdogs over the simulator's own stalls, on an injected clock: a freeze of the
whole host (both processes stop) is not a silent bus, a master silent beside a running simulator still times the
drives out (sim/runner.py OwnStalls, sim/drive.py ``not_running``). Deterministic (frames dispatched and the reader's
state set by hand, no threads, no sockets): the unit tier. The reader thread itself on the wall clock:
tests/test_sim_realtime.py."""

from __future__ import annotations

import os
import struct
from typing import Any

import can
import pytest
from test_sim_canopen import TRUTH

pytestmark = pytest.mark.unit


def _host_freeze_rig(hold: bool) -> tuple[list[float], Any, list[Any], Any, list[can.Message]]:
    """Six drives (RPDO1 deadline 50 ms, as ``safety.rpdo_timeout_ms``) on one SimNetwork, everything on an injected
    clock read through OwnStalls (``hold``: the drives leave the simulator's stalls out, as sim/runner.py wires
    them); the reader's state is set by hand, frames are dispatched by hand: nothing here depends on scheduling."""
    from sim.axis import AxisIO
    from sim.drive import SimDrive
    from sim.network import SimNetwork
    from sim.runner import OwnStalls
    from sim.truth import drive_params

    t = [100.0]
    stalls = OwnStalls(source=lambda: t[0])
    sent: list[can.Message] = []
    drives = [SimDrive(drive_params(j, fd=False), AxisIO(), sent.append, clock=stalls.now) for j in TRUTH.joints]
    if hold:
        for d in drives:
            d.not_running = stalls.held
    bus = can.Bus(interface="virtual", channel=f"freeze-{os.getpid()}-{hold}")
    net = SimNetwork(bus, drives, clock=stalls.now)
    for d in drives:
        d.boot()
        d.store.sdo_write(0x1400, 5, struct.pack("<H", 50))
    net.dispatch_data(0x000, b"\x01\x00")  # NMT start all
    net._running, net._idle = True, True  # (a reader waiting on an empty socket: caught up as of now)
    bus.shutdown()
    return t, stalls, drives, net, sent


def _rpdo(node: int) -> tuple[int, bytes]:
    return 0x200 + node, struct.pack("<Hh", 0x06, 0)


def _tick(t: list[float], stalls: Any, drives: list[Any], net: Any, frames_to: list[Any] | None) -> None:
    """One millisecond of a running simulator: the master's RPDOs (to ``frames_to``) dispatched, then the physics
    loop's communication timers (sim/runner.py ``_period``)."""
    t[0] += 0.001
    for d in frames_to or ():
        net.dispatch_data(*_rpdo(d.node_id))
    now = stalls.now()
    for d in drives:
        d.comm(now)


@pytest.mark.parametrize("hold", [True, False], ids=["own-stalls-left-out", "without-(the-CI-failure)"])
def test_rpdo_watchdog_leaves_out_a_freeze_of_the_whole_host(hold: bool) -> None:
    """CI saw EMCY 8250h from nodes 4, 5, 6 only, after the daemon missed 88 cycles: the host froze both processes
    for ~88 ms. After the freeze the simulator's reader found the socket empty (the daemon had not run yet), then
    took the daemon's datagram; the physics thread's watchdog ran when nodes 1-3's RPDOs of that datagram had been
    handed over and 4-6's not: by the clock, 88 ms without an RPDO. But the simulated drive watches the bus only while
    the simulator runs; over the freeze the master could not send either. Its watchdogs leave out the simulator's own
    stalls (OwnStalls: a gap between two of its readings over 2 ms) — and a master silent beside a running simulator
    still times every drive out after exactly its 50 ms. Without that (the parameter's second case) the same sequence
    gives the CI failure, nodes 4-6 and only they."""
    t, stalls, drives, net, sent = _host_freeze_rig(hold)
    for _ in range(40):
        _tick(t, stalls, drives, net, drives)
    assert stalls.count == 0 and not any(d.counters.rpdo_timeouts for d in drives)
    t[0] += 0.088  # the host freezes both processes: nobody reads a clock, nobody sends
    net._caught_up_s, net._idle = net._now(), False  # the reader runs first: the socket is empty; then a datagram
    t[0] += 0.0002
    for d in drives[:3]:  # the reader hands over nodes 1-3's RPDOs; the physics thread takes the GIL
        net.dispatch_data(*_rpdo(d.node_id))
    now = stalls.now()
    for d in drives:
        d.comm(now)
    timed_out = [d.node_id for d in drives if d.counters.rpdo_timeouts]
    emcy_nodes = sorted(m.arbitration_id - 0x80 for m in sent if 0x81 <= m.arbitration_id <= 0xFF
                        and bytes(m.data[:2]) == b"\x50\x82")
    assert stalls.count == 1 and stalls.total_s == pytest.approx(0.088 - stalls.max_gap_s)
    if not hold:
        assert timed_out == emcy_nodes == [d.node_id for d in drives[3:]]
        return
    assert timed_out == emcy_nodes == [], "a freeze of the whole host is not a silent bus"
    assert [d.counters.watchdog_holds for d in drives] == [0, 0, 0, 1, 1, 1]
    for d in drives[3:]:  # the rest of the datagram
        net.dispatch_data(*_rpdo(d.node_id))
    net._idle = True
    for _ in range(20):
        _tick(t, stalls, drives, net, drives)
    assert not any(d.counters.rpdo_timeouts for d in drives)
    # the master falls silent beside a running simulator: every drive times out after its 50 ms (the tick that ends
    # them, or the next: float milliseconds), not before
    fired = _silent_until_timeout(t, stalls, drives, net, 60)
    assert fired in (50, 51) and [d.counters.rpdo_timeouts for d in drives] == [1] * 6 and stalls.count == 1
    # a freeze inside a silence leaves out the freeze only: 30 ms silent, 100 ms frozen, then the rest of the 50 ms
    for d in drives:
        d.rpdos[0].timed_out = False
    _tick(t, stalls, drives, net, drives)
    for _ in range(30):
        _tick(t, stalls, drives, net, None)
    t[0] += 0.100
    fired = _silent_until_timeout(t, stalls, drives, net, 40)
    # running time since the last RPDO: 30 + 2 (the first 2 ms of a gap count as running) + the ticks after it
    assert 30 + 2 + fired in (50, 51) and [d.counters.rpdo_timeouts for d in drives] == [2] * 6
    assert stalls.count == 2 and stalls.total_s == pytest.approx(0.086 + 0.099)  # (the tick reads 1 ms after it)


def _silent_until_timeout(t: list[float], stalls: Any, drives: list[Any], net: Any, limit_ms: int) -> int:
    """Ticks without RPDOs until every drive has timed out (all on the same tick): that tick's number."""
    before = [d.counters.rpdo_timeouts for d in drives]
    for ms in range(1, limit_ms + 1):
        _tick(t, stalls, drives, net, None)
        done = [d.counters.rpdo_timeouts - b for d, b in zip(drives, before, strict=True)]
        if any(done):
            assert done == [1] * len(drives), f"every drive on the same tick, got {done} at {ms} ms"
            return ms
    raise AssertionError(f"no RPDO timeout within {limit_ms} ms of silence")


def test_own_stalls_are_gaps_between_the_simulators_readings() -> None:
    """OwnStalls: readings a tick apart are running time; a gap over ``max_gap_s`` is a stall from ``max_gap_s`` after
    the earlier reading to the later one; ``held`` gives the part of an interval that was stalled; readings never go
    backwards (another thread's earlier read of the source)."""
    from sim.runner import OwnStalls

    t = [10.0]
    s = OwnStalls(max_gap_s=0.002, source=lambda: t[0])
    for _ in range(5):
        t[0] += 0.001
        assert s.now() == pytest.approx(t[0])
    t[0] += 0.0019
    s.now()
    assert s.count == 0
    t0 = t[0]
    t[0] += 0.050
    assert s.now() == pytest.approx(t0 + 0.050)
    assert (s.count, s.total_s, s.max_s) == (1, pytest.approx(0.048), pytest.approx(0.048))
    assert s.held(t0 - 1.0, t0 + 1.0) == pytest.approx(0.048)
    assert s.held(t0, t0 + 0.002) == 0.0  # (the first 2 ms of a gap count as running)
    assert s.held(t0 + 0.010, t0 + 0.020) == pytest.approx(0.010)
    assert s.held(t0 + 0.050, t0 + 0.060) == 0.0
    t[0] -= 0.0005  # a source read earlier, taken later
    assert s.now() == pytest.approx(t0 + 0.050)
    t[0] += 0.1
    s.now()
    assert s.count == 2 and s.held(t0 - 1.0, t[0]) == pytest.approx(0.048 + 0.1 - 0.0005 - 0.002)
    s.reset_counts()
    assert (s.count, s.total_s, s.max_s) == (0, 0.0, 0.0)
