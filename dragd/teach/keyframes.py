"""Post-processing of a continuous recording: keyframes that keep the path within a tolerance.

1. Mandatory keyframes: the first and last sample, every pause (the hand held the arm still for ``pause_min_s``:
   one keyframe at the pause's middle, replayed as a stop) and every marked waypoint.
2. Between two mandatory keyframes, Ramer–Douglas–Peucker in joint space (Euclidean distance, so every joint
   stays within the tolerance of the chord).
3. The replay draws a cubic spline (chord-length parameter) through the keyframes, not the polyline: samples
   farther than the tolerance from that spline add the worst one as a keyframe, until none is.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline

from dragd.teach.program import KeyframeKind


@dataclass(frozen=True)
class KeyframeResult:
    index: np.ndarray  # sample indices of the keyframes, increasing
    kind: list[KeyframeKind]
    max_deviation_rad: float  # of the recorded samples from the spline through the keyframes


def find_pauses(t: np.ndarray, q: np.ndarray, speed_rad_s: float = 0.01, min_s: float = 0.3) -> list[tuple[int, int]]:
    """Index ranges [i0, i1] in which every joint moved slower than ``speed_rad_s`` for at least ``min_s``."""
    if len(t) < 3:
        return []
    v = np.abs(np.gradient(q, t, axis=0)).max(axis=1)
    still = v < speed_rad_s
    out, i = [], 0
    while i < len(t):
        if still[i]:
            j = i
            while j + 1 < len(t) and still[j + 1]:
                j += 1
            if t[j] - t[i] >= min_s:
                out.append((i, j))
            i = j + 1
        else:
            i += 1
    return out


def _rdp(q: np.ndarray, i0: int, i1: int, tol: float) -> list[int]:
    """Indices strictly between i0 and i1 kept by Ramer–Douglas–Peucker (iterative)."""
    keep: list[int] = []
    stack = [(i0, i1)]
    while stack:
        a, b = stack.pop()
        if b - a < 2:
            continue
        seg = q[b] - q[a]
        pts = q[a + 1:b] - q[a]
        L2 = float(seg @ seg)
        if L2 > 0:
            s = np.clip(pts @ seg / L2, 0.0, 1.0)
            d = np.linalg.norm(pts - np.outer(s, seg), axis=1)
        else:
            d = np.linalg.norm(pts, axis=1)
        k = int(np.argmax(d))
        if d[k] > tol:
            m = a + 1 + k
            keep.append(m)
            stack.append((a, m))
            stack.append((m, b))
    return keep


def chord_parameter(q: np.ndarray) -> np.ndarray:
    """Cumulative joint-space chord length (the spline parameter)."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(q, axis=0), axis=1))])


def path_spline(u: np.ndarray, q: np.ndarray, closed: bool = False) -> CubicSpline:
    """The replayed curve through points ``q`` at parameters ``u``: not-a-knot cubic (periodic when closed)."""
    if closed:
        return CubicSpline(u, q, bc_type="periodic")
    if len(u) == 2:
        return CubicSpline(u, q, bc_type=((1, (q[1] - q[0]) / (u[1] - u[0])), (1, (q[1] - q[0]) / (u[1] - u[0]))))
    if len(u) == 3:
        return CubicSpline(u, q, bc_type="natural")
    return CubicSpline(u, q, bc_type="not-a-knot")


def spline_deviation(q: np.ndarray, idx: np.ndarray, stops: set[int]) -> np.ndarray:
    """Distance of every recorded sample from the replayed curve through the keyframes ``idx``.

    The curve is a chord-length cubic spline (``path_spline``) in each section between stops (what the planner draws);
    a sample between keyframes a and b is compared at the parameter its own path length maps to.
    """
    dev = np.zeros(len(q))
    cuts = [0] + [k for k in range(1, len(idx) - 1) if int(idx[k]) in stops] + [len(idx) - 1]
    for c0, c1 in itertools.pairwise(cuts):
        kid = idx[c0:c1 + 1]
        kq = q[kid]
        u = chord_parameter(kq)
        if u[-1] <= 0:
            continue
        sp = path_spline(u, kq)
        for m in range(len(kid) - 1):
            a, b = int(kid[m]), int(kid[m + 1])
            seg = q[a:b + 1]
            arc = chord_parameter(seg)
            frac = arc / arc[-1] if arc[-1] > 0 else np.zeros_like(arc)
            uu = u[m] + frac * (u[m + 1] - u[m])
            ref = sp(uu)
            dev[a:b + 1] = np.maximum(dev[a:b + 1], np.linalg.norm(seg - ref, axis=1))
    return dev


_RANK = {"start": 4, "end": 4, "pause": 3, "mark": 2, "shape": 1}


def _dedupe(q: np.ndarray, idx: list[int], kinds: dict[int, KeyframeKind], min_chord: float) -> np.ndarray:
    """Merge keyframes closer than ``min_chord`` (a still hand gives several at one place): the most important kind
    stays (start/end, then pause, mark, shape); the recording's first and last sample always do."""
    out = [idx[0]]
    for k in idx[1:]:
        if np.linalg.norm(q[k] - q[out[-1]]) >= min_chord:
            out.append(k)
            continue
        prev = out[-1]
        if kinds.get(prev) == "start":
            if kinds.get(k) == "end" and len(out) > 1:
                out[-1] = k
            continue
        if kinds.get(k) == "end" or _RANK[kinds.get(k, "shape")] > _RANK[kinds.get(prev, "shape")]:
            out[-1] = k
    return np.array(out)


def extract_keyframes(t: np.ndarray, q: np.ndarray, tol_rad: float = np.radians(0.5),
                      marks_t: list[float] | None = None, pause_speed_rad_s: float = 0.01,
                      pause_min_s: float = 0.3, min_chord_rad: float = 1e-4,
                      max_keyframes: int = 2000) -> KeyframeResult:
    """Keyframes of a recording (t [s], q [rad] N×joints) keeping the replayed spline within ``tol_rad``."""
    t = np.asarray(t, dtype=float)
    q = np.asarray(q, dtype=float)
    if q.ndim != 2 or len(t) != len(q) or len(t) < 2:
        raise ValueError(f"keyframes: expected t (N ≥ 2) and q (N, joints), got {t.shape} and {q.shape}")
    if not tol_rad > 0:
        raise ValueError(f"keyframes: expected a positive tolerance, got {tol_rad}")
    kinds: dict[int, KeyframeKind] = {0: "start", len(t) - 1: "end"}
    stops: set[int] = set()
    for i0, i1 in find_pauses(t, q, pause_speed_rad_s, pause_min_s):
        m = (i0 + i1) // 2
        if 0 < m < len(t) - 1:
            kinds.setdefault(m, "pause")
            stops.add(m)
    for tm in marks_t or []:
        m = int(np.clip(np.searchsorted(t, tm), 0, len(t) - 1))
        if 0 < m < len(t) - 1:
            kinds[m] = "mark"
    fixed = sorted(kinds)
    keep = set(fixed)
    for a, b in itertools.pairwise(fixed):
        keep.update(_rdp(q, a, b, tol_rad))
    idx = _dedupe(q, sorted(keep), kinds, min_chord_rad)
    stops = {k for k in stops if k in set(idx.tolist())}
    dev = spline_deviation(q, idx, stops)
    while dev.max() > tol_rad and len(idx) < max_keyframes:
        worst = int(np.argmax(dev))
        if np.linalg.norm(q[idx] - q[worst], axis=1).min() < min_chord_rad:
            break
        idx = np.array(sorted(set(idx.tolist()) | {worst}))
        dev = spline_deviation(q, idx, stops)
    kind = [kinds.get(int(k), "shape") for k in idx]
    return KeyframeResult(idx, kind, float(dev.max()))
