"""The per_node layout (one SYNC RPDO per drive, no dummy entries) driving the simulated robot through the daemon:
on two classic buses drag only (statusword and controlword in event PDOs), motions refused with the reason; on CAN FD
with position targets an identification run (CSP). On the lockstep clock."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from dragd.lab.rig import Rig, multicast_group

from conftest import REPO
from daemon_helpers import derived_config

pytestmark = pytest.mark.lockstep


def _push_and_drift(rig: Rig, joint: str) -> tuple[float, float]:
    """Push ``joint`` in drag, let go: (how far it moved [deg], how far it crept in 2 s after rest [deg])."""
    before = np.array(rig.sim_call("state")["q_rad"])
    rig.sim_call("operator", scenario={"name": "push", "segments": [
        {"kind": "push", "joint": joint, "torque_Nm": 7.0, "duration_s": 0.6}, {"kind": "release", "duration_s": 0.0}]})
    rig.sleep(0.7)
    rig.wait_for(lambda: max(abs(v) for v in rig.sim_call("state")["dq_rad_s"]) < 1e-4, 8.0, "the arm at rest")
    rig.sleep(0.2)
    rest = np.array(rig.sim_call("state")["q_rad"])
    rig.sleep(2.0)
    later = np.array(rig.sim_call("state")["q_rad"])
    return float(np.degrees(np.abs(rest - before)).max()), float(np.degrees(np.abs(later - rest)).max())


def test_per_node_on_two_classic_buses_drags_and_refuses_motions(tmp_path: Path) -> None:
    def edit(d: dict) -> None:
        two = yaml.safe_load((REPO / "config" / "two_buses.yaml").read_text())
        d["buses"] = [dict(b, layout="per_node", position_targets=False) for b in two["buses"]]
        for j, tj in zip(d["joints"], two["joints"], strict=True):
            j["bus"] = tj["bus"]

    cfg = derived_config(tmp_path, "per_node", edit)
    bus = ",".join(f"udp_multicast:{multicast_group(f'per-node-{k}')}" for k in range(2))
    with Rig("per-node", workdir=tmp_path, config=cfg, sim_config=REPO / "sim" / "config" / "seed_cobot_two_buses.yaml",
             bus=bus) as rig:
        rig.start_sim()
        rig.start_daemon()
        log = rig.daemon.output()
        assert "protection: RPDO deadline 50 ms on RPDO1 (1400h:05)" in log, log
        status = rig.must("status")
        assert max(status["bus_load_pct"].values()) < 70.0
        assert any(line.startswith("protection: RPDO deadline 50 ms") for line in status["drives"][0]["boot"])
        assert status["drives"][0]["eds"] == "joint_drive.eds"
        rig.must("start")
        rig.wait_for(lambda: rig.must("status")["mode"] == "hold", 5.0, "hold")
        rig.sleep(0.5)
        p = rig.cli("mode", "drag")
        assert p.returncode == 0, (p.stderr, rig.daemon.tail())
        rig.sleep(0.5)
        moved, drift = _push_and_drift(rig, "joint1")
        assert moved > 2.0 and drift <= 0.1, (moved, drift)
        st = rig.must("status")
        assert st["mode"] == "drag" and st["faults"] == []
        q = st["q_rad"]
        resp = rig.call("track", t_s=[0.0, 0.5], q_rad=[q, q])
        assert not resp["ok"]
        assert "the drives cannot follow position targets (CSP): bus 'can0': layout 'per_node' carries no position " \
               "targets" in resp["error"], resp


@pytest.mark.slow
def test_per_node_with_targets_on_can_fd_runs_an_identification(tmp_path: Path) -> None:
    from dragd.config import load_config
    from dragd.identify import excitation as E
    from dragd.model import RobotModel

    # (6 joints' 8-byte FD frames: 71.6 % worst case, above the default 70 % limit: a function test, not a budget)
    cfg = derived_config(tmp_path, "per_node_fd", lambda d: d["buses"][0].update(layout="per_node", load_limit_pct=80))
    with Rig("per-node-fd", workdir=tmp_path, config=cfg) as rig:
        rig.start_sim()
        rig.start_daemon()
        rig.must("start")
        rig.wait_for(lambda: rig.must("status")["mode"] == "hold", 5.0, "hold")
        rig.sleep(0.3)
        q0 = np.array(rig.must("status")["q_rad"])
        model = RobotModel.from_urdf("seed_cobot")
        b = E.PlanBuilder(q0, E.Limits.from_model(model, load_config(cfg)))
        lo = q0.copy()
        lo[1] -= 0.3
        b.move(lo, speed=0.2, acceleration=0.8, kind="synchronous", joint=1)
        b.move(q0, speed=0.2, acceleration=0.8, kind="synchronous", joint=1)
        plan = b.build("per-node")
        pf = tmp_path / "plan.npz"
        plan.save(pf)
        out = tmp_path / "run.mcap"
        with rig.running():  # (the CLI polls the daemon on the wall clock; the plan runs on the daemon's)
            proc = rig.cli("identify", "run", "--plan", str(pf), "--out", str(out), "--no-progress", "--json",
                           timeout_s=300.0)
        assert proc.returncode == 0, proc.stderr + proc.stdout
        res = json.loads(proc.stdout)
        st = rig.must("status")
    assert "faults" not in res and st["faults"] == [] and st["mode"] == "hold"
    assert res["dropped_rows"] == 0 and st["missed_cycles"] == 0, (res, st["missed_cycles"])
    assert math.isclose(st["q_rad"][1], q0[1], abs_tol=0.01)
