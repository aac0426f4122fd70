"""End to end: ``dragd identify run`` drives a short plan through the daemon (CSP) on the simulated robot, records
MCAP, and ``dragd identify fit`` finds joint 2's torque constant in it. On the lockstep clock: the recording has every
cycle of the plan."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dragd.config import load_config
from dragd.identify import excitation as E
from dragd.identify.data import load_log
from dragd.lab.rig import Rig
from dragd.model import RobotModel

from conftest import run_cli
from identify_helpers import run_plan, truth

# a hang guard of wall time: on a loaded machine the lockstep clock runs slower, never wrong
pytestmark = [pytest.mark.lockstep, pytest.mark.slow, pytest.mark.timeout(1200)]


def test_identify_run_through_the_daemon_then_fit(tmp_path):
    with Rig("identify-run", workdir=tmp_path) as rig:
        rig.start_sim()
        rig.start_daemon()
        rig.must("start")
        rig.sleep(0.3)
        q0 = np.array(rig.must("status")["q_rad"])
        model = RobotModel.from_urdf("seed_cobot")
        b = E.PlanBuilder(q0, E.Limits.from_model(model, load_config()))
        lo = q0.copy()
        lo[1] -= 0.8  # joint 2 lifts the arm by ~46° and back, at two speeds (seed 002's passes, one pose)
        for v in (0.2, 0.4):
            b.move(lo, speed=v, acceleration=0.8, kind="synchronous", joint=1)
            b.move(q0, speed=v, acceleration=0.8, kind="synchronous", joint=1)
        plan = b.build("e2e")
        assert 8.0 < plan.duration_s < 25.0
        res, out = run_plan(rig, plan, tmp_path)
        status = rig.must("status")
        rig.must("stop")
    assert res["log"] == str(out) and res["chunks"] == 1
    assert "faults" not in res and status["faults"] == [] and status["mode"] == "hold"
    log = load_log(out)  # the daemon's recording: TRACK rows of the whole plan
    assert res["dropped_rows"] == 0 and log.modes["track"] == round(plan.duration_s * 1000), (res, log.modes)
    assert log.t[-1] - log.t[0] == pytest.approx(plan.duration_s - 0.001, abs=1e-6)  # one row a cycle, none lost
    fit = run_cli("identify", "fit", "--log", str(out), "--method", "synchronous", "--out", str(tmp_path / "p.yaml"),
                  "--json")
    d = json.loads(fit.stdout)
    j2 = d["joints"]["joint2"]
    kt = truth()["joints"]["joint2"]["torque_constant_Nm_per_A"]
    err, std = j2["torque_constant_Nm_per_A"] - kt, j2["std"]["torque_constant_Nm_per_A"]
    assert abs(err) / kt < 0.03 and abs(err) < 3 * std + 0.005 * kt, j2  # a short live run: determined to ~1-3 %
    assert j2["friction"]["coulomb_pos_A"] > 0 > j2["friction"]["coulomb_neg_A"]

