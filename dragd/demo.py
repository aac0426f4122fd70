"""``dragd demo``: the simulated robot and the daemon as separate processes, a scripted drag, an MCAP log.

Scenario ``drag``: enable (hold) → drag mode → nobody touches the arm (it must not move) → the scripted
operator's hand pulls joints 1–4 to a new pose and lets go → the arm stays where it was released.
All figures come from the daemon (its encoders and timing), as they would on a real robot.
"""

from __future__ import annotations

import math
import time
from datetime import datetime
from pathlib import Path
from typing import Any

from .procs import REPO, ProcessError, Rig


class DemoError(RuntimeError):
    """The demo could not run; the message says which step and carries the process output."""


HAND_TARGET_RAD = [0.25, 0.15, -0.20, 0.30, 0.0, 0.0]  # relative joint-space pull of the operator's hand


def _say(progress: bool, text: str) -> None:
    if progress:
        print(f"demo: {text}", flush=True)


def _max_deg(a: list[float], b: list[float]) -> float:
    return max(abs(math.degrees(x - y)) for x, y in zip(a, b))


def run_demo(seconds: float = 20.0, config: Path | None = None, out: Path | None = None, scenario: str = "drag",
             progress: bool = True) -> dict[str, Any]:
    if scenario != "drag":
        raise DemoError(f"--scenario: expected 'drag', got '{scenario}'")
    if not seconds >= 8.0:
        raise DemoError(f"--seconds: expected at least 8 s (hold, untouched drag, hand pull, release), got {seconds}")
    out = Path(out) if out is not None else REPO / "out"
    out.mkdir(parents=True, exist_ok=True)
    mcap = out / f"demo-{datetime.now().strftime('%Y%m%d-%H%M%S')}.mcap"
    rig = Rig("demo", config=config, telemetry=mcap)
    try:
        _say(progress, f"starting the simulated robot on {rig.bus} ...")
        rig.start_sim()
        _say(progress, "starting the daemon (NMT reset, SDO configuration, 402 walk) ...")
        rig.start_daemon()
        rig.must("start")
        time.sleep(0.5)
        rig.must("mode", mode="drag")
        _say(progress, "drag mode; nobody touching the arm ...")
        untouched_s = 2.0
        q0 = rig.must("status")["q_rad"]
        time.sleep(untouched_s)
        q1 = rig.must("status")["q_rad"]
        hand_s = 3.0
        _say(progress, "the operator's hand pulls joints 1-4, then lets go ...")
        rig.sim_call("operator", scenario={"name": "demo_hand", "segments": [
            {"kind": "hand", "q_rad": HAND_TARGET_RAD, "relative": True, "stiffness": 60.0, "damping": 12.0,
             "max_load": 25.0, "duration_s": hand_s},
            {"kind": "release", "ramp_down_s": 0.1, "duration_s": 0.0}]})
        time.sleep(hand_s + 0.1)
        settle_s = 0.5
        time.sleep(settle_s)
        q_release = rig.must("status")["q_rad"]
        observe_s = max(2.0, seconds - untouched_s - hand_s - settle_s - 0.6)
        time.sleep(observe_s)
        status = rig.must("status")
        q_end = status["q_rad"]
        _say(progress, "stopping: ramp to hold, disable, SIGTERM ...")
        rig.must("stop")
        codes = rig.close()
        if codes.get("dragd") != 0:
            raise DemoError(f"the daemon exited with {codes.get('dragd')} on SIGTERM (expected 0):\n{rig.daemon.tail()}")
        return {
            "cycles": status["cycles"],
            "period_p50_us": status["period_p50_us"],
            "period_p99_us": status["period_p99_us"],
            "missed_cycles": status["missed_cycles"],
            "drift_untouched_deg": round(_max_deg(q1, q0), 4),
            "moved_by_hand_deg": round(_max_deg(q_release, q1), 3),
            "drift_after_release_deg": round(_max_deg(q_end, q_release), 4),
            "observed_after_release_s": round(observe_s, 1),
            "bus_load_pct": max(status["bus_load_pct"].values()),
            "faults": len(status["faults"]),
            "mcap": str(mcap),
        }
    except ProcessError as exc:
        raise DemoError(str(exc)) from None
    finally:
        rig.close()
