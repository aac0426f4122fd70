"""Seed 001's experiments as commands (`dragd experiment startup | sine-sweep | drag-quality`) on the simulated robot.

Real processes: each condition is a simulator + daemon pair on a private multicast group, on the lockstep clock
(``--lockstep``: a loaded machine cannot take part in a measurement); the identification that feeds the compensation
runs first (plan, ``python -m sim log``, ``dragd identify fit``). One light joint (joint 4) and short ramps keep the
suite fast; the all-joint figures are in docs/EXPERIMENTS.md.
"""

from __future__ import annotations

import json

import pytest
import yaml

from dragd.config import load_params
from dragd.lab.experiment import startup as startup_experiment
from dragd.lab.experiment.bench import Bench

from conftest import run_cli

# (the timeout: a hang guard of wall time; on a loaded machine the lockstep clock runs slower, never wrong)
pytestmark = [pytest.mark.lockstep, pytest.mark.slow, pytest.mark.timeout(1800)]


@pytest.fixture
def short(tmp_path_factory):
    """A work folder with a short path (the rigs' control sockets under it: AF_UNIX paths end at 108 bytes, and a
    test's own tmp_path under an xdist worker's folder leaves too few for the sweep's rig names)."""
    return tmp_path_factory.mktemp("x")


@pytest.fixture(scope="module")
def startup(tmp_path_factory):
    work = tmp_path_factory.mktemp("startup")  # given as a relative path, as a user types it (the rigs run inside it)
    proc = run_cli("experiment", "startup", "--joints", "4", "--reps", "2", "--ramp-s", "5", "--work-dir", work.name,
                   "--plots", f"{work.name}/plots", "--lockstep", "--json", timeout=1500, cwd=work.parent)
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
    assert all((work.parent / p).stat().st_size > 10_000 for p in data["plots"])


def test_sine_sweep_picks_a_frequency_writes_it_and_beats_the_published_hand_over(startup, short):
    work, _ = startup
    out = short / "params.yaml"
    proc = run_cli("experiment", "sine-sweep", "--joint", "4", "--frequencies", "8,16", "--reps", "4", "--ramp-s", "4",
                   "--params", str(work / "identified.yaml"), "--out", str(out), "--work-dir", str(short / "w"),
                   "--lockstep", "--json", timeout=1500)
    data = json.loads(proc.stdout)
    assert [p["frequency_Hz"] for p in data["points"]] == [8.0, 16.0]
    ok = [p for p in data["points"] if p["oscillation_deg"] <= 0.06]
    assert data["best_frequency_Hz"] == min(ok, key=lambda p: p["starting_torque_Nm"])["frequency_Hz"]
    written = load_params(out)
    assert written.joints["joint4"].startup.frequency_Hz == data["best_frequency_Hz"]
    assert written.joints["joint4"].friction.static_pos_A is not None  # the identified params are kept
    c = data["comparisons"]
    assert set(c) == {"sine_fade", "square_fade", "sine_fade_no_breakout", "sine_abrupt"}
    assert all(len(v["repetitions_Nm"]) == 4 and v["void_repetitions"] >= 0 for v in c.values()), c
    # the break-out latch needs less starting torque than seed 001's velocity switch and than the fade alone. On
    # this light joint with a short ramp all are good — 80-85 % below the static level — so the margins are small
    # (clean runs of 2 repetitions: −13…−24 % and −21…−32 %), and which sine peak first meets the rising load is
    # chance (±0.03 N·m a repetition at 8 Hz): 4 repetitions, margins 5 and 10 %
    assert c["sine_fade"]["starting_torque_Nm"] < 0.95 * c["sine_abrupt"]["starting_torque_Nm"], c
    assert c["sine_fade"]["starting_torque_Nm"] < 0.9 * c["sine_fade_no_breakout"]["starting_torque_Nm"], c


def test_a_repetition_the_daemon_held_the_arm_through_is_void_and_repeated(startup, short, monkeypatch):
    """Lost feedback in the middle of a ramp (on the wall clock a host stall of tens of ms; here joint 4's drive
    silent for 25 ms, 0.15 s of arm time into the first ramp: no TPDO of it for 25 cycles) makes the daemon hold the
    arm: the start-up term is off meanwhile, and the load at breakaway measures the outage, not the law (CI: one such
    stall cost the latch its lead). That repetition is void and run again, in the same direction."""
    work, _ = startup
    bench = Bench(short / "w", params=work / "identified.yaml", progress=False, lockstep=True)
    real_ramp, signs, stalls = startup_experiment.ramp_breakaway, [], []

    def ramp_with_a_stall(rig, joint, sign, rate_Nm_s, timeout_s):
        if not signs:  # the first ramp: 0.15 s after it starts (the breakaway comes after ~0.6 s), 25 ms silent
            sim_call = rig.sim_call

            def operator_then_silence(cmd, **args):
                got = sim_call(cmd, **args)
                if cmd == "operator":  # (the ramp's scenario is in: its time starts with the next grant)
                    monkeypatch.setattr(rig, "sim_call", sim_call)
                    rig.sleep(0.15)
                    stalls.append(sim_call("inject", kind="drive_silent", node_id=4, seconds=0.025))
                return got

            monkeypatch.setattr(rig, "sim_call", operator_then_silence)
        signs.append(sign)
        return real_ramp(rig, joint, sign, rate_Nm_s, timeout_s)

    monkeypatch.setattr(startup_experiment, "ramp_breakaway", ramp_with_a_stall)
    with bench.rig("void") as rig:
        holds0 = rig.must("status")["feedback_holds"]
        loads, _, void = startup_experiment._starting_torques(bench, rig, [3], 2, ramp_s=4.0)
        st = rig.must("status")
    assert len(stalls) == 1 and stalls[0]["ok"] and st["feedback_holds"] == holds0 + 1  # held once, for the outage
    assert st["mode"] == "drag" and st["faults"] == []  # ... and went back to drag (no fault: 25 < 50 cycles)
    assert void == {3: 1} and signs == [1, 1, -1]  # the held repetition repeated, in its direction
    # the two kept repetitions are the law's: well below the static level (≈ 2.1 N·m), as the fixture's run
    assert len(loads[3]) == 2 and max(loads[3]) < 0.5 * bench.static_Nm(3), loads


def test_drag_quality_effort_and_drift(startup, short):
    work, _ = startup
    proc = run_cli("experiment", "drag-quality", "--joints", "4", "--params", str(work / "identified.yaml"),
                   "--work-dir", str(short / "w"), "--lockstep", "--json", timeout=1500)
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
