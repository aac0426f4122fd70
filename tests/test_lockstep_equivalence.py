"""The lockstep clock simulates what the wall clock runs: the same drag scenario on both agrees within a stated
tolerance.

What may differ, physically: on the wall clock the simulator's 1 ms physics grid and the daemon's SYNC grid have an
arbitrary phase (a TPDO samples the arm up to one physics tick before the SYNC; a command starts at the next tick),
the cycle's period jitters (the velocity estimate divides by the measured period), a loaded host misses a tick now
and then (the command held two periods), and the operator's push starts when the simulator gets the request, up to
a period off the daemon's cycle; in lockstep the grids are one and every period is exact.

The scenario runs without the law's start-up sine: its phase when the push begins is set by when the operator's
request reaches the simulator, which on the wall clock is arbitrary (16 Hz: a cycle is 62.5 ms), and a push that
starts against the sine's trough breaks the joint away later and slower. With the sine, two wall runs of the same
push differed by up to 10 % of the motion (2026-11-27: onsets 339 ms and 375 ms after the drag began, the sine at
+0.25 A and -0.25 A) — the scenario's own spread, not the clock's.

So, aligned at the push's onset on the cycle's time (a missed tick leaves no telemetry row: rows are not a grid):
while the hand pushes, the path is forced and agrees within ``PUSH_TOLERANCE`` (1 % of the motion); after the
release the arm coasts weightless, braked only by the law's damping, and the small differences above grow: within
``COAST_TOLERANCE`` (8 %) 1.5 s after the release. Measured on this 2-core VM at load 8–10 (other jobs running),
five wall runs against lockstep, each with 17–31 missed ticks: the push within 0.15 %; the coast 0.3, 1.1, 1.6, 0.07
and 2.7 %; beside two busy loops (a CPU hog) one run was 2.33 % off in the push. The claim is about a wall run that
kept real time: only a run whose daemon did not hold the arm for lost feedback, whose cycle did not stall inside the
compared window (no gap between two cycles of 2.5 ms or more: one missed tick is the jitter above, two in a row a
stall) and whose simulator dropped no physics step is a reference; otherwise the test says so instead of judging.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from dragd.lab.rig import Rig
from dragd.telemetry.reader import read_rows

from daemon_helpers import derived_config

pytestmark = pytest.mark.rig  # (one run of it on the wall clock: serial)

PUSH_S, COAST_S = 0.5, 1.5  # the push; how long the coast after the release is compared
PUSH_TOLERANCE, COAST_TOLERANCE = 0.01, 0.08  # of the motion's extent
STALL_S = 0.0025  # a gap between two cycles from here (two or more ticks missed in a row) is a stall, not jitter
RESOLUTION_RAD = 2.0 * math.pi / 524288 * 10  # a few encoder counts (524288 per revolution)
PUSH = {"name": "push", "segments": [{"kind": "push", "joint": "joint1", "torque_Nm": 8.0, "duration_s": PUSH_S},
                                     {"kind": "release", "duration_s": 0.0}]}


def run(tmp: Path, lockstep: bool) -> dict[str, Any]:
    mcap = tmp / "run.mcap"
    tmp.mkdir(parents=True, exist_ok=True)
    config = derived_config(tmp, "no_sine", lambda c: c["law"].update(startup=False))
    with Rig("equivalence", workdir=tmp, config=config, telemetry=mcap, lockstep=lockstep,
             as_deployed=not lockstep) as rig:
        rig.start_sim()
        rig.start_daemon()
        rig.must("start")
        rig.sleep(0.5)
        rig.must("mode", mode="drag")
        rig.sleep(0.3)
        sim_before = rig.sim_call("state")
        rig.sim_call("operator", scenario=PUSH)
        rig.sleep(2.0)
        sim_after = rig.sim_call("state")
        status = rig.must("status")
        rig.must("stop")
    rows = read_rows(mcap)
    mode = np.asarray(rows["mode"])
    t = np.asarray(rows["t_s"], dtype=float)
    q = np.asarray(rows["q_rad"], dtype=float)[:, 0]
    dq = np.asarray(rows["dq_rad_s"], dtype=float)[:, 0]
    k0 = int(np.flatnonzero(mode == "drag")[0])
    onset = k0 + int(np.flatnonzero(np.abs(q[k0:] - q[k0]) > 10 * RESOLUTION_RAD)[0])
    # on the cycle's time, 1 ms apart from 20 ms before the onset: a missed tick leaves no row (the arm moved on
    # meanwhile), so rows are not samples of a grid; the cycle's t_s is
    grid = t[onset] + (np.arange(-20, int((PUSH_S + COAST_S) * 1000) + 20) * 1e-3)
    q_at = np.interp(grid, t, q)
    inside = t[(t >= grid[0]) & (t <= grid[-1])]
    return {"q": q_at - q_at[0], "dq": np.interp(grid, t, dq), "status": status,
            "longest_gap_s": float(np.diff(inside).max()) if len(inside) > 1 else 0.0,
            "sim_dropped_steps": int(sim_after["dropped_steps"]) - int(sim_before["dropped_steps"])}


def test_wall_clock_and_lockstep_agree(tmp_path: Path) -> None:
    lock = run(tmp_path / "lockstep", True)
    wall = run(tmp_path / "wall", False)
    st = wall["status"]
    if st["feedback_holds"] or st["faults"]:
        pytest.skip(f"the wall-clock run is no reference on this machine now: {st['feedback_holds']} feedback "
                    f"hold(s), faults {st['faults'][-1:]} ({st['missed_cycles']} missed ticks): run it on a quiet one")
    if wall["longest_gap_s"] > STALL_S or wall["sim_dropped_steps"]:
        pytest.skip(f"the wall-clock run is no reference on this machine now: inside the compared window the daemon's "
                    f"longest gap between cycles was {1e3 * wall['longest_gap_s']:.1f} ms (a stall from "
                    f"{1e3 * STALL_S:g} ms), the simulator dropped {wall['sim_dropped_steps']} physics step(s): run it "
                    f"on a quiet one")
    ql, qw = lock["q"], wall["q"]
    extent = float(np.abs(ql).max())
    assert extent > 0.3 and float(np.abs(lock["dq"]).max()) > 0.2  # the push moved the joint: something to compare
    off = np.abs(qw - ql) / extent
    pushed = int(PUSH_S * 1000) + 20  # samples (1 ms apart) from 20 ms before the onset to the release
    for name, window, tol in (("push", slice(0, pushed), PUSH_TOLERANCE),
                              ("coast", slice(pushed, pushed + int(COAST_S * 1000)), COAST_TOLERANCE)):
        k = window.start + int(off[window].argmax())
        assert off[k] <= tol + RESOLUTION_RAD / extent, (
            f"{name}: the wall clock's path is {100 * off[k]:.2f} % of the motion off the lockstep path {k - 20} ms "
            f"after the onset ({qw[k]:.4f} against {ql[k]:.4f} rad; allowed {100 * tol:g} %; the wall run: "
            f"{st['missed_cycles']} missed ticks, {st['late_tpdo_cycles']} cycles with late TPDOs)")
