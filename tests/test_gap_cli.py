"""``dragd gap`` on CSV and MCAP logs: exact JSON keys, the report, the extended params file (loaded by dragd.config,
used by the law and by the simulator), and bad input named."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from dragd.config import ConfigError, ParamsFile, apply_params, load_config, load_params
from dragd.control.law import LawOutput, Workspace, compensate
from dragd.control.params import LawParams
from dragd.gap.run import analyse
from dragd.model import RobotModel

from conftest import run_cli
from gap_helpers import as_log, generate_all, model_for, plan, truth_for

pytestmark = pytest.mark.unit


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """One pose of the gap plan (~27 s) with a 80 mA current offset hidden on joint 4, as CSV and MCAP."""
    from sim.offline import write_log

    d = tmp_path_factory.mktemp("gap-cli")
    data = generate_all(["current_offset"], seed=11, poses=1, workers=1)["current_offset"]
    write_log(d / "log.csv", data)
    write_log(d / "log.mcap", data)
    (d / "model.yaml").write_text(yaml.safe_dump(model_for("current_offset")))
    return d


@pytest.fixture(scope="module")
def csv_run(files):
    out = files / "out.yaml"
    proc = run_cli("gap", "--measured", str(files / "log.csv"), "--model", str(files / "model.yaml"), "--out",
                   str(out), "--report", str(files / "report"), "--json")
    return json.loads(proc.stdout), out


def test_json_has_exactly_the_issue_keys(csv_run):
    d, _ = csv_run
    assert list(d) == ["baseline", "effects", "final"]
    assert set(d["baseline"]) == {"rmse_A", "joints"} and set(d["final"]) == {"rmse_A"}
    assert set(d["baseline"]["joints"]) == {f"joint{k}" for k in range(1, 7)}
    assert [set(e) for e in d["effects"]] == [{"effect", "joints", "params", "rmse_A", "ambiguous_with"}]
    e = d["effects"][0]
    assert e["effect"] == "current_offset" and e["joints"] == ["joint4"]
    assert e["params"]["joint4"]["current_offset_A"] == pytest.approx(0.08, abs=0.01)
    assert d["final"]["rmse_A"] < d["baseline"]["rmse_A"] and e["rmse_A"] == pytest.approx(d["final"]["rmse_A"])


def test_mcap_input_gives_the_same_answer(files, csv_run):
    proc = run_cli("gap", "--measured", str(files / "log.mcap"), "--model", str(files / "model.yaml"), "--json")
    d = json.loads(proc.stdout)
    assert [(e["effect"], e["joints"]) for e in d["effects"]] == [("current_offset", ["joint4"])]
    assert d["final"]["rmse_A"] == pytest.approx(csv_run[0]["final"]["rmse_A"], rel=0.05)


def test_report_has_pngs_and_markdown(files, csv_run):
    rep = files / "report"
    md = (rep / "report.md").read_text()
    assert "current_offset" in md and "joint4" in md
    pngs = sorted(p.name for p in rep.glob("*.png"))
    assert pngs == sorted(["overview.png"] + [f"joint{k}.png" for k in range(1, 7)])
    assert all((rep / p).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in pngs)
    assert json.loads((rep / "gap.json").read_text())["details"]["baseline_kind"] == "given"


def test_extended_params_drive_the_law(csv_run):
    _, out = csv_run
    params = load_params(out)
    assert params.joints["joint4"].effects.current_offset_A == pytest.approx(0.08, abs=0.01)
    law = LawParams.from_config(apply_params(load_config(), params, str(out)))
    assert law.effects is not None
    model = RobotModel.from_urdf("seed_cobot")
    q, dq = np.array([0.1, -0.5, 1.0, -0.4, 1.5, 0.2]), np.array([0.0, 0.2, -0.2, 0.3, 0.0, 0.0])
    g = model.gravity(q)
    a = compensate(g, dq, 1.0, law.replace(effects=None), LawOutput.zeros(6), Workspace(6), q_rad=q)
    b = compensate(g, dq, 1.0, law, LawOutput.zeros(6), Workspace(6), q_rad=q)
    off = params.joints["joint4"].effects.current_offset_A
    assert b.current_A - a.current_A == pytest.approx(np.array([0, 0, 0, off, 0, 0]), abs=1e-9)
    assert b.effects_A[3] == pytest.approx(off)


def test_the_simulator_runs_the_extended_model(csv_run):
    """The sim built from the extended params has the effect; the gap on its log finds nothing missing."""
    from sim.offline import generate
    from sim.truth import truth_from_params

    _, out = csv_run
    params = load_params(out)
    truth = truth_from_params(params)
    assert truth.joints[3].hidden.current_offset_A == pytest.approx(params.joints["joint4"].effects.current_offset_A)
    p = plan(1)
    data = generate(p.t_s, p.q_rad, truth, seed=12)
    res = analyse(as_log(data, "sim-of-extended"), RobotModel.from_urdf("seed_cobot"), load_config(), params)
    assert res.to_json()["effects"] == [] and res.rmse_ratio <= 1.3


def test_ripple_round_trip_sign():
    """A position-periodic effect in params → the sim's ripple torque → the same current in params again."""
    from sim.truth import params_from_truth, truth_from_params

    t = truth_for("position_periodic")
    p = ParamsFile.model_validate(params_from_truth(t))
    back = truth_from_params(p)
    r0, r1 = t.joints[2].hidden.ripple[0], back.joints[2].hidden.ripple[0]
    assert r1.amplitude_Nm == pytest.approx(r0.amplitude_Nm) and r1.cycles_per_rev == r0.cycles_per_rev
    assert np.sin(r1.phase_rad) == pytest.approx(np.sin(r0.phase_rad)) and \
        np.cos(r1.phase_rad) == pytest.approx(np.cos(r0.phase_rad))


def test_bad_input_is_named(files, tmp_path):
    missing = run_cli("gap", "--measured", str(tmp_path / "nope.csv"), check=False)
    assert missing.returncode == 2 and "nope.csv: file not found" in missing.stderr
    bad = tmp_path / "bad.csv"
    bad.write_text("t,q1,x1\n0,0,0\n")
    cols = run_cli("gap", "--measured", str(bad), check=False)
    assert cols.returncode == 2 and "bad.csv" in cols.stderr and "x1" in cols.stderr
    m = yaml.safe_load((files / "model.yaml").read_text())
    m["joints"]["joint2"]["effects"]["friction_wobble"] = 1.0
    pf = tmp_path / "m.yaml"
    pf.write_text(yaml.safe_dump(m))
    with pytest.raises(ConfigError, match=r"m\.yaml: joints\.joint2\.effects\.friction_wobble: unknown key; expected "
                                          r"one of: position_periodic"):
        load_params(pf)
    unk = run_cli("gap", "--measured", str(files / "log.csv"), "--model", str(pf), check=False)
    assert unk.returncode == 2 and "friction_wobble" in unk.stderr
    eff = run_cli("gap", "--measured", str(files / "log.csv"), "--effects", "viscous_friction,wobble", check=False)
    assert eff.returncode == 2 and "--effects: unknown wobble" in eff.stderr


def test_json_keeps_the_warnings_on_stderr(files, tmp_path):
    """With ``--json`` stdout is exactly the result; what the text output warns about is said on stderr."""
    lines = (files / "log.csv").read_text().splitlines()
    lines[500] = ",".join(["nan"] * len(lines[500].split(",")))
    bad = tmp_path / "nan.csv"
    bad.write_text("\n".join(lines) + "\n")
    proc = run_cli("gap", "--measured", str(bad), "--model", str(files / "model.yaml"), "--drop-bad-rows", "--json")
    d = json.loads(proc.stdout)
    assert list(d) == ["baseline", "effects", "final"]
    warned = [ln for ln in proc.stderr.splitlines() if ln.startswith("warning: ")]
    assert warned and any("501" in ln for ln in warned), proc.stderr
