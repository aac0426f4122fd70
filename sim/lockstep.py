"""The simulator's side of the lockstep clock (``python -m sim run --lockstep``; dragd/clock.py is the daemon's).

Each SYNC the master sends is one period of simulated time: the drives answer it as always (their TPDOs sample the
arm as the SYNC finds it and the commands that came with it are applied, as on the wall clock), then the same
thread runs the period (``physics_rate_Hz × period`` steps, every drive's ``update``, the operator, payload changes),
the faults due by then and the drives' communication timers at the period's end (``comm``: heartbeats, RPDO
deadlines, event TPDOs, EMCYs), and last a CANopen TIME frame (COB-ID 100h, TIME_OF_DAY of the sim time) on every
bus: the master's sign that everything of that period has been sent. All of it leaves as one datagram per bus (where
the bus batches): two trips between the processes per period, no thread hand-over. With several buses a period runs
once the SYNC of every bus arrived. Nothing here reads the wall clock: the simulator waits for the next SYNC however
long it takes.

``SimClock.now`` is the drives' communication clock: the time of the last period's end, which the network hands to
``on_sync`` and the runner to ``comm`` (the drives read no clock of their own: sim/drive.py), and the fault injector's.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import can

from dragd.clock import TIME_COB_ID, encode_time_of_day

__all__ = ["SimClock", "LockstepSync"]


class SimClock:
    """Simulated time at the last period's end, for the drives' communication timers (thread-safe to read)."""

    def __init__(self, t_s: float = 0.0) -> None:
        self.t_s = t_s

    def now(self) -> float:
        return self.t_s


class LockstepSync:
    """A period per SYNC on every bus. The bus reader that receives a SYNC calls ``on_sync`` after its drives
    answered it, inside its batch (one datagram per bus and period): the last bus's SYNC of a period runs it
    (``run_period``, the simulator's steps and the drives' timers), the others wait for it; then each reader adds its
    bus's TIME frame to its batch. The answer to a SYNC thus leaves at the period's end: its TPDOs (sampled as the
    SYNC found the arm), what the period sent (heartbeats, EMCYs, delayed frames), the TIME frame last."""

    def __init__(self, buses: list[can.BusABC], period_s: float, physics_dt_s: float) -> None:
        steps = period_s / physics_dt_s
        if not (period_s > 0 and abs(steps - round(steps)) < 1e-6 and round(steps) >= 1):
            raise ValueError(f"--period-ms {period_s * 1e3:g}: expected a whole number of physics steps of "
                             f"{physics_dt_s * 1e3:g} ms (physics_rate_Hz)")
        self.buses = buses
        self.period_s = period_s
        self.steps = int(round(steps))
        self.clock = SimClock()
        self.run_period: Callable[[int], object] = lambda steps: None  # set by the simulator (SimProcess._period)
        self.periods = 0  # periods run (their CPU: the bus readers' SimNetwork.cpu_ns; no clock read per period)
        self.time_frames = 0
        self._syncs = [0] * len(buses)
        self._cv = threading.Condition()

    def on_sync(self, bus_index: int) -> None:
        """A SYNC arrived on bus ``bus_index`` and its drives answered (the caller's batch is open): run the period if
        every bus has its SYNC, else wait until it ran; then this bus's TIME frame."""
        with self._cv:
            self._syncs[bus_index] += 1
            due = self._syncs[bus_index]
            if min(self._syncs) >= due and self.periods < due:
                try:
                    self.run_period(self.steps)
                finally:
                    self.periods += 1
                    self._cv.notify_all()
            else:
                while self.periods < due:
                    self._cv.wait(1.0)
            t = self.clock.t_s
        bus = self.buses[bus_index]
        send_data = getattr(bus, "send_data", None)  # (dragd's udp_multicast: the same bytes, without a can.Message)
        if send_data is not None:
            send_data(TIME_COB_ID, encode_time_of_day(t))
        else:
            bus.send(can.Message(arbitration_id=TIME_COB_ID, data=encode_time_of_day(t), is_extended_id=False))
        self.time_frames += 1
