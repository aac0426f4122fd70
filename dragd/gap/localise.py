"""Where the residual lives: per joint, by phase, against velocity, position (angle spectrum), gravity load and time,
and its even/odd split from passes through the same position in opposite directions.

All on the work-rate residual r = i − î of each joint (anti-aliased current, ≤ 200 Hz).

- phases: *rest* (|q̇| < 0.01 rad/s), *reversal* (within 0.3 s of a sign change of q̇), *acceleration*
  (|H(q̈)| > 0.3 rad/s²), *constant speed* (the rest of the sliding samples): RMS and mean of r per phase;
- binned means of r against q̇ (12 bins), against |G| (8 bins) and against time (10 bins);
- the angle-domain spectrum: Lomb–Scargle periodogram of r against q on sliding samples, its largest peak
  (order in cycles per joint revolution and amplitude);
- even/odd split (seed 001's half-sum/half-difference, eq. 7–8 applied to the residual): position bins visited in
  both directions; odd = (r₊ − r₋)/2 (friction-like: direction-dependent), even = (r₊ + r₋)/2 (a function of q:
  gravity, payload, offset, ripple).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from dragd.gap.context import GapData
from dragd.gap.effects import spectrum_peaks


def _binned(x: np.ndarray, r: np.ndarray, bins: int) -> dict[str, list[float]]:
    if x.size < bins * 5:
        return {"x": [], "mean_A": [], "count": []}
    edges = np.quantile(x, np.linspace(0, 1, bins + 1))
    edges = np.unique(edges)
    if edges.size < 2:
        return {"x": [], "mean_A": [], "count": []}
    k = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, edges.size - 2)
    cnt = np.bincount(k, minlength=edges.size - 1)
    s = np.bincount(k, weights=r, minlength=edges.size - 1)
    mid = 0.5 * (edges[:-1] + edges[1:])
    keep = cnt > 0
    return {"x": [float(v) for v in mid[keep]], "mean_A": [float(v) for v in (s[keep] / cnt[keep])],
            "count": [int(c) for c in cnt[keep]]}


def localise(d: GapData, pred: np.ndarray) -> dict[str, Any]:
    """The residual's localisation per joint (JSON-ready)."""
    p = d.p
    r_all = p.i - pred
    ddqH = d.H(p.ddq)
    out: dict[str, Any] = {}
    for j, nm in enumerate(d.names):
        r = r_all[:, j]
        v = p.dq[:, j]
        rest = np.abs(v) < 0.01
        s = np.sign(v)
        rev = np.zeros_like(rest)
        idx = np.nonzero((s[1:] * s[:-1]) < 0)[0]
        w = int(round(0.3 * p.fs))
        for k in idx:
            rev[max(0, k - w):k + w] = True
        acc = (np.abs(ddqH[:, j]) > 0.3) & ~rest & ~rev
        const = d.slide[:, j] & ~acc & ~rev
        phases = {}
        for name, m in (("rest", rest), ("reversal", rev & ~rest), ("acceleration", acc), ("constant_speed", const)):
            phases[name] = {"rms_A": float(np.sqrt(np.mean(r[m] ** 2))) if m.any() else None,
                            "mean_A": float(np.mean(r[m])) if m.any() else None, "samples": int(m.sum())}
        m = d.slide[:, j]
        peaks = spectrum_peaks(d, j, r)
        spec = None
        if peaks:
            c = peaks[0]
            X = np.column_stack([np.sin(c * p.q[m, j]), np.cos(c * p.q[m, j])])
            th, *_ = np.linalg.lstsq(X, r[m], rcond=None)
            spec = {"order_cycles_per_rev": c, "amplitude_A": float(math.hypot(*th)), "other_peaks": peaks[1:]}
        # even/odd: position bins crossed in both directions
        eo = None
        if m.sum() > 100:
            q = p.q[m, j]
            edges = np.linspace(q.min(), q.max(), 41)
            k = np.clip(np.searchsorted(edges, q) - 1, 0, 39)
            pos, neg = v[m] > 0, v[m] < 0
            rp = np.bincount(k[pos], weights=r[m][pos], minlength=40) / np.maximum(np.bincount(k[pos], minlength=40), 1)
            rn = np.bincount(k[neg], weights=r[m][neg], minlength=40) / np.maximum(np.bincount(k[neg], minlength=40), 1)
            both = (np.bincount(k[pos], minlength=40) > 3) & (np.bincount(k[neg], minlength=40) > 3)
            if both.sum() >= 3:
                odd, even = 0.5 * (rp - rn)[both], 0.5 * (rp + rn)[both]
                eo = {"odd_rms_A": float(np.sqrt(np.mean(odd ** 2))), "even_rms_A": float(np.sqrt(np.mean(even ** 2))),
                      "even_mean_A": float(np.mean(even)), "bins": int(both.sum())}
        out[nm] = {"rms_A": float(np.sqrt(np.mean(r[m] ** 2))) if m.any() else None, "phases": phases,
                   "vs_velocity": _binned(v[m], r[m], 12), "vs_gravity_Nm": _binned(np.abs(d.G[m, j]), r[m], 8),
                   "vs_time": _binned(d.t_rel[m], r[m], 10), "spectrum": spec, "even_odd": eo}
    return out
