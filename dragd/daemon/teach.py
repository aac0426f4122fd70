"""Teaching: while the operator guides the arm in drag, positions at the record rate, marked waypoints and the raw
MCAP window; ``stop`` writes the program (in the planner process). docs/TEACH.md."""

from __future__ import annotations

import asyncio
import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from dragd.control.modes import MODE_NAMES, Mode
from dragd.teach.program import ProgramError, check_name, resolve_program
from dragd.teach.recorder import TeachRecorder

if TYPE_CHECKING:
    from dragd.config import Config
    from dragd.control.controller import Controller, Event
    from dragd.daemon.cycle import Cycle
    from dragd.daemon.motion import Motions
    from dragd.daemon.paths import PathPolicy
    from dragd.daemon.recording import Recorder


class Teaching:
    """Teach sessions: the recording window, positions at the teach rate, marks, the program written at the end."""

    def __init__(self, cfg: Config, controller: Controller, cycle: Cycle, motions: Motions, paths: PathPolicy,
                 recorder: Recorder, log: Callable[[str], None]) -> None:
        """``motions``: a session starts only while no motion runs, waits for the drives' CST, and has the program
        written by the motions' planner process."""
        self.cfg, self.controller, self.cycle, self.motions = cfg, controller, cycle, motions
        self.paths, self.rec, self.log = paths, recorder, log
        self.recorder: TeachRecorder | None = None

    def replay_refusal(self) -> str | None:
        """What forbids a replay now: a teach session in progress."""
        if self.recorder is None:
            return None
        return f"teaching '{self.recorder.name}' is in progress; 'dragd teach stop' first"

    def on_fault(self, ev: Event) -> None:
        """A fault while teaching: the recording says so."""
        if self.recorder is not None:
            self.rec.event("teach_fault", program=self.recorder.name, text=ev.text)

    def add(self) -> None:
        """The cycle's log step: the present pose, at the recorder's rate."""
        if self.recorder is not None:
            self.recorder.add(self.cycle.t, self.cycle.est.q_rad)

    async def start(self, name: str, rate_Hz: float | None = None, overwrite: bool = False,
                    lease: int = 0) -> dict[str, Any]:
        """Start teaching: the raw MCAP window, positions at ``rate_Hz`` and marks; the arm goes to drag where drag is
        permitted now (``lease``: the drag lease the client holds; else the enabling switch's press starts it)."""
        c, motions = self.controller, self.motions
        try:
            path = resolve_program(name, self.cfg.program_dir)
            check_name(path.stem)
            path = self.paths.check("teach start", path)
        except ProgramError as exc:
            raise ValueError(f"teach start: {exc}") from None
        if self.recorder is not None:
            raise ValueError(f"teach start: already teaching '{self.recorder.name}'; 'dragd teach stop' first")
        if c.mode not in (Mode.HOLD, Mode.DRAG) or c.track.active or motions.planning:
            raise ValueError(f"teach start: expected the arm enabled in hold or drag, it is {MODE_NAMES[c.mode]}"
                             + (" (a motion is running)" if c.track.active or motions.planning else ""))
        if self.rec.recording is not None:
            raise ValueError(f"teach start: a record window is open ({self.rec.recording_path}); 'record stop' first")
        rc = self.cfg.replay
        rate = rc.record_rate_Hz if rate_Hz is None else float(rate_Hz)
        if not 0.0 < rate <= self.cfg.loop.rate_Hz:
            raise ValueError(f"teach start: rate: expected (0, {self.cfg.loop.rate_Hz:.0f}] Hz, got {rate}")
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
        await self.rec.start_recording(str(mcap), label=f"teach {path.stem}")
        self.recorder = TeachRecorder(path.stem, path, mcap, self.cfg.joint_names, rate, self.cycle.dt, rc.max_record_s,
                                      self.cycle.t)
        # the recording is the autosave: this event says how to rebuild the program if the session is cut short
        # (dragd teach recover)
        assert self.rec.recording is not None  # (opened just above)
        self.rec.recording.event("teach_start", stamp_ns=self.rec.log_time_ns(), session=self.recorder.autosave_info(
            str(self.cfg.robot.urdf), self.cfg.replay.frame, self.cfg.source))
        motions.planner.warm()
        if c.mode == Mode.HOLD and not c.feedback_hold:
            try:
                await motions.wait_cst("teach start")
                if c.drag_refusal() is None:
                    c.request(Mode.DRAG, self.cycle.est.q_rad, lease=lease)
            except ValueError:
                pass  # the drives are still in CSP after a motion, or drag needs a lease: teaching starts in hold
        return {**self.recorder.status(), "mode": MODE_NAMES[c.mode]}

    def mark(self, name: str | None = None) -> dict[str, Any]:
        """Mark the present pose (absolute encoders) as the next waypoint."""
        if self.recorder is None:
            raise ValueError("teach mark: not teaching; 'dragd teach start NAME' first")
        if name is not None:
            try:
                check_name(name)
            except ProgramError as exc:
                raise ValueError(f"teach mark: {exc}".replace("program name", "waypoint name")) from None
        m = self.recorder.mark(self.cycle.t, self.cycle.est.q_rad, name)
        ev = {"waypoint": m["name"], "t_s": m["t_s"], "q_rad": m["q_rad"]}
        if self.rec.recording is not None:
            self.rec.recording.event("mark", stamp_ns=self.rec.log_time_ns(), **ev)
        self.rec.event("mark", program=self.recorder.name, **ev)
        return {"program": self.recorder.name, "index": len(self.recorder.marks), **m,
                "q_deg": [round(math.degrees(x), 4) for x in m["q_rad"]]}

    async def stop(self) -> dict[str, Any]:
        """Stop teaching: close the MCAP, write the program (in the planner process)."""
        if self.recorder is None:
            raise ValueError("teach stop: not teaching")
        rec, self.recorder = self.recorder, None
        snap = rec.snapshot()
        stats = await self.rec.stop_recording() if self.rec.recording is not None else {}
        args = (snap, str(self.cfg.robot.urdf), self.cfg.replay.frame, self.cfg.source)
        try:
            result = await self.motions.planner.call("write_program", *args)
        except RuntimeError as exc:  # the worker died: write it here rather than lose what was taught
            from dragd.teach.recorder import write_program

            self.log(f"teach: planner worker failed ({exc}); writing the program in the daemon")
            result = await asyncio.get_running_loop().run_in_executor(None, write_program, *args)
        return {**result, "mcap": stats.get("path"), "mcap_rows": stats.get("written")}

    async def list(self) -> dict[str, Any]:
        return {"program_dir": str(self.cfg.program_dir),
                "programs": await self.motions.planner.call("list_programs", str(self.cfg.program_dir))}
