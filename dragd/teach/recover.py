"""A teach session the daemon did not finish (killed, power lost, crashed): its program from the raw MCAP.

While teaching, the daemon records every cycle to ``NAME.mcap`` beside the program and writes each waypoint into it
as a ``mark`` event; the writer thread flushes complete chunks to the file as it goes (dragd/telemetry/writer.py), so
the recording *is* the autosave: a session cut short leaves ``NAME.mcap`` without ``NAME.yaml``. Its teach_start
event carries what ``teach stop`` would have written (name, rate, start time, robot, frame, config): ``recover``
rebuilds the program from the file's complete part with the recorder's own sampling rule. docs/TEACH.md.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from dragd.teach.program import ProgramError, check_name


def teach_info(mcap: str | Path) -> dict[str, Any]:
    """The session's parameters from its teach_start event; ProgramError when the file is not a teach recording."""
    from dragd.telemetry.reader import TelemetryFileError, read_events

    try:
        starts = read_events(mcap, "teach_start")
    except TelemetryFileError as exc:
        raise ProgramError(str(exc)) from None
    session = starts[0].fields.get("session") if starts else None
    if not isinstance(session, dict):
        raise ProgramError(f"{mcap}: not a teach recording (no teach_start event with the session: recorded by "
                           "'dragd identify run' or 'record', or by an older dragd)")
    return dict(session)


def sample_rows(t_s: np.ndarray, period_s: float, t0_s: float) -> np.ndarray:
    """Indices of the rows the teach recorder keeps: the first cycle at or after each due time (missed cycles do not
    make bursts), as ``TeachRecorder.add``."""
    from dragd.teach.recorder import next_due

    keep = []
    due = t0_s - 1e-9  # (as the recorder starts)
    for k, t in enumerate(t_s.tolist()):
        if t >= due:
            keep.append(k)
            due = next_due(t, due, period_s)
    return np.asarray(keep, dtype=int)


def recover(mcap: str | Path, out: str | Path | None = None, overwrite: bool = False) -> dict[str, Any]:
    """Write the program of an interrupted teach session from ``mcap``; returns the program's summary."""
    from dragd.teach.recorder import write_program
    from dragd.telemetry.reader import TelemetryFileError, read_events, read_log

    mcap = Path(mcap)
    if not mcap.is_file():
        raise ProgramError(f"{mcap}: no such teach recording")
    info = teach_info(mcap)
    target = Path(out) if out is not None else mcap.with_suffix(".yaml")
    if target.exists() and not overwrite:
        raise ProgramError(f"{target}: exists (the session was finished, or recovered before); choose --out or "
                           "--overwrite")
    try:
        check_name(str(info["name"]))
        log = read_log(mcap, ["t_s", "q_rad"])
        marks = read_events(mcap, "mark")
        period, t0, cap = float(info["period_s"]), float(info["t0_s"]), int(info["capacity_rows"])
        joints = [str(j) for j in info["joints"]]
    except TelemetryFileError as exc:
        raise ProgramError(str(exc)) from None
    except (KeyError, TypeError, ValueError) as exc:
        raise ProgramError(f"{mcap}: teach_start event: expected name, period_s, t0_s, capacity_rows, joints "
                           f"({exc})") from None
    if log.n_rows == 0:
        raise ProgramError(f"{mcap}: no complete cycle row to recover (the session ended before its first chunk)")
    t, q = np.asarray(log.rows["t_s"], dtype=float), np.asarray(log.rows["q_rad"], dtype=float)
    if q.ndim != 2 or q.shape[1] != len(joints):
        raise ProgramError(f"{mcap}: q_rad has {q.shape[1] if q.ndim == 2 else 1} columns, the session's joints "
                           f"{len(joints)}")
    keep = sample_rows(t, period, t0)
    rows = np.column_stack([t[keep] - t0, q[keep]])
    snap = {"name": str(info["name"]), "path": str(target), "joints": joints, "mcap": mcap.name,
            "rate_Hz": 1.0 / period, "rows": rows[:cap], "dropped": max(0, len(rows) - cap),
            "marks": [{"name": str(e.fields["waypoint"]), "t_s": float(e.fields["t_s"]),
                       "q_rad": [float(x) for x in e.fields["q_rad"]]} for e in marks if "waypoint" in e.fields],
            "created": str(info.get("created", "")), "duration_s": round(float(t[-1] - t0), 4),
            "notes": {"recovered": f"from {mcap.name}, an interrupted teach session ("
                                   + ("its recording truncated at the last complete chunk" if log.truncated
                                      else "its recording complete") + ")"}}
    return {**write_program(snap, str(info.get("robot", "seed_cobot")), str(info.get("frame", "tool0")),
                            info.get("config")), "truncated": log.truncated}
