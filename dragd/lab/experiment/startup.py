"""Seed 001's start-up experiments: starting torque with and without the start-up term, the frequency sweep.

``startup``: per joint, in drag mode, a slowly rising external torque (the seed's weight over a pulley) until the
joint moves 0.11°; the load at that moment is the starting torque. Without the start-up term (law.startup off)
and with it, repetitions in both directions averaged; plus the oscillation range at rest with the term on.
``sine_sweep``: one joint, the start-up frequency swept (seed 001 Fig. 13): oscillation range and starting
torque per frequency; picks the frequency with the lowest starting torque whose oscillation stays ≤ 0.06°;
compares a square wave of the same amplitude (the peers' dither), the faded hand-over without the break-out
latch, and seed 001 as published (abrupt switch at Φ, eq. 28, no latch) against ours (faded hand-over + latch),
including the current step at the hand-over.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from dragd.config import ParamsFile, load_params, save_params
from dragd.lab.experiment.bench import (
    Bench,
    feedback_holds,
    handover_step_A,
    oscillation_deg,
    ramp_breakaway,
    record,
    wait_rest,
)

OSCILLATION_LIMIT_DEG = 0.06  # seed 001: the oscillation range at the chosen frequency stays below it
RAMP_S = 10.0  # seconds the load ramp takes to reach the believed static friction
DEFAULT_FREQUENCIES_HZ = (2.0, 4.0, 8.0, 12.0, 16.0, 20.0, 25.0, 30.0, 40.0)
VOID_RETRIES = 3  # a repetition the daemon did not drag through is repeated up to this many times


def _starting_torques(bench: Bench, rig: Any, joints: list[int], reps: int, rows_path: Path | None = None,
                      ramp_s: float | None = None) -> tuple[dict[int, list[float]], dict[str, np.ndarray] | None,
                                                            dict[int, int]]:
    """Ramp each joint ``reps`` times (alternating direction); the breakaway loads [N·m] per joint, and per joint
    the repetitions voided because the daemon held the arm for lost feedback during the ramp (a host stall of
    tens of ms: the start-up term was off and faded back in, so the load measured the host, not the law)."""
    out: dict[int, list[float]] = {}
    void: dict[int, int] = {}
    if rows_path is not None:
        rig.must("record", action="start", path=str(rows_path), label=rows_path.stem)
    for j in joints:
        name = bench.cfg.joints[j].name
        fs = bench.static_Nm(j)
        ramp = ramp_s or RAMP_S
        rate = fs / ramp  # a slow ramp (the seed adds weights one by one): ``ramp`` s to the believed static level
        loads = []
        void[j] = 0
        for r in range(reps):
            sign = 1 if r % 2 == 0 else -1
            for _ in range(VOID_RETRIES + 1):
                holds = feedback_holds(rig)
                # up to 3 × the believed level: an identified static friction that came out low (a log from a
                # loaded host) must not end the experiment — the seed adds weights until the joint moves
                ev = ramp_breakaway(rig, name, sign, rate, timeout_s=3.0 * ramp)
                if ev["kind"] != "breakaway":
                    raise RuntimeError(f"{name}: no breakaway within the ramp ({ev['kind']}: {ev}); the daemon then: "
                                       f"{_daemon_state(rig)}")
                held = feedback_holds(rig) - holds
                wait_rest(rig)
                if held == 0:
                    loads.append(abs(float(ev["torque_Nm"])))
                    break
                void[j] += 1
                bench.say(f"{name}: repetition {r + 1} void (the daemon held the arm {held}× for lost feedback "
                          f"during the ramp: a stalled host); repeating")
            else:
                raise RuntimeError(f"{name}: repetition {r + 1} disturbed {VOID_RETRIES + 1} times in a row (the "
                                   f"daemon held the arm for lost feedback during each ramp): the host is too loaded "
                                   f"for this experiment; the daemon then: {_daemon_state(rig)}")
        out[j] = loads
    rows = None
    if rows_path is not None:
        rig.must("record", action="stop")
        from dragd.telemetry.reader import read_rows

        rows = read_rows(rows_path)
    return out, rows, void


def _daemon_state(rig: Any) -> str:
    """What the daemon was doing (a ramp that never moves the joint: a hold, a fault, a disabled drive?)."""
    try:
        st = rig.must("status")
    except Exception as exc:  # noqa: BLE001 — a diagnostic only; the daemon may be gone
        return f"status failed: {exc}"
    g = st.get("guard") or {}
    return (f"mode {st.get('mode')} (requested {st.get('requested_mode')}), drives enabled {st.get('drives_enabled')} "
            f"{[d['state'] for d in st.get('drives', [])]}, feedback hold {st.get('feedback_hold')}, guard trips "
            f"{g.get('trips')} (last {g.get('last_trip')}), missed cycles {st.get('missed_cycles')}, faults "
            f"{st.get('faults', [])[-3:]}")


def run_startup(bench: Bench, joints: list[int], reps: int = 2, rest_s: float = 2.0,
                ramp_s: float | None = None) -> dict[str, Any]:
    """Table XI of seed 001: starting torque without/with the start-up term, reduction, oscillation at rest."""
    bench.say(f"without start-up compensation: ramping joints {', '.join(str(j + 1) for j in joints)} ...")
    with bench.rig("startup-off", {("law", "startup"): False}) as rig:
        without, _, void_without = _starting_torques(bench, rig, joints, reps, ramp_s=ramp_s)
    bench.say("with start-up compensation: oscillation at rest, then the same ramps ...")
    with bench.rig("startup-on", {("law", "startup"): True}) as rig:
        rest = record(rig, bench.workdir / "rest.mcap", rest_s)
        osc = oscillation_deg(rest)
        with_, rows, void_with = _starting_torques(bench, rig, joints, reps, bench.workdir / "ramps_on.mcap", ramp_s)
    result: dict[str, Any] = {"joints": {}}
    reductions = []
    for j in joints:
        w0, w1 = float(np.mean(without[j])), float(np.mean(with_[j]))
        red = 100.0 * (1.0 - w1 / w0) if w0 > 0 else float("nan")
        reductions.append(red)
        result["joints"][bench.cfg.joints[j].name] = {
            "starting_torque_without_Nm": round(w0, 4),
            "starting_torque_with_Nm": round(w1, 4),
            "reduction_pct": round(red, 2),
            "oscillation_deg": round(float(osc[j]), 5),
            "handover_step_A": round(handover_step_A(rows, j, bench.cfg.joints[j].startup.rest_threshold_rad_s), 4)
            if rows is not None else None,
            "repetitions": {"without_Nm": [round(x, 4) for x in without[j]],
                            "with_Nm": [round(x, 4) for x in with_[j]]},
            "void_repetitions": void_without[j] + void_with[j],
        }
    result["mean_reduction_pct"] = round(float(np.mean(reductions)), 2)
    result["max_oscillation_deg"] = round(float(max(osc[j] for j in joints)), 5)
    return result


def run_sweep(bench: Bench, joint: int, frequencies: list[float] | None = None, reps: int = 2,
              rest_s: float = 1.5, ramp_s: float | None = None) -> dict[str, Any]:
    """Seed 001 Fig. 13: oscillation and starting torque per start-up frequency; the best; square/abrupt compared."""
    freqs = list(frequencies or DEFAULT_FREQUENCIES_HZ)
    name = bench.cfg.joints[joint].name
    phi = bench.cfg.joints[joint].startup.rest_threshold_rad_s
    points: list[dict[str, Any]] = []
    for f in freqs:
        bench.say(f"{name}: start-up sine at {f:g} Hz ...")
        with bench.rig(f"sweep-{f:g}", {("joints", joint, "startup", "frequency_Hz"): float(f)}) as rig:
            osc = oscillation_deg(record(rig, bench.workdir / f"rest-{f:g}.mcap", rest_s))[joint]
            loads, _, void = _starting_torques(bench, rig, [joint], reps, ramp_s=ramp_s)
        points.append({"frequency_Hz": f, "oscillation_deg": round(float(osc), 5),
                       "starting_torque_Nm": round(float(np.mean(loads[joint])), 4),
                       "repetitions_Nm": [round(x, 4) for x in loads[joint]], "void_repetitions": void[joint]})
    ok = [p for p in points if p["oscillation_deg"] <= OSCILLATION_LIMIT_DEG]
    best = min(ok, key=lambda p: p["starting_torque_Nm"]) if ok else None
    f_best = best["frequency_Hz"] if best else max(freqs)
    comparisons: dict[str, dict[str, Any]] = {}
    no_edits: dict[tuple[Any, ...], Any] = {}
    for label, edits in (("sine_fade", no_edits),  # ours: faded hand-over + break-out latch
                         ("square_fade", {("law", "startup_waveform"): "square"}),  # the peers' dither
                         ("sine_fade_no_breakout", {("law", "startup_breakout"): False}),
                         ("sine_abrupt", {("law", "startup_handover"): "abrupt",  # seed 001 as published
                                          ("law", "startup_breakout"): False})):
        bench.say(f"{name}: {label.replace('_', ' + ')} at {f_best:g} Hz ...")
        e = {("joints", joint, "startup", "frequency_Hz"): float(f_best), **edits}
        with bench.rig(f"compare-{label}", e) as rig:
            osc = oscillation_deg(record(rig, bench.workdir / f"rest-{label}.mcap", rest_s))[joint]
            loads, rows, void = _starting_torques(bench, rig, [joint], reps, bench.workdir / f"ramps-{label}.mcap",
                                                  ramp_s)
        assert rows is not None  # (a rows_path was given: the ramps were recorded)
        comparisons[label] = {"oscillation_deg": round(float(osc), 5),
                              "starting_torque_Nm": round(float(np.mean(loads[joint])), 4),
                              "handover_step_A": round(handover_step_A(rows, joint, phi), 4),
                              "repetitions_Nm": [round(x, 4) for x in loads[joint]], "void_repetitions": void[joint]}
    return {"joint": name, "points": points, "best_frequency_Hz": best["frequency_Hz"] if best else None,
            "oscillation_limit_deg": OSCILLATION_LIMIT_DEG, "comparisons": comparisons}


def write_frequency(params_in: Path | None, params_out: Path, joint: str, frequency_Hz: float) -> None:
    """Write the chosen start-up frequency into a params file (keeping what it holds)."""
    params = load_params(params_in) if params_in and Path(params_in).exists() else ParamsFile()
    data = params.model_dump()
    data.setdefault("joints", {}).setdefault(joint, {}).setdefault("startup", {})["frequency_Hz"] = frequency_Hz
    save_params(ParamsFile.model_validate(data), params_out)
