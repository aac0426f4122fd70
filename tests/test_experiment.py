"""Seed 001's experiments as commands (`dragd experiment startup | sine-sweep | drag-quality`) on the simulated robot.

Real processes: each condition is a simulator + daemon pair on a private multicast group; the identification
that feeds the compensation runs first (plan, ``python -m sim log``, ``dragd identify fit``). One light joint
(joint 4) and short ramps keep the suite fast; the all-joint figures are in docs/EXPERIMENTS.md.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from dragd.config import load_params

from conftest import run_cli

pytestmark = [pytest.mark.rig, pytest.mark.slow]


@pytest.fixture(scope="module")
def startup(tmp_path_factory):
    work = tmp_path_factory.mktemp("startup")
    proc = run_cli("experiment", "startup", "--joints", "4", "--reps", "2", "--ramp-s", "5", "--work-dir", str(work),
                   "--plots", str(work / "plots"), "--json", timeout=600)
    return work, json.loads(proc.stdout)


def test_startup_identifies_first_and_cuts_the_starting_torque(startup):
    work, data = startup
    # the compensation ran on parameters identified from a current log, not on the simulator's truth
    params = load_params(work / "identified.yaml")
    assert params.joints["joint4"].friction.static_pos_A is not None
    used = yaml.safe_load(next(work.glob("startup-on-*.yaml")).read_text())
    assert used["law"]["startup"] is True
    j = data["joints"]["joint4"]
    assert set(j) >= {"starting_torque_without_Nm", "starting_torque_with_Nm", "reduction_pct", "oscillation_deg"}
    # without the term the ramp must overcome static friction (truth 2.05-2.2 N·m); with it, a fraction of it
    assert 1.5 < j["starting_torque_without_Nm"] < 3.0
    assert j["reduction_pct"] > 60.0, j  # measured 85 % (docs/EXPERIMENTS.md); seed 001: 60.58 % mean
    assert j["oscillation_deg"] <= 0.06
    assert data["mean_reduction_pct"] == pytest.approx(j["reduction_pct"], abs=0.01)
    assert all(Path(p).stat().st_size > 10_000 for p in data["plots"])


def test_sine_sweep_picks_a_frequency_writes_it_and_beats_the_published_hand_over(startup, tmp_path):
    work, _ = startup
    out = tmp_path / "params.yaml"
    proc = run_cli("experiment", "sine-sweep", "--joint", "4", "--frequencies", "8,16", "--reps", "2", "--ramp-s", "4",
                   "--params", str(work / "identified.yaml"), "--out", str(out), "--work-dir", str(tmp_path / "w"),
                   "--json", timeout=600)
    data = json.loads(proc.stdout)
    assert [p["frequency_Hz"] for p in data["points"]] == [8.0, 16.0]
    ok = [p for p in data["points"] if p["oscillation_deg"] <= 0.06]
    assert data["best_frequency_Hz"] == min(ok, key=lambda p: p["starting_torque_Nm"])["frequency_Hz"]
    written = load_params(out)
    assert written.joints["joint4"].startup.frequency_Hz == data["best_frequency_Hz"]
    assert written.joints["joint4"].friction.static_pos_A is not None  # the identified params are kept
    c = data["comparisons"]
    assert set(c) == {"sine_fade", "square_fade", "sine_fade_no_breakout", "sine_abrupt"}
    # the break-out latch needs less starting torque than seed 001's velocity switch (on this light joint with a
    # short ramp both are good — 80-85 % below the static level — so the margin is ~15-25 %, docs/EXPERIMENTS.md)
    assert c["sine_fade"]["starting_torque_Nm"] < 0.9 * c["sine_abrupt"]["starting_torque_Nm"], c
    assert c["sine_fade"]["starting_torque_Nm"] < 0.9 * c["sine_fade_no_breakout"]["starting_torque_Nm"], c


def test_drag_quality_effort_and_drift(startup, tmp_path):
    work, _ = startup
    proc = run_cli("experiment", "drag-quality", "--joints", "4", "--params", str(work / "identified.yaml"),
                   "--work-dir", str(tmp_path / "w"), "--json", timeout=600)
    data = json.loads(proc.stdout)
    assert data["guard_trips"] == 0  # the runaway guard never takes the hand's moves for a runaway
    j = data["joints"]["joint4"]
    # at 10°/s the hand pushes against Coulomb + viscous friction without compensation; with it only the
    # under-compensation (5 %) and the virtual damping are left
    assert j["effort_uncompensated_Nm"] > 1.0
    assert j["effort_pct"] < 15.0, j  # measured ≤ 10 % (docs/EXPERIMENTS.md)
    assert j["drift_after_release_deg"] < 0.1


@pytest.mark.parametrize("args, message", [
    (["startup", "--joints", "9", "--params", "x.yaml"], "--joints: expected joints 1..6, got [9]"),
    (["startup", "--joints", "4", "--ramp-s", "0.2", "--params", "x.yaml"], "--ramp-s: expected seconds in [1, 120]"),
    (["sine-sweep", "--joint", "1,2", "--params", "x.yaml"], "--joint: expected one joint"),
])
def test_bad_arguments_are_named(args, message, tmp_path):
    p = tmp_path / "x.yaml"
    p.write_text("version: 1\n")
    proc = run_cli("experiment", *[str(p) if a == "x.yaml" else a for a in args], "--work-dir", str(tmp_path / "w"),
                   check=False)
    assert proc.returncode != 0 and message in proc.stderr, proc.stderr
