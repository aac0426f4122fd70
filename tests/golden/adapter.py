"""The daemon as the golden trace sees it: feedback frames and operator requests in, command frames out.

This is the one place that knows the daemon's internal API; a restructure changes this file only. One cycle is
exactly what the running daemon does between two ticks (dragd/daemon/cycle.py: tick → read → step → log), with
the bus replaced by lists of frames and the drive-mode switch (an SDO exchange in the daemon) completed right after
the cycle (or request) that asked for it.
"""

from __future__ import annotations

import asyncio
from typing import Any

import can
import numpy as np

from dragd.config import Config
from dragd.control.trajectory import Trajectory
from dragd.daemon.core import Daemon
from dragd.hardware.cia301 import HEARTBEAT_BASE, SYNC_COB_ID
from dragd.hardware.cia402 import MODE_CSP, MODE_CST

TELEMETRY_SKIP = ("compute_us",)  # wall time, not behaviour


class _FrameSink:
    """Stands in for a bus: collects the command frames the daemon sends (SYNC and heartbeat left out)."""

    def __init__(self, name: str, out: list[tuple[str, int, bytes]], skip: set[int]) -> None:
        self.name, self.out, self.skip = name, out, skip

    def send(self, msg: Any, timeout: float | None = None) -> None:
        if msg.arbitration_id not in self.skip:
            self.out.append((self.name, int(msg.arbitration_id), bytes(msg.data)))


class DaemonAdapter:
    def __init__(self, cfg: Config) -> None:
        self.sent: list[tuple[str, int, bytes]] = []
        self.log: list[str] = []
        d = self.d = Daemon(cfg, bus_override=",".join(f"virtual:golden{i}" for i in range(len(cfg.buses))),
                            log=self.log.append, lab_unguarded_drag=True)  # (the traces' drags hold no lease)
        skip = {SYNC_COB_ID, HEARTBEAT_BASE + cfg.master.node_id}
        d.attach({name: _FrameSink(name, self.sent, skip) for name in d.layouts})  # type: ignore[misc]
        self.listeners = {name: d.io.listener(name) for name in d.layouts}
        self.drive_mode_events: list[int] = []
        m = d.motions

        async def switch(mode: int) -> None:  # the SDO exchange: done at once, in order
            m.switch_pending = True
            await asyncio.sleep(0)
            m._set_drive_mode(mode)
            m.switch_pending = False
            self.drive_mode_events.append(int(mode))

        m.switch_drive_mode = switch  # type: ignore[method-assign]
        self.fields = [k for k in d.recorder.layout if k not in TELEMETRY_SKIP]
        self.row = np.zeros(d.recorder.width)

    @property
    def n(self) -> int:
        return self.d.n

    @property
    def q(self) -> np.ndarray:
        return self.d.cycle.est.q_rad

    @property
    def drive_mode(self) -> int:
        return int(self.d.motions.drive_mode)

    @property
    def mode(self) -> int:
        return int(self.d.controller.mode)

    async def request(self, name: str, args: dict[str, Any]) -> Any:
        """An operator request, as the control socket's handlers make it (without their waits)."""
        d, m = self.d, self.d.motions
        try:
            if name == "start":
                return d.start()
            if name == "stop":
                return d.stop()
            if name == "mode":
                return d.set_mode(args["mode"])
            if name == "track":
                traj = Trajectory(np.array(args["t_s"]), np.array(args["q_rad"]), d.cycle.dt, "track")
                return await m.track(traj)
            if name == "replay":
                traj = Trajectory.from_table(np.array(args["q"]), d.cycle.dt, "replay golden", dq=np.array(args["dq"]),
                                             ff_Nm=np.array(args["ff_Nm"]), body_row=args["body_row"])
                return await m.track(traj, rate=args["speed"], cycles=args["cycles"])
            if name == "pause":
                return m.pause()
            if name == "resume":
                return m.resume()
            if name == "track_stop":
                return m.stop()
            if name == "speed":
                return m.set_speed(args["speed"])
            raise ValueError(f"golden adapter: unknown request {name!r}")
        finally:
            d.record_events()  # (a drive-mode switch the request asked for runs after the next cycle, as it would)

    async def cycle(self, frames: list[tuple[str, int, bytes]], period_us: float, expirations: int) -> dict[str, Any]:
        """One cycle: the frames that arrived after SYNC in, the command frames and the telemetry row out."""
        d, cy = self.d, self.d.cycle
        self.sent.clear()
        cy.tick(period_us, expirations)
        d.io.begin_cycle()
        for bus, cob, data in frames:
            self.listeners[bus].on_message_received(can.Message(arbitration_id=cob, data=data, is_extended_id=False))
        complete = d.io.end_read()
        out: dict[str, Any] = {"computed": False}
        if not cy.step(complete):
            return out
        cy.cycles += 1
        d.recorder.fill_row(self.row, period_us, 0.0)
        for fn in cy.after_cycle:
            fn()  # type: ignore[operator]
        await asyncio.sleep(0)  # a drive-mode switch asked for in this cycle completes before the next
        await asyncio.sleep(0)
        cols = d.recorder.cols
        out.update(computed=True, frames=list(self.sent), mode=self.mode, drive_mode=self.drive_mode,
                   telemetry={k: np.atleast_1d(self.row[cols[k]]).copy() for k in self.fields},
                   faults=len(d.faults))
        return out

    @property
    def faults(self) -> list[dict[str, Any]]:
        return self.d.faults


__all__ = ["DaemonAdapter", "MODE_CSP", "MODE_CST"]
