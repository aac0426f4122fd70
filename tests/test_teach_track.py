"""The daemon's TRACK clock, monitors and teach recorder, cycle by cycle, without a bus or real time.

The daemon in this process (tests/inproc.py) runs its cycle against an ideal arm that is wherever the CSP target
of the previous cycle put it (plus what a test injects): deterministic checks of pause / resume / speed override /
controlled stop / cycles, the protective stops, the stall behaviour and the bumpless start, independent of the
machine's load. The rig tests (test_teach_daemon.py) run the same against the simulated robot.
"""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from dragd.config import load_config
from dragd.control.modes import Mode
from dragd.control.trajectory import Trajectory
from dragd.hardware.cia402 import MODE_CSP, MODE_CST
from dragd.teach.plan import plan_replay, request_from_config
from dragd.teach.program import Program, Waypoint, save_program

from conftest import DEFAULT_CONFIG
from inproc import InProcess

pytestmark = pytest.mark.unit

Q0 = np.array([0.0, -0.6, 1.2, -0.6, 1.5708, 0.0])
STEPS = [[0.0] * 6, [0.3, 0.15, -0.15, 0.2, 0.2, 0.3], [-0.1, 0.1, 0.1, -0.2, 0.2, -0.2]]


class Arm(InProcess):
    """The daemon and an ideal arm: each cycle the arm is at the previous cycle's CSP target (+ ``offset``)."""

    def __init__(self, cfg=None) -> None:
        super().__init__(cfg or load_config(DEFAULT_CONFIG))
        self.offset = np.zeros(self.d.n)
        self.extra_current_A = np.zeros(self.d.n)
        self.hold(Q0)

    def step(self, n: int = 1, ticks: int = 1) -> None:
        for _ in range(n):
            q = self.target_rad() + self.offset if self.m.drive_mode == MODE_CSP else self.c.q_hold + self.offset
            # the drive's current: what the daemon commands (+ an injected effort)
            self.feed(q, self.c.cmd_A + self.extra_current_A)
            self.cycle(ticks)

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
        c, tr = arm.c, arm.c.track
        await arm.m.track(traj, rate=0.5, cycles=2)
        assert c.mode == Mode.TRACK and arm.m.drive_mode == MODE_CSP and tr.rate == 0.5
        arm.step(200)
        assert tr.tau == pytest.approx(0.5 * 0.201, abs=2e-3)  # the clock runs at the override
        arm.m.set_speed(1.0)
        arm.until(lambda: tr.rate == 1.0)
        arm.until(lambda: tr.tau > traj.body_start_s + 0.8)
        # pause: decelerate along the path, then hold still in CSP
        refs = []
        arm.m.pause()
        for _ in range(3000):
            arm.step()
            refs.append(tr.q_ref.copy())
            if tr.state == "paused":
                break
        assert tr.state == "paused" and tr.rate == 0.0
        refs = np.array(refs)
        v = np.diff(refs, axis=0) / arm.cy.dt
        a = np.diff(v, axis=0) / arm.cy.dt
        assert np.abs(a).max() < 2.0 * 1.6  # within the acceleration budget (limit 2 rad/s², ramp ≤ half extra)
        tau = tr.tau
        held = tr.q_ref.copy()
        arm.step(300)
        assert tr.tau == tau and np.array_equal(tr.q_ref, held) and c.mode == Mode.TRACK
        # the reference stayed on the planned path: it is the table at the paused time
        assert np.abs(held - traj.table[int(round(tau / arm.cy.dt))]).max() < 1e-3
        assert arm.m.resume() == "running"
        arm.until(lambda: tr.tau > tau + 0.2)
        # two cycles of the body, then done: hold at the end (= p1), drives back to CST
        arm.until(lambda: tr.trajectory is None)
        assert tr.cycle == 1 and c.mode == Mode.HOLD
        assert np.abs(c.q_hold - traj.table[-1]).max() < 1e-9
        await arm.settle_tasks()  # the CST switch task
        assert arm.switches[-1] == MODE_CST

        # controlled stop: ramp down, hold at the point reached
        await arm.m.track(traj, rate=1.0, cycles=0)
        arm.until(lambda: tr.tau > traj.body_start_s + 0.5)
        arm.m.stop()
        prev = tr.q_ref.copy()
        steps = []
        while tr.trajectory is not None:
            arm.step()
            steps.append(np.abs(tr.q_ref - prev).max())
            prev = tr.q_ref.copy()
        assert steps[-2] < 1e-5 and max(steps) < 1.6 * arm.cy.dt  # no jump; slowed to rest
        assert c.mode == Mode.HOLD and np.abs(c.q_hold - prev).max() < 1e-9

    run(main())


def test_stall_waits_and_start_is_bumpless(tmp_path):
    traj = _plan(tmp_path, "linear", start=Q0 + 0.002)  # planned from a pose 0.11° off where the arm is

    async def main():
        arm = Arm()
        tr = arm.c.track
        await arm.m.track(traj)
        # the target starts exactly where the arm is, and reaches the plan by the end of the move to start
        assert np.abs(tr.q_ref - arm.cy.est.q_rad).max() < 1e-12
        arm.step()
        assert np.abs(tr.q_ref - Q0).max() < 2e-5
        arm.until(lambda: tr.tau >= traj.body_start_s)
        assert np.abs(tr.q_ref - traj.table[traj.body_row]).max() < 1e-6
        arm.until(lambda: tr.tau > traj.body_start_s + 0.3)
        tau = tr.tau
        arm.step(ticks=51)  # the loop stalled for 50 ms
        assert tr.tau == pytest.approx(tau + arm.cy.dt, abs=1e-9)  # the reference waits, no jump along the path
        arm.until(lambda: tr.trajectory is None)
        assert arm.m.replay is None  # (a bare track, not a replay)

    run(main())


@pytest.mark.parametrize("kind", ["tracking_error", "residual_current", "soft_limit"])
def test_monitors_stop_the_motion_and_hold_where_the_arm_is(tmp_path, kind):
    cfg = load_config(DEFAULT_CONFIG)
    traj = _plan(tmp_path, "linear")

    async def main():
        arm = Arm(cfg)
        c, tr = arm.c, arm.c.track
        await arm.m.track(traj)
        arm.until(lambda: tr.tau > traj.body_start_s + 0.3)
        assert arm.d.faults == []
        if kind == "tracking_error":
            arm.offset[2] = 0.04  # joint3 pushed 2.3° off (limit 2°)
        elif kind == "residual_current":
            arm.extra_current_A[1] = -3.0  # the shoulder's drive works 3 A harder than the model expects
        else:
            arm.c.track.lim.position_hi_rad[4] = arm.cy.est.q_rad[4] - 0.01  # joint5 beyond its limit
        k = arm.until(lambda: tr.trajectory is None, 500)
        assert k >= cfg.replay.monitor_cycles - 1  # debounced
        f = arm.d.faults[-1]
        assert f["kind"] == kind and f["reaction"] == "hold" and c.mode == Mode.HOLD
        assert f["joint"] == {"tracking_error": "joint3", "residual_current": "joint2", "soft_limit": "joint5"}[kind]
        assert np.abs(c.q_hold - arm.cy.est.q_rad).max() < 1e-3  # holds where the arm is, not where the path wanted it
        await arm.settle_tasks()
        assert arm.m.drive_mode == MODE_CST

    run(main())


def test_teach_recorder_rate_and_marks(tmp_path):
    from dragd.teach.program import load_program
    from dragd.teach.recorder import TeachRecorder, write_program

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


def test_start_during_a_motion_ends_it_and_motions_work_again(tmp_path):
    """`dragd start` while a replay runs holds where the arm is and ends the motion (it used to leave the
    trajectory set: every later motion refused with "a motion is running", `replay stop` with "no motion")."""
    traj = _plan(tmp_path, "linear")

    async def main():
        arm = Arm()
        c = arm.c
        await arm.m.track(traj, rate=1.0, cycles=0)
        arm.until(lambda: c.track.tau > traj.body_start_s + 0.2)
        arm.d.start()
        assert c.mode == Mode.HOLD and not c.track.active and arm.m.replay is None
        await arm.settle_tasks()
        assert arm.m.drive_mode == MODE_CST
        with pytest.raises(ValueError, match="no motion is running"):
            arm.m.stop()
        arm.step(300)
        q = arm.cy.est.q_rad.copy()
        again = Trajectory(np.array([0.0, 1.0]), np.stack([q, q + 0.01]), arm.cy.dt, "track")
        await arm.m.track(again)
        assert c.mode == Mode.TRACK

    run(main())
