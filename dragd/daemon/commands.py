"""The control socket's commands: one table, one function per command with its fields as keyword arguments.

Unknown or missing fields are refused by the table (dragd/server.py); a handler's ValueError (bad value,
wrong state), DriveError, OSError or RuntimeError becomes ``{"ok": false, "error": ...}``. Every command records
the controller's events before it answers (a fault or mode change it caused is in the next ``status``).
"""

from __future__ import annotations

import functools
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from dragd.control.modes import MODE_NAMES, Mode
from dragd.hardware.cia402 import MODE_CST
from dragd.hardware.master import DriveError
from dragd.protocol import ControlError
from dragd.server import CommandTable

HOLD_WAIT_S = 3.0  # mode drag --accept waits this long beyond the settle time for the arm to rest in HOLD

if TYPE_CHECKING:
    from dragd.daemon.core import Daemon

Handler = Callable[..., Awaitable[dict[str, Any]]]


def command_table(d: Daemon) -> CommandTable:
    table = CommandTable()
    c, motions, teaching, recorder = d.controller, d.motions, d.teaching, d.recorder

    def command(name: str) -> Callable[[Handler], Handler]:
        def register(fn: Handler) -> Handler:
            @functools.wraps(fn)
            async def run(**kw: Any) -> dict[str, Any]:
                try:
                    return await fn(**kw)
                except (ValueError, DriveError, OSError, RuntimeError) as exc:
                    raise ControlError(str(exc)) from None
                finally:
                    d.record_events()

            table.add(name, run)
            return fn

        return register

    @command("status")
    async def status() -> dict[str, Any]:
        return d.status()

    @command("missed_ticks")
    async def missed_ticks(since: int = 0) -> dict[str, Any]:
        if since < 0:  # (the table refuses anything but an integer)
            raise ValueError(f"since: expected an episode number >= 0, got {since!r}")
        episodes, lost = d.cycle.missed_since(since)
        return {"missed_episodes": d.cycle.missed_episodes, "episodes": episodes, "lost": lost}

    @command("start")
    async def start() -> dict[str, Any]:
        d.start()
        ok = await d.wait_for(lambda: c.mode == Mode.FAULT or d.supervisor.all_enabled,
                              d.cfg.master.enable_timeout_s + 0.5)
        if c.mode == Mode.FAULT or not ok:
            raise ValueError("enable failed: " + (d.faults[-1]["text"] if d.faults else "timeout"))
        if motions.drive_mode != MODE_CST and not c.track.active and not motions.switch_pending:
            await motions.switch_drive_mode(MODE_CST)  # e.g. a fault during a motion left them in CSP
        return {"mode": MODE_NAMES[c.mode]}

    @command("stop")
    async def stop() -> dict[str, Any]:
        d.stop()
        await d.wait_for(lambda: c.mode in (Mode.IDLE, Mode.FAULT), 5.0)
        return {"mode": MODE_NAMES[c.mode]}

    @command("mode")
    async def mode(mode: str, accept: bool = False, lease: int | None = None) -> dict[str, Any]:
        if mode == "drag" and (why := c.drag_refusal()) is not None:
            raise ValueError(f"mode drag: refused: {why}")  # (at once: no wait for the drives or the hold current)
        if mode in ("hold", "drag") and not c.track.active and c.mode not in (Mode.IDLE, Mode.FAULT):
            await motions.wait_cst(f"mode {mode}")  # after a motion the drives return to CST first (bumpless)
        if mode == "drag" and accept:
            await _hold_measured()
        check = d.set_mode(str(mode), accept=bool(accept), lease=int(lease or 0))
        return {"mode": MODE_NAMES[c.mode], **({"gravity_check": check} if check else {}),
                **({"lease": c.drag_lease} if mode == "drag" and c.drag_lease else {})}

    @command("lease")
    async def lease(action: str, lease: int | None = None, holder: str = "client",
                    period_s: float | None = None, paced: bool = False) -> dict[str, Any]:
        """The drag lease (docs/HAND.md): ``open`` (answers its number and period), ``renew`` (within the period;
        ``paced``: the answer comes a third of the period later on the daemon's clock, when the next renewal is
        due), ``close`` (drag bound to it ends into HOLD), ``status``."""
        if action == "renew" and paced:
            return await d.guiding.renew_paced(lease)
        return d.guiding.lease(str(action), lease, str(holder), period_s)

    async def _hold_measured() -> None:
        """``mode drag --accept`` right after ``start`` or ``mode hold``: wait (up to the settle time + 3 s) until the
        arm has rested in HOLD long enough for its hold current to be measured; an arm that keeps moving is refused
        by the check itself."""
        g = d.cfg.safety.guard
        await d.wait_for(lambda: not (g.check and c.mode == Mode.HOLD and c.hold_rest_s < g.check_settle_s),
                         g.check_settle_s + HOLD_WAIT_S)

    @command("track")
    async def track(file: str | None = None, t_s: list[float] | None = None, q_rad: list[list[float]] | None = None,
                    label: str = "track") -> dict[str, Any]:
        return await motions.track_request(str(label), file, t_s, q_rad)

    @command("stream_open")
    async def stream_open(label: str = "stream") -> dict[str, Any]:
        return await d.streams.open(str(label))

    @command("stream")
    async def stream(stream: int, t_s: float, q_rad: list[float]) -> dict[str, Any]:
        return d.streams.sample(stream, t_s, q_rad)

    @command("stream_close")
    async def stream_close(stream: int) -> dict[str, Any]:
        return d.streams.close(stream)

    @command("state")
    async def state() -> dict[str, Any]:
        return _state(d)

    @command("events")
    async def events(since: int = 0) -> dict[str, Any]:
        return _events(d, since)

    @command("robot")
    async def robot() -> dict[str, Any]:
        return _robot(d)

    @command("record")
    async def record(action: str, path: str | None = None, label: str = "") -> dict[str, Any]:
        if action == "start":
            if path is None:
                raise ValueError("record start: missing field 'path'")
            return {"recording": await recorder.start_recording(str(d.paths.check("record start", path)), str(label))}
        if action == "stop":
            return await recorder.stop_recording()
        raise ValueError(f"record: action: expected 'start' or 'stop', got {action!r}")

    @command("teach")
    async def teach(action: str, name: str | None = None, rate_Hz: float | None = None,
                    overwrite: bool = False, lease: int | None = None) -> dict[str, Any]:
        if action == "start":
            if name is None:
                raise ValueError("teach start: missing field 'name'")
            return await teaching.start(str(name), None if rate_Hz is None else float(rate_Hz), bool(overwrite),
                                        lease=int(lease or 0))
        if action == "mark":
            return teaching.mark(None if name is None else str(name))
        if action == "stop":
            return await teaching.stop()
        if action == "list":
            return await teaching.list()
        raise ValueError(f"teach: action: expected start, mark, stop or list, got {action!r}")

    @command("replay")
    async def replay(program: str, interp: str = "linear", speed: float = 1.0, cycles: int = 1,
                     source: str | None = None) -> dict[str, Any]:
        return await motions.replay_start(str(program), interp=str(interp), speed=float(speed), cycles=int(cycles),
                                          source=source)

    async def _motion_state(wait_until: Callable[[], bool] | None, extra_s: float) -> dict[str, Any]:
        if wait_until is not None:
            await d.wait_for(wait_until, c.track.rate_T + extra_s)
        state = c.track.state if c.track.active else MODE_NAMES[c.mode]
        return {"state": state, "mode": MODE_NAMES[c.mode], "replay": motions.replay_status()}

    @command("replay_pause")
    async def replay_pause(wait: bool = True) -> dict[str, Any]:
        motions.pause()
        return await _motion_state((lambda: c.track.state != "pausing") if wait else None, 0.5)

    @command("replay_resume")
    async def replay_resume(wait: bool = True) -> dict[str, Any]:
        motions.resume()
        return await _motion_state(None, 0.0)

    @command("replay_stop")
    async def replay_stop(wait: bool = True) -> dict[str, Any]:
        motions.stop()
        return await _motion_state((lambda: not c.track.active) if wait else None, 1.0)

    @command("replay_speed")
    async def replay_speed(speed: float) -> dict[str, Any]:
        return {"speed_override": motions.set_speed(float(speed)), "state": c.track.state}

    @command("payload")
    async def payload(action: str, mass_kg: float | None = None, com_m: list[float] | None = None, poses: int = 6,
                      apply: bool = False) -> dict[str, Any]:
        """The flange payload (docs/PAYLOAD.md): estimate from hold currents, set a known one, clear it, show it."""
        tools = d.payload
        if action == "estimate":
            return await tools.estimate(int(poses), bool(apply))
        if action == "set":
            if mass_kg is None:
                raise ValueError("payload set: missing field 'mass_kg'")
            return tools.apply(float(mass_kg), list(com_m) if com_m is not None else [0.0, 0.0, 0.0],
                               "dragd payload set")
        if action == "clear":
            return tools.apply(0.0, [0.0, 0.0, 0.0], "dragd payload clear")
        if action == "show":
            return {"mass_kg": d.model.payload_mass_kg, "com_m": d.model.payload_com_m.tolist(),
                    "params": str(tools.params_path()) if tools.params_path() else None}
        raise ValueError(f"payload: action: expected estimate, set, clear or show, got {action!r}")

    @command("check_model")
    async def check_model(step_rad: float = 0.25) -> dict[str, Any]:
        return await d.model_check.run(float(step_rad))

    @command("clock")
    async def clock(action: str = "status", seconds: float | None = None) -> dict[str, Any]:
        """The cycle's clock (dragd/clock.py): ``status``; on the lockstep clock also ``advance`` (let the arm run
        ``seconds`` of simulated time and answer when they have passed), ``run`` (time runs without grants, as fast
        as the daemon and the simulator can) and ``pause``."""
        from dragd.clock import LockstepClock

        clk = d.clock
        if action == "status":
            return {"clock": clk.status(), "cycles": d.cycle.cycles}
        if action not in ("advance", "run", "pause"):
            raise ValueError(f"clock: action: expected status, advance, run or pause, got {action!r}")
        if not isinstance(clk, LockstepClock):
            raise ValueError(f"clock {action}: this daemon runs on the wall clock; only a daemon started with "
                             "--lockstep (against 'dragd sim --lockstep') lets its time be granted")
        if action == "advance":
            if seconds is None or not isinstance(seconds, (int, float)) or not 0 <= seconds < 1e6:
                raise ValueError(f"clock advance: seconds: expected a number of seconds in [0, 1e6), got {seconds!r}")
            await clk.grant(float(seconds))
        else:
            clk.set_free_run(action == "run")
        return {"clock": clk.status(), "cycles": d.cycle.cycles}

    @command("shutdown")
    async def shutdown() -> dict[str, Any]:
        d.request_exit()
        return {}

    return table


def _state(d: Daemon) -> dict[str, Any]:
    """The ``state`` command: the cycle's time, mode and joints, the effort K_t·I, what changed since (counters)."""
    c, cy = d.controller, d.cycle
    est = cy.est
    return {"t_s": cy.t, "cycles": cy.cycles, "mode": MODE_NAMES[c.mode],
            # what the operator asked for (a feedback hold shows hold, then returns to it by itself)
            "requested_mode": MODE_NAMES[c.resume_mode if c.feedback_hold else c.mode],
            "drives_enabled": d.supervisor.all_enabled,
            "q_rad": est.q_rad.tolist(), "dq_rad_s": est.dq_rad_s.tolist(), "current_A": est.current_A.tolist(),
            # the joint torque the drives' measured current gives through the model's torque constants
            "effort_Nm": (est.current_A * c.kt).tolist(), "command_A": c.cmd_A.tolist(),
            "fault_count": d.fault_sink.fault_count, "event_seq": d.recorder.events.seq, "stream": d.streams.status()}


def _events(d: Daemon, since: int) -> dict[str, Any]:
    if since < 0:
        raise ValueError(f"since: expected an event number >= 0, got {since}")
    got, lost = d.recorder.events.since(since)
    return {"event_seq": d.recorder.events.seq, "events": got, "lost": lost}


def _robot(d: Daemon) -> dict[str, Any]:
    """The ``robot`` command: joint names (the URDF's), limits, torque constants, loop and stream settings, the URDF."""
    cfg, c = d.cfg, d.controller
    urdf = d.model.urdf_path
    text = Path(urdf).read_text(encoding="utf-8") if urdf is not None else None
    return {"joint_names": list(cfg.joint_names), "urdf_path": str(urdf) if urdf is not None else None, "urdf": text,
            "rate_Hz": cfg.loop.rate_Hz,
            "position_limits_rad": np.column_stack([c.safety.lim_lo_rad, c.safety.lim_hi_rad]).tolist(),
            "velocity_limits_rad_s": [j.velocity_limit_rad_s for j in cfg.joints],
            "current_limit_A": c.params.current_limit_A.tolist(), "kt_Nm_per_A": c.kt.tolist(),
            "stream": cfg.stream.model_dump(), "program_dir": str(cfg.program_dir)}
