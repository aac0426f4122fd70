"""``dragd demo --scenario buttons``: a whole teach session from the hand alone (docs/HAND.md, #30).

The simulated arm's guiding device (the enabling switch, mark, stop and teach buttons on joint6's 60FDh) is wired in
the daemon's configuration, and drag requires the switch (``drag.require: enable_input``). The simulated operator:

1. a client asks for drag without the switch: refused (``drag_without_enable_refused``);
2. presses teach (a recording starts, named by the daemon), presses the enabling switch to the middle (drag), guides
   the arm to three poses and presses mark at each (the waypoints);
3. guides it on and releases the switch *and the arm* mid-motion: out of drag (``enable_release_to_hold_ms``, from
   the contact's change at the drive to the daemon's hold) and the arm braked where it was
   (``moved_after_release_deg``);
4. presses teach again (the program is written), and the program is replayed (``waypoint_error_deg_max``);
5. a software client takes a drag lease while the operator holds the switch, then stops renewing it (dies): drag ends
   within 1.5 lease periods of its last renewal (``lease_lapse_detected_ms``).

Times are the daemon's clock and the simulator's (the lockstep clock's simulated time with ``--lockstep``).
"""

from __future__ import annotations

import math
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from dragd.lab.rig import ProcessError, Rig

HAND_WIRING = [{"function": "enable", "joint": "joint6", "bit": 16, "second_bit": 17, "panic_bit": 18},
               {"function": "mark", "joint": "joint6", "bit": 19},
               {"function": "stop", "joint": "joint6", "bit": 20, "active": "low"},
               {"function": "teach", "joint": "joint6", "bit": 21}]  # (the simulated arm's device: sim/truth.py hand)
STEPS_RAD = [[0.20, 0.10, -0.10, 0.10, 0.0, 0.0],
             [0.25, 0.20, -0.35, 0.15, 0.15, 0.25],
             [-0.35, 0.05, 0.25, -0.05, -0.20, -0.15]]
ON_RAD = [0.4, 0.3, -0.3, 0.3, 0.0, 0.0]  # the last pull, released mid-motion
LEASE_S = 0.3
RELEASE_AFTER_S = 0.35  # into the last pull (the arm at a brisk hand-guiding speed)


class ButtonsDemoError(RuntimeError):
    """The demo could not run (the message says where)."""


def _config(base: Path | None, out: Path) -> Path:
    from dragd.resources import config_path

    data = yaml.safe_load((base or config_path("default.yaml")).read_text())
    if base is None:
        data["robot"]["urdf"] = "seed_cobot"
    data["hand"] = {**(data.get("hand") or {}), "inputs": HAND_WIRING}
    data["drag"] = {**(data.get("drag") or {}), "require": "enable_input", "lease_s": LEASE_S}
    data["replay"] = {**(data.get("replay") or {}), "program_dir": str(out / "programs")}
    path = out / "buttons.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _say(progress: bool, text: str) -> None:
    if progress:
        print(f"dragd demo: {text}", flush=True)


def _press(rig: Rig, button: str, hold_s: float | None = 0.1) -> None:
    """The simulated operator presses ``button`` (momentary: let go ``hold_s`` later; None: keeps it pressed)."""
    rig.sim_call("hand", action="press", button=button)
    if hold_s is not None:
        rig.sleep(hold_s)
        rig.sim_call("hand", action="let_go", button=button)


def _mode(rig: Rig) -> str:
    return str(rig.must("status")["mode"])


def _sim_offset(rig: Rig) -> tuple[float, float]:
    """Simulator time minus daemon time, and its uncertainty: exact on the lockstep clock (both stand still between
    grants); on the wall clock the sample with the shortest round trip of five (± half of it)."""
    best: tuple[float, float] | None = None
    for _ in range(1 if rig.lockstep else 5):
        d0 = float(rig.must("status")["t_s"])
        s = float(rig.sim_call("state")["t"])
        d1 = float(rig.must("status")["t_s"])
        if best is None or d1 - d0 < 2.0 * best[1]:
            best = (s - 0.5 * (d0 + d1), 0.5 * (d1 - d0))
    assert best is not None
    return best


def _guide(rig: Rig, step: list[float], name: str, hand_s: float = 1.5) -> None:
    rig.sim_call("operator", scenario={"name": name, "segments": [
        {"kind": "hand", "q_rad": list(step), "relative": True, "stiffness": 60.0, "damping": 12.0,
         "max_load": 25.0, "duration_s": hand_s},
        {"kind": "release", "ramp_down_s": 0.1, "duration_s": 0.3}]})
    rig.sleep(hand_s)
    rig.wait_for(lambda: bool(rig.sim_call("operator_events")["done"])
                 and max(abs(v) for v in rig.must("status")["dq_rad_s"]) < 0.002, 30.0,
                 f"the hand to let go at {name} and the arm to rest")


def run_buttons_demo(config: Path | None = None, out: Path | None = None, progress: bool = True,
                     lockstep: bool = False) -> dict[str, Any]:
    from dragd.teach.analysis import replay_errors
    from dragd.telemetry.reader import read_rows

    out = Path(out) if out is not None else Path.cwd() / "out"
    out.mkdir(parents=True, exist_ok=True)
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    mcap = out / f"demo-buttons-{stamp}.mcap"
    cfg = _config(config, out)
    rig = Rig("demo-buttons", config=cfg, telemetry=mcap, allow_dirs=[out], as_deployed=not lockstep,
              lockstep=lockstep, drag_guard="config")
    try:
        _say(progress, f"starting the simulated robot on {rig.bus}{' (lockstep clock)' if lockstep else ''} ...")
        rig.start_sim()
        _say(progress, "starting the daemon (the guiding device on joint6's 60FDh, drag.require: enable_input) ...")
        rig.start_daemon()
        rig.must("start")
        rig.sleep(0.3)
        refused = rig.call("mode", mode="drag")
        _say(progress, f"a client asks for drag without the switch: {refused.get('error')}")

        _say(progress, "the operator presses teach, then the enabling switch to the middle ...")
        _press(rig, "teach")
        rig.wait_for(lambda: bool(rig.must("status").get("teach")), 2.0, "teaching after the teach button")
        _press(rig, "enable", hold_s=None)
        rig.wait_for(lambda: _mode(rig) == "drag", 0.5, "drag after the enabling switch's press")
        for i, step in enumerate(STEPS_RAD):
            _guide(rig, step, f"p{i + 1}")
            n = int(rig.must("status")["teach"]["marks"])
            _press(rig, "mark")
            def marked(n: int = n) -> bool:
                return int(rig.must("status")["teach"]["marks"]) > n

            rig.wait_for(marked, 1.0, f"waypoint {i + 1} after the mark button")
            _say(progress, f"marked waypoint {i + 1} by the mark button")

        _say(progress, "the operator guides the arm on and lets go of it and of the switch mid-motion ...")
        rig.sim_call("operator", scenario={"name": "let_go_mid_motion", "segments": [
            {"kind": "hand", "q_rad": ON_RAD, "relative": True, "stiffness": 20.0, "damping": 30.0,
             "max_load": 25.0, "duration_s": RELEASE_AFTER_S},
            {"kind": "let_go", "button": "enable", "duration_s": 0.5}]})
        offset, offset_err = _sim_offset(rig)
        rig.sleep(RELEASE_AFTER_S + 1.0)
        st = rig.must("status")
        if st["mode"] != "hold":
            raise ButtonsDemoError(f"the release of the enabling switch left the arm in {st['mode']}: "
                                   f"{[f['text'] for f in st['faults']][-3:]}")
        end = st["drag"]["last_drag_end"]
        let_go = [e for e in rig.sim_call("operator_events")["events"] if e.get("kind") == "let_go"]
        t_change = float(let_go[-1]["t"]) - offset  # the contact opened (daemon time)

        _say(progress, "the operator presses teach again: the program is written ...")
        _press(rig, "teach")
        rig.wait_for(lambda: not rig.must("status").get("teach"), 5.0, "the end of teaching after the teach button")
        programs = out / "programs"
        rig.wait_for(lambda: any(programs.glob("hand_*.yaml")), 10.0, f"the program written to {programs}")
        program = max(programs.glob("hand_*.yaml"), key=lambda p: p.stat().st_mtime)
        waypoints = {w["name"]: w["q_rad"] for w in yaml.safe_load(program.read_text())["waypoints"]}

        _say(progress, f"replaying {program.name} ...")
        t0 = rig.must("status")["t_s"]
        resp = rig.must("replay", program=str(program), interp="linear", timeout_s=60.0)
        got: list[dict[str, Any]] = []

        def ended() -> bool:
            got[:] = [rig.must("status")]
            return bool((got[0].get("replay") or {}).get("outcome"))

        rig.wait_for(ended, resp["duration_s"] / 0.5 + 30.0, "the end of the replay")
        if got[0]["replay"]["outcome"] != "done":
            raise ButtonsDemoError(f"the replay ended with: {got[0]['replay']['outcome']}")
        t1 = got[0]["t_s"]
        rig.sleep(0.3)

        _say(progress, f"a client takes a {LEASE_S:g} s drag lease while the operator holds the switch, then dies ...")
        rig.sim_call("hand", action="let_go", button="enable")
        rig.sleep(0.05)
        rig.sim_call("hand", action="press", button="enable")
        rig.wait_for(lambda: _mode(rig) == "drag", 0.5, "drag after the enabling switch's press")
        rig.drag()  # a lease bound to this drag, renewed (lockstep: between grants; wall: paced by the daemon)
        rig.sleep(1.0)
        if _mode(rig) != "drag":
            raise ButtonsDemoError("drag did not last while the lease was renewed")
        rig.drop_lease(close=False)
        rig.wait_for(lambda: _mode(rig) != "drag", 3 * LEASE_S, "the lapsed lease to end drag")
        st = rig.must("status")
        lease = st["drag"]["lease"]
        lapse_end = st["drag"]["last_drag_end"]
        last_renewal = st["t_s"] - lease["since_renewal_s"]
        rig.sim_call("hand", action="let_go", button="enable")
        rig.sleep(0.1)
        status = rig.must("status")
        _say(progress, "stopping: ramp to hold, disable, SIGTERM ...")
        rig.must("stop")
        codes = rig.close()
        if codes.get("dragd") != 0:
            raise ButtonsDemoError(f"the daemon exited with {codes.get('dragd')} on SIGTERM (expected 0):\n"
                                   f"{rig.daemon.tail() if rig.daemon else ''}")
        rows = read_rows(mcap)
        t, m, q = rows["t_s"], rows["mode"], np.asarray(rows["q_rad"])
        k = int(np.argmax((m == "hold") & (t >= end["t_s"] - 1e-9)))
        k_end = int(np.searchsorted(t, end["t_s"] + 1.0))
        errors = replay_errors(rows, t0, t1, resp["marks"], waypoints, resp["move_to_start_s"])
        wp = [p["error_deg"] for p in errors["waypoints"]]
        return {
            "enable_release_to_hold_ms": round((end["t_s"] - t_change) * 1e3, 1),
            "enable_release_to_hold_uncertainty_ms": round(offset_err * 1e3, 1),  # (0 on the lockstep clock)
            "moved_after_release_deg": round(math.degrees(float(np.abs(q[k:k_end] - q[k]).max())), 3),
            "released_at_rad_s": round(float(np.abs(np.asarray(rows["dq_rad_s"])[k]).max()), 3),
            "lease_s": lease["period_s"],
            "lease_lapse_detected_ms": round((lapse_end["t_s"] - last_renewal) * 1e3, 1),
            "lease_lapse_reason": lapse_end["reason"],
            "drag_without_enable_refused": not refused.get("ok") and "enabling switch" in str(refused.get("error")),
            "refusal": refused.get("error"),
            "waypoints": len(waypoints),
            "waypoint_error_deg_max": max(wp) if wp else None,
            "program": str(program),
            "faults": [f["text"] for f in status["faults"]],
            "cycles": status["cycles"],
            "clock": "lockstep" if lockstep else "wall",
            "mcap": str(mcap),
        }
    except ProcessError as exc:
        raise ButtonsDemoError(str(exc)) from None
    finally:
        rig.close()
