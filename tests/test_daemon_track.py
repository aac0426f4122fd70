"""TRACK: the CSP entry point that identification runs and replay use — switch to CSP, follow, back to CST (on the
lockstep clock)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dragd.lab.rig import Rig

from daemon_helpers import cycle_rows

pytestmark = pytest.mark.lockstep


def test_track_follows_trajectory_in_csp_and_returns_to_hold(tmp_path):
    mcap = tmp_path / "track.mcap"
    with Rig("track", workdir=tmp_path, telemetry=mcap) as rig:
        rig.start_sim()
        rig.start_daemon()
        rig.must("start")
        rig.sleep(0.3)
        q0 = np.array(rig.must("status")["q_rad"])
        t = np.linspace(0.0, 3.0, 31)
        step = np.array([0.2, 0.1, -0.1, 0.15, 0.1, 0.2])
        q = q0 + np.outer((1 - np.cos(np.pi * t / 3.0)) / 2, step)
        np.savez(tmp_path / "traj.npz", t_s=t, q_rad=q)
        bad = rig.call("track", t_s=[0.0, 1.0], q_rad=[(q0 + 0.5).tolist(), q0.tolist()])
        assert not bad["ok"] and "starts" in bad["error"]  # refuses a jump to a far start
        # built in the planner process: its errors come back named, and scipy (the spline) never loads in the daemon
        bad_t = rig.call("track", t_s=[0.0, 0.0, 1.0], q_rad=[q0.tolist()] * 3)
        assert not bad_t["ok"] and "t must increase strictly" in bad_t["error"], bad_t
        (tmp_path / "bad.csv").write_text("t,q1\nx,y\n")
        bad_f = rig.call("track", file=str(tmp_path / "bad.csv"))
        assert not bad_f["ok"] and "bad.csv" in bad_f["error"], bad_f
        resp = rig.must("track", file=str(tmp_path / "traj.npz"), label="identify")
        assert resp["mode"] == "track" and resp["duration_s"] == 3.0
        s = rig.must("status")
        assert s["drive_mode"] == "csp" and s["trajectory"]["label"] == "identify"
        rig.wait_for(lambda: rig.must("status")["mode"] == "hold", 6.0, "the end of the motion")
        assert "/scipy/" not in Path(f"/proc/{rig.daemon.proc.pid}/maps").read_text()  # (numpy.libs: scipy_openblas)
        rig.wait_for(lambda: rig.must("status")["drive_mode"] == "cst", 2.0, "the drives back in CST")
        rig.sleep(0.3)
        end = rig.must("status")
        sim = np.array(rig.sim_call("state")["q_rad"])
        rig.must("stop")
    assert end["faults"] == []
    err = np.degrees(np.abs(sim - q[-1]))
    assert err.max() < 0.5, err  # the drives' own PD loops with gravity + friction fed forward
    rows = cycle_rows(mcap)
    assert "track" in set(rows["mode"])


def test_record_window_to_separate_mcap(tmp_path):
    with Rig("record", workdir=tmp_path) as rig:
        rig.start_sim()
        rig.start_daemon()
        rig.must("start")
        path = tmp_path / "window.mcap"
        assert rig.must("record", action="start", path=str(path), label="unit")["recording"] == str(path)
        again = rig.call("record", action="start", path=str(tmp_path / "other.mcap"))
        assert not again["ok"] and "already recording" in again["error"]
        rig.sleep(0.5)
        stats = rig.must("record", action="stop")
        assert not rig.call("record", action="stop")["ok"]
        rig.must("stop")
    rows = cycle_rows(path)
    assert len(rows["t_s"]) == 500 and stats["written"] == 500  # the window's cycles, every one
    assert set(rows["mode"]) == {"hold"}
