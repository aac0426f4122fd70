"""The simulator's side of the lockstep clock (``python -m sim run --lockstep``; dragd/clock.py is the daemon's).

Each SYNC the master sends is one period of simulated time: the drives answer it at once (their TPDOs sample the
arm as the SYNC finds it and latch the commands that came with it, as on the wall clock), then the physics thread
runs the period (``physics_rate_Hz × period`` steps, every drive's ``update``, the operator, payload changes), the
drives' communication timers at the period's end (``comm``: heartbeats, RPDO deadlines, event TPDOs, EMCYs), the
faults due by then, and last a CANopen TIME frame (COB-ID 100h, TIME_OF_DAY of the sim time) on every bus: the
master's sign that everything of that period has been sent. With several buses a period starts once the SYNC of
every bus arrived. Nothing here reads the wall clock: the simulator waits for the next SYNC however long it takes.

``SimClock.now`` is the drives' communication clock (it reads the time of the last period's end). SimDrive reads
``time.monotonic()`` itself for a frame's reception time and its heartbeat schedule (sim/drive.py); until it takes a
clock, ``drive_clock`` points the ``time`` those modules see at this clock in the simulator's process (lockstep
only, where the process is the simulator alone).
"""

from __future__ import annotations

import sys
import threading
import time
import types
from collections.abc import Callable, Iterable
from typing import Any

import can

from dragd.clock import TIME_COB_ID, encode_time_of_day

__all__ = ["SimClock", "LockstepSync", "drive_clock"]


class SimClock:
    """Simulated time at the last period's end, for the drives' communication timers (thread-safe to read)."""

    def __init__(self, t_s: float = 0.0) -> None:
        self.t_s = t_s

    def now(self) -> float:
        return self.t_s


class LockstepSync:
    """A period per SYNC on every bus: the bus readers count SYNCs (``sync``), the physics thread waits for them
    (``wait``) and ends each period with a TIME frame on every bus (``done``)."""

    def __init__(self, buses: list[can.BusABC], period_s: float, physics_dt_s: float) -> None:
        steps = period_s / physics_dt_s
        if not (period_s > 0 and abs(steps - round(steps)) < 1e-6 and round(steps) >= 1):
            raise ValueError(f"--period-ms {period_s * 1e3:g}: expected a whole number of physics steps of "
                             f"{physics_dt_s * 1e3:g} ms (physics_rate_Hz)")
        self.buses = buses
        self.period_s = period_s
        self.steps = int(round(steps))
        self.clock = SimClock()
        self.periods = 0  # periods run
        self._syncs = [0] * len(buses)
        self._cv = threading.Condition()
        self.time_frames = 0

    def sync(self, bus_index: int) -> None:
        """A SYNC arrived on bus ``bus_index`` (its drives have answered it)."""
        with self._cv:
            self._syncs[bus_index] += 1
            if min(self._syncs) > self.periods:
                self._cv.notify()

    def wait(self, stop: threading.Event, poll_s: float = 0.1) -> bool:
        """Block until a period is due (True) or ``stop`` is set (False)."""
        with self._cv:
            while min(self._syncs) <= self.periods:
                if stop.is_set():
                    return False
                self._cv.wait(poll_s)
        return True

    def done(self, t_s: float, before: Iterable[Callable[[float], None]] = ()) -> None:
        """The period ended at sim time ``t_s``: the drives' clock moves there, ``before`` run (the drives' ``comm``,
        faults due), then the TIME frame goes out on every bus, with what ``before`` sent, as one datagram where the
        bus batches."""
        self.clock.t_s = t_s
        self.periods += 1
        data = encode_time_of_day(t_s)
        batches = [getattr(bus, "batch", None) for bus in self.buses]
        ctxs = [b() for b in batches if b is not None]
        for c in ctxs:
            c.__enter__()
        try:
            for fn in before:
                fn(t_s)
            for bus in self.buses:
                bus.send(can.Message(arbitration_id=TIME_COB_ID, data=data, is_extended_id=False))
                self.time_frames += 1
        finally:
            for c in reversed(ctxs):
                c.__exit__(None, None, None)


def drive_clock(clock: SimClock, classes: Iterable[type]) -> list[str]:
    """Point ``time`` in the modules defining ``classes`` (SimDrive and its bases) at ``clock``: their
    ``time.monotonic()`` reads simulated time. Returns the modules changed. For the simulator's process in lockstep
    only (see the module doc); every other name of ``time`` is the real one."""
    shim = types.ModuleType("time")
    shim.__dict__.update({k: v for k, v in vars(time).items() if not k.startswith("__")})
    shim.monotonic = clock.now  # type: ignore[attr-defined]
    changed = []
    for cls in classes:
        for base in cls.__mro__:
            mod: Any = sys.modules.get(base.__module__)
            if mod is None or not base.__module__.startswith("sim.") or getattr(mod, "time", None) is not time:
                continue
            mod.time = shim
            changed.append(base.__module__)
    return sorted(set(changed))
