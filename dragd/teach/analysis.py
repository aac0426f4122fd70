"""How well a replay went, from the daemon's own telemetry (encoders, the reference it commanded).

* waypoint error: how close the arm came to the taught position while the reference was at it (a stop: the
  move's end and the settle dwell) or passed it (circle, spline: within ``window_s``) — "passed within" — per joint;
  the figure is the max over joints (and over the passes, with several cycles). For stops also ``settled_deg``:
  the distance at the end of the dwell.
* path error: the distance of every actual sample from the reference *path* (the nearest reference sample
  within ``window_s`` in trajectory time), max over joints — a contour error, without the lag along the path.
* tracking error: |q − q_ref| at the same instant, max over joints (includes the lag along the path).

Only cycles with every joint's position fresh (TPDOs received that cycle) count: a stale position is the daemon's
old view, not where the arm is. The rows come from dragd.telemetry.reader.read_rows.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np


def _rows_between(rows: dict[str, np.ndarray], t0: float, t1: float) -> dict[str, np.ndarray]:
    m = (rows["t_s"] >= t0) & (rows["t_s"] <= t1) & (rows["mode"] == "track")
    if "rx" in rows:
        m &= np.asarray(rows["rx"], dtype=bool).reshape(len(m), -1).all(axis=1)
    return {k: v[m] for k, v in rows.items()}


def _passes(track_t: np.ndarray, t_mark: float, window_s: float) -> list[np.ndarray]:
    """Index groups of the rows within ±window of each time the trajectory clock passes ``t_mark``."""
    near = np.abs(track_t - t_mark) <= window_s
    idx = np.flatnonzero(near)
    if len(idx) == 0:
        return []
    splits = np.flatnonzero(np.diff(idx) > 1) + 1
    return np.split(idx, splits)


def replay_errors(rows: dict[str, np.ndarray], t0: float, t1: float, marks: list[dict[str, Any]],
                  waypoints: dict[str, list[float]], body_start_s: float = 0.0,
                  window_s: float = 0.3) -> dict[str, Any]:
    """Waypoint, path and tracking errors [deg] of the replay the daemon ran between daemon times t0 and t1."""
    r = _rows_between(rows, t0, t1)
    if len(r["t_s"]) == 0:
        raise ValueError("replay_errors: no TRACK rows in the window")
    q = np.asarray(r["q_rad"], dtype=float)
    ref = np.asarray(r["q_ref_rad"], dtype=float)
    tt = np.asarray(r["track_t_s"], dtype=float)
    per_wp = []
    for m in marks:
        name = m["name"]
        if name not in waypoints:
            continue
        wq = np.asarray(waypoints[name], dtype=float)
        worst = None
        settled = None
        for g in _passes(tt, m["t_s"], window_s):
            if m["kind"] == "stop":
                g = g[tt[g] <= m["t_s"] + 1e-9]  # the reference is at the waypoint: the end of the move, the dwell
                if len(g) == 0:
                    continue
                s = np.abs(q[g[-1]] - wq)  # at the end of the dwell
                if settled is None or s.max() > settled.max():
                    settled = s
            d = np.abs(q[g] - wq).max(axis=1)
            err = np.abs(q[g[int(np.argmin(d))]] - wq)  # the closest approach
            if worst is None or err.max() > worst.max():
                worst = err
        if worst is not None:
            entry = {"name": name, "kind": m["kind"], "t_s": m["t_s"],
                     "error_deg": round(math.degrees(float(worst.max())), 4),
                     "per_joint_deg": [round(math.degrees(float(x)), 4) for x in worst]}
            if settled is not None:
                entry["settled_deg"] = round(math.degrees(float(settled.max())), 4)
            per_wp.append(entry)
    body = tt >= body_start_s
    track_err = np.abs(q - ref).max(axis=1)
    # contour error: nearest reference sample within ±window in trajectory time (body only)
    qb, rb, tb = q[body], ref[body], tt[body]
    path_err = np.zeros(len(qb))
    w = max(1, int(window_s / max(np.median(np.diff(r["t_s"])) if len(r["t_s"]) > 1 else 1e-3, 1e-4)))
    for i0 in range(0, len(qb), 512):
        i1 = min(len(qb), i0 + 512)
        lo, hi = max(0, i0 - w), min(len(qb), i1 + w)
        d = np.abs(qb[i0:i1, None, :] - rb[None, lo:hi, :]).max(axis=2)
        # only reference samples close in trajectory time (a closed path passes the same place twice)
        d[np.abs(tb[i0:i1, None] - tb[None, lo:hi]) > window_s] = np.inf
        path_err[i0:i1] = d.min(axis=1)
    return {
        "waypoints": per_wp,
        "waypoint_error_deg_max": max((p["error_deg"] for p in per_wp), default=None),
        "path_error_deg_max": round(math.degrees(float(path_err.max())), 4) if len(path_err) else None,
        "tracking_error_deg_max": round(math.degrees(float(track_err.max())), 4),
        "rows": int(len(q)),
    }
