"""Daemon pieces that need no processes: frame decoding, bus-spec overrides."""

from __future__ import annotations

import can
import numpy as np
import pytest

from dragd.config import load_config
from dragd.daemon.core import Daemon

from conftest import DEFAULT_CONFIG

pytestmark = pytest.mark.unit


@pytest.fixture
def daemon() -> Daemon:
    d = Daemon(load_config(DEFAULT_CONFIG), bus_override="udp_multicast:239.74.200.1", log=lambda msg: None)
    d.attach({"arm": can.Bus(interface="virtual", channel="unit-daemon")})
    return d


def _listener(d: Daemon) -> can.Listener:
    return d.io.listener("arm")


def test_error_frames_are_never_decoded(daemon: Daemon) -> None:
    rx = _listener(daemon)
    for cob in (0x081, 0x181):  # error class bits that equal node 1's EMCY and TPDO1 COB-IDs
        rx.on_message_received(can.Message(arbitration_id=cob, is_error_frame=True, data=bytes(8),
                                           is_extended_id=False))
    assert daemon.io.error_frames == 2 and daemon.faults == [] and daemon.io.feedback.counts[0] == 0
    rx.on_message_received(can.Message(arbitration_id=0x081, data=bytes([0x10, 0x23, 0x01, 0, 0, 0, 0, 0]),
                                       is_extended_id=False))
    assert daemon.faults and "EMCY 0x2310" in daemon.faults[0]["text"]


def test_bus_override_count_must_match(daemon: Daemon) -> None:
    with pytest.raises(ValueError, match="expected 1 INTERFACE:CHANNEL"):
        Daemon(load_config(DEFAULT_CONFIG), bus_override="virtual:a,virtual:b")


def test_tpdo_wait_ends_when_every_joint_has_reported_once(daemon: Daemon) -> None:
    """The read step's wait completes on the n-th distinct joint's position TPDO; a repeat of one joint does not
    count twice, and a cycle without all joints falls back to the stale counters."""
    import asyncio
    import struct

    codec = struct.Struct("<HiH")
    rx, fb = _listener(daemon), daemon.io.feedback

    def tpdo(node: int, pos: int) -> can.Message:
        return can.Message(arbitration_id=0x180 + node, data=codec.pack(0x0637, pos, 0), is_extended_id=False)

    async def main() -> None:
        loop = asyncio.get_running_loop()
        read = loop.create_task(daemon.io.read(loop, 1.0))
        await asyncio.sleep(0)
        for k in range(6):  # node 1 six times (a late frame and repeats): still one joint
            rx.on_message_received(tpdo(1, 100 + k))
        daemon.io.after_frames()  # (the bus reader's call once a wake-up's frames are decoded)
        await asyncio.sleep(0)
        assert fb.rx_count == 1 and not read.done() and fb.counts[0] == 105
        for node in range(2, 6):
            rx.on_message_received(tpdo(node, node))
        daemon.io.after_frames()
        await asyncio.sleep(0)
        assert fb.rx_count == 5 and not read.done()
        rx.on_message_received(tpdo(6, 6))
        assert not read.done()  # the step ends after the wake-up's frames, not inside their decoding
        daemon.io.after_frames()
        assert await asyncio.wait_for(read, 0.5) is True
        assert fb.rx_count == 6 and fb.rx.all() and list(fb.counts[1:]) == [2, 3, 4, 5, 6]

    asyncio.run(main())
    # a complete set: nothing stale, whatever the counters held before
    assert fb.worst_stale() == (0, 0)
    # joint 3 missing for 12 cycles: the watch sees it although five joints reported this cycle
    fb.rx_count, fb.stale[2] = 5, 12
    assert fb.worst_stale() == (12, 2)
    c = daemon.controller
    c.feedback(12, 2, 3, np.zeros(6), 10, 50)
    assert c.fresh_cycles == 0


def test_cycle_runs_as_loop_callbacks_and_raises_what_stops_it() -> None:
    """The cycle as a chain of loop callbacks (tick → SYNC; the reader's wake-up → step), on the lockstep clock: a
    peer answering each SYNC with every TPDO and a TIME frame runs exactly the granted cycles; ``request_exit`` ends
    ``run``; an exception in a cycle ends ``run`` with it (the loop must not swallow it) and leaves no read step
    open."""
    import asyncio
    import struct
    import threading

    from dragd.clock import TIME_COB_ID, LockstepClock, encode_time_of_day
    from dragd.hardware.reader import BusReader

    d = Daemon(load_config(DEFAULT_CONFIG), bus_override="udp_multicast:239.74.200.1", log=lambda msg: None,
               lockstep=True)
    d.attach({"arm": can.Bus(interface="virtual", channel="unit-daemon-cycle")})
    codec = struct.Struct("<HiH")
    peer = can.Bus(interface="virtual", channel="unit-daemon-cycle")
    stop = threading.Event()

    def answer() -> None:
        k = 0
        while not stop.is_set():
            m = peer.recv(0.05)
            if m is not None and m.arbitration_id == 0x080:
                k += 1
                for node in range(1, 7):
                    peer.send(can.Message(arbitration_id=0x180 + node, data=codec.pack(0x0637, 1000 * node + k, 0),
                                          is_extended_id=False))
                peer.send(can.Message(arbitration_id=TIME_COB_ID, data=encode_time_of_day(k * 1e-3),
                                      is_extended_id=False))

    async def main() -> None:
        loop = asyncio.get_running_loop()
        io, cycle, clock = d.io, d.cycle, d.clock
        assert isinstance(clock, LockstepClock)
        clock.attach(loop)
        notifier = BusReader(d.buses["arm"], [io.listener("arm")], loop=loop, timeout=0.05,
                                    on_data=io.tpdo_decoder("arm"), after=io.after_frames, until=io.read_done)
        try:
            run = loop.create_task(cycle.run())
            assert await clock.grant(0.02) == 20
            assert cycle.cycles == 20 and cycle.late_tpdo == 0 and not io.reading  # (exactly: nothing ran ahead)
            cycle.request_exit()
            await asyncio.wait_for(run, 10.0)  # (a guard only: it ends at once)
            fb = io.feedback
            assert fb.rx.all() and [c // 1000 for c in fb.counts.tolist()] == [1, 2, 3, 4, 5, 6]
            assert [c % 1000 for c in fb.counts.tolist()] == [20] * 6

            def boom(complete: bool) -> bool:
                raise RuntimeError("boom in the step")

            cycle.exit_requested = False
            cycle.step = boom  # type: ignore[method-assign]
            run = loop.create_task(cycle.run())
            grant = clock.grant(0.01)
            with pytest.raises(RuntimeError, match="boom in the step"):
                await asyncio.wait_for(run, 10.0)
            assert not io.reading and cycle.exit_requested
            grant.cancel()
        finally:
            notifier.stop()

    worker = threading.Thread(target=answer, daemon=True)
    worker.start()
    try:
        asyncio.run(main())
    finally:
        stop.set()
        worker.join()
        peer.shutdown()


def test_run_realtime_priority_override_goes_through_the_schema() -> None:
    from dragd.cli.app import CliError
    from dragd.cli.daemon import with_realtime_priority

    cfg = load_config(DEFAULT_CONFIG)
    assert cfg.loop.realtime_priority is None
    assert with_realtime_priority(cfg, 70).loop.realtime_priority == 70
    assert with_realtime_priority(with_realtime_priority(cfg, 70), 0).loop.realtime_priority is None
    assert with_realtime_priority(cfg, 70).loop.rate_Hz == cfg.loop.rate_Hz  # the rest of the section is kept
    with pytest.raises(CliError, match="1..99"):
        with_realtime_priority(cfg, 100)


_REALTIME_PROBE = """
import asyncio, json, os, subprocess, sys, threading
from dragd.daemon.core import go_realtime
from dragd.realtime import demote_current_thread

RESET = os.SCHED_RESET_ON_FORK

async def main():
    loop = asyncio.get_running_loop()
    label = go_realtime(loop, 10, None)
    def probe():
        p = os.sched_getscheduler(0)
        child = subprocess.run([sys.executable, "-c", "import os; print(os.sched_getscheduler(0))"],
                               capture_output=True, text=True, check=True).stdout
        got = []
        def helper_of_helper():  # (a thread started by a helper, e.g. the telemetry writer's: it demotes itself)
            demote_current_thread()
            got.append((os.sched_getscheduler(0) & ~RESET, os.sched_getparam(0).sched_priority))
        t = threading.Thread(target=helper_of_helper)
        t.start()
        t.join()
        return (p & ~RESET, bool(p & RESET), os.sched_getparam(0).sched_priority, threading.current_thread().name,
                int(child), got[0])
    pool = await loop.run_in_executor(None, probe)
    thread = await asyncio.to_thread(probe)
    print(json.dumps({"label": label, "cycle": os.sched_getscheduler(0), "pool": pool, "to_thread": thread,
                      "fifo": os.SCHED_FIFO, "other": os.SCHED_OTHER}))

asyncio.run(main())
"""


def test_realtime_cycle_thread_puts_helper_threads_below_it() -> None:
    """After go_realtime the cycle thread is SCHED_FIFO (where permitted) and the loop's executor threads — which
    would inherit it — run SCHED_FIFO 1: below the cycle (a long resampling job at the cycle's priority would starve
    it), above every normal task (a SCHED_OTHER helper preempted while holding the GIL stalls the cycle); and the
    processes they start (the planner, the telemetry encoder) run SCHED_OTHER (SCHED_RESET_ON_FORK)."""
    import json
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", _REALTIME_PROBE], capture_output=True, text=True, timeout=60,
                         check=True)
    r = json.loads(out.stdout)
    if r["cycle"] != r["fifo"]:
        assert "refused" in r["label"], r  # not permitted here: said so, nothing else changes
        pytest.skip(f"SCHED_FIFO not permitted: {r['label']}")
    assert r["label"] == "SCHED_FIFO 10"
    for helper in (r["pool"], r["to_thread"]):
        policy, reset_on_fork, priority, name, child, grandchild_thread = helper
        assert (policy, reset_on_fork, priority) == (r["fifo"], True, 1), r
        assert child == r["other"], r
        assert grandchild_thread == [r["fifo"], 1], r
    assert r["pool"][3].startswith("dragd-exec")


_HELPERS_FIRST_PROBE = """
import asyncio, json, os, sys, tempfile, threading, time
from concurrent.futures import ThreadPoolExecutor
from dragd.daemon.core import go_realtime
from dragd.realtime import demote_current_thread, thread_policies
from dragd.telemetry.writer import TelemetryWriter

async def main():
    loop = asyncio.get_running_loop()
    # as the daemon's boot does: the SDO worker and the telemetry forwarder start before the cycle turns real-time
    sdo = ThreadPoolExecutor(1, thread_name_prefix="dragd-sdo", initializer=demote_current_thread, initargs=(None,))
    sdo.submit(lambda: None).result()
    w = TelemetryWriter(os.path.join(tempfile.mkdtemp(), "t.mcap"), {"t_s": 1}, process=True)
    while w.stats()["writer_pid"] is None:  # (the forwarder has demoted itself and started the encoder)
        time.sleep(0.01)
    before = {t.name: os.sched_getscheduler(t.native_id) for t in threading.enumerate()}
    label = go_realtime(loop, 10, None)
    await loop.run_in_executor(None, lambda: None)  # (an executor thread started after)
    reset = os.SCHED_RESET_ON_FORK
    after = {t.name: [os.sched_getscheduler(t.native_id) & ~reset, os.sched_getparam(t.native_id).sched_priority]
             for t in threading.enumerate()}
    print(json.dumps({"label": label, "before": before, "after": after, "reported": thread_policies(),
                      "encoder": os.sched_getscheduler(w.stats()["writer_pid"]), "main": threading.main_thread().name,
                      "fifo": os.SCHED_FIFO, "other": os.SCHED_OTHER}))
    w.close()
    sdo.shutdown()

asyncio.run(main())
"""


def test_helpers_started_before_the_cycle_turns_realtime_go_below_it_too() -> None:
    """The daemon's SDO worker and telemetry forwarder start during boot, before go_realtime: they were left
    SCHED_OTHER, and under the host's load the cycle waited for the GIL one of them held while off a CPU (156 missed
    cycles, the RPDO watchdogs faulted the arm: docs/DECISIONS.md). After go_realtime every thread of the process but
    the cycle runs SCHED_FIFO 1, whenever it started, and status's ``threads`` says so; the encoder process it
    started stays SCHED_OTHER."""
    import json
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", _HELPERS_FIRST_PROBE], capture_output=True, text=True, timeout=60,
                         check=True)
    r = json.loads(out.stdout)
    if "refused" in r["label"]:
        pytest.skip(f"SCHED_FIFO not permitted: {r['label']}")
    assert r["before"]["dragd-sdo_0"] == r["before"]["dragd-telemetry"] == r["other"], r  # (the case at hand)
    helpers = {name: pol for name, pol in r["after"].items() if name != r["main"]}
    assert {"dragd-sdo_0", "dragd-telemetry"} <= set(helpers) and any(n.startswith("dragd-exec") for n in helpers)
    assert all(pol == [r["fifo"], 1] for pol in helpers.values()), r
    assert r["after"][r["main"]] == [r["fifo"], 10], r
    assert r["reported"] == {name: "SCHED_FIFO 10" if name == r["main"] else "SCHED_FIFO 1" for name in r["after"]}
    assert r["encoder"] == r["other"], r


def test_helpers_that_ended_are_forgotten():
    """demote_current_thread remembers its thread (set_realtime re-applies the helper policy to it); one that ended
    is forgotten at the next registration, so a daemon opening record window after record window keeps none."""
    import threading

    from dragd import realtime
    from dragd.realtime import demote_current_thread

    first = threading.Thread(target=demote_current_thread, name="helper-ended")
    first.start()
    first.join()
    second = threading.Thread(target=demote_current_thread, name="helper-next")
    second.start()
    second.join()
    kept = [t for t, _ in realtime._HELPERS.values()]
    assert first not in kept and second in kept


def test_gravity_beyond_a_current_limit_is_refused_not_clamped(tmp_path) -> None:
    """A pose whose gravity current exceeds a joint's limit: start (and drag) are refused naming the joint and the
    numbers, instead of a silently clamped command that lets the arm sag."""
    import yaml

    from inproc import InProcess

    data = yaml.safe_load(DEFAULT_CONFIG.read_text())
    data["joints"][1]["current_limit_A"] = 1.0  # the shoulder needs ~5 A at the sim's start pose
    path = tmp_path / "weak.yaml"
    path.write_text(yaml.safe_dump(data))
    arm = InProcess(load_config(path))
    arm.feed(np.array([0.0, -0.6, 1.2, -0.6, 1.5708, 0.0]))
    arm.cycle()
    with pytest.raises(ValueError,
                       match=r"start: joint2 needs \d+\.\d+ A to hold .* above its current_limit_A 1\.00 A"):
        arm.d.start()
    assert arm.c.mode.name == "IDLE" and not arm.d.faults


@pytest.mark.parametrize("batch", [True, False])
def test_command_frames_ride_with_the_next_sync_on_a_batching_bus(batch: bool) -> None:
    """udp_multicast with batch_frames: the cycle's command RPDO leaves with the next SYNC, ahead of it, in one
    datagram, carrying what was written (the drives apply it at that SYNC either way); without batching it leaves
    at once. A stopping cycle flushes what waits."""
    import asyncio
    import time

    from dragd.hardware.bus import open_bus, parse_bus

    group = f"239.74.201.{11 if batch else 12}"
    d = Daemon(load_config(DEFAULT_CONFIG), bus_override=f"udp_multicast:{group}", log=lambda msg: None)
    spec = parse_bus(f"udp_multicast:{group}", fd=True)
    bus, peer = open_bus(spec, batch_frames=batch), open_bus(spec)
    try:
        d.attach({"arm": bus})
        (cmd_cob,) = [fr.cob_id for fr in d.layouts["arm"].frames if fr.direction == "rpdo"]

        def datagrams() -> list[list[tuple[int, bytes]]]:
            out = []
            while True:
                got: list[tuple[int, bytes]] = []
                if not peer.drain(lambda cob, data, got=got: not got.append((cob, bytes(data))), lambda m: None,
                                  limit=1):
                    return out
                out.append(got)

        permille = np.array([10, -20, 30, -40, 50, -60])
        d.io.write(np.full(6, 0x0F), np.arange(6) * 1000, permille, 0.001)
        time.sleep(0.05)
        early = datagrams()

        async def one_read() -> None:
            await d.io.read(asyncio.get_running_loop(), 0.002)

        asyncio.run(one_read())
        time.sleep(0.05)
        late = datagrams()
        if batch:
            assert early == [], "the command frame left before the next SYNC"
            assert len(late) == 1 and [cob for cob, _ in late[0]] == [cmd_cob, 0x080]
            command = late[0][0][1]
        else:
            assert len(early) == 1 and [cob for cob, _ in early[0]] == [cmd_cob]
            assert late == [[(0x080, b"")]]
            command = early[0][0][1]
        assert command == bytes(d.io._commands[0][2].buffer)  # what write() packed
        d.io.write(np.full(6, 0x0F), np.zeros(6), permille, 0.002)
        d.io.flush()
        time.sleep(0.05)
        assert [[cob for cob, _ in dg] for dg in datagrams()] == [[cmd_cob]]  # (batching: by flush; else at once)
    finally:
        bus.shutdown()
        peer.shutdown()
