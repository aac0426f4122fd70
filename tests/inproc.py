"""A daemon in this process, cycle by cycle, without a bus or real time (deterministic unit-level tests).

``InProcess`` builds the real ``Daemon`` on frame sinks instead of buses and drives its cycle the way
``Cycle.run`` does (tick → read → step → log), with the feedback written straight into the read step's arrays.
The drives' CST ↔ CSP switch (an SDO exchange on a real bus) completes at once and is recorded.
"""

from __future__ import annotations

import asyncio
import math
from typing import Any

import numpy as np

from dragd.config import Config
from dragd.daemon.core import Daemon

ENABLED = 0x0027  # statusword: operation enabled


class _Sink:
    def __init__(self) -> None:
        self.frames: list[Any] = []

    def send(self, msg: Any, timeout: float | None = None) -> None:
        self.frames.append(msg)


class InProcess:
    def __init__(self, cfg: Config, lab_unguarded_drag: bool = True) -> None:
        """``lab_unguarded_drag``: as a lab's daemon runs (drag needs no lease); False: as ``drag.require`` says."""
        d = self.d = Daemon(cfg, socket_path="/nonexistent/dragd.sock", log=lambda msg: None,
                            lab_unguarded_drag=lab_unguarded_drag)
        d.attach({name: _Sink() for name in d.layouts})  # type: ignore[misc]
        self.c, self.cy, self.m = d.controller, d.cycle, d.motions
        self.fb = d.io.feedback
        self.switches: list[int] = []

        async def switch(mode: int) -> None:
            self.switches.append(int(mode))
            self.m._set_drive_mode(mode)

        self.m.switch_drive_mode = switch  # type: ignore[method-assign]
        self.fb.statusword[:] = ENABLED
        self.scaling = d.scaling

    def counts(self, q: np.ndarray) -> np.ndarray:
        s = self.scaling
        return np.rint(np.asarray(q) * s.counts_per_rev / (2 * math.pi) * s.direction).astype(np.int64) + s.offset_counts

    def feed(self, q: np.ndarray, current_A: np.ndarray | None = None) -> None:
        """What the drives report this cycle: positions [rad] and currents [A]."""
        self.fb.counts[:] = self.counts(q)
        if current_A is not None:
            self.fb.current_permille[:] = np.asarray(current_A) * self.scaling.permille_per_A

    def target_rad(self) -> np.ndarray:
        """The CSP target the last cycle sent [rad]."""
        s = self.scaling
        return (self.cy.target_counts - s.offset_counts) * s.rad_per_count

    def torque_offset_A(self) -> np.ndarray:
        return self.cy.torque_permille * self.scaling.A_per_permille

    def cycle(self, ticks: int = 1) -> None:
        """One cycle, ``ticks`` periods after the previous one (a stalled loop misses the ones between)."""
        cy, io = self.cy, self.d.io
        cy.tick(cy.dt * ticks * 1e6, ticks)
        io.begin_cycle()
        self.fb.rx[:] = True
        self.fb.rx_count = self.fb.rx.shape[0]
        complete = io.end_read()
        if cy.step(complete):
            cy.cycles += 1
            for fn in cy.after_cycle:
                fn()  # type: ignore[operator]

    def hold(self, q: np.ndarray) -> None:
        """Start enabled, holding ``q`` (the drives already in operation enabled)."""
        self.feed(q)
        self.cycle()
        self.d.start()
        self.cycle()

    async def settle_tasks(self) -> None:
        """Let tasks the daemon scheduled (the drives' return to CST) run."""
        for _ in range(3):
            await asyncio.sleep(0)
