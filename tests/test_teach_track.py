"""The daemon's TRACK clock, monitors and teach recorder, cycle by cycle, without a bus or real time.

A ``Daemon`` object (no I/O started) runs ``cycle_compute`` against an ideal arm that is wherever the CSP target
of the previous cycle put it (plus what a test injects): deterministic checks of pause / resume / speed override /
controlled stop / cycles, the protective stops, the stall behaviour and the bumpless start, independent of the
machine's load. The rig tests (test_teach_daemon.py) run the same against the simulated robot.
"""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest

from dragd.config import load_config
from dragd.daemon.core import MODE_CSP, MODE_CST, Daemon, Mode, Trajectory
from dragd.teach.plan import plan_replay, request_from_config
from dragd.teach.program import Program, Waypoint, save_program

from conftest import DEFAULT_CONFIG

Q0 = np.array([0.0, -0.6, 1.2, -0.6, 1.5708, 0.0])
STEPS = [[0.0] * 6, [0.3, 0.15, -0.15, 0.2, 0.2, 0.3], [-0.1, 0.1, 0.1, -0.2, 0.2, -0.2]]
ENABLED = 0x0027  # statusword: operation enabled


class Arm:
    """A daemon and an ideal arm: each cycle the arm is at the previous cycle's CSP target (+ ``offset``)."""

    def __init__(self, cfg=None) -> None:
        self.d = Daemon(cfg or load_config(DEFAULT_CONFIG), socket_path="/nonexistent/dragd.sock")
        d = self.d
        self.offset = np.zeros(d.n)
        self.extra_current_A = np.zeros(d.n)
        self.switches: list[int] = []

        async def switch(mode: int) -> None:
            self.switches.append(mode)
            d.drive_mode = mode

        d._switch_drive_mode = switch
        d.statusword[:] = ENABLED
        d.counts[:] = self.counts(Q0)
        d.rx[:] = True
        d.vel.reset(d.counts)
        d.mode = Mode.HOLD
        d.q_hold[:] = Q0
        self.step()

    def counts(self, q: np.ndarray) -> np.ndarray:
        d = self.d
        return np.rint(np.asarray(q) * d.cpr / (2 * math.pi) * d.direction).astype(np.int64) + d.offset_counts

    def step(self, n: int = 1, dt_extra: float = 0.0) -> None:
        d = self.d
        for _ in range(n):
            d.t += d.dt + dt_extra
            if d.drive_mode == MODE_CSP:
                q = (d.target_counts - d.offset_counts) * d.direction * 2 * math.pi / d.cpr + self.offset
                d.counts[:] = self.counts(q)
            # the drive's current: what the daemon commands (+ an injected effort)
            d.current_raw[:] = (d.cmd_A + self.extra_current_A) * d.direction * 1000.0 / d.rated_A
            d.cycle_compute()
            d.cycles += 1

    def until(self, cond, max_cycles: int = 60000) -> int:
        for k in range(max_cycles):
            if cond():
                return k
            self.step()
        raise AssertionError("condition not reached")


def _plan(tmp_path, interp="linear", start=Q0, steps=STEPS):
    wps, q = [], np.array(Q0)
    for s in steps:
        q = q + np.array(s)
        wps.append(q.copy())
    prog = Program(name="p", joints=[f"joint{i + 1}" for i in range(6)],
                   waypoints=[Waypoint(name=f"p{i + 1}", t_s=float(i), q_rad=w.tolist()) for i, w in enumerate(wps)])
    path = save_program(prog, tmp_path / "p.yaml")
    cfg = load_config(DEFAULT_CONFIG)
    res = plan_replay(request_from_config(cfg, path, start, interp=interp))
    return Trajectory.from_table(res["q"], 1e-3, "replay p", dq=res["dq"], ff_Nm=res["ff_Nm"], body_row=res["body_row"],
                                 marks=res["marks"], info=res["summary"])


def run(coro):
    return asyncio.run(coro)


def test_track_pause_resume_override_cycles_and_stop(tmp_path):
    traj = _plan(tmp_path, "spline")

    async def main():
        arm = Arm()
        d = arm.d
        await d.track(traj, rate=0.5, cycles=2)
        assert d.mode == Mode.TRACK and d.drive_mode == MODE_CSP and d.track_rate == 0.5
        arm.step(200)
        assert d.track_tau == pytest.approx(0.5 * 0.201, abs=2e-3)  # the clock runs at the override
        d.set_speed_override(1.0)
        arm.until(lambda: d.track_rate == 1.0)
        arm.until(lambda: d.track_tau > traj.body_start_s + 0.8)
        # pause: decelerate along the path, then hold still in CSP
        refs = []
        d.track_pause()
        for _ in range(3000):
            arm.step()
            refs.append(d.q_ref.copy())
            if d.track_state == "paused":
                break
        assert d.track_state == "paused" and d.track_rate == 0.0
        refs = np.array(refs)
        v = np.diff(refs, axis=0) / d.dt
        a = np.diff(v, axis=0) / d.dt
        assert np.abs(a).max() < 2.0 * 1.6  # within the acceleration budget (limit 2 rad/s², ramp ≤ half extra)
        tau = d.track_tau
        held = d.q_ref.copy()
        arm.step(300)
        assert d.track_tau == tau and np.array_equal(d.q_ref, held) and d.mode == Mode.TRACK
        # the reference stayed on the planned path: it is the table at the paused time
        assert np.abs(held - traj.table[int(round(tau / d.dt))]).max() < 1e-3
        assert d.track_resume() == "running"
        arm.until(lambda: d.track_tau > tau + 0.2)
        # two cycles of the body, then done: hold at the end (= p1), drives back to CST
        arm.until(lambda: d.trajectory is None)
        assert d.track_cycle == 1 and d.mode == Mode.HOLD
        assert np.abs(d.q_hold - traj.table[-1]).max() < 1e-9
        await asyncio.sleep(0)  # the CST switch task
        assert arm.switches[-1] == MODE_CST

        # controlled stop: ramp down, hold at the point reached
        await d.track(traj, rate=1.0, cycles=0)
        arm.until(lambda: d.track_tau > traj.body_start_s + 0.5)
        d.track_stop()
        prev = d.q_ref.copy()
        steps = []
        while d.trajectory is not None:
            arm.step()
            steps.append(np.abs(d.q_ref - prev).max())
            prev = d.q_ref.copy()
        assert steps[-2] < 1e-5 and max(steps) < 1.6 * d.dt  # no jump; slowed to rest
        assert d.mode == Mode.HOLD and np.abs(d.q_hold - prev).max() < 1e-9

    run(main())


def test_stall_waits_and_start_is_bumpless(tmp_path):
    traj = _plan(tmp_path, "linear", start=Q0 + 0.002)  # planned from a pose 0.11° off where the arm is

    async def main():
        arm = Arm()
        d = arm.d
        await d.track(traj)
        # the target starts exactly where the arm is, and reaches the plan by the end of the move to start
        assert np.abs(d.q_ref - d.q).max() < 1e-12
        arm.step()
        assert np.abs(d.q_ref - Q0).max() < 2e-5
        arm.until(lambda: d.track_tau >= traj.body_start_s)
        assert np.abs(d.q_ref - traj.table[traj.body_row]).max() < 1e-6
        arm.until(lambda: d.track_tau > traj.body_start_s + 0.3)
        tau = d.track_tau
        arm.step(dt_extra=0.05)  # the loop stalled for 50 ms
        assert d.track_tau == pytest.approx(tau + d.dt, abs=1e-9)  # the reference waits, no jump along the path
        arm.until(lambda: d.trajectory is None)
        assert d.replay is None  # (a bare track, not a replay)

    run(main())


@pytest.mark.parametrize("kind", ["tracking_error", "residual_current", "soft_limit"])
def test_monitors_stop_the_motion_and_hold_where_the_arm_is(tmp_path, kind):
    cfg = load_config(DEFAULT_CONFIG)
    traj = _plan(tmp_path, "linear")

    async def main():
        arm = Arm(cfg)
        d = arm.d
        await d.track(traj)
        arm.until(lambda: d.track_tau > traj.body_start_s + 0.3)
        assert d.faults == []
        if kind == "tracking_error":
            arm.offset[2] = 0.04  # joint3 pushed 2.3° off (limit 2°)
        elif kind == "residual_current":
            arm.extra_current_A[1] = -3.0  # the shoulder's drive works 3 A harder than the model expects
        else:
            d.lim_hi[4] = d.q[4] - 0.01  # joint5 beyond its limit
        k = arm.until(lambda: d.trajectory is None, 500)
        assert k >= cfg.replay.monitor_cycles - 1  # debounced
        f = d.faults[-1]
        assert f["kind"] == kind and f["reaction"] == "hold" and d.mode == Mode.HOLD
        assert f["joint"] == {"tracking_error": "joint3", "residual_current": "joint2", "soft_limit": "joint5"}[kind]
        assert np.abs(d.q_hold - d.q).max() < 1e-3  # holds where the arm is, not where the path wanted it
        await asyncio.sleep(0)
        assert d.drive_mode == MODE_CST

    run(main())


def test_teach_recorder_rate_and_marks(tmp_path):
    from dragd.teach.recorder import TeachRecorder, write_program
    from dragd.teach.program import load_program

    rec = TeachRecorder("t", tmp_path / "t.yaml", tmp_path / "t.mcap", [f"joint{i + 1}" for i in range(6)], 50.0,
                        1e-3, 10.0, t0=5.0)
    assert rec.every == 20 and rec.buf.shape == (502, 7)
    for k in range(2000):
        rec.add(5.0 + k * 1e-3, Q0 + k * 1e-5)
        if k == 700:
            rec.mark(5.0 + k * 1e-3, Q0 + k * 1e-5)
    assert rec.count == 100 and rec.dropped == 0
    with pytest.raises(ValueError, match="exists already"):
        rec.mark(7.0, Q0, "p1")
    out = write_program(rec.snapshot(), "seed_cobot", "tool0", "cfg.yaml")
    prog = load_program(out["program"])
    assert prog.waypoints[0].name == "p1" and prog.waypoints[0].t_s == pytest.approx(0.7)
    t, q = prog.path_arrays()
    assert len(t) == 100 and np.allclose(np.diff(t), 0.02) and prog.recording.mcap == "t.mcap"
    # capacity: beyond it samples are counted, not stored
    small = TeachRecorder("s", tmp_path / "s.yaml", None, ["joint1"], 1000.0, 1e-3, 0.01, t0=0.0)
    for k in range(100):
        small.add(k * 1e-3, np.zeros(1))
    assert small.count == small.buf.shape[0] and small.dropped == 100 - small.count
