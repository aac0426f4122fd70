"""Rerun views of the arm: a recorded telemetry MCAP (``dragd log view``) and the running daemon (``dragd view``).

Both feed `RerunSink` (dragd/telemetry/sinks.py): the arm in 3D from the URDF at the measured pose, per-joint
currents and their components, the mode and the faults on a timeline.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from dragd.telemetry.layout import RowLayout
from dragd.telemetry.schema import cycle_layout
from dragd.telemetry.sinks import RerunSink

__all__ = ["log_to_rerun", "live_to_rerun", "STATUS_FIELDS"]


def _rows_of(log: Any, lay: RowLayout) -> np.ndarray:
    n = log.n_rows
    rows = np.full((n, lay.width), np.nan)
    for c in lay.columns:
        if c.name not in log.rows:
            continue
        v = log.rows[c.name]
        if c.labels is not None:
            inv = {label: k for k, label in c.labels.items()}
            v = np.array([inv.get(str(x), -1) for x in np.asarray(v).reshape(-1)], dtype=float)
        rows[:, c.offset:c.offset + c.width] = np.asarray(v, dtype=float).reshape(n, c.width)
    return rows


def log_to_rerun(path: str | os.PathLike[str], sink_factory: Callable[[Sequence[str]], RerunSink],
                 default_joints: Sequence[str]) -> dict[str, Any]:
    """Send a telemetry MCAP's cycle rows and events to a `RerunSink`; returns counts."""
    from dragd.telemetry.reader import read_log

    log = read_log(path)
    if log.n_rows == 0:
        raise ValueError(f"{path}: no /dragd/cycle rows")
    width = np.asarray(log.rows["q_rad"]).reshape(log.n_rows, -1).shape[1]
    joints = next((e.fields.get("joints") for e in log.events if e.name in ("start", "record_start")
                   and isinstance(e.fields.get("joints"), list)), None) or list(default_joints)[:width]
    if len(joints) != width:
        joints = [f"joint{j + 1}" for j in range(width)]
    lay = RowLayout(cycle_layout(width))
    rows = _rows_of(log, lay)
    t_ns = np.asarray(log.rows["log_time_ns"], dtype=np.int64) if "log_time_ns" in log.rows else None
    if t_ns is None:  # the cycle's own clock, anchored at the first event (or 0)
        t0 = log.events[0].time_ns if log.events else 0
        t_s = rows[:, lay.slices["t_s"].start]
        t_ns = t0 + np.round((t_s - t_s[0]) * 1e9).astype(np.int64)
    sink = sink_factory(joints)
    events = sorted(log.events, key=lambda e: e.time_ns)
    k = 0
    step = 5000
    for start in range(0, len(rows), step):
        end = min(len(rows), start + step)
        while k < len(events) and events[k].time_ns <= t_ns[end - 1]:
            sink.write_event(events[k].time_ns, events[k].name, events[k].fields)
            k += 1
        sink.write_rows(lay, rows[start:end], t_ns[start:end])
    for e in events[k:]:
        sink.write_event(e.time_ns, e.name, e.fields)
    sink.close()
    return {"rows": int(log.n_rows), "events": len(events), "joints": joints, "truncated": log.truncated}


STATUS_FIELDS = ("q_rad", "dq_rad_s", "current_A", "command_A")


def _hand_key(st: dict[str, Any]) -> Any:
    """What of the hand guiding state is worth a new sample (its inputs, the lease's state, the refusal)."""
    lease = st.get("lease") or {}
    return (repr(st.get("inputs")), lease.get("state"), lease.get("id"), st.get("refusal"), st.get("mode"))


def live_to_rerun(call: Callable[[], dict[str, Any]], sink: RerunSink, n: int, rate_Hz: float,
                  seconds: float | None, on_poll: Callable[[dict[str, Any]], None] | None = None) -> dict[str, Any]:
    """Poll the daemon's ``status`` at ``rate_Hz`` and send it to ``sink`` until ``seconds`` (None: Ctrl-C).
    ``on_poll(status)`` after each poll (``dragd view --drag`` renews its lease there)."""
    from dragd.control.modes import MODE_NAMES

    lay = RowLayout(cycle_layout(n))
    inv = {name: int(m) for m, name in MODE_NAMES.items()}
    seen_faults = 0
    last_mode = None
    last_hand = None
    polls = 0
    period = 1.0 / rate_Hz
    end = None if seconds is None else time.monotonic() + seconds
    next_t = time.monotonic()
    row = np.zeros((1, lay.width))
    try:
        while end is None or time.monotonic() < end:
            st = call()
            if not st.get("ok"):
                raise RuntimeError(f"status: {st.get('error')}")
            t_ns = time.time_ns()
            row[:] = 0.0
            row[0, lay.slices["t_s"]] = st.get("t_s") or 0.0
            row[0, lay.slices["mode"]] = inv.get(str(st.get("mode")), -1)
            for src, dst in (("q_rad", "q_rad"), ("dq_rad_s", "dq_rad_s"), ("current_A", "current_measured_A"),
                             ("command_A", "current_command_A")):
                row[0, lay.slices[dst]] = st[src]
            for name, value in (st.get("components_A") or {}).items():
                if name in lay.slices:
                    row[0, lay.slices[name]] = value
            if st.get("mode") != last_mode:
                sink.write_event(t_ns, "mode", {"mode": st.get("mode"), "previous": last_mode})
                last_mode = st.get("mode")
            faults = st.get("faults") or []
            for f in faults[seen_faults:]:
                sink.write_event(t_ns, "fault", f)
            seen_faults = len(faults)
            hand = st.get("drag")
            leased = (hand or {}).get("lease", {}).get("state") == "active"
            if hand is not None and (leased or _hand_key(hand) != last_hand):
                sink.write_event(t_ns, "hand", hand)  # the inputs and the lease (every poll while a lease runs)
                last_hand = _hand_key(hand)
            sink.write_rows(lay, row, np.array([t_ns], dtype=np.int64))
            if on_poll is not None:
                on_poll(st)
            polls += 1
            next_t += period
            time.sleep(max(0.0, next_t - time.monotonic()))
    except KeyboardInterrupt:
        pass
    finally:
        sink.close()
    return {"polls": polls}
