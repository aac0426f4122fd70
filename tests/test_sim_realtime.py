"""The simulator on the wall clock: its real-time runner (``--seconds``, SIGINT) and its bus reader (a SYNC's answer in
one datagram, a reader woken but not yet run, the RPDO watchdog judged by what the reader has read). This is the
simulator's real-time behaviour (threads, the GIL, a stalled process), so it stays in the wall-clock tier (its
watchdogs over a frozen host, judged on an injected clock, are unit tests: tests/test_sim_stalls.py);
tests/test_sim_canopen.py, test_sim_process.py and test_sim_vendor_eds.py run the drives against a CANopen master on
the lockstep clock."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import struct
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import can
import pytest
from test_sim_canopen import TRUTH
from test_sim_process import REPO, SimProc, unique_group

from dragd.hardware.bus import open_bus, parse_bus

pytestmark = [pytest.mark.rig, pytest.mark.timeout(120)]


def test_sync_answer_leaves_in_one_datagram_with_batch_frames(request: pytest.FixtureRequest) -> None:
    """The simulated drives answer a SYNC with every drive's TPDOs in one datagram on a batching bus (--batch-frames);
    the daemon's side reads them as separate frames."""
    from sim.axis import AxisIO
    from sim.drive import SimDrive
    from sim.network import SimNetwork
    from sim.truth import drive_params

    h = int.from_bytes(hashlib.sha256(f"{request.node.name}:{os.getpid()}".encode()).digest()[:2], "big")
    spec = parse_bus(f"udp_multicast:239.75.{h % 250}.{1 + (h >> 8) % 250}")
    sim_bus, master = open_bus(spec, batch_frames=True), open_bus(spec)
    drives = [SimDrive(drive_params(j, fd=False), AxisIO(), sim_bus.send) for j in TRUTH.joints]
    net = SimNetwork(sim_bus, drives)
    try:
        net.start(boot=True)
        master.send(can.Message(arbitration_id=0x000, data=b"\x01\x00", is_extended_id=False))  # NMT start all
        time.sleep(0.2)
        while master.recv(0.05) is not None:
            pass
        before = sim_bus.counters()
        master.send(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False))
        got = []
        while (msg := master.recv(0.3)) is not None:
            got.append(msg.arbitration_id)
        after = sim_bus.counters()
        tpdos = sorted(0x180 + d.node_id for d in drives)
        assert sorted(c for c in got if c in tpdos) == tpdos, f"every drive's TPDO1 once, got {[hex(c) for c in got]}"
        assert after.frames_sent - before.frames_sent == len(got)
        assert after.datagrams_sent - before.datagrams_sent == 1
    finally:
        net.stop()
        sim_bus.shutdown()
        master.shutdown()


def test_a_reader_woken_but_not_yet_run_is_not_caught_up(request: pytest.FixtureRequest) -> None:
    """The reader waits on its socket (idle) when frames arrive, and another thread of the process holds the GIL
    (physics catching up): those frames are not handed over, so the watchdogs must not judge by the clock."""
    from sim.network import SimNetwork

    h = int.from_bytes(hashlib.sha256(f"{request.node.name}:{os.getpid()}".encode()).digest()[:2], "big")
    spec = parse_bus(f"udp_multicast:239.76.{h % 250}.{1 + (h >> 8) % 250}")
    sim_bus, master = open_bus(spec), open_bus(spec)
    try:
        net = SimNetwork(sim_bus, [])
        net._running, net._idle, net._caught_up_s = True, True, 5.0  # (the state of a reader waiting in select)
        assert net.caught_up(9.0) == 9.0  # nothing queued: caught up as of now
        master.send(can.Message(arbitration_id=0x201, data=b"\x06\x00", is_extended_id=False))
        end = time.monotonic() + 2.0
        while net.caught_up(9.0) != 5.0:
            assert time.monotonic() < end, "a queued frame left the reader counted as caught up"
            time.sleep(0.002)
        assert sim_bus.recv(1.0) is not None
        assert net.caught_up(9.0) == 9.0
    finally:
        sim_bus.shutdown()
        master.shutdown()


def test_rpdo_watchdog_waits_for_frames_the_reader_has_not_read(request: pytest.FixtureRequest) -> None:
    """A real drive takes each frame off the wire as it comes; the simulated one reads them in a thread of a process
    the OS may not schedule. A deadline that passes while RPDOs wait for the reader is judged by what it has read up
    to then (no false EMCY 8250 from a stalled simulator); silence on the bus still faults the drive, and so does a
    reader that is gone."""
    from sim.axis import AxisIO
    from sim.drive import SimDrive
    from sim.network import SimNetwork
    from sim.truth import drive_params

    h = int.from_bytes(hashlib.sha256(f"{request.node.name}:{os.getpid()}".encode()).digest()[:2], "big")
    spec = parse_bus(f"udp_multicast:239.76.{h % 250}.{1 + (h >> 8) % 250}")
    sim_bus, master = open_bus(spec), open_bus(spec, batch_frames=True)
    sent: list[can.Message] = []

    def tx(msg: can.Message) -> None:
        sent.append(msg)
        sim_bus.send(msg)

    drive = SimDrive(drive_params(TRUTH.joints[0], fd=False), AxisIO(), tx)
    node = drive.node_id
    net = SimNetwork(sim_bus, [drive])

    def emcys() -> list[bytes]:
        return [bytes(m.data) for m in sent if m.arbitration_id == 0x80 + node and bytes(m.data[:2]) == b"\x50\x82"]

    def wait_for(cond: Callable[[], bool], what: str) -> None:
        end = time.monotonic() + 2.0
        while not cond():
            assert time.monotonic() < end, what
            time.sleep(0.002)

    rpdo = can.Message(arbitration_id=0x200 + node, data=struct.pack("<Hh", 0x06, 0), is_extended_id=False)
    try:
        net.start(boot=True)
        drive.store.sdo_write(0x1400, 5, struct.pack("<H", 50))  # RPDO1 deadline 50 ms
        master.send(can.Message(arbitration_id=0x000, data=bytes((0x01, node)), is_extended_id=False))
        wait_for(lambda: drive.nmt_state.name == "OPERATIONAL", "NMT start")
        drive.comm(time.monotonic())  # the drive's clock (the simulator's loop hands it in every tick)
        master.send(rpdo)
        wait_for(lambda: drive.rpdos[0].last_rx_s is not None, "the first RPDO")
        wait_for(lambda: net.caught_up(-1.0) == -1.0, "the reader waiting again")  # (idle: caught up as of now)
        first = drive.rpdos[0].last_rx_s
        # the simulator "stalls": its reader is held up (here: on the drive's lock) while three RPDOs and a SYNC
        # arrive in one datagram; the physics thread's comm tick then runs a second past the deadline
        with drive._lock:
            with master.batch():
                for _ in range(3):
                    master.send(rpdo)
                master.send(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False))
            wait_for(lambda: net.caught_up(-1.0) != -1.0, "the reader taking the datagram")
            drive._comm_tick(first + 1.0)
            assert not emcys() and drive.counters.rpdo_timeouts == 0 and drive.counters.watchdog_waits == 1
        wait_for(lambda: drive.counters.rpdos_received == 4, "the held-up RPDOs")
        drive._comm_tick(drive.rpdos[0].last_rx_s + 0.01)  # read: within the deadline
        assert not emcys() and drive.counters.rpdo_timeouts == 0
        # nothing waits and nothing came for a second: the bus is silent, the watchdog fires
        wait_for(lambda: net.caught_up(-1.0) == -1.0, "the reader waiting again")
        drive._comm_tick(drive.rpdos[0].last_rx_s + 1.0)
        assert drive.counters.rpdo_timeouts == 1 and len(emcys()) == 1 and emcys()[0][3] == 1
        # a reader that has stopped reads nothing more: its drives judge by the clock
        net.stop()
        assert net.caught_up(123.0) == 123.0
    finally:
        sim_bus.shutdown()
        master.shutdown()


def test_sigint_and_seconds_exit_cleanly(tmp_path: Path) -> None:
    group = unique_group()
    proc = subprocess.run([sys.executable, "-m", "sim", "run", "--bus", f"udp_multicast:{group}", "--seconds", "1.5",
                           "--json"], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout.splitlines()[-1])
    assert summary["sim_time_s"] == pytest.approx(1.5) and summary["steps"] == 6000
    # paced by the wall clock, never ahead of it (behind it: a loaded host, a benchmark's figure)
    assert summary["rtf"] < 1.05

    sim = SimProc(tmp_path, unique_group(), lockstep=False)
    try:
        rc, summary, err = sim.finish(signal.SIGINT)
    finally:
        sim.kill()
    assert rc == 0, err
    assert summary["ok"] and summary["steps"] > 0


def test_a_stopped_simulator_reports_its_own_stall(tmp_path: Path) -> None:
    """The simulator notes the time it did not run (SIGSTOP: the OS does not schedule it, as a host freeze does):
    its summary's ``own_stalls``, the time its drives' reception watchdogs leave out (tests/test_sim_stalls.py). The
    process is stopped at least 0.3 s by construction: the stall it reports is at least that, less the 2 ms a gap
    between two of its readings may be running time; setting up before the loop is not a stall."""
    sim = SimProc(tmp_path, unique_group(), lockstep=False)
    try:
        sim.proc.send_signal(signal.SIGSTOP)
        time.sleep(0.3)
        sim.proc.send_signal(signal.SIGCONT)
        sim.call("state")  # (running again)
        rc, summary, err = sim.finish(signal.SIGINT)
    finally:
        sim.kill()
    assert rc == 0, err
    stalls = summary["own_stalls"]
    assert stalls["count"] >= 1 and stalls["max_s"] >= 0.3 - stalls["gap_threshold_s"], stalls
    assert all("watchdog_holds" in d for d in summary["drives"].values())
