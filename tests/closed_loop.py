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
    def __init__(self, cfg: Config | None = None, truth: Truth | None = None, wrong_sign: tuple[int, ...] = ()) -> None:
        """``wrong_sign``: joints whose configured direction is wrong (the drive's counts and current, as the
        daemon decodes them, are the physics' negated)."""
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

    @property
    def t(self) -> float:
        return self.phys.t_s

    def cycle(self) -> None:
        ip, ph = self.ip, self.phys
        ip.feed(ph.q_rad * self.flip, ph.current_measured_A * self.flip)
        ip.cycle()
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
