"""The model gap on the daemon's own MCAP telemetry: the simulated arm with a Hall offset hidden on joint 4 is driven
through a short gap plan by ``dragd identify run`` (CSP through the daemon, on the lockstep clock), then ``dragd gap``
names it, and nothing else: no missed cycle leaves a velocity-proportional gap of the host's timing."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from dragd.config import load_config
from dragd.identify import excitation as E
from dragd.lab.rig import Rig
from dragd.model import RobotModel

from conftest import run_cli
from identify_helpers import run_plan

# a hang guard of wall time: on a loaded machine the lockstep clock runs slower, never wrong
pytestmark = [pytest.mark.lockstep, pytest.mark.slow, pytest.mark.timeout(1200)]


def test_gap_on_daemon_telemetry(tmp_path):
    from sim.truth import load_truth, params_from_truth

    truth = load_truth()
    hidden = truth.model_dump(mode="json")
    hidden["joints"][3]["hidden"]["current_offset_A"] = 0.1
    tf = tmp_path / "truth.yaml"
    tf.write_text(yaml.safe_dump(hidden))
    model = tmp_path / "model.yaml"
    model.write_text(yaml.safe_dump(params_from_truth(truth)))
    with Rig("gap-daemon", workdir=tmp_path, sim_config=tf) as rig:
        rig.start_sim()
        rig.start_daemon()
        rig.must("start")
        rig.sleep(0.3)
        q0 = np.array(rig.must("status")["q_rad"])
        b = E.PlanBuilder(q0, E.Limits.from_model(RobotModel.from_urdf("seed_cobot"), load_config()))
        E.add_gap(b, speeds=(0.25, 0.35, 0.5), half_range=0.3, poses=2, rng=np.random.default_rng(2))
        plan = b.build("gap-e2e")
        assert plan.duration_s < 40.0
        _, out = run_plan(rig, plan, tmp_path)
        rig.must("stop")
    gap = run_cli("gap", "--measured", str(out), "--model", str(model), "--out", str(tmp_path / "ext.yaml"), "--json")
    d = json.loads(gap.stdout)
    named = [(e["effect"], e["joints"]) for e in d["effects"]]
    why = json.dumps({k: v for k, v in d.items() if k != "details"}, default=str)[:4000] + gap.stderr[-2000:]
    assert "missed cycles" not in gap.stderr, gap.stderr[-2000:]
    assert named == [("current_offset", ["joint4"])], why
    offset = next(e for e in d["effects"] if e["effect"] == "current_offset")
    assert abs(offset["params"]["joint4"]["current_offset_A"] - 0.1) < 0.015
    assert d["final"]["rmse_A"] < d["baseline"]["rmse_A"]
