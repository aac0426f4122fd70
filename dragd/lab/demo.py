"""``dragd demo``: the simulated robot and the daemon as separate processes, a scripted drag, an MCAP log.

Scenario ``drag``: enable (hold) → drag mode → nobody touches the arm (it must not move) → the scripted
operator's hand pulls joints 1–4 to a new pose and lets go → the arm stays where it was released.

Scenario ``teach`` (seed 000 §5): ``teach start`` → the operator's hand drags the arm to three waypoints, each
marked (absolute encoders) → ``teach stop`` writes the program → replayed linearly (point-to-point) and circularly
(the Cartesian circle through p1, p2, p3) in CSP → how close every taught waypoint was passed, on every joint.

All figures come from the daemon (its encoders and timing), as they would on a real robot. On the wall clock the
drag session's missed cycles are split into the machine's (a stall probe per CPU saw the host stall then:
dragd/lab/bench/stalls.py) and the daemon's own. ``lockstep``: both processes on the lockstep clock (simulated
time, as fast as they go; the same run gives the same telemetry, whose digest is reported with the real-time factor).
"""

from __future__ import annotations

import math
import sys
from datetime import datetime
from pathlib import Path
from typing import Any

from dragd.lab.demo_common import TEACH_STEPS_RAD, DemoError, guide_and_settle
from dragd.lab.rig import ProcessError, Rig, timing_fault

HAND_TARGET_RAD = [0.25, 0.15, -0.20, 0.30, 0.0, 0.0]  # relative joint-space pull of the operator's hand


def _say(progress: bool, text: str) -> None:
    if progress:
        print(f"demo: {text}", file=sys.stderr, flush=True)


def _max_deg(a: list[float], b: list[float]) -> float:
    return max(abs(math.degrees(x - y)) for x, y in zip(a, b, strict=True))


def run_demo(seconds: float = 20.0, config: Path | None = None, out: Path | None = None, scenario: str = "drag",
             progress: bool = True, lockstep: bool = False) -> dict[str, Any]:
    if scenario == "teach":
        return run_teach_demo(seconds, config, out, progress, lockstep)
    if scenario == "payload":
        from dragd.lab.demo_payload import PayloadDemoError, run_payload_demo

        try:
            return run_payload_demo(config, out, progress, lockstep)
        except PayloadDemoError as exc:
            raise DemoError(str(exc)) from None
    if scenario == "contact":
        from dragd.lab.demo_contact import ContactDemoError, run_contact_demo

        try:
            return run_contact_demo(config, out, progress, lockstep)
        except ContactDemoError as exc:
            raise DemoError(str(exc)) from None
    if scenario == "buttons":  # (#30: a teach session from the guiding device at the hand)
        from dragd.lab.demo_buttons import ButtonsDemoError, run_buttons_demo

        try:
            return run_buttons_demo(config, out, progress, lockstep)
        except ButtonsDemoError as exc:
            raise DemoError(str(exc)) from None
    if scenario != "drag":
        raise DemoError(f"--scenario: expected 'drag', 'teach', 'payload', 'buttons' or 'contact', got '{scenario}'")
    if not seconds >= 8.0:
        raise DemoError(f"--seconds: expected at least 8 s (hold, untouched drag, hand pull, release), got {seconds}")
    out = Path(out) if out is not None else Path.cwd() / "out"
    out.mkdir(parents=True, exist_ok=True)
    mcap = out / f"demo-{datetime.now().strftime('%Y%m%d-%H%M%S')}.mcap"
    rig = Rig("demo", config=config, telemetry=mcap, as_deployed=not lockstep, lockstep=lockstep)
    probe = None
    try:
        _say(progress, f"starting the simulated robot on {rig.bus}{' (lockstep clock)' if lockstep else ''} ...")
        rig.start_sim()
        _say(progress, "starting the daemon (NMT reset, SDO configuration, 402 walk) ...")
        rig.start_daemon()
        rig.must("start")
        started = rig.must("status")
        probe = None if lockstep else _start_probe(started)  # (the machine's stalls from here: beside any fault too)
        rig.sleep(0.5)
        try:
            rig.must("mode", mode="drag")
        except ProcessError:
            faults = rig.must("status")["faults"]
            if lockstep or not faults or not all(timing_fault(f) for f in faults):
                raise
            return _faulted(rig, started, probe, mcap, progress, "before the drag session")
        _say(progress, "drag mode; nobody touching the arm ...")
        untouched_s = 2.0
        before = rig.must("status")
        q0 = before["q_rad"]
        rig.sleep(untouched_s)
        q1 = rig.must("status")["q_rad"]
        hand_s = 3.0
        _say(progress, "the operator's hand pulls joints 1-4, then lets go ...")
        rig.sim_call("operator", scenario={"name": "demo_hand", "segments": [
            {"kind": "hand", "q_rad": HAND_TARGET_RAD, "relative": True, "stiffness": 60.0, "damping": 12.0,
             "max_load": 25.0, "duration_s": hand_s},
            {"kind": "release", "ramp_down_s": 0.1, "duration_s": 0.0}]})
        rig.sleep(hand_s + 0.1)
        settle_s = 0.5
        rig.sleep(settle_s)
        q_release = rig.must("status")["q_rad"]
        observe_s = max(2.0, seconds - untouched_s - hand_s - settle_s - 0.6)
        rig.sleep(observe_s)
        status = rig.must("status")
        q_end = status["q_rad"]
        stalls = _missed_by_cause(rig, before, status, probe) if probe is not None else None
        schedulers = rig.schedulers()
        if lockstep and status["faults"]:  # (no host timing reaches the lockstep clock: a fault is the demo failing)
            tail = rig.daemon.tail() if rig.daemon is not None else ""
            raise DemoError(f"the arm faulted on the lockstep clock: {status['faults'][-1]}\n{tail}")
        _say(progress, "stopping: ramp to hold, disable, SIGTERM ...")
        rig.must("stop")
        _closed_cleanly(rig)
        return {
            "cycles": status["cycles"],
            **_timing(status, stalls, lockstep, mcap),
            "scheduler": schedulers,  # as deployed where permitted (SCHED_FIFO), else SCHED_OTHER and why
            "drift_untouched_deg": round(_max_deg(q1, q0), 4),
            "moved_by_hand_deg": round(_max_deg(q_release, q1), 3),
            "drift_after_release_deg": round(_max_deg(q_end, q_release), 4),
            "observed_after_release_s": round(observe_s, 1),
            "bus_load_pct": max(status["bus_load_pct"].values()),
            "faults": len(status["faults"]),
            # on the wall clock a fault is reported, not raised: the machine may have starved the daemon past the
            # drives' deadlines (its stalls beside it: session_missed_host, host_stall_max_ms)
            **({"fault_texts": [f.get("text", f) if isinstance(f, dict) else f for f in status["faults"][-3:]]}
               if status["faults"] else {}),
            "guard_trips": status["guard"]["trips"],  # runaway-guard holds: the hand's pull is not one (0 expected)
            "mcap": str(mcap),
        }
    except ProcessError as exc:
        raise DemoError(str(exc)) from None
    finally:
        if probe is not None:
            probe.__exit__(None, None, None)
        rig.close()


def _closed_cleanly(rig: Rig) -> None:
    codes = rig.close()
    if codes.get("dragd") != 0:
        raise DemoError(f"the daemon exited with {codes.get('dragd')} on SIGTERM (expected 0):\n"
                        f"{rig.daemon.tail() if rig.daemon else ''}")


def _faulted(rig: Rig, started: dict[str, Any], probe: Any, mcap: Path, progress: bool, when: str) -> dict[str, Any]:
    """The wall clock's drag demo when a communication deadline faulted the arm before drag (refused then): the session
    cannot run; the demo reports the faults beside the machine's own stalls since the start (a host that starved the
    daemon past the drives' deadlines is the real-time path's outcome, not the demo failing) and shuts down as
    always. Any other fault is the demo failing."""
    status = rig.must("status")
    stalls = _missed_by_cause(rig, started, status, probe) if probe is not None else None
    _say(progress, f"the arm faulted {when}: {status['faults'][-1] if status['faults'] else '?'}; stopping ...")
    rig.must("stop")
    _closed_cleanly(rig)
    return {
        "session": f"not run: the arm faulted {when}",
        "cycles": status["cycles"],
        **_timing(status, stalls, False, mcap),
        "faults": len(status["faults"]),
        "fault_texts": [f.get("text", f) if isinstance(f, dict) else f for f in status["faults"][-3:]],
        "mcap": str(mcap),
    }


def _start_probe(before: dict[str, Any]) -> Any:
    """The machine's stall probes for the session (None where they cannot run: the demo says why)."""
    from dragd.lab.bench.stalls import PROBE_PRIORITY, StallProbe

    probe = StallProbe(PROBE_PRIORITY)
    try:
        probe.__enter__()
    except OSError as e:
        probe.errors.append(str(e))
    probe.before = before  # type: ignore[attr-defined]
    return probe


def _missed_by_cause(rig: Rig, before: dict[str, Any], after: dict[str, Any], probe: Any) -> dict[str, Any]:
    """The drag session's missed cycles: the machine's (a probe saw the host stall then) and the daemon's own."""
    from dragd.lab.bench.stalls import attribute

    probe.__exit__(None, None, None)
    missed = after["missed_cycles"] - before["missed_cycles"]
    ticks = max(1, after["cycles"] - before["cycles"] + missed)
    if not probe.complete:
        return {"missed": missed, "ticks": ticks, "measured": False, "reason": "; ".join(probe.errors)}
    log = rig.must("missed_ticks", since=before["missed_episodes"])
    n_new = after["missed_episodes"] - before["missed_episodes"]
    episodes = log["episodes"][:max(0, n_new - log["lost"])]
    host, _ = attribute(episodes, probe.stalls, 1.0 / rig_rate_Hz(rig))
    host = min(host, missed)
    st = probe.summary()
    return {"missed": missed, "ticks": ticks, "measured": True, "host": host, "own": missed - host,
            "host_stall_max_ms": round(st["late_max_ms"], 2), "host_late_wakeups": st["late_wakeups"]}


def rig_rate_Hz(rig: Rig) -> float:
    from dragd.lab.rig import config_rate_Hz

    return config_rate_Hz(rig.config)


def _timing(status: dict[str, Any], stalls: dict[str, Any] | None, lockstep: bool, mcap: Path) -> dict[str, Any]:
    """The run's timing figures: wall clock (periods, missed cycles: the machine's and the daemon's own) or lockstep
    (the real-time factor and the telemetry's digest: the same run gives the same)."""
    if lockstep:
        from dragd.telemetry.digest import digest

        clock = status["clock"]
        return {"clock": "lockstep", "sim_time_s": round(clock["t_s"], 3), "rtf": clock["rtf"],
                "late_tpdo_cycles": status["late_tpdo_cycles"], "telemetry_sha256": digest(mcap)["sha256"]}
    out: dict[str, Any] = {
        "clock": "wall",
        "period_p50_us": status["period_p50_us"],
        "period_p99_us": status["period_p99_us"],
        "missed_cycles": status["missed_cycles"],
        "missed_ratio": round(status["missed_cycles"] / max(1, status["cycles"]), 6),
    }
    if stalls is not None:  # the drag session's: how many of its missed cycles the machine's own stalls explain
        if stalls["measured"]:
            out.update({"session_missed_cycles": stalls["missed"], "session_missed_host": stalls["host"],
                        "session_missed_own": stalls["own"],
                        "missed_ratio_own": round(stalls["own"] / stalls["ticks"], 6),
                        "host_stall_max_ms": stalls["host_stall_max_ms"]})
        else:
            out["host_stalls"] = f"not measured ({stalls['reason']})"
    return out


def _wait_fresh(rig: Rig, timeout_s: float = 20.0) -> None:
    """A feedback hold (late TPDOs under machine load) must be over before a replay is asked for."""
    try:
        rig.wait_for(lambda: not rig.must("status")["feedback_hold"], timeout_s, "the end of a feedback hold")
    except ProcessError:
        raise DemoError(f"the arm stayed in a feedback hold (late TPDOs) for {timeout_s:.0f} s") from None


def _wait_replay(rig: Rig, timeout_s: float) -> dict[str, Any]:
    got: list[dict[str, Any]] = []

    def ended() -> bool:
        got[:] = [rig.must("status")]
        return bool((got[0].get("replay") or {}).get("outcome"))

    try:
        rig.wait_for(ended, timeout_s, "the end of the replay")
    except ProcessError:
        raise DemoError(f"the replay did not end within {timeout_s:.0f} s:\n"
                        f"{rig.daemon.tail() if rig.daemon else ''}") from None
    return got[0]


def run_teach_demo(seconds: float = 20.0, config: Path | None = None, out: Path | None = None,
                   progress: bool = True, lockstep: bool = False) -> dict[str, Any]:
    """Teach p1, p2, p3 by hand, replay them linearly and circularly; waypoint and path errors [deg]."""
    from dragd.teach.analysis import replay_errors
    from dragd.telemetry.reader import read_rows

    if not seconds >= 6.0:
        raise DemoError(f"--seconds: expected at least 6 s of teaching (three hand-guided waypoints), got {seconds}")
    out = Path(out) if out is not None else Path.cwd() / "out"
    out.mkdir(parents=True, exist_ok=True)
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    mcap = out / f"demo-teach-{stamp}.mcap"
    program = out / "programs" / f"teach-{stamp}.yaml"
    per_point = seconds / len(TEACH_STEPS_RAD)
    hand_s = max(1.5, per_point - 0.5)
    rig = Rig("demo-teach", config=config, telemetry=mcap, allow_dirs=[out], as_deployed=not lockstep,
              lockstep=lockstep)
    try:
        _say(progress, f"starting the simulated robot on {rig.bus} ...")
        rig.start_sim()
        _say(progress, "starting the daemon ...")
        rig.start_daemon()
        rig.must("start")
        rig.sleep(0.3)
        rig.must("teach", action="start", name=str(program))
        _say(progress, f"teaching {program.name}: the arm is in drag mode")
        marks = []
        for i, step in enumerate(TEACH_STEPS_RAD):
            _say(progress, f"the operator's hand guides the arm to p{i + 1} and lets go ...")
            guide_and_settle(rig, step, hand_s, f"teach_p{i + 1}")
            marks.append(rig.must("teach", action="mark"))
            _say(progress, f"marked {marks[-1]['name']}: {', '.join(f'{x:.2f}' for x in marks[-1]['q_deg'])} deg")
        taught = rig.must("teach", action="stop")
        _say(progress, f"program written: {taught['program']} ({taught['samples']} samples)")
        waypoints = {m["name"]: m["q_rad"] for m in marks}
        runs = {}
        for interp in ("linear", "circular"):
            _wait_fresh(rig)
            t0 = rig.must("status")["t_s"]
            resp = rig.must("replay", program=str(program), interp=interp, timeout_s=60.0)
            _say(progress, f"replaying {interp}: move to start {resp['move_to_start_s']:.1f} s, "
                           f"cycle {resp['cycle_s']:.1f} s")
            st = _wait_replay(rig, resp["duration_s"] / 0.5 + 30.0)
            runs[interp] = {"t0": t0, "t1": st["t_s"], "marks": resp["marks"], "body_start_s": resp["move_to_start_s"],
                            "outcome": st["replay"]["outcome"], "duration_s": resp["duration_s"]}
            if st["replay"]["outcome"] != "done":
                raise DemoError(f"the {interp} replay ended with: {st['replay']['outcome']}")
            rig.sleep(0.3)
        rig.must("mode", mode="drag")  # back to the hand
        rig.sleep(0.5)
        status = rig.must("status")
        _say(progress, "stopping: ramp to hold, disable, SIGTERM ...")
        rig.must("stop")
        codes = rig.close()
        if codes.get("dragd") != 0:
            raise DemoError(f"the daemon exited with {codes.get('dragd')} on SIGTERM (expected 0):\n"
                            f"{rig.daemon.tail() if rig.daemon is not None else ''}")
        rows = read_rows(mcap)
        results = {k: replay_errors(rows, r["t0"], r["t1"], r["marks"], waypoints, r["body_start_s"])
                   for k, r in runs.items()}
        wp = [p["error_deg"] for res in results.values() for p in res["waypoints"]]
        return {
            "waypoints": len(waypoints),
            "waypoint_error_deg_max": max(wp),
            "path_error_deg_max": max(res["path_error_deg_max"] for res in results.values()),
            "tracking_error_deg_max": max(res["tracking_error_deg_max"] for res in results.values()),
            "linear": {k: v for k, v in results["linear"].items() if k != "rows"},
            "circular": {k: v for k, v in results["circular"].items() if k != "rows"},
            "replay_s": {k: r["duration_s"] for k, r in runs.items()},
            "cycles": status["cycles"],
            "missed_cycles": status["missed_cycles"],
            "faults": len(status["faults"]),
            "program": str(program),
            "mcap": str(mcap),
        }
    except ProcessError as exc:
        raise DemoError(str(exc)) from None
    finally:
        rig.close()
