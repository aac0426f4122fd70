"""What a client that follows the arm polls: ``state`` (the joints, small and cheap, for 100+ Hz), ``events`` (every
event the daemon records, numbered, from any point on) and ``robot`` (names, limits and the URDF, once).

`EventLog` is the one path of events to clients: whatever the daemon records as a telemetry event (mode changes,
faults, protective stops of the guard and the monitors, motions' ends, streams, teach marks, and the kinds later
issues add) is numbered here too, so a client (the ROS 2 bridge) passes new kinds on without knowing them.
"""

from __future__ import annotations

from collections import deque
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from dragd.control.modes import MODE_NAMES

if TYPE_CHECKING:
    from dragd.daemon.core import Daemon

EVENTS_KEPT = 512  # the newest events kept for clients (older ones count as lost to a client that asks for them)


class EventLog:
    """The newest ``EVENTS_KEPT`` events, numbered from 1: ``{"seq", "t_s", "name", **fields}``."""

    def __init__(self, keep: int = EVENTS_KEPT) -> None:
        self.seq = 0  # the newest event's number (0: none yet)
        self._events: deque[dict[str, Any]] = deque(maxlen=keep)

    def add(self, t_s: float, name: str, fields: dict[str, Any]) -> None:
        self.seq += 1
        self._events.append({"seq": self.seq, "t_s": round(float(t_s), 4), "name": name, **fields})

    def since(self, since: int) -> tuple[list[dict[str, Any]], int]:
        """Events numbered above ``since`` still kept, oldest first; and how many of those were dropped."""
        kept = [e for e in self._events if e["seq"] > since]
        first = kept[0]["seq"] if kept else self.seq + 1
        return kept, max(0, first - since - 1)


def state(d: Daemon) -> dict[str, Any]:
    """The ``state`` command: the cycle's time, mode and joints, the effort K_t·I, what changed since (counters)."""
    c, cy = d.controller, d.cycle
    est = cy.est
    return {"t_s": cy.t, "cycles": cy.cycles, "mode": MODE_NAMES[c.mode],
            # what the operator asked for (a feedback hold shows hold, then returns to it by itself)
            "requested_mode": MODE_NAMES[c.resume_mode if c.feedback_hold else c.mode],
            "drives_enabled": d.supervisor.all_enabled,
            "q_rad": est.q_rad.tolist(), "dq_rad_s": est.dq_rad_s.tolist(), "current_A": est.current_A.tolist(),
            # the joint torque the drives' measured current gives through the model's torque constants
            "effort_Nm": (est.current_A * c.kt).tolist(), "command_A": c.cmd_A.tolist(),
            "fault_count": d.fault_count, "event_seq": d.recorder.events.seq, "stream": d.streams.status()}


def events(d: Daemon, since: int) -> dict[str, Any]:
    if since < 0:
        raise ValueError(f"since: expected an event number >= 0, got {since}")
    got, lost = d.recorder.events.since(since)
    return {"event_seq": d.recorder.events.seq, "events": got, "lost": lost}


def robot(d: Daemon) -> dict[str, Any]:
    """The ``robot`` command: joint names (the URDF's), limits, torque constants, loop and stream settings, the URDF."""
    cfg, c = d.cfg, d.controller
    urdf = d.model.urdf_path
    text = Path(urdf).read_text(encoding="utf-8") if urdf is not None else None
    return {"joint_names": list(cfg.joint_names), "urdf_path": str(urdf) if urdf is not None else None, "urdf": text,
            "rate_Hz": cfg.loop.rate_Hz,
            "position_limits_rad": np.column_stack([c.safety.lim_lo_rad, c.safety.lim_hi_rad]).tolist(),
            "velocity_limits_rad_s": [j.velocity_limit_rad_s for j in cfg.joints],
            "current_limit_A": c.params.current_limit_A.tolist(), "kt_Nm_per_A": c.kt.tolist(),
            "stream": cfg.stream.model_dump(), "program_dir": str(cfg.program_dir)}
