"""``dragd identify plan|fit|check`` and ``python -m sim truth|log`` as real processes: JSON keys, errors, files."""

from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest
import yaml

from conftest import REPO, run_cli, run_sim
from identify_helpers import START, sync_log

pytestmark = pytest.mark.unit


def _sim(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return run_sim(*args, check=check, timeout=300, cwd=REPO)


def test_fit_json_and_params_file(tmp_path):
    out = tmp_path / "params.yaml"
    proc = run_cli("identify", "fit", "--log", str(sync_log("mcap")), "--method", "synchronous", "--out", str(out),
                   "--json")
    d = json.loads(proc.stdout)
    assert d["method"] == "synchronous" and set(d["joints"]) == {f"joint{i}" for i in range(1, 7)}
    j2 = d["joints"]["joint2"]
    assert set(j2) >= {"torque_constant_Nm_per_A", "friction", "std", "reasons"}
    assert set(j2["friction"]) >= {"coulomb_pos_A", "coulomb_neg_A", "viscous_A_s_per_rad", "static_pos_A",
                                   "static_neg_A", "stribeck_velocity_rad_s"}
    assert j2["friction"]["coulomb_neg_A"] < 0 < j2["friction"]["coulomb_pos_A"]
    assert j2["std"]["torque_constant_Nm_per_A"] > 0
    j1 = d["joints"]["joint1"]
    assert j1["torque_constant_Nm_per_A"] is None and "never moves" in j1["reasons"]["torque_constant_Nm_per_A"]
    data = yaml.safe_load(out.read_text())
    assert data["method"] == "synchronous" and data["joints"]["joint2"]["torque_constant_Nm_per_A"] > 8.9
    # the daemon's configuration loads it
    cfg = tmp_path / "cfg.yaml"
    base = yaml.safe_load((REPO / "config" / "default.yaml").read_text())
    base["params"] = str(out)
    cfg.write_text(yaml.safe_dump(base))
    chk = json.loads(run_cli("config", "check", "--config", str(cfg), "--json").stdout)
    assert chk["ok"]


def test_fit_text_names_nulls(tmp_path):
    proc = run_cli("identify", "fit", "--log", str(sync_log("csv")), "--method", "synchronous",
                   "--out", str(tmp_path / "p.yaml"))
    assert "joint1: torque_constant_Nm_per_A" in proc.stdout and "never moves" in proc.stdout
    assert "K_t N·m/A" in proc.stdout


def test_fit_several_logs_stacked(tmp_path):
    """``--log A --log B``: both logs fitted together (each its own stretch, rows stacked); formats may differ."""
    one = json.loads(run_cli("identify", "fit", "--log", str(sync_log("csv")), "--method", "synchronous",
                             "--out", str(tmp_path / "one.yaml"), "--json").stdout)
    two = json.loads(run_cli("identify", "fit", "--log", str(sync_log("csv")), "--log", str(sync_log("mcap")),
                             "--method", "synchronous", "--out", str(tmp_path / "two.yaml"), "--json").stdout)
    assert two["log"] == f"{sync_log('csv')} + {sync_log('mcap')}"
    assert any("2 logs stacked" in w for w in two["warnings"]), two["warnings"]
    rows1, rows2 = (d["joints"]["joint2"]["diagnostics"]["rows"] for d in (one, two))
    assert rows2 > 1.8 * rows1  # the second log's rows are in the regression
    k1, k2 = (d["joints"]["joint2"]["torque_constant_Nm_per_A"] for d in (one, two))
    assert k2 == pytest.approx(k1, rel=0.01)  # the same run twice: the same K_t


def test_check_json_and_plots(tmp_path):
    params = tmp_path / "params.yaml"
    run_cli("identify", "fit", "--log", str(sync_log("mcap")), "--method", "synchronous", "--out", str(params))
    proc = run_cli("identify", "check", "--params", str(params), "--log", str(sync_log("csv")), "--json",
                   "--plots", str(tmp_path / "plots"))
    d = json.loads(proc.stdout)
    assert 0.015 < d["rmse_A"] < 0.035
    j2 = d["joints"]["joint2"]
    assert set(j2) >= {"rmse_A", "mae_A", "max_A"} and j2["mae_A"] < j2["rmse_A"] < j2["max_A"]
    assert (tmp_path / "plots" / "joint2.png").stat().st_size > 10_000
    assert d["joints"]["joint1"]["rmse_A"] is None


def test_bad_inputs_exit_2_with_the_reason(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("t,q1,q2,i1\n0,0,0,0\n")
    proc = run_cli("identify", "fit", "--log", str(bad), "--out", str(tmp_path / "p.yaml"), check=False)
    assert proc.returncode == 2 and "columns: missing i2" in proc.stderr
    proc = run_cli("identify", "fit", "--log", str(tmp_path / "none.mcap"), "--out", str(tmp_path / "p.yaml"),
                   check=False)
    assert proc.returncode == 2 and "file not found" in proc.stderr
    proc = run_cli("identify", "fit", "--log", str(sync_log("csv")), "--method", "magic", "--out", "x.yaml",
                   check=False)
    assert proc.returncode == 2 and "invalid choice" in proc.stderr
    proc = run_cli("identify", "check", "--params", str(tmp_path / "nope.yaml"), "--log", str(sync_log("csv")),
                   check=False)
    assert proc.returncode == 2 and "nope.yaml: file not found" in proc.stderr


def test_plan_cli_writes_a_plan_in_limits(tmp_path):
    out = tmp_path / "plan.npz"
    start = ",".join(str(x) for x in START)
    d = json.loads(run_cli("identify", "plan", "--kind", "synchronous", "--joints", "2", "--scale", "0.3",
                           "--start", start, "--out", str(out), "--json").stdout)
    assert d["kind"] == "synchronous" and d["segments"]["synchronous"] > 0 and d["duration_s"] > 10
    with np.load(out) as z:
        assert z["q_rad"].shape[1] == 6 and z["t_s"][0] == 0.0
    proc = run_cli("identify", "plan", "--kind", "synchronous", "--out", str(out), check=False)
    assert proc.returncode == 2 and "--start" in proc.stderr
    proc = run_cli("identify", "plan", "--kind", "friction", "--start", "0,0,0", "--out", str(out), check=False)
    assert proc.returncode == 2 and "expected 6 values" in proc.stderr


def test_sim_truth_and_offline_log(tmp_path):
    truth = json.loads(_sim("truth", "--json").stdout)
    j2 = truth["joints"]["joint2"]
    assert j2["torque_constant_Nm_per_A"] == 9.05
    assert abs(j2["friction"]["coulomb_pos_A"] - 8.0 / 9.05) < 1e-12 and j2["friction"]["coulomb_neg_A"] < 0
    plan = tmp_path / "plan.npz"
    t = np.linspace(0.0, 2.0, 201)
    q = np.tile(START, (t.size, 1))
    q[:, 1] += 0.05 * (1 - np.cos(np.pi * t / 2.0)) / 2
    np.savez(plan, t_s=t, q_rad=q)
    d = json.loads(_sim("log", "--plan", str(plan), "--out", str(tmp_path / "l.csv"), "--json").stdout)
    assert d["rows"] == 2001 and d["rtf"] > 0  # (how fast it ran is a benchmark's figure, not a verdict)
    head = (tmp_path / "l.csv").read_text().splitlines()[0]
    assert head.startswith("t,q1,") and ",i6,dq1," in head
    bad = _sim("log", "--plan", str(plan), "--out", str(tmp_path / "l.txt"), check=False)
    assert bad.returncode == 2 and "expected a .mcap or .csv" in bad.stderr
