"""Teaching: while the operator guides the arm in drag, positions at the record rate, marked waypoints and the raw
MCAP window; ``stop`` writes the program (in the planner process). docs/TEACH.md."""

from __future__ import annotations

import asyncio
import math
from typing import TYPE_CHECKING, Any

from dragd.control.modes import MODE_NAMES, Mode
from dragd.teach.program import ProgramError, check_name, resolve_program
from dragd.teach.recorder import TeachRecorder

if TYPE_CHECKING:
    from dragd.daemon.core import Daemon


class Teaching:
    def __init__(self, daemon: Daemon) -> None:
        self.d = daemon
        self.recorder: TeachRecorder | None = None

    def add(self) -> None:
        """The cycle's log step: the present pose, at the recorder's rate."""
        if self.recorder is not None:
            self.recorder.add(self.d.cycle.t, self.d.cycle.est.q_rad)

    async def start(self, name: str, rate_Hz: float | None = None, overwrite: bool = False,
                    lease: int = 0) -> dict[str, Any]:
        """Start teaching: the raw MCAP window, positions at ``rate_Hz`` and marks; the arm goes to drag where drag is
        permitted now (``lease``: the drag lease the client holds; else the enabling switch's press starts it)."""
        d, c, motions = self.d, self.d.controller, self.d.motions
        try:
            path = resolve_program(name, d.cfg.program_dir)
            check_name(path.stem)
            path = d.paths.check("teach start", path)
        except ProgramError as exc:
            raise ValueError(f"teach start: {exc}") from None
        if self.recorder is not None:
            raise ValueError(f"teach start: already teaching '{self.recorder.name}'; 'dragd teach stop' first")
        if c.mode not in (Mode.HOLD, Mode.DRAG) or c.track.active or motions.planning:
            raise ValueError(f"teach start: expected the arm enabled in hold or drag, it is {MODE_NAMES[c.mode]}"
                             + (" (a motion is running)" if c.track.active or motions.planning else ""))
        if d.recorder.recording is not None:
            raise ValueError(f"teach start: a record window is open ({d.recorder.recording_path}); 'record stop' first")
        rc = d.cfg.replay
        rate = rc.record_rate_Hz if rate_Hz is None else float(rate_Hz)
        if not 0.0 < rate <= d.cfg.loop.rate_Hz:
            raise ValueError(f"teach start: rate: expected (0, {d.cfg.loop.rate_Hz:.0f}] Hz, got {rate}")
        if path.suffix not in (".yaml", ".yml"):
            path = path.with_suffix(".yaml")
        mcap = path.with_suffix(".mcap")
        exists = [str(p) for p in (path, mcap) if p.exists()]
        if exists and not overwrite:
            raise ValueError(f"teach start: {' and '.join(exists)} exist(s); choose another name or overwrite")
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            for p in (path, mcap):
                if overwrite and p.exists():
                    p.unlink()
        except OSError as exc:
            raise ValueError(f"teach start: cannot write programs to {path.parent}: {exc.strerror} "
                             "(replay.program_dir, or give a path)") from None
        await d.recorder.start_recording(str(mcap), label=f"teach {path.stem}")
        self.recorder = TeachRecorder(path.stem, path, mcap, d.cfg.joint_names, rate, d.cycle.dt, rc.max_record_s,
                                      d.cycle.t)
        # the recording is the autosave: this event says how to rebuild the program if the session is cut short
        # (dragd teach recover)
        assert d.recorder.recording is not None  # (opened just above)
        d.recorder.recording.event("teach_start", stamp_ns=d.recorder.log_time_ns(), session=self.recorder.autosave_info(
            str(d.cfg.robot.urdf), d.cfg.replay.frame, d.cfg.source))
        motions.planner.warm()
        if c.mode == Mode.HOLD and not c.feedback_hold:
            try:
                await motions.wait_cst("teach start")
                if c.drag_refusal() is None:
                    c.request(Mode.DRAG, d.cycle.est.q_rad, lease=lease)
            except ValueError:
                pass  # the drives are still in CSP after a motion, or drag needs a lease: teaching starts in hold
        return {**self.recorder.status(), "mode": MODE_NAMES[c.mode]}

    def mark(self, name: str | None = None) -> dict[str, Any]:
        """Mark the present pose (absolute encoders) as the next waypoint."""
        d = self.d
        if self.recorder is None:
            raise ValueError("teach mark: not teaching; 'dragd teach start NAME' first")
        if name is not None:
            try:
                check_name(name)
            except ProgramError as exc:
                raise ValueError(f"teach mark: {exc}".replace("program name", "waypoint name")) from None
        m = self.recorder.mark(d.cycle.t, d.cycle.est.q_rad, name)
        ev = {"waypoint": m["name"], "t_s": m["t_s"], "q_rad": m["q_rad"]}
        if d.recorder.recording is not None:
            d.recorder.recording.event("mark", stamp_ns=d.recorder.log_time_ns(), **ev)
        d.recorder.event("mark", program=self.recorder.name, **ev)
        return {"program": self.recorder.name, "index": len(self.recorder.marks), **m,
                "q_deg": [round(math.degrees(x), 4) for x in m["q_rad"]]}

    async def stop(self) -> dict[str, Any]:
        """Stop teaching: close the MCAP, write the program (in the planner process)."""
        d = self.d
        if self.recorder is None:
            raise ValueError("teach stop: not teaching")
        rec, self.recorder = self.recorder, None
        snap = rec.snapshot()
        stats = await d.recorder.stop_recording() if d.recorder.recording is not None else {}
        args = (snap, str(d.cfg.robot.urdf), d.cfg.replay.frame, d.cfg.source)
        try:
            result = await d.motions.planner.call("write_program", *args)
        except RuntimeError as exc:  # the worker died: write it here rather than lose what was taught
            from dragd.teach.recorder import write_program

            d.log(f"teach: planner worker failed ({exc}); writing the program in the daemon")
            result = await asyncio.get_running_loop().run_in_executor(None, write_program, *args)
        return {**result, "mcap": stats.get("path"), "mcap_rows": stats.get("written")}

    async def list(self) -> dict[str, Any]:
        d = self.d
        return {"program_dir": str(d.cfg.program_dir),
                "programs": await d.motions.planner.call("list_programs", str(d.cfg.program_dir))}
