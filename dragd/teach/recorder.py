"""The daemon-side teach recorder: joint positions at a chosen rate into a preallocated table, and marks.

``add`` runs in the 1 kHz cycle (O(1), no allocation of arrays); everything else runs between cycles.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from dragd.teach.program import Program, Recording, Waypoint, now_iso, save_program


def next_due(t: float, due: float, period: float) -> float:
    """The teach recorder's sampling rule: a sample was taken at ``t`` (the first cycle at or after ``due``); the
    next is due a period later — or a period after ``t`` when the loop stalled past it (no burst to catch up)."""
    due += period
    return t + period if due <= t else due


class TeachRecorder:
    def __init__(self, name: str, program_path: Path, mcap_path: Path | None, joints: list[str], rate_Hz: float,
                 loop_dt: float, max_s: float, t0: float) -> None:
        self.name = name
        self.program_path = Path(program_path)
        self.mcap_path = mcap_path
        self.joints = list(joints)
        self.every = max(1, int(round(1.0 / (rate_Hz * loop_dt))))
        self.rate_Hz = 1.0 / (self.every * loop_dt)
        self.buf = np.zeros((int(max_s * self.rate_Hz) + 2, 1 + len(joints)))
        self.count = 0
        self.dropped = 0
        self.t0 = t0
        self.t_last = t0
        self.period_s = self.every * loop_dt
        self._next_t = t0 - 1e-9
        self.marks: list[dict[str, Any]] = []
        self.created = now_iso()

    def add(self, t: float, q: np.ndarray) -> None:
        """One cycle: keep the position when a sample is due (every 1/rate of the cycle's time; called by the cycle)."""
        self.t_last = t
        if t < self._next_t:
            return
        self._next_t = next_due(t, self._next_t, self.period_s)
        if self.count < self.buf.shape[0]:
            row = self.buf[self.count]
            row[0] = t - self.t0
            row[1:] = q
            self.count += 1
        else:
            self.dropped += 1

    def mark(self, t: float, q: np.ndarray, name: str | None = None) -> dict[str, Any]:
        name = name or f"p{len(self.marks) + 1}"
        if any(m["name"] == name for m in self.marks):
            raise ValueError(f"teach mark: a waypoint named '{name}' exists already in '{self.name}'")
        m = {"name": name, "t_s": round(t - self.t0, 4), "q_rad": [float(x) for x in q]}
        self.marks.append(m)
        return m

    def status(self) -> dict[str, Any]:
        return {"name": self.name, "program": str(self.program_path),
                "mcap": str(self.mcap_path) if self.mcap_path else None, "rate_Hz": self.rate_Hz,
                "samples": self.count, "dropped": self.dropped, "marks": len(self.marks),
                "mark_names": [m["name"] for m in self.marks], "t_s": round(self.t_last - self.t0, 3)}

    def autosave_info(self, robot: str, frame: str, config: str | None) -> dict[str, Any]:
        """What ``teach stop`` would write, for the recording's record_start event: an interrupted session's program
        is rebuilt from its MCAP with it (dragd/teach/recover.py)."""
        return {"name": self.name, "program": str(self.program_path), "joints": self.joints, "t0_s": self.t0,
                "period_s": self.period_s, "capacity_rows": int(self.buf.shape[0]), "created": self.created,
                "robot": robot, "frame": frame, "config": config}

    def snapshot(self) -> dict[str, Any]:
        """Plain data for ``write_program`` (copied: the table is reused by nobody after stop)."""
        return {"name": self.name, "path": str(self.program_path), "joints": self.joints,
                "mcap": self.mcap_path.name if self.mcap_path else None, "rate_Hz": self.rate_Hz,
                "rows": self.buf[:self.count].copy(), "dropped": self.dropped, "marks": list(self.marks),
                "created": self.created, "duration_s": round(self.t_last - self.t0, 4)}


def write_program(snap: dict[str, Any], robot: str, frame: str, config: str | None) -> dict[str, Any]:
    """Build and save the program file from a recorder snapshot (runs in the planner worker)."""
    rows = np.asarray(snap["rows"], dtype=float)
    prog = Program(name=snap["name"], created=snap["created"], robot=robot, frame=frame, joints=snap["joints"],
                   config=config,
                   recording=Recording(mcap=snap["mcap"], rate_Hz=snap["rate_Hz"], duration_s=snap["duration_s"],
                                       samples=len(rows), dropped=snap["dropped"]),
                   waypoints=[Waypoint(**m) for m in snap["marks"]],
                   path=rows.tolist(), notes=dict(snap.get("notes") or {}))
    path = save_program(prog, snap["path"])
    return {"program": str(path), **prog.summary()}
