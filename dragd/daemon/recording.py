"""The cycle's log step and the files it feeds: the telemetry MCAP (``--telemetry``) and record windows.

Every cycle one row (dragd/telemetry/schema.py ``cycle_layout``) goes into each open writer's ring; the writers
encode and write off the loop. A record window (``record start|stop``, identification runs, teach) is a second
writer for a time span.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from dragd.control.modes import Mode
from dragd.daemon.feed import EventLog
from dragd.telemetry.schema import cycle_layout

if TYPE_CHECKING:
    from dragd.config import Config
    from dragd.control.controller import Controller, Estimate
    from dragd.hardware.io import Feedback
    from dragd.telemetry.writer import TelemetryWriter


class Recorder:
    """The telemetry writer and the record window; ``log_row`` is the cycle's log step."""

    def __init__(self, cfg: Config, n: int, telemetry_path: str | None, rerun: bool) -> None:
        self.cfg = cfg
        self.layout = cycle_layout(n)
        self.telemetry_path = telemetry_path
        self.rerun = rerun
        self.telemetry: TelemetryWriter | None = None
        self.recording: TelemetryWriter | None = None
        self.recording_path: str | None = None
        self._writers: list[TelemetryWriter] = []
        cols: dict[str, Any] = {}
        k = 0
        for name, f in self.layout.items():
            width = f if isinstance(f, int) else f.width
            cols[name] = k if width == 1 else slice(k, k + width)
            k += width
        self.cols = cols
        self.width = k
        self._sources: tuple[Controller, Estimate, Feedback] | None = None
        # the rows' and events' log time: None, the writer's CLOCK_REALTIME; on the lockstep clock the clock's own
        self.stamp_ns: Callable[[], int | None] | None = None
        self.events = EventLog()  # every event, numbered, for clients (the `events` command; the ROS 2 bridge)

    def attach(self, controller: Controller, est: Estimate, feedback: Feedback) -> None:
        """The arrays a row is filled from."""
        self._sources = (controller, est, feedback)

    # ------------------------------------------------------------------------------------------ the log step

    def log_row(self, period_us: float, compute_us: float) -> None:
        stamp = self.stamp_ns
        for tw in self._writers:
            row = tw.begin()
            if row is not None:
                self.fill_row(row, period_us, compute_us)
                tw.commit(None if stamp is None else stamp())

    def rings_have_room(self) -> bool:
        """Every open writer's ring is less than half full (the lockstep clock waits for this: no row dropped)."""
        return all(tw.pending_rows() * 2 < tw.capacity for tw in self._writers)

    def fill_row(self, row: np.ndarray, period_us: float, compute_us: float) -> None:
        """Every field of the cycle's row (slots are reused: each is written every cycle)."""
        assert self._sources is not None
        c, est, fb = self._sources
        cols, out, mode = self.cols, c.law_out, c.mode
        drag = mode == Mode.DRAG
        row[cols["t_s"]] = c.t
        row[cols["mode"]] = int(mode)
        row[cols["q_rad"]] = est.q_rad
        row[cols["dq_rad_s"]] = est.dq_rad_s
        row[cols["current_measured_A"]] = est.current_A
        row[cols["current_command_A"]] = c.cmd_A
        if drag:
            row[cols["gravity_A"]] = out.gravity_A
        else:
            np.divide(est.tau_g_Nm, c.kt, out=row[cols["gravity_A"]])  # into the row: no temporary array
        row[cols["friction_A"]] = out.friction_A if drag else 0.0
        row[cols["startup_A"]] = out.startup_A if drag else 0.0
        row[cols["damping_A"]] = out.damping_A if drag else 0.0
        row[cols["back_emf_A"]] = out.back_emf_A if drag else 0.0
        row[cols["effects_A"]] = (out.effects_A if drag and c.params.effects is not None
                                  else 0.0)  # with the terms above (+ safety walls) the command before the clamp
        row[cols["statusword"]] = fb.statusword
        row[cols["rx"]] = fb.rx
        row[cols["period_us"]] = period_us
        row[cols["compute_us"]] = compute_us
        # the position reference (TRACK: the path; HOLD: the hold pose, whether the drives' CSP loop or the PD
        # of CST holds it; otherwise where the arm is)
        row[cols["q_ref_rad"]] = c.q_hold if mode == Mode.HOLD else c.ref_rad
        track = mode == Mode.TRACK
        row[cols["track_t_s"]] = c.track.tau if track else -1.0
        row[cols["residual_A"]] = c.track.residual_A if track else 0.0
        w = c.contact
        watch = w.watching if w is not None and w.det.armed else ""
        row[cols["contact_residual_A"]] = w.det.e if watch else 0.0  # type: ignore[union-attr]
        row[cols["contact_band_A"]] = w.det.band if watch and watch != "drag" else 0.0  # type: ignore[union-attr]
        row[cols["hand_force_N"]] = w.force_N if watch == "drag" and w.force_valid else 0.0  # type: ignore[union-attr]
        row[cols["grip_m"]] = w.grip_m if watch == "drag" and w.force_valid else 0.0  # type: ignore[union-attr]

    def log_time_ns(self) -> int | None:
        """An event's log time: None (the writer's CLOCK_REALTIME), or the lockstep clock's."""
        return None if self.stamp_ns is None else self.stamp_ns()

    def event(self, name: str, **fields: Any) -> None:
        """An event in the telemetry file (not in a record window) and in the clients' event log."""
        self.events.add(self._sources[0].t if self._sources is not None else 0.0, name, fields)
        if self.telemetry is not None:
            self.telemetry.event(name, stamp_ns=self.log_time_ns(), **fields)

    # ------------------------------------------------------------------------------------------ files

    def open_telemetry(self) -> None:
        if not self.telemetry_path:
            return
        from dragd.telemetry.writer import TelemetryWriter

        tc = self.cfg.telemetry
        foxglove = None
        if tc.foxglove:
            from dragd.robots import resolve_urdf
            from dragd.telemetry.foxglove import FoxgloveSpec

            kt = self._sources[0].kt.tolist() if self._sources is not None else None
            foxglove = FoxgloveSpec(self.cfg.joint_names, resolve_urdf(self.cfg.robot.urdf, self.cfg.base_dir),
                                    rate_Hz=tc.foxglove_rate_Hz, encoding=tc.foxglove_encoding, kt_Nm_per_A=kt)
        sinks = []
        if self.rerun:  # the live view (dragd/telemetry/sinks.py): 3D arm, currents and components, mode, faults
            from dragd.robots import resolve_urdf
            from dragd.telemetry.sinks import RerunSink

            sinks.append(RerunSink(joint_names=self.cfg.joint_names,
                                   urdf=resolve_urdf(self.cfg.robot.urdf, self.cfg.base_dir)))
        self.telemetry = TelemetryWriter(self.telemetry_path, self.layout, capacity=tc.capacity_rows,
                                         sinks=sinks, max_bytes=tc.max_file_MiB * 2**20,
                                         keep_rotated=tc.keep_rotated, avoid_cpus=set(self.cfg.loop.cpus or ()),
                                         foxglove=foxglove, cycle_decimation=tc.cycle_decimation,
                                         forward_interval_s=tc.forward_interval_s,
                                         process=not sinks,  # encoding in its own process (the live view: here)
                                         metadata={"config": self.cfg.source,
                                                   "cycle_decimation": str(tc.cycle_decimation)})
        self._writers = [w for w in (self.telemetry, self.recording) if w is not None]
        self.event("start", config=self.cfg.source, joints=self.cfg.joint_names)

    async def start_recording(self, path: str, label: str = "") -> str:
        """Record every cycle to a separate MCAP file until ``stop_recording`` (identification runs, teach)."""
        from dragd.telemetry.writer import TelemetryWriter

        if self.recording is not None:
            raise ValueError(f"record: already recording to {self.recording_path}; stop it first")
        loop = asyncio.get_running_loop()
        writer = await loop.run_in_executor(None, lambda: TelemetryWriter(
            path, self.layout, capacity=self.cfg.telemetry.capacity_rows, on_exists="error",
            metadata={"label": label, "config": self.cfg.source}, avoid_cpus=set(self.cfg.loop.cpus or ()),
            forward_interval_s=self.cfg.telemetry.forward_interval_s, process=True))
        self.recording, self.recording_path = writer, str(path)
        writer.event("record_start", stamp_ns=self.log_time_ns(), label=label, joints=self.cfg.joint_names)
        self._writers = [w for w in (self.telemetry, self.recording) if w is not None]
        return self.recording_path

    async def stop_recording(self) -> dict[str, Any]:
        if self.recording is None:
            raise ValueError("record: not recording")
        writer, path = self.recording, self.recording_path
        self.recording, self.recording_path = None, None
        self._writers = [w for w in (self.telemetry,) if w is not None]
        writer.event("record_stop", stamp_ns=self.log_time_ns())
        await writer.aclose()
        return {"path": path, **writer.stats()}

    async def close(self, cycles: int) -> None:
        if self.recording is not None:
            await self.stop_recording()
        if self.telemetry is not None:
            self.event("stop", cycles=cycles)
            await self.telemetry.aclose()
