"""Motions in TRACK: identification tracks and replays of taught programs, and the drives' CST ↔ CSP switch.

A motion starts from hold: the drives switch to CSP (an SDO write of 6060h per drive, confirmed on 6061h, in the
master's worker thread), the controller enters TRACK along a trajectory table built off the loop; at its end the
arm holds where the path ended and the drives return to CST. Drives whose profile follows motions in CST (a drive
without a torque offset 60B2h: CSP would ignore dragd's feed-forward) stay in CST: dragd's position loop is theirs.
Planning a replay and the rigid-body prediction of a track run in the planner process (dragd/teach/worker.py):
seconds of Python there would hold the GIL here.
"""

from __future__ import annotations

import asyncio
import functools
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from dragd.control.modes import MODE_NAMES, Mode
from dragd.control.trajectory import Trajectory
from dragd.hardware.cia402 import MODE_CSP, MODE_CST
from dragd.hardware.master import DriveError
from dragd.realtime import demote_current_thread
from dragd.teach.program import ProgramError, resolve_program
from dragd.teach.request import INTERPS, SOURCES, ReplayRequest, limits_from_config

if TYPE_CHECKING:
    from dragd.clock import Clock
    from dragd.config import Config
    from dragd.control.controller import Controller, Event
    from dragd.daemon.cycle import Cycle
    from dragd.daemon.faults import FaultSink
    from dragd.daemon.paths import PathPolicy
    from dragd.daemon.recording import Recorder
    from dragd.hardware.io import BusIO
    from dragd.hardware.master import Master
    from dragd.hardware.scaling import Scaling
    from dragd.model import RobotModel

START_TOLERANCE_RAD = 0.02  # a track must start this close to where the arm is


class Planner:
    """The planner process (started on first use) and the normal-priority thread that talks to it."""

    def __init__(self, avoid_cpus: set[int], clock: Clock | None = None) -> None:
        self.avoid_cpus = avoid_cpus
        self.clock = clock
        self._helper: ThreadPoolExecutor | None = None
        self._worker: Any = None

    async def call(self, name: str, *args: Any, **kwargs: Any) -> Any:
        """``name(*args, **kwargs)`` in the planner process (on the lockstep clock its time stands still meanwhile)."""
        return await self._submit(True, name, *args, **kwargs)

    async def _submit(self, track: bool, name: str, *args: Any, **kwargs: Any) -> Any:
        if self._helper is None:
            from dragd.teach.worker import Worker

            self._helper = ThreadPoolExecutor(1, thread_name_prefix="dragd-planner", initializer=demote_current_thread,
                                              initargs=(self.avoid_cpus or None,))
            self._worker = Worker(self.avoid_cpus)
        call = functools.partial(self._worker.call, name, *args, **kwargs)
        loop = asyncio.get_running_loop()
        if track or self.clock is None:
            return await loop.run_in_executor(self._helper, call)
        with self.clock.untracked():
            fut = loop.run_in_executor(self._helper, call)
        return await fut

    def warm(self) -> None:
        # nothing waits for the warm-up: it does not hold the lockstep clock (a call after it waits in line)
        task = asyncio.get_running_loop().create_task(self._submit(False, "warm_up"))
        task.add_done_callback(lambda t: t.exception())  # a failure shows at the next real call

    def close(self) -> None:
        if self._worker is not None:
            self._worker.close()
        if self._helper is not None:
            self._helper.shutdown(wait=False)


class Motions:
    """Starting, steering and ending motions; the drives' operating mode (CST or CSP)."""

    def __init__(self, cfg: Config, controller: Controller, cycle: Cycle, io: BusIO, model: RobotModel,
                 scaling: Scaling, planner: Planner, paths: PathPolicy, recorder: Recorder, faults: FaultSink) -> None:
        """``planner``: the process that plans replays (and writes taught programs). ``master`` (the drives' SDO
        access, for the CST ↔ CSP switch) is set once the drives are booted; ``replay_refusal()`` names what
        forbids a replay now (teaching), None if nothing does."""
        self.cfg, self.controller, self.cycle, self.io, self.model = cfg, controller, cycle, io, model
        self.scaling, self.planner, self.paths, self.recorder, self.faults = scaling, planner, paths, recorder, faults
        self.clock = cycle.clock
        self.master: Master | None = None
        self.replay_refusal: Callable[[], str | None] = lambda: None
        self.drive_mode: int = MODE_CST
        self.switch_pending = False
        self.planning = False  # a replay is being planned (the arm held in CSP meanwhile)
        self.replay: dict[str, Any] | None = None  # the running (or last) replay: program, options, outcome
        self._cst_task: asyncio.Task[None] | None = None

    # ------------------------------------------------------------------------------------------ drive mode

    @property
    def cst_joints(self) -> np.ndarray:
        """Joints whose drives follow motions in CST (their profile's motion_mode): dragd's position loop, no switch."""
        return self.controller.track.cst

    def untargeted_buses(self) -> list[str]:
        """Buses without position targets (layout 'compact', or position_targets false) that carry a joint whose drive
        follows motions in CSP."""
        csp_buses = {j.bus for j, cst in zip(self.cfg.joints, self.cst_joints, strict=True) if not cst}
        return [b for b in self.io.compact_buses if b in csp_buses]

    async def switch_drive_mode(self, mode: int) -> None:
        """6060h on every drive that follows motions in CSP (confirmed on 6061h), in the master's SDO worker; the
        drives that follow them in CST stay in CST (with none in CSP the drive mode stays CST)."""
        master = self.master
        assert master is not None
        self.switch_pending = True
        try:
            switched = False
            for rt in master.runtimes.values():
                for node_id, info in rt.nodes.items():
                    if info.profile.motion_mode == "csp":
                        await master.run_sdo(master.set_mode, rt, node_id, mode)
                        switched = True
            self._set_drive_mode(mode if switched else MODE_CST)
        finally:
            self.switch_pending = False

    def _set_drive_mode(self, mode: int) -> None:
        self.drive_mode = mode
        self.controller.drive_csp = mode == MODE_CSP

    def return_to_cst(self) -> None:
        """After a motion: the drives back to CST (a task; the arm holds meanwhile)."""
        self._cst_task = asyncio.get_running_loop().create_task(self.switch_drive_mode(MODE_CST))

    async def settle(self) -> None:
        """Let a pending return of the drives to CST finish before switching them again."""
        task = self._cst_task
        if task is not None and not task.done():
            try:
                await task
            except DriveError:
                pass

    async def wait_cst(self, what: str) -> None:
        """A law in torque mode waits for the drives' return to CST after a motion (bumpless)."""
        if self.switch_pending or self.drive_mode != MODE_CST:
            await self.clock.wait_for(lambda: not self.switch_pending and self.drive_mode == MODE_CST, 2.0)
            if self.drive_mode != MODE_CST:
                raise ValueError(f"{what}: the drives did not return to CST after the motion")

    def check_csp(self, what: str) -> None:
        """Refuse a motion in CSP where a bus carries no position targets or a drive has no CSP (drag needs CST
        only: the boot does not require CSP)."""
        reason = self.master.csp_refusal() if self.master is not None else None
        if reason is None and (untargeted := self.untargeted_buses()):
            reason = f"bus(es) {', '.join(untargeted)} carry no position targets"
        if reason is not None:
            raise ValueError(f"{what}: the drives cannot follow position targets (CSP): {reason}; drag, hold and "
                             "idle work (docs/DRIVES.md)")

    # ------------------------------------------------------------------------------------------ tracks

    def validate(self, traj: Trajectory) -> None:
        """Refuse (ValueError, before any motion) a trajectory beyond the position limits, faster or accelerating
        harder than allowed (a step target would drive full current), or outside the drives' 32-bit position
        encoding. The current a motion needs is checked against the limits by ``check_current``."""
        c = self.controller
        table = np.asarray(traj.table)
        names = self.cfg.joint_names
        lo, hi = c.safety.lim_lo_rad, c.safety.lim_hi_rad
        for j in range(c.n):
            qj = table[:, j]
            if qj.min() < lo[j] or qj.max() > hi[j]:
                k = int(np.argmax((qj < lo[j]) | (qj > hi[j])))
                raise ValueError(f"track: {names[j]} leaves its position limits [{lo[j]:+.3f}, {hi[j]:+.3f}] rad at "
                                 f"t = {k * traj.dt_s:.3f} s ({qj[k]:+.4f} rad)")
        vmax = self.cfg.safety.encoder_plausible_speed_rad_s
        if table.shape[0] > 1:
            v = np.abs(np.diff(table, axis=0)) / traj.dt_s
            j = int(np.argmax(v.max(axis=0)))
            if v[:, j].max() > vmax:
                k = int(np.argmax(v[:, j]))
                raise ValueError(f"track: {names[j]} would move at {v[k, j]:.1f} rad/s at t = {k * traj.dt_s:.3f} s "
                                 f"(a step in the target?), beyond safety.encoder_plausible_speed_rad_s {vmax:g}")
        amax = self.cfg.safety.track_acceleration_limit_rad_s2
        if table.shape[0] > 2:
            a = np.abs(np.diff(table, n=2, axis=0)) / traj.dt_s ** 2
            j = int(np.argmax(a.max(axis=0)))
            if a[:, j].max() > amax:
                k = int(np.argmax(a[:, j])) + 1
                raise ValueError(f"track: {names[j]} would accelerate at {a[k - 1, j]:.1f} rad/s² at t = "
                                 f"{k * traj.dt_s:.3f} s, beyond safety.track_acceleration_limit_rad_s2 {amax:g}")
        sc = self.scaling
        counts = (table * sc.counts_per_rev / (2 * np.pi)) * sc.direction + sc.offset_counts
        if np.abs(counts).max() >= 2 ** 31:
            j = int(np.argmax(np.abs(counts).max(axis=0)))
            raise ValueError(f"track: {names[j]}'s target is beyond the drives' 32-bit position encoding")

    def check_current(self, traj: Trajectory, peak_Nm: np.ndarray, peak_row: np.ndarray) -> None:
        """Refuse a motion whose rigid-body effort (the URDF's M q̈ + C q̇ + G, friction aside) needs more current
        than a joint's ``current_limit_A``: the drives would clamp it and the arm leave the path."""
        c, names = self.controller, self.cfg.joint_names
        need = np.abs(np.asarray(peak_Nm, dtype=float)) / c.kt
        over = need - c.params.current_limit_A
        j = int(np.argmax(over))
        if over[j] > 0:
            raise ValueError(f"track: {names[j]} would need {need[j]:.2f} A at "
                             f"t = {int(peak_row[j]) * traj.dt_s:.3f} s "
                             f"(rigid-body effort {float(peak_Nm[j]):.1f} N·m), beyond its current_limit_A "
                             f"{c.params.current_limit_A[j]:.2f} A: slow the motion down")

    async def track(self, traj: Trajectory, *, rate: float = 1.0, cycles: int = 1) -> None:
        """Switch the drives to CSP and follow ``traj`` (identification runs and replay).

        ``rate`` is the speed override (the trajectory clock's rate), ``cycles`` the repetitions of its body
        (rows ``body_row`` to the end; 0: until stopped).
        """
        c, q = self.controller, self.cycle.est.q_rad
        if c.mode not in (Mode.HOLD, Mode.DRAG):
            raise ValueError(f"track: expected the arm enabled in hold or drag, it is {MODE_NAMES[c.mode]}")
        if c.track.active:
            raise ValueError("track: a motion is running; stop it first")
        if traj.table.shape[1] != c.n:
            raise ValueError(f"track: expected {c.n} joints per sample, got {traj.table.shape[1]}")
        if not 0.0 < rate <= 1.0:
            raise ValueError(f"track: speed: expected a fraction in (0, 1], got {rate}")
        self.validate(traj)
        self.check_csp("track")
        c.take_over_feedback_hold("track")
        start_err = np.abs(traj.start_q - q)
        if np.any(start_err > START_TOLERANCE_RAD):
            raise ValueError(f"track: the trajectory starts {np.degrees(start_err.max()):.2f}° from the current pose "
                             f"(max {np.degrees(START_TOLERANCE_RAD):.1f}°); move there first")
        if c.mode != Mode.HOLD:
            c.q_hold[:] = q
        c.set_mode(Mode.HOLD)
        await self.settle()
        if self.drive_mode != MODE_CSP:
            await self.switch_drive_mode(MODE_CSP)
        if c.mode != Mode.HOLD:  # a fault or stop while the drives switched
            raise ValueError(f"track: the arm left hold while the drives switched to CSP ({MODE_NAMES[c.mode]})")
        c.begin_track(traj, self.cycle.est.q_rad, rate, cycles)

    async def track_request(self, label: str, file: str | None, t_s: list[float] | None,
                            q_rad: list[list[float]] | None) -> dict[str, Any]:
        """The ``track`` command: a trajectory file or samples, built off the loop, then followed."""
        self.check_csp("track")
        dt = self.cycle.dt
        if file is not None:
            traj = await self._trajectory(dt, label, file=str(self.paths.check("track", file)))
        elif t_s is not None and q_rad is not None:
            traj = await self._trajectory(dt, label, t_s=t_s, q_rad=q_rad)
        else:
            raise ValueError("track: expected 'file' or both 't_s' and 'q_rad'")
        # the residual monitor's rigid-body effort of the motion (in the planner process: seconds of Pinocchio
        # calls for a long run would hold the GIL against the cycle)
        try:
            traj.pred_table, peak_Nm, peak_row = await self.planner.call(
                "rigid_body_effort", str(self.model.urdf_path), tuple(self.cfg.robot.gravity_m_s2), traj.table, dt)
        except RuntimeError as exc:
            raise ValueError(f"track: the motion's effort could not be computed ({exc}); not started (its current "
                             "cannot be checked against the drives' limits)") from None
        self.check_current(traj, peak_Nm, peak_row)
        await self.track(traj)
        return {"mode": MODE_NAMES[self.controller.mode], "duration_s": traj.duration_s}

    async def _trajectory(self, dt: float, label: str, **source: Any) -> Trajectory:
        """The trajectory built in the planner process; its errors (a bad file or samples) as ValueError."""
        try:
            traj = await self.planner.call("trajectory", dt, label, **source)
        except RuntimeError as exc:  # the worker died (a bad file or samples come back as ValueError)
            raise ValueError(f"track: the trajectory could not be built ({exc})") from None
        if not isinstance(traj, Trajectory):
            raise ValueError(f"track: the planner returned {type(traj).__name__}, not a trajectory")
        return traj

    def _running(self, what: str) -> Any:
        c = self.controller
        if not c.track.active or c.mode != Mode.TRACK:
            raise ValueError(f"{what}: no motion is running")
        return c.track

    def pause(self) -> str:
        return str(self._running("pause").pause(self.controller.t))

    def resume(self) -> str:
        return str(self._running("resume").resume(self.controller.t))

    def stop(self) -> str:
        return str(self._running("stop").stop(self.controller.t))

    def set_speed(self, speed: float) -> float:
        if not 0.0 < speed <= 1.0:
            raise ValueError(f"speed: expected a fraction in (0, 1], got {speed}")
        c = self.controller
        c.track.set_override(speed, c.t)
        return float(c.track.override)

    # ------------------------------------------------------------------------------------------ replays

    async def replay_start(self, program: str, interp: str = "linear", speed: float = 1.0, cycles: int = 1,
                           source: str | None = None) -> dict[str, Any]:
        """Plan (in the planner process, from the held pose) and run a taught program in CSP."""
        c = self.controller
        why = self.replay_refusal()
        if why is not None:
            raise ValueError(f"replay: {why}")
        self.check_csp("replay")
        if c.mode not in (Mode.HOLD, Mode.DRAG):
            raise ValueError(f"replay: expected the arm enabled in hold or drag, it is {MODE_NAMES[c.mode]}")
        if c.track.active or self.planning:
            raise ValueError("replay: a motion is running (or being planned); 'dragd replay stop' first")
        if interp not in INTERPS:
            raise ValueError(f"replay: interp: expected one of {', '.join(INTERPS)}, got '{interp}'")
        if source is not None and source not in SOURCES:
            raise ValueError(f"replay: source: expected one of {', '.join(SOURCES)}, got '{source}'")
        if not 0.0 < speed <= 1.0:
            raise ValueError(f"replay: speed: expected a fraction in (0, 1], got {speed}")
        if cycles < 0:
            raise ValueError(f"replay: cycles: expected 0 (until stopped) or more, got {cycles}")
        c.take_over_feedback_hold("replay")
        try:
            path = resolve_program(program, self.cfg.program_dir)
        except ProgramError as exc:
            raise ValueError(f"replay: {exc}") from None
        path = self.paths.check("replay", path)
        if not path.is_file():
            raise ValueError(f"replay: program {path} not found")
        self.planning = True
        try:
            return await self._replay_start(path, interp, speed, cycles, source)
        finally:
            self.planning = False

    async def _replay_start(self, path: Path, interp: str, speed: float, cycles: int,
                            source: str | None) -> dict[str, Any]:
        c = self.controller
        was = c.mode
        # hold where the arm is (not where an older hold wanted it), stiffly: the drives' own position loops (CSP)
        # keep the pose while the plan is made, and the plan starts there
        c.q_hold[:] = self.cycle.est.q_rad
        c.set_mode(Mode.HOLD)
        try:
            await self.settle()
            await self.switch_drive_mode(MODE_CSP)
        except DriveError:
            self.faults.fault(None, "replay: the drives did not switch to CSP")
            raise
        if c.mode != Mode.HOLD:
            raise ValueError(f"replay: the arm left hold ({MODE_NAMES[c.mode]})")
        rc = self.cfg.replay
        req = ReplayRequest(program=str(path), q_start=c.q_hold.tolist(), dt=self.cycle.dt,
                            urdf=str(self.model.urdf_path),
                            gravity_m_s2=self.cfg.robot.gravity_m_s2,
                            limits=limits_from_config(self.cfg, self.model.model).as_dict(), interp=interp,
                            source=source, frame=rc.frame, move_to_start_speed=rc.move_to_start_speed,
                            settle_s=rc.settle_s, keyframe_tolerance_rad=rc.keyframe_tolerance_rad,
                            feedforward=rc.inertia_feedforward)
        try:
            res = await self.planner.call("plan_replay", req)
            summary = res["summary"]
            traj = Trajectory.from_table(res["q"], self.cycle.dt, f"replay {path.stem}", dq=res["dq"],
                                         ff_Nm=res["ff_Nm"], body_row=res["body_row"], marks=res["marks"],
                                         info=summary)
            replay = {"program": str(path), "name": path.stem, "interp": interp, "source": summary.get("source"),
                      "speed": speed, "cycles": cycles, "started_t_s": round(c.t, 4), "outcome": None,
                      "marks": [{k: v for k, v in m.items() if k != "q_rad"} for m in res["marks"]],
                      "duration_s": summary["duration_s"], "cycle_s": summary["cycle_s"],
                      "move_to_start_s": summary["move_to_start_s"]}
            await self.track(traj, rate=speed, cycles=cycles)
            self.replay = replay  # (no await since TRACK began: the cycle cannot have ended it yet)
        except (ValueError, RuntimeError):
            if c.mode == Mode.HOLD and not c.track.active:
                await self.switch_drive_mode(MODE_CST)
                if was == Mode.DRAG and c.mode == Mode.HOLD:
                    c.set_mode(Mode.DRAG)  # back to the hand
            raise
        self.recorder.event("replay", program=str(path), interp=interp, speed=speed, cycles=cycles)
        return {"mode": MODE_NAMES[c.mode], "program": str(path), **summary}

    def on_end(self, ev: Event) -> None:
        """A motion ended (the controller's track_end event): the replay's outcome; the drives back to CST."""
        outcome, t_s, cycle = ev.text, ev.t_s, int((ev.fields or {}).get("cycle", 0))
        r = self.replay
        if r is not None and r.get("outcome") is None:
            r["outcome"] = outcome
            r["ended_t_s"] = round(t_s, 4)
            r["cycles_done"] = cycle + (1 if outcome == "done" else 0)
        self.return_to_cst()

    def on_fault(self, ev: Event) -> None:
        """A fault: the replay it ended (when the fault stopped a motion) has it as its outcome."""
        text, t_s, had_motion = ev.text, ev.t_s, bool((ev.fields or {}).get("motion"))
        r = self.replay
        if r is not None and r.get("outcome") is None and had_motion:
            r["outcome"] = f"fault: {text}"
            r["ended_t_s"] = round(t_s, 4)

    def replay_status(self) -> dict[str, Any] | None:
        r = self.replay
        if r is None:
            return None
        tr = self.controller.track
        traj = tr.trajectory
        active = traj is not None and traj.label == f"replay {r['name']}" and r["outcome"] is None
        out = {k: v for k, v in r.items() if k != "marks"}
        out["state"] = tr.state if active else (r["outcome"] or "ended")
        if active and traj is not None:
            tau = tr.tau
            out.update(t_s=round(tau, 4), cycle=tr.cycle + 1, rate=round(tr.rate, 4), speed_override=tr.override,
                       segment=next((s["label"] for s in traj.info.get("segments", [])
                                     if s["t0_s"] <= tau < s["t1_s"]), None),
                       next_waypoint=next((m["name"] for m in r["marks"] if m["t_s"] > tau), None))
        return out

    def status(self) -> dict[str, Any]:
        tr = self.controller.track
        return {"drive_mode": {int(MODE_CSP): "csp", int(MODE_CST): "cst"}.get(self.drive_mode, str(self.drive_mode)),
                "trajectory": (None if tr.trajectory is None else
                               {"label": tr.trajectory.label, "t_s": tr.tau, "duration_s": tr.trajectory.duration_s,
                                "state": tr.state, "rate": tr.rate, "cycle": tr.cycle + 1, "cycles": tr.cycles}),
                "replay": self.replay_status(), "speed_override": tr.override}
