"""A simulated drive that skips physics steps while nothing can change its outputs (sim/drive.py ``_steady``).

Two twin drives get the same frames, SYNCs, SDO commands, injected faults (sim/faults.py, as the control socket
injects them), watchdog timeouts and axis readings on one clock; one skips steady steps, the other is forced to
compute every step. Their outputs to the physics, statuswords, states and every frame they send (TPDOs with the
actual values, EMCYs, heartbeats) must agree at every step, and actual values read over SDO are those of the moment
they are read.
"""

from __future__ import annotations

import math
import struct
import threading
from collections.abc import Callable

import can
import numpy as np
import pytest

from dragd.hardware.cia402 import (
    CMD_DISABLE_VOLTAGE,
    CMD_ENABLE_OPERATION,
    CMD_FAULT_RESET,
    CMD_QUICK_STOP,
    CMD_SHUTDOWN,
)
from sim.axis import AxisIO
from sim.drive import SimDrive
from sim.faults import FaultInjector
from sim.truth import drive_params, load_truth

from conftest import REPO

pytestmark = pytest.mark.unit

TRUTH = load_truth(REPO / "sim/config/seed_cobot.yaml")
Action = Callable[[SimDrive], None]


def _sdo_download(drive: SimDrive, index: int, sub: int, value: int, size: int) -> None:
    """An expedited SDO download frame straight into a drive (signed little-endian value)."""
    cs = {1: 0x2F, 2: 0x2B, 4: 0x23}[size]
    data = struct.pack("<BHB", cs, index, sub) + value.to_bytes(size, "little", signed=True).ljust(4, b"\0")
    drive.on_data(0x600 + drive.node_id, data)


def _sdo_upload(drive: SimDrive, index: int) -> None:
    drive.on_data(0x600 + drive.node_id, struct.pack("<BHB4x", 0x40, index, 0))


def _frames(sent: list[can.Message]) -> list[tuple[int, bytes]]:
    out = [(m.arbitration_id, bytes(m.data)) for m in sent]
    sent.clear()
    return out


def test_a_steady_drive_computes_what_a_full_update_would() -> None:
    # one clock for both twins (handed to the drives by comm and on_sync: reception times, deadlines, inhibit times):
    # it advances with the physics steps, and jumps where the master falls silent
    clock = [1000.0]
    params = drive_params(TRUTH.joints[1], fd=False)
    sent: tuple[list[can.Message], list[can.Message]] = ([], [])
    skip, ref = (SimDrive(params, AxisIO(), out.append) for out in sent)
    bus = can.Bus(interface="virtual", channel="steady-twins")
    injector, lock = FaultInjector(bus), threading.Lock()
    node = params.node_id
    for d in (skip, ref):
        d.boot()
        _sdo_download(d, 0x1400, 5, 30, 2)  # RPDO1 event timer: a 30 ms reception deadline (watchdog → 6007h)
        _sdo_download(d, 0x6007, 0, 2, 2)  # abort connection option 2: disable voltage
        d.on_data(0x000, bytes((0x01, node)))  # NMT start: RPDOs and SYNC count
    rng = np.random.default_rng(5)
    dt, skipped, silent_until = 0.00025, 0, 0
    words = [CMD_SHUTDOWN, CMD_SHUTDOWN | 0x1, CMD_ENABLE_OPERATION, CMD_QUICK_STOP, CMD_DISABLE_VOLTAGE,
             CMD_FAULT_RESET]
    torque = 0
    for step in range(30_000):
        t = step * dt
        r = rng.random()
        actions: list[Action] = []
        if r < 0.0005:  # a disruptive controlword over SDO (disable, quick stop, shutdown, ...)
            w = int(rng.choice(words))
            actions.append(lambda d, w=w: _sdo_download(d, 0x6040, 0, w, 2))
        elif r < 0.003:
            v = int(rng.integers(-1500, 1500))
            actions.append(lambda d, v=v: _sdo_download(d, 0x6071, 0, v, 2))
        elif r < 0.004:
            v = int(rng.integers(-300, 300))
            actions.append(lambda d, v=v: _sdo_download(d, 0x60B2, 0, v, 2))
        elif r < 0.0045:
            v, index = int(rng.integers(200, 3000)), int(rng.choice([0x6072, 0x6073]))  # max torque / current
            actions.append(lambda d, v=v, index=index: _sdo_download(d, index, 0, v, 2))
        elif r < 0.0047:
            m = int(rng.choice([10, 10, 10, 4]))  # mostly CST, sometimes profile torque (never steady)
            actions.append(lambda d, m=m: _sdo_download(d, 0x6060, 0, m, 1))
        elif r < 0.0048:
            actions.append(lambda d: d.inject_fault(0x2310))
        elif r < 0.0050:  # what the control socket's `inject` does, straight into the drive's state
            kind = str(rng.choice(["switched_on", "emcy"]))
            actions.append(lambda d, kind=kind: injector.inject(kind, {node: d}, {"node_id": node}, lock))
        elif r < 0.0051:  # the master silent for 50 ms: the RPDO deadline passes (abort connection → disable voltage)
            silent_until = step + 200
        if step >= silent_until and step % 4 == 0:  # the master's cycle: RPDO1 (controlword, target torque) ...
            torque = int(np.clip(torque + rng.integers(-40, 41), -1500, 1500)) if rng.random() < 0.5 else torque
            actions.append(lambda d, v=torque: d.on_data(0x200 + node, struct.pack("<Hh", CMD_ENABLE_OPERATION, v)))
        if step >= silent_until and step % 4 == 2:  # ... latched until the SYNC, two physics steps later
            actions.append(lambda d: d.on_sync(clock[0]))  # (as SimNetwork calls it: not through on_data)
        if step % 1500 == 100:  # regularly back to operational, operation enabled, CST (one time in four PT)
            mode = 4 if step % 6000 == 100 else 10
            actions += [lambda d: d.on_data(0x000, bytes((0x01, node))),
                        lambda d, m=mode: _sdo_download(d, 0x6060, 0, m, 1)] + [
                lambda d, w=w: _sdo_download(d, 0x6040, 0, w, 2)
                for w in (CMD_DISABLE_VOLTAGE, CMD_FAULT_RESET, CMD_SHUTDOWN, CMD_SHUTDOWN | 0x1, CMD_ENABLE_OPERATION)]
        q = 0.3 * math.sin(2.0 * t) + 1e-4 * step
        clock[0] += dt
        for d in (skip, ref):
            for act in actions:
                act(d)
            d.io.position_rad, d.io.velocity_rad_s, d.io.current_measured_A = q, 0.6 * math.cos(2.0 * t), 0.1 * q
            if step % 4 == 0:  # the simulator's loop: the comm timers once per 1 ms tick
                d.comm(clock[0])
        skipped += skip._steady
        ref._steady = False  # the twin computes every step
        for d in (skip, ref):
            d.update(t, dt)
        assert (skip.io.current_demand_A, skip.io.power_stage_on, skip.io.brake_engaged) == \
            (ref.io.current_demand_A, ref.io.power_stage_on, ref.io.brake_engaged), step
        assert skip.store.get(0x6041) == ref.store.get(0x6041) and skip.state is ref.state, step
        assert _frames(sent[0]) == _frames(sent[1]), step  # TPDOs (actual values as of the SYNC), EMCY, heartbeats
        if step % 997 == 0:  # actual values over SDO: sampled when read, whatever the last computed step
            for d in (skip, ref):
                d.io.position_rad += 0.01
                _sdo_upload(d, 0x6064)
            assert _frames(sent[0]) == _frames(sent[1]), step
            assert skip.store.get(0x6064) == round((q + 0.01) * skip._counts_per_rad), step
    timeouts = skip.counters.rpdo_timeouts
    bus.shutdown()
    assert skip.counters.rpdos_applied > 5_000
    assert 3_000 < skipped < 28_000, skipped  # both paths ran: steady stretches and computed steps
    assert timeouts > 0 and timeouts == ref.counters.rpdo_timeouts  # the watchdog fired on steady drives too
