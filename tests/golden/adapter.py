"""The daemon as the golden trace sees it: feedback frames and operator requests in, command frames out.

This is the one place that knows the daemon's internal API; a restructure changes this file only. One cycle is
exactly what the running daemon does between two ticks (read → estimate → compute → write → log), with the bus
replaced by lists of frames and the drive-mode switch (an SDO exchange in the daemon) completed right after the
cycle that asked for it.
"""

from __future__ import annotations

import asyncio
from typing import Any

import numpy as np

from dragd.config import Config
from dragd.daemon.core import Daemon, Trajectory
from dragd.hardware.master import MODE_CSP, MODE_CST

TELEMETRY_SKIP = ("compute_us",)  # wall time, not behaviour


class _FrameSink:
    """Stands in for a bus: collects what the daemon sends."""

    def __init__(self, name: str, out: list[tuple[str, int, bytes]]) -> None:
        self.name, self.out = name, out

    def send(self, msg: Any, timeout: float | None = None) -> None:
        self.out.append((self.name, int(msg.arbitration_id), bytes(msg.data)))


class DaemonAdapter:
    def __init__(self, cfg: Config) -> None:
        self.sent: list[tuple[str, int, bytes]] = []
        self.log: list[str] = []
        d = self.d = Daemon(cfg, bus_override=",".join(f"virtual:golden{i}" for i in range(len(cfg.buses))),
                            log=self.log.append)
        d.buses = {name: _FrameSink(name, self.sent) for name in d.layouts}  # type: ignore[misc]
        d._build_io()
        self.tables = {name: d._tpdo.setdefault(name, {}) for name in d.layouts}
        self.primed = False
        self.drive_mode_events: list[int] = []

        async def switch(mode: int) -> None:  # the SDO exchange: done at once, in order
            d.mode_switch_pending = True
            await asyncio.sleep(0)
            d.drive_mode = mode
            d.mode_switch_pending = False
            self.drive_mode_events.append(int(mode))

        d._switch_drive_mode = switch  # type: ignore[method-assign]
        layout = d._telemetry_layout()
        self.fields = [k for k in layout if k not in TELEMETRY_SKIP]
        width = sum(v if isinstance(v, int) else v.width for v in layout.values())
        self.row = np.zeros(width)

    @property
    def n(self) -> int:
        return self.d.n

    @property
    def q(self) -> np.ndarray:
        return self.d.q

    @property
    def drive_mode(self) -> int:
        return int(self.d.drive_mode)

    @property
    def mode(self) -> int:
        return int(self.d.mode)

    async def request(self, name: str, args: dict[str, Any]) -> Any:
        """An operator request, as the control socket's handlers make it (without their waits)."""
        d = self.d
        if name == "start":
            return d.start()
        if name == "stop":
            return d.stop()
        if name == "mode":
            return d.set_mode(args["mode"])
        if name == "track":
            traj = Trajectory(np.array(args["t_s"]), np.array(args["q_rad"]), d.dt, "track")
            return await d.track(traj)
        if name == "replay":
            traj = Trajectory.from_table(np.array(args["q"]), d.dt, "replay golden", dq=np.array(args["dq"]),
                                         ff_Nm=np.array(args["ff_Nm"]), body_row=args["body_row"])
            return await d.track(traj, rate=args["speed"], cycles=args["cycles"])
        if name == "pause":
            return d.track_pause()
        if name == "resume":
            return d.track_resume()
        if name == "track_stop":
            return d.track_stop()
        if name == "speed":
            return d.set_speed_override(args["speed"])
        raise ValueError(f"golden adapter: unknown request {name!r}")

    async def cycle(self, frames: list[tuple[str, int, bytes]], period_us: float, expirations: int) -> dict[str, Any]:
        """One cycle: the frames that arrived after SYNC in, the command frames and the telemetry row out."""
        import can

        d = self.d
        self.sent.clear()
        if expirations > 1:
            d.missed += expirations - 1
        d.sample_dt_s = period_us * 1e-6
        d.t += d.dt * expirations
        d.rx.fill(False)
        d._rx_count = 0
        for bus, cob, data in frames:
            d._on_frame(can.Message(arbitration_id=cob, data=data, is_extended_id=False), self.tables[bus])
        complete = d._rx_count >= d.n
        if not complete:
            d.late_tpdo += 1
        np.add(d.stale, 1, out=d.stale)
        np.copyto(d.stale, 0, where=d.rx)
        out: dict[str, Any] = {"computed": False}
        if not self.primed:
            if not complete:
                return out
            d.vel.reset(d.counts)
            self.primed = True
        cfg = d.cfg
        d._feedback_watch(cfg.loop.stale_cycles_hold, cfg.loop.stale_cycles_disable)
        d.cycle_compute()
        d._write()
        d.cycles += 1
        d._fill_row(self.row, period_us, 0.0)
        await asyncio.sleep(0)  # a drive-mode switch asked for in this cycle completes before the next
        await asyncio.sleep(0)
        cols = d._cols
        out.update(computed=True, frames=list(self.sent), mode=int(d.mode), drive_mode=int(d.drive_mode),
                   telemetry={k: np.atleast_1d(self.row[cols[k]]).copy() for k in self.fields},
                   faults=len(d.faults))
        return out


__all__ = ["DaemonAdapter", "MODE_CSP", "MODE_CST"]
