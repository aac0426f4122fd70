"""Detector events against contact labels: hits, misses, false alarms, delays (docs/CONTACT.md).

An event *hits* a contact when it starts within [contact start − ``tol_s``, contact end + ``tol_s``]; the first such
event is the contact's detection, its delay the event's start − the contact's onset (where the labels' deviation
first reaches their level). Any event that starts within no contact's window is a *false alarm* — wherever it ends,
so an alarm raised in a post-release tail counts, and one that began in a contact and outlived it does not.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

TOL_S = 0.2
MIN_PEAK_A = 1.0  # contacts at least this large must be found


def score(contacts: list[Any], events: list[tuple[float, float, list[str]]], tol_s: float = TOL_S,
          min_peak_A: float = MIN_PEAK_A) -> dict[str, Any]:
    """``events``: (start, end, joints), times from the log's first sample like the contacts'."""
    used: set[int] = set()
    rows = []
    for c in contacts:
        lo, hi = c.t_start_s - tol_s, c.t_end_s + tol_s
        found = [i for i, (a, _, _) in enumerate(events) if lo <= a <= hi]
        used.update(found)
        row: dict[str, Any] = {"t_start_s": round(c.t_start_s, 3), "t_onset_s": round(c.t_onset_s, 3),
                               "t_end_s": round(c.t_end_s, 3), "peak_A": round(c.peak_A, 3), "impact": c.impact,
                               "required": c.peak_A >= min_peak_A}
        if found:
            a, b, js = events[found[0]]
            row.update({"found": True, "delay_ms": round((a - c.t_onset_s) * 1e3, 1),
                        "delay_from_edge_ms": round((a - c.t_start_s) * 1e3, 1), "event_s": [round(a, 3),
                                                                                                  round(b, 3)],
                        "joints": js, "events_in_window": len(found)})
        else:
            row.update({"found": False, "delay_ms": None, "delay_from_edge_ms": None})
        rows.append(row)
    fa = [{"t_start_s": round(a, 3), "t_end_s": round(b, 3), "joints": js}
          for i, (a, b, js) in enumerate(events) if i not in used]
    req = [r for r in rows if r["required"]]
    delays = [r["delay_ms"] for r in req if r["found"] and r["impact"]]
    edge = [r["delay_from_edge_ms"] for r in req if r["found"] and r["impact"]]
    return {"contacts": rows, "false_alarms": fa, "found": sum(r["found"] for r in rows), "total": len(rows),
            "required_found": sum(r["found"] for r in req), "required": len(req),
            "impact_delays_ms": delays,
            "median_impact_delay_ms": None if not delays else round(float(np.median(delays)), 1),
            "median_impact_delay_from_edge_ms": None if not edge else round(float(np.median(edge)), 1)}


def combine(parts: list[dict[str, Any]]) -> dict[str, Any]:
    """Totals over several logs' scores."""
    delays = [d for p in parts for d in p["impact_delays_ms"]]
    edge = [r["delay_from_edge_ms"] for p in parts for r in p["contacts"]
            if r["found"] and r["required"] and r["impact"]]
    all_delays = [r["delay_ms"] for p in parts for r in p["contacts"] if r["found"] and r["required"]]
    return {"found": sum(p["found"] for p in parts), "total": sum(p["total"] for p in parts),
            "required_found": sum(p["required_found"] for p in parts), "required": sum(p["required"] for p in parts),
            "false_alarms": sum(len(p["false_alarms"]) for p in parts),
            "median_impact_delay_ms": None if not delays else round(float(np.median(delays)), 1),
            "median_impact_delay_from_edge_ms": None if not edge else round(float(np.median(edge)), 1),
            "median_delay_ms_all_required": None if not all_delays else round(float(np.median(all_delays)), 1),
            "impacts": len(delays)}


def max_ratio_outside(t: np.ndarray, ratio: np.ndarray, contacts: list[Any], tol_s: float = TOL_S) -> list[float]:
    """Per joint the largest |deviation|/band outside every contact's window (NaN: none)."""
    tt = t - t[0]
    inside = np.zeros(tt.shape[0], dtype=bool)
    for c in contacts:
        inside |= (tt >= c.t_start_s - tol_s) & (tt <= c.t_end_s + tol_s)
    out = []
    for j in range(ratio.shape[1]):
        v = ratio[~inside, j]
        v = v[np.isfinite(v)]
        out.append(round(float(v.max()), 3) if v.size else math.nan)
    return out
