"""Motions on drives without a torque offset (no 60B2h: Eyou), end to end on the lockstep clock: the in-repo variant
tests/data/eds/no_60b2h.eds as every joint's drive, in the daemon (its profile, ``config init --eds``) and in the
simulator (``--eds``). Their command is 6071h, which CiA 402 CSP ignores; the profile makes them follow motions in
CST with dragd's position loop and the model's feed-forward (docs/DRIVES.md). Forced into CSP (``motion_mode: csp``)
the same motion drops the shoulder at the switch, and the residual monitor stops it: what Eyou's identify run did.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from dragd.lab.bench.drives import _datasheet, _truth
from dragd.lab.rig import Rig, multicast_group

from conftest import REPO, run_cli
from daemon_helpers import cycle_rows

pytestmark = pytest.mark.lockstep

EDS = REPO / "tests" / "data" / "eds" / "no_60b2h.eds"


def _setup(tmp_path: Path, motion_mode: str | None = None) -> tuple[Path, Path, str]:
    """``config init --eds`` (+ what the datasheet says), the simulator's truth for it, the buses."""
    cfg = tmp_path / "cfg.yaml"
    run_cli("config", "init", "--robot", "seed_cobot", "--eds", str(EDS), "--out", str(cfg))
    truth = tmp_path / "truth.yaml"
    robot = yaml.safe_load(cfg.read_text())["robot"]["urdf"]
    assert _truth(robot, cfg, truth) is None
    _datasheet(EDS, cfg, truth)
    if motion_mode is not None:  # the integrator's choice, with the position targets CSP needs
        data = yaml.safe_load(cfg.read_text())
        for d in data["drives"].values():
            d["motion_mode"] = motion_mode
        for b in data["buses"]:
            b.update(position_targets=True, load_limit_pct=100)  # (a function test, not a bus budget)
        cfg.write_text(yaml.safe_dump(data, sort_keys=False))
    n_bus = len(yaml.safe_load(cfg.read_text())["buses"])
    bus = ",".join(f"udp_multicast:{multicast_group(f'{tmp_path.name}-{k}')}" for k in range(n_bus))
    return cfg, truth, bus


def _lift(rig: Rig, tmp_path: Path, rise_rad: float = 0.2, seconds: float = 2.0) -> tuple[np.ndarray, Path]:
    """A track lifting the shoulder by ``rise_rad`` and back (what ``identify run`` does at 0.2 rad/s)."""
    q0 = np.array(rig.must("status")["q_rad"])
    t = np.linspace(0.0, 2 * seconds, 81)
    s = np.where(t < seconds, (1 - np.cos(np.pi * t / seconds)) / 2, (1 + np.cos(np.pi * (t - seconds) / seconds)) / 2)
    q = np.tile(q0, (t.size, 1))
    q[:, 1] += rise_rad * s
    path = tmp_path / "lift.npz"
    np.savez(path, t_s=t, q_rad=q)
    return q0, path


def test_a_drive_without_torque_offset_follows_motions_in_cst_and_a_collision_stops_it(tmp_path: Path) -> None:
    cfg, truth, bus = _setup(tmp_path)
    mcap = tmp_path / "run.mcap"
    with Rig("cst-motion", workdir=tmp_path, config=cfg, sim_config=truth, bus=bus, sim_args=["--eds", str(EDS)],
             telemetry=mcap) as rig:
        rig.start_sim()
        rig.start_daemon()
        st = rig.must("status")
        assert {d["motion_mode"] for d in st["drives"]} == {"cst"}
        rig.must("start")
        rig.sleep(0.5)
        q0, lift = _lift(rig, tmp_path)
        resp = rig.must("track", file=str(lift), label="identify")
        assert resp["mode"] == "track"
        modes = set()
        for _ in range(40):  # the drives never leave CST: no 6060h switch, no CSP
            rig.sleep(0.1)
            s = rig.must("status")
            modes.add(s["drive_mode"])
            if s["mode"] != "track":
                break
        assert modes == {"cst"}, modes
        rig.wait_for(lambda: rig.must("status")["mode"] == "hold", 2.0, "the end of the motion")
        done = rig.must("status")
        assert done["faults"] == [], done["faults"]
        rig.sleep(0.5)
        assert np.degrees(np.abs(np.array(rig.sim_call("state")["q_rad"]) - q0)).max() < 0.2
        # a collision on the shoulder while it lifts: the residual monitor stops the motion, the arm holds
        rig.must("track", file=str(lift), label="identify")
        rig.sleep(1.0)
        rig.sim_call("operator", scenario={"name": "collision", "segments": [
            {"kind": "push", "joint": "joint2", "torque_Nm": -40.0, "duration_s": 0.8}]})
        rig.wait_for(lambda: rig.must("status")["mode"] != "track", 1.0, "a monitor to stop the motion")
        end = rig.must("status")
        rig.must("stop")
    assert end["mode"] == "hold" and end["faults"], end
    f = end["faults"][-1]
    assert f["joint"] == "joint2" and f["kind"] == "residual_current" and f["reaction"] == "hold", f
    rows = cycle_rows(mcap)
    m = rows["mode"] == "track"
    first = np.flatnonzero(m)
    first = first[first < np.flatnonzero(np.diff(m.astype(int)) == -1)[0] + 1]  # the first motion's rows
    err = np.degrees(np.abs(rows["q_rad"][first] - rows["q_ref_rad"][first]))
    res = np.abs(rows["residual_A"][first])
    # within half the monitors' bounds (2°, 2 A): the residual is the friction this fresh configuration does not
    # believe (the shoulder's static friction is 0.79 A) and the acceleration, as a drive's CSP loop would leave it
    # (measured: 0.47°, 0.98 A)
    assert err.max() < 1.0 and res.max() < 1.2, (err.max(axis=0), res.max(axis=0))


def test_forced_into_csp_the_shoulder_drops_at_the_switch_and_the_residual_stops_it(tmp_path: Path) -> None:
    """``motion_mode: csp`` on a drive without 60B2h (config check warns): at the switch the drive's CSP loop, its
    integral at zero and 6071h ignored, lets go of the shoulder's weight; measured minus the model's current is the
    missing gravity current, and the monitor stops the motion within its first 0.1 s."""
    cfg, truth, bus = _setup(tmp_path, motion_mode="csp")
    check = run_cli("config", "check", "--config", str(cfg), check=False)
    assert "the arm sags" in check.stdout, check.stdout
    mcap = tmp_path / "run.mcap"
    with Rig("csp-sag", workdir=tmp_path, config=cfg, sim_config=truth, bus=bus, sim_args=["--eds", str(EDS)],
             telemetry=mcap) as rig:
        rig.start_sim()
        rig.start_daemon()
        rig.must("start")
        rig.sleep(0.5)
        _, lift = _lift(rig, tmp_path)
        rig.must("track", file=str(lift), label="identify")
        rig.wait_for(lambda: rig.must("status")["mode"] != "track", 1.0, "a monitor to stop the motion")
        end = rig.must("status")
        rig.must("stop")
    f = end["faults"][-1]
    assert f["joint"] == "joint2" and f["kind"] == "residual_current", end["faults"]
    rows = cycle_rows(mcap)
    track = np.flatnonzero(rows["mode"] == "track")
    assert rows["t_s"][track[-1]] - rows["t_s"][track[0]] < 0.1
    # at the trip the shoulder carried a fraction of its weight: the measured current far from the model's
    k = track[-1]
    assert abs(rows["current_measured_A"][k, 1]) < 0.5 * abs(rows["gravity_A"][k, 1]), (
        rows["current_measured_A"][k, 1], rows["gravity_A"][k, 1])
    # ... and it had fallen ahead of the reference in the direction gravity pulls (the gravity current opposes it)
    assert (rows["q_rad"][k, 1] - rows["q_ref_rad"][k, 1]) * rows["gravity_A"][k, 1] < 0
