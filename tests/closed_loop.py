"""The real daemon (in process, tests/inproc.py) on the simulated arm's physics (sim/physics.py), cycle by cycle.

No bus, no processes, no wall clock: every 1 ms cycle the daemon reads the physics' positions and Hall currents
and its current command becomes the drives' current demand (the drive's current loop and 402 machine are the
sim's business; here the power stage is on and brakes off while the daemon's drives are enabled). Deterministic,
so the runaway guard's unit tests can run the scripted operator's hand and a hung-on mass in closed loop.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from dragd.config import Config, load_config
from dragd.control.modes import Mode
from sim.axis import AxisIO
from sim.operator import Operator
from sim.physics import ArmPhysics
from sim.scenario_payload import set_flange_payload
from sim.truth import Truth, load_truth
from tests.inproc import InProcess


class ClosedLoop:
    def __init__(self, cfg: Config | None = None, truth: Truth | None = None, wrong_sign: tuple[int, ...] = (),
                 loaded_host: int | None = None) -> None:
        """``wrong_sign``: joints whose configured direction is wrong (the drive's counts and current, as the
        daemon decodes them, are the physics' negated). ``loaded_host`` (an RNG seed): the timing of a loaded
        2-core host as measured on the rig (session notes in git): 15 % of cycles late by 1–2 periods (the physics runs
        on with the old command), 20 % of position samples repeated from the cycle before (the drive's TPDO lags)."""
        self.cfg = cfg or load_config()
        self.truth = truth or load_truth()
        self.robot = self.truth.load_model()
        self.axes = [AxisIO() for _ in self.truth.joints]
        self.phys = ArmPhysics(self.truth, self.robot, self.axes)
        self.sub = self.truth.physics_rate_Hz // 1000
        self.ip = InProcess(self.cfg)
        self.d, self.c = self.ip.d, self.ip.c
        self.q_log: list[np.ndarray] = []
        self.flip = np.ones(len(self.axes))
        self.flip[list(wrong_sign)] = -1.0
        self.rng = np.random.default_rng(loaded_host) if loaded_host is not None else None
        self._q_sent = self.phys.q_rad.copy()

    @property
    def t(self) -> float:
        return self.phys.t_s

    def cycle(self) -> None:
        ip, ph = self.ip, self.phys
        ticks = 1
        if self.rng is not None:
            if self.rng.random() < 0.15:  # the loop was parked: the physics ran on with the last command
                ticks = int(self.rng.integers(2, 4))
                for _ in range(self.sub * (ticks - 1)):
                    ph.step()
            if self.rng.random() >= 0.2:  # else the drive's sample is the one before (repeated)
                self._q_sent = ph.q_rad.copy()
        else:
            self._q_sent = ph.q_rad
        ip.feed(self._q_sent * self.flip, ph.current_measured_A * self.flip)
        ip.cycle(ticks)
        cmd = ip.torque_offset_A() * self.flip
        on = self.c.mode not in (Mode.IDLE, Mode.FAULT)
        for k, ax in enumerate(self.axes):
            ax.power_stage_on = on
            ax.brake_engaged = not on
            ax.current_demand_A = float(cmd[k]) if on else 0.0
        for _ in range(self.sub):
            ph.step()

    def run(self, seconds: float) -> None:
        for _ in range(int(round(seconds * 1000))):
            self.cycle()
            self.q_log.append(self.phys.q_rad.copy())

    def start(self, settle_s: float = 0.5) -> None:
        self.ip.hold(self.phys.q_rad * self.flip)
        self.run(settle_s)

    def mode(self, name: str, accept: bool = False) -> Any:
        return self.d.set_mode(name, accept=accept)

    def operator(self, scenario: dict[str, Any]) -> Operator:
        op = Operator(scenario, self.phys.model, start_t_s=self.phys.t_s)
        self.phys.operator = op
        return op

    def hang(self, mass_kg: float, com_m: Any = (0.0, 0.0, 0.0)) -> None:
        set_flange_payload(self.phys, mass_kg, com_m)

    def runaway_stops(self) -> list[dict[str, Any]]:
        return [f for f in self.d.faults if f.get("kind") == "runaway"]


def payload_scenario() -> dict[str, Any]:
    """The payload scenario's figures in the closed loop (deterministic; the rig version: dragd demo --scenario
    payload): hand guiding (false trips), 2 kg hung on (trip, drift), estimate --apply, drag (drift), taken off."""
    import asyncio

    steps = [[0.25, 0.15, -0.20, 0.30, 0.0, 0.0], [-0.25, -0.15, 0.20, -0.30, 0.0, 0.0]]
    cl = ClosedLoop()
    cl.start(0.6)
    cl.mode("drag")
    cl.run(0.5)
    for st in steps:
        cl.operator({"name": "hand", "segments": [
            {"kind": "hand", "q_rad": st, "relative": True, "stiffness": 60.0, "damping": 12.0, "max_load": 25.0,
             "duration_s": 3.0}, {"kind": "release", "ramp_down_s": 0.1, "duration_s": 0.3}]})
        cl.run(4.0)
    false_trips = cl.c.guard_trips

    def event(kg: float) -> dict[str, Any]:
        q0, t0, n0 = cl.phys.q_rad.copy(), cl.t, cl.c.guard_trips
        cl.hang(kg, (0.0, 0.0, 0.05))
        drift = 0.0
        while cl.c.guard_trips == n0 and cl.t - t0 < 5.0:
            cl.cycle()
            drift = max(drift, float(np.degrees(np.abs(cl.phys.q_rad - q0)).max()))
        trip_ms = (cl.t - t0) * 1000.0
        cl.run(1.0)
        return {"guard_trip_ms": round(trip_ms, 1), "drift_before_guard_deg": round(drift, 3),
                "drift_held_deg": round(float(np.degrees(np.abs(cl.phys.q_rad - q0)).max()), 3),
                "stop": cl.runaway_stops()[-1]["text"] if cl.runaway_stops() else None}

    hung = event(2.0)
    cl.mode("hold")
    cl.run(0.5)

    async def est() -> dict[str, Any]:
        task = asyncio.ensure_future(cl.d.payload.estimate(6, apply=True))
        while not task.done():
            cl.cycle()
            await asyncio.sleep(0)
        return task.result()

    e = asyncio.run(est())
    cl.run(1.2)
    cl.mode("drag")
    q0 = cl.phys.q_rad.copy()
    cl.run(3.0)
    drift_apply = float(np.degrees(np.abs(cl.phys.q_rad - q0)).max())
    trips_apply = cl.c.guard_trips - false_trips - 1
    removed = event(0.0)
    return {"payload_kg_true": 2.0, "payload_kg_estimated": e["mass_kg"],
            "drift_before_guard_deg": hung["drift_before_guard_deg"], "guard_trip_ms": hung["guard_trip_ms"],
            "false_trips": false_trips + trips_apply, "drift_after_apply_deg": round(drift_apply, 4),
            "hung_on": hung, "taken_off": removed, "estimate": e}


if __name__ == "__main__":
    import json

    print(json.dumps(payload_scenario()))
