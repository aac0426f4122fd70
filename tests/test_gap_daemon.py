"""The model gap on the daemon's own MCAP telemetry: the simulated arm with a Hall offset hidden on joint 4 is driven
through a short gap plan by ``dragd identify run`` (real time, CSP through the daemon), then ``dragd gap`` names it."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
import yaml

from dragd.config import load_config
from dragd.identify import excitation as E
from dragd.lab.rig import Rig
from dragd.model import RobotModel

from conftest import run_cli
from daemon_helpers import AS_DEPLOYED
from identify_helpers import run_plan

pytestmark = [pytest.mark.rig, pytest.mark.slow]


def test_gap_on_daemon_telemetry(tmp_path):
    from sim.truth import load_truth, params_from_truth

    truth = load_truth()
    hidden = truth.model_dump(mode="json")
    hidden["joints"][3]["hidden"]["current_offset_A"] = 0.1
    tf = tmp_path / "truth.yaml"
    tf.write_text(yaml.safe_dump(hidden))
    model = tmp_path / "model.yaml"
    model.write_text(yaml.safe_dump(params_from_truth(truth)))
    with Rig("gap-daemon", workdir=tmp_path, sim_config=tf, **AS_DEPLOYED) as rig:
        rig.start_sim()
        rig.start_daemon()
        rig.must("start")
        time.sleep(0.3)
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
    if "missed cycles throughout the log" in gap.stderr:
        # a loaded host: the two processes' timing leaves a velocity-proportional gap on the big joints (the
        # daemon's q̇ against the sim's clock) that may be named as well — a real gap of that rig, said on stderr;
        # the hidden offset must still be named, on joint 4 alone, with its value
        assert ("current_offset", ["joint4"]) in named, why
        assert all("joint4" not in js for e, js in named if e != "current_offset"), why
    else:
        assert named == [("current_offset", ["joint4"])], why
    offset = next(e for e in d["effects"] if e["effect"] == "current_offset")
    assert abs(offset["params"]["joint4"]["current_offset_A"] - 0.1) < 0.015
    assert d["final"]["rmse_A"] < d["baseline"]["rmse_A"]
