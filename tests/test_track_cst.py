"""TRACK for joints whose drives follow motions in CST (drives.X.motion_mode: cst; docs/DRIVES.md): dragd's position
loop is their only one. The controller of config/default.yaml, cycle by cycle, against a rigid joint per axis
(inertia, gravity, friction the model does not know), the command applied one cycle late as on the bus.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from dragd.config import load_config
from dragd.control.controller import Controller, Estimate
from dragd.control.law import Workspace, friction_current
from dragd.control.modes import Mode
from dragd.control.track import CST_FADE_S
from dragd.control.trajectory import Trajectory
from dragd.model import RobotModel

from conftest import DEFAULT_CONFIG

pytestmark = pytest.mark.unit

DT = 1e-3
J_KGM2 = np.array([5.0, 5.0, 1.6, 0.2, 0.2, 0.2])  # link + reflected rotor inertia, about the seed cobot's
GRAVITY_NM = np.array([0.0, -60.0, -20.0, -2.0, -0.5, 0.0])
UNKNOWN_COULOMB_A = 0.5  # friction beyond the configuration's belief, per joint (what the loop's integral learns)


class Arm:
    """The controller and a rigid joint per axis in CST: I = command of the previous cycle."""

    def __init__(self, cst: bool = True) -> None:
        cfg = load_config(DEFAULT_CONFIG)
        self.c = Controller.from_config(cfg, RobotModel.from_config(cfg).position_limits_rad)
        n = self.n = self.c.n
        self.c.track.cst[:] = cst
        self.q, self.dq = np.zeros(n), np.zeros(n)
        self.applied_A = np.zeros(n)
        self.ext_Nm = np.zeros(n)  # an external torque (an obstacle)
        self.wall: tuple[int, float] | None = None  # (joint, position) the arm cannot pass
        self._ws, self._fr = Workspace(n), np.zeros(n)
        self.est = Estimate(self.q.copy(), self.dq.copy(), np.zeros(n), -GRAVITY_NM.copy(), np.zeros(n))
        self.c.start(self.q)
        self.run(0.5)

    def cycle(self) -> None:
        c, p = self.c, self.c.params
        friction_current(self.dq, p, self._fr, self._ws)  # the belief / friction_scale, + what it misses
        fr_Nm = (self._fr / p.friction_scale + UNKNOWN_COULOMB_A * np.sign(self.dq)) * p.kt_Nm_per_A
        tau = self.applied_A * p.kt_Nm_per_A + GRAVITY_NM - fr_Nm + self.ext_Nm
        self.dq += tau / J_KGM2 * DT
        self.q += self.dq * DT
        if self.wall is not None:
            j, qw = self.wall
            if self.q[j] > qw:
                self.q[j], self.dq[j] = qw, 0.0
        c.t += DT
        self.est.q_rad[:] = self.q
        self.est.dq_rad_s[:] = self.dq
        self.est.current_A[:] = self.applied_A  # CST: the drive's current is the command
        c.advance(self.est, 0)
        c.compute(self.est, np.ones(self.n))
        self.applied_A[:] = c.cmd_A

    def run(self, seconds: float, until=None) -> None:
        for _ in range(round(seconds / DT)):
            self.cycle()
            if until is not None and until():
                return

    def move(self, dq_rad: np.ndarray, duration_s: float, dwell_s: float = 0.0) -> Trajectory:
        """An identification-like track: a smooth move, then ``dwell_s`` at rest."""
        t = np.linspace(0.0, duration_s + dwell_s, 201 + round(dwell_s * 100))
        s = (1 - np.cos(np.pi * np.minimum(t, duration_s) / duration_s)) / 2
        traj = Trajectory(t, self.q + np.outer(s, dq_rad), DT, "identify")
        self.c.begin_track(traj, self.q, 1.0, 1)
        return traj


def test_cst_joints_follow_with_dragds_loop_and_the_residual_is_the_models():
    arm = Arm()
    c, tr = arm.c, arm.c.track
    q0 = arm.q.copy()
    step = np.array([0.2, 0.2, -0.2, 0.3, 0.3, 0.3])
    arm.move(step, 2.0)
    assert tr.loop_on and c.mode == Mode.TRACK
    worst_err, worst_res, pid_vs_res = np.zeros(6), np.zeros(6), []
    kt = c.params.kt_Nm_per_A
    while c.mode == Mode.TRACK:
        arm.cycle()
        worst_err = np.maximum(worst_err, np.abs(tr.error_rad))
        worst_res = np.maximum(worst_res, np.abs(tr.residual_A))
        # what the residual compares: the measured current with the model's feed-forward, not with the loop's output
        pid_vs_res.append(np.abs(arm.applied_A - tr.pred_A - tr.pid_Nm / kt).max())
    assert c.events[-1].kind == "track_end" and c.events[-1].text == "done", c.events[-1]
    # the loop keeps every joint well inside the tracking bound (2°) and the unknown friction inside the residual's
    # (measured: 0.40°; 0.95 A = the 0.5 A of unknown friction + the acceleration, which identification tracks do
    # not feed forward)
    assert np.degrees(worst_err).max() < 1.0, np.degrees(worst_err)
    assert worst_res.max() < 0.6 * 2.0, worst_res
    assert max(pid_vs_res[250:]) < 1e-9  # (after the mode blend) command = feed-forward + the loop, exactly
    arm.run(1.0)
    assert np.abs(arm.q - (q0 + step)).max() < math.radians(0.2)  # HOLD at the end of the path


def test_the_integral_learns_friction_while_moving_and_fades_at_rest():
    arm = Arm()
    tr = arm.c.track
    kt = arm.c.params.kt_Nm_per_A[1]
    arm.move(np.array([0.0, 0.4, 0.0, 0.0, 0.0, 0.0]), 2.0, dwell_s=1.0)
    arm.run(1.2)  # past mid-move (~0.3 rad/s): the unknown friction (0.5 A) is mostly in the integral
    learned = tr.int_Nm[1] / kt
    assert 0.25 < learned <= 1.2, learned  # (within cst_integral_limit_A)
    arm.run(1.0, until=lambda: abs(tr.dq_ref[1]) <= 0.005)
    at_rest = tr.int_Nm[1]
    arm.run(0.5)
    assert arm.c.mode == Mode.TRACK  # (dwelling at the end of the path)
    assert abs(tr.int_Nm[1]) <= abs(at_rest) * math.exp(-0.49 / CST_FADE_S), (tr.int_Nm[1], at_rest)


@pytest.mark.parametrize("kind", ["wall", "push"])
def test_an_obstacle_stops_a_cst_motion(kind):
    """A wall in the path (the arm stops dead) or a hand pushing against the motion: the monitors stop it and the
    arm holds where it is — the loop's integral never hides the obstacle from the residual."""
    arm = Arm()
    c = arm.c
    q0 = arm.q.copy()
    arm.move(np.array([0.0, 0.3, 0.0, 0.0, 0.0, 0.0]), 3.0)
    if kind == "wall":
        arm.wall = (1, q0[1] + 0.1)
    else:
        arm.run(1.0)
        arm.ext_Nm[1] = -40.0
    arm.run(3.0, until=lambda: c.mode != Mode.TRACK)
    trips = [e for e in c.events if e.kind == "protective_stop"]
    assert trips and trips[-1].joint == 1 and c.mode == Mode.HOLD, [e.text for e in c.events]
    assert trips[-1].fields["kind"] == "residual_current", trips[-1].text  # kp 1500 N·m/rad: 2 A at 0.7°


def test_a_csp_joint_on_the_same_motion_gets_no_loop_from_dragd():
    """Identification tracks: joints whose drives follow in CSP get the feed-forward only (their drive's loop holds
    them), as before motion modes; a replay's outer loop stays bounded (position_output_limit_A)."""
    arm = Arm(cst=False)
    arm.c.track.cst[3:] = True
    arm.move(np.array([0.1, 0.1, 0.1, 0.1, 0.1, 0.1]), 1.0)
    arm.run(0.5)
    tr = arm.c.track
    assert np.all(tr.pid_Nm[:3] == 0.0) and np.any(tr.pid_Nm[3:] != 0.0)
    assert np.all(np.isinf(tr._out_max[3:])) and np.all(tr._out_max[:3] == 0.0)
    # a replay plan (dq table): the CSP joints' outer loop with its bounded authority, the CST joints' own
    t = np.linspace(0, 1, 11)
    q = arm.q + np.outer(t, np.full(6, 0.05))
    dq = np.tile(np.full(6, 0.05), (11, 1))
    arm.c.end_track("stopped", arm.q)
    arm.run(0.3)
    arm.c.begin_track(Trajectory.from_table(q, 0.1, "replay p", dq=dq, ff_Nm=np.zeros_like(q)), arm.q, 1.0, 1)
    lim = arm.c.track.lim
    assert np.array_equal(tr._out_max[:3], lim.output_max_Nm[:3]) and np.all(np.isinf(tr._out_max[3:]))
    assert np.array_equal(tr._kp[:3], lim.kp_Nm_per_rad[:3]) and np.array_equal(tr._kp[3:],
                                                                                tr.cst_loop.kp_Nm_per_rad[3:])
