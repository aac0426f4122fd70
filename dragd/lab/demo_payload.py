"""``dragd demo --scenario payload``: the gravity model made wrong on the simulated robot, and dragd's answers to it
(docs/PAYLOAD.md). Processes as in the drag demo (sim + daemon over a real python-can bus); the sim's ``payload``
control command hangs a mass on the flange / takes it off between two physics steps (sim/scenario_payload.py).

1. drag; the scripted operator's hand pulls the arm and lets go (the drag demo's pull and back): guard trips here
   are false trips;
2. a ``PAYLOAD_KG`` tool is hung on the released arm: the runaway guard must hold it (trip time, drift until then);
3. ``payload estimate --apply`` from that hold: the estimated mass, applied to the running law and the params file;
4. drag again (the check before drag must pass now): drift after release;
5. the tool is taken off in drag: the arm rises, the guard holds it.

All figures from the daemon (its encoders, its clock), as on a real robot.
"""

from __future__ import annotations

import math
from datetime import datetime
from pathlib import Path
from typing import Any

import yaml

from dragd.config import default_config_path
from dragd.lab.rig import ProcessError, Rig

PAYLOAD_KG = 2.0
PAYLOAD_COM_M = [0.0, 0.0, 0.05]
HAND_STEPS_RAD = [[0.25, 0.15, -0.20, 0.30, 0.0, 0.0], [-0.25, -0.15, 0.20, -0.30, 0.0, 0.0]]


class PayloadDemoError(RuntimeError):
    pass


def _say(progress: bool, text: str) -> None:
    if progress:
        print(f"demo: {text}", flush=True)


def _max_deg(a: list[float], b: list[float]) -> float:
    return max(abs(math.degrees(x - y)) for x, y in zip(a, b, strict=True))


def _wait_trip(rig: Rig, trips_before: int, timeout_s: float) -> dict[str, Any]:
    got: list[dict[str, Any]] = []

    def tripped() -> bool:
        got[:] = [rig.must("status")]
        return bool(got[0]["guard"]["trips"] > trips_before)

    try:
        rig.wait_for(tripped, timeout_s, "the runaway guard's hold")
    except ProcessError:
        raise PayloadDemoError(f"the runaway guard did not hold the arm within {timeout_s:.0f} s:\n"
                               f"{rig.daemon.tail() if rig.daemon else ''}") from None
    return got[0]


def _rest(rig: Rig, timeout_s: float = 10.0) -> None:
    try:
        rig.wait_for(lambda: max(abs(v) for v in rig.must("status")["dq_rad_s"]) < 0.002, timeout_s, "the arm at rest")
    except ProcessError:
        pass  # (the next step judges the arm as it is)


def _payload_event(rig: Rig, mass_kg: float, what: str) -> dict[str, Any]:
    """Hang/remove the mass; the guard's reaction: trip time from the daemon clock just before, drift until then."""
    st0 = rig.must("status")
    trips, t0, q0 = st0["guard"]["trips"], st0["t_s"], st0["q_rad"]
    rig.sim_call("payload", mass_kg=mass_kg, com_m=PAYLOAD_COM_M)
    st = _wait_trip(rig, trips, 5.0)
    trip = st["guard"]["last_trip"]
    rig.sleep(1.0)
    q_held = rig.must("status")["q_rad"]
    return {"what": what, "guard_trip_ms": round((trip["t_s"] - t0) * 1000.0, 1),
            "drift_before_guard_deg": round(_max_deg(trip["q_rad"], q0), 3),
            "drift_held_deg": round(_max_deg(q_held, q0), 3), "joint": trip["joint"],
            "missing_torque_Nm": trip["residual_Nm"], "guard_payload_kg": trip["payload_kg"]}


def run_payload_demo(config: Path | None = None, out: Path | None = None, progress: bool = True,
                     lockstep: bool = False) -> dict[str, Any]:
    out = Path(out) if out is not None else Path.cwd() / "out"
    out.mkdir(parents=True, exist_ok=True)
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    # a config whose params file receives `payload estimate --apply`
    src = Path(config) if config is not None else default_config_path()
    data = yaml.safe_load(src.read_text())
    if (config is not None and isinstance(data.get("robot", {}).get("urdf"), str)
            and not Path(data["robot"]["urdf"]).is_absolute()):
        cand = src.parent / data["robot"]["urdf"]
        if cand.exists():
            data["robot"]["urdf"] = str(cand.resolve())
    params = out / f"payload-params-{stamp}.yaml"
    data["params"] = str(params)
    params.write_text("version: 1\njoints: {}\n")  # identified values would be here; `--apply` adds `payload:`
    cfg_path = out / f"payload-config-{stamp}.yaml"
    cfg_path.write_text(yaml.safe_dump(data, sort_keys=False))
    mcap = out / f"demo-payload-{stamp}.mcap"
    rig = Rig("demo-payload", config=cfg_path, telemetry=mcap, as_deployed=not lockstep, lockstep=lockstep)
    try:
        _say(progress, f"starting the simulated robot on {rig.bus} and the daemon ...")
        rig.start_sim()
        rig.start_daemon()
        rig.must("start")
        rig.sleep(0.6)
        rig.must("mode", mode="drag")
        rig.sleep(0.5)
        _say(progress, "hand guiding: the operator's hand pulls the arm and lets go, twice ...")
        for i, step in enumerate(HAND_STEPS_RAD):
            rig.sim_call("operator", scenario={"name": f"hand{i}", "segments": [
                {"kind": "hand", "q_rad": step, "relative": True, "stiffness": 60.0, "damping": 12.0, "max_load": 25.0,
                 "duration_s": 3.0}, {"kind": "release", "ramp_down_s": 0.1, "duration_s": 0.3}]})
            rig.sleep(3.5)
        _rest(rig)
        st = rig.must("status")
        false_trips = st["guard"]["trips"]
        if st["mode"] == "fault":
            raise PayloadDemoError("the daemon faulted during hand guiding (not the runaway guard: "
                                   + "; ".join(f["text"] for f in st["faults"][-3:])
                                   + "); on a loaded machine missed cycles lose the drives' heartbeat: rerun it "
                                   "quieter")
        if st["mode"] != "drag":
            rig.must("mode", mode="drag")  # (a false trip held it: counted; drag again for the rest)
            rig.sleep(0.5)
        _say(progress, f"hanging a {PAYLOAD_KG:g} kg tool on the released arm ...")
        hang = _payload_event(rig, PAYLOAD_KG, "hung on")
        _say(progress, f"held after {hang['guard_trip_ms']} ms, {hang['drift_before_guard_deg']} deg; "
                       "payload estimate --apply ...")
        rig.must("mode", mode="hold")
        rig.sleep(0.5)
        est = rig.must("payload", action="estimate", poses=6, apply=True, timeout_s=300.0)
        rig.sleep(1.0)
        _say(progress, f"estimated {est['mass_kg']:.3f} kg; drag again ...")
        rig.must("mode", mode="drag")
        rig.sleep(0.5)
        q0 = rig.must("status")["q_rad"]
        rig.sleep(3.0)
        st = rig.must("status")
        drift_apply = _max_deg(st["q_rad"], q0)
        trips_after_apply = st["guard"]["trips"] - false_trips - 1
        _say(progress, f"drift after apply {drift_apply:.3f} deg; taking the tool off ...")
        removed = _payload_event(rig, 0.0, "taken off")
        rig.must("stop")
        codes = rig.close()
        if codes.get("dragd") != 0:
            raise PayloadDemoError(f"the daemon exited with {codes.get('dragd')} on SIGTERM (expected 0)")
        return {
            "payload_kg_true": PAYLOAD_KG,
            "payload_kg_estimated": est["mass_kg"],
            "payload_estimate_error_pct": round(abs(est["mass_kg"] - PAYLOAD_KG) / PAYLOAD_KG * 100.0, 2),
            "drift_before_guard_deg": hang["drift_before_guard_deg"],
            "guard_trip_ms": hang["guard_trip_ms"],
            "false_trips": false_trips + max(0, trips_after_apply),
            "drift_after_apply_deg": round(drift_apply, 4),
            "hung_on": hang,
            "taken_off": removed,
            "estimate": {k: v for k, v in est.items() if k != "ok"},
            "params": str(params),
            "faults": len(st["faults"]),
            "mcap": str(mcap),
        }
    except ProcessError as exc:
        raise PayloadDemoError(str(exc)) from None
    finally:
        rig.close()
