"""Contact labels of the real robot's logs (the public UR10e dataset), made without any model (docs/CONTACT.md).

* **A periodic run** (``periodic_labels``): the arm repeats one motion, so what it draws without contact is in its
  own other cycles. For every sample, the current of the 9 nearest samples in (q, q̇) — positions within ~20 mrad,
  speeds within ~0.02 rad/s — taken from other cycles (at least ``min_sep_s`` away in time) is the expected
  current; the median of those neighbours is robust to a contact in one of them. The deviation, smoothed over
  50 ms, marks a contact where it exceeds max(``k_sigma``·σ, ``floor_A``) on a joint (σ: the robust spread of that
  joint's deviation over the whole run); samples closer than ``merge_s`` join one contact, whose edges are where
  every joint is back within ``edge_sigma``·σ.
* **A held pose** (``held_labels``): the arm holds still and a person pushes it. Each push is a hand-set window
  around it (``HELD_WINDOWS``, from plots of the current); within it the held current is the median of the
  ``held_s`` before the window, the onset is the first sample where a joint's 50 ms mean leaves it by
  ``onset_A``, and the end is the release — the first sample after the peak where the joint that moved most is
  back within half of its peak excursion (what follows, the position loop unwinding, is not contact).

The peak of a contact is its largest 50 ms-mean excursion over the joints, in amperes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

# hand-set windows [s from the log's first sample] around each push: where the arm is touched and released
HELD_WINDOWS: dict[str, tuple[tuple[float, float], ...]] = {
    "ur-20_01_22-push_pose_1": ((1.6, 3.0), (4.3, 6.0), (7.9, 9.6), (11.3, 13.0)),
    "ur-20_01_22-push_pose_2": ((0.3, 1.6), (2.2, 3.9), (4.6, 5.9), (7.5, 9.2), (10.9, 12.6), (14.2, 15.2)),
}
SMOOTH = 5  # samples of the centred mean (50 ms at the dataset's 100 Hz)


@dataclass
class Contact:
    t_start_s: float  # from the log's first sample: where the contact's deviation leaves the noise
    t_end_s: float
    peak_A: float  # the largest 50 ms-mean excursion over the joints
    peaks_A: list[float]  # per joint
    joint: int  # the joint with the largest excursion
    impact: bool  # from a struck moving arm (delays are judged on these)
    t_onset_s: float = math.nan  # where it first reaches the labels' level (delays are measured from here)

    def to_json(self, names: list[str]) -> dict[str, Any]:
        return {"t_start_s": round(self.t_start_s, 3), "t_onset_s": round(self.t_onset_s, 3),
                "t_end_s": round(self.t_end_s, 3),
                "peak_A": round(self.peak_A, 3), "joint": names[self.joint],
                "peaks_A": [round(x, 3) for x in self.peaks_A], "impact": self.impact}


@dataclass
class Labels:
    contacts: list[Contact]
    method: str
    deviation_A: np.ndarray | None = None  # (N, n) the smoothed deviation the labels come from
    sigma_A: list[float] = field(default_factory=list)


def _smooth(x: np.ndarray, k: int = SMOOTH) -> np.ndarray:
    """Centred mean over k samples, edges by the available samples (no zero padding)."""
    c = np.cumsum(np.vstack([np.zeros((1, x.shape[1])), x]), axis=0)
    n = x.shape[0]
    lo = np.clip(np.arange(n) - k // 2, 0, n)
    hi = np.clip(np.arange(n) + k - k // 2, 0, n)
    return (c[hi] - c[lo]) / (hi - lo)[:, None]


def periodic_labels(t: np.ndarray, q: np.ndarray, dq: np.ndarray, i_A: np.ndarray, min_sep_s: float = 2.0,
                    neighbours: int = 9, q_scale_rad: float = 0.02, dq_scale_rad_s: float = 0.02,
                    k_sigma: float = 6.0, floor_A: float = 0.3, edge_sigma: float = 2.0,
                    merge_s: float = 0.3) -> Labels:
    """Contacts of a periodic run against its own other cycles (see the module docstring)."""
    from scipy.spatial import cKDTree

    t = t - t[0]
    X = np.hstack([q / q_scale_rad, dq / dq_scale_rad_s])
    tree = cKDTree(X)
    k_query = min(X.shape[0], 12 * neighbours)
    _, idx = tree.query(X, k=k_query)
    expected = np.empty_like(i_A)
    for s in range(t.shape[0]):
        cand = idx[s][np.abs(t[idx[s]] - t[s]) > min_sep_s][:neighbours]
        if cand.size == 0:
            raise ValueError(f"periodic labels: sample {s} (t = {t[s]:.2f} s) has no neighbour from another cycle; "
                             "is the run periodic?")
        expected[s] = np.median(i_A[cand], axis=0)
    dev = _smooth(i_A - expected)
    sigma = 1.4826 * np.median(np.abs(dev - np.median(dev, axis=0)), axis=0)
    level = np.maximum(k_sigma * sigma, floor_A)
    hot = np.flatnonzero((np.abs(dev) > level).any(axis=1))
    segs: list[list[int]] = []
    for s in (int(x) for x in hot):
        if segs and t[s] - t[segs[-1][1]] < merge_s:
            segs[-1][1] = s
        else:
            segs.append([s, s])
    calm = (np.abs(dev) < edge_sigma * sigma).all(axis=1)
    contacts = []
    for a, b in segs:
        while a > 0 and not calm[a - 1]:
            a -= 1
        while b < t.shape[0] - 1 and not calm[b + 1]:
            b += 1
        pk = np.abs(dev[a:b + 1]).max(axis=0)
        k_on = a + int(np.flatnonzero((np.abs(dev[a:b + 1]) > level).any(axis=1))[0])
        contacts.append(Contact(float(t[a]), float(t[b]), float(pk.max()), pk.tolist(), int(np.argmax(pk)), True,
                                float(t[k_on])))
    merged: list[Contact] = []  # edges may have grown into each other
    for c in contacts:
        if merged and c.t_start_s <= merged[-1].t_end_s:
            m = merged[-1]
            pk = np.maximum(m.peaks_A, c.peaks_A)
            merged[-1] = Contact(m.t_start_s, max(m.t_end_s, c.t_end_s), float(pk.max()), pk.tolist(),
                                 int(np.argmax(pk)), True, m.t_onset_s)
        else:
            merged.append(c)
    return Labels(merged, f"periodic: {neighbours} nearest samples in (q, q̇) from other cycles (> {min_sep_s:g} s "
                          f"away), median; 50 ms mean of the deviation above max({k_sigma:g}σ, {floor_A:g} A); edges "
                          f"within {edge_sigma:g}σ", dev, sigma.tolist())


def held_labels(t: np.ndarray, i_A: np.ndarray, windows: tuple[tuple[float, float], ...], held_s: float = 0.3,
                onset_A: float = 0.25) -> Labels:
    """Contacts of a held pose in hand-set windows, edges against the held current (see the module docstring)."""
    t = t - t[0]
    s = _smooth(i_A)
    contacts = []
    for a, b in windows:
        pre = (t >= a - held_s) & (t < a)
        win = np.flatnonzero((t >= a) & (t <= b))
        if pre.sum() < 3 or win.size < 3:
            raise ValueError(f"held labels: window {a:g}–{b:g} s lies outside the log (0–{t[-1]:.2f} s)")
        held = np.median(i_A[pre], axis=0)
        dev = s[win] - held
        away = np.abs(dev) > onset_A
        if not away.any():
            raise ValueError(f"held labels: no joint leaves its held current by {onset_A} A in {a:g}–{b:g} s")
        k0 = int(np.flatnonzero(away.any(axis=1))[0])
        pk = np.abs(dev[k0:]).max(axis=0)
        j = int(np.argmax(pk))
        kp = k0 + int(np.argmax(np.abs(dev[k0:, j])))
        back = np.flatnonzero(np.abs(dev[kp:, j]) < 0.5 * pk[j])
        k1 = kp + (int(back[0]) if back.size else dev.shape[0] - 1 - kp)
        pk = np.abs(dev[k0:k1 + 1]).max(axis=0)
        contacts.append(Contact(float(t[win[k0]]), float(t[win[k1]]), float(pk.max()), pk.tolist(), j, False,
                                float(t[win[k0]])))
    return Labels(contacts, f"held: hand-set windows; the held current is the median of the {held_s:g} s before; "
                            f"onset where a joint's 50 ms mean leaves it by {onset_A:g} A; end at the release (the "
                            "main joint back within half its peak)")
