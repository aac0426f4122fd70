"""``dragd contact detect``: the cycle's contact detector run over a log, sample by sample (docs/CONTACT.md).

The model's terms (dragd/contact/model.py) at every sample, then ``ContactDetector.update`` — the same code and
arithmetic the daemon's cycle runs — armed at the log's first sample. A log without a velocity column gets the
causal estimate a controller has: the backward difference of q low-passed at ``VELOCITY_CUTOFF_HZ`` (first order).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from dragd.control.contact import ContactBands, ContactDetector, ContactEvent, ContactSettings, contact_kernel

VELOCITY_CUTOFF_HZ = 50.0


@dataclass
class Run:
    """A detector's pass over a log: per-sample traces (N, n) and the events."""

    t: np.ndarray
    e_A: np.ndarray  # residual r/K_t
    d_A: np.ndarray  # deviation judged (residual, or residual − held baseline)
    band_A: np.ndarray
    state: np.ndarray
    over: np.ndarray
    speed: np.ndarray
    features: np.ndarray  # (N, n, 4): the band's filtered low-speed indicator, speed, acceleration, arm moving
    events: list[ContactEvent]
    warnings: list[str] = field(default_factory=list)

    def ratio(self) -> np.ndarray:
        """|d|/band per sample and joint (NaN while the detector settles after arming)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.abs(self.d_A) / self.band_A


def causal_velocity(t: np.ndarray, q: np.ndarray, cutoff_Hz: float = VELOCITY_CUTOFF_HZ) -> np.ndarray:
    """Backward difference of q, first-order low-passed at ``cutoff_Hz`` (what a controller has in real time)."""
    v = np.zeros_like(q)
    for k in range(1, q.shape[0]):
        dt = t[k] - t[k - 1]
        raw = (q[k] - q[k - 1]) / dt if dt > 0 else v[k - 1]
        a = 1.0 - math.exp(-2.0 * math.pi * cutoff_Hz * dt) if dt > 0 else 0.0
        v[k] = v[k - 1] + a * (raw - v[k - 1])
    return v


@dataclass
class Terms:
    """The model's terms over a log (what the cycle computes each sample), kept to run several detectors."""

    t: np.ndarray
    dq: np.ndarray
    p: np.ndarray  # M̄(q)·q̇
    tau_in: np.ndarray  # K_t·(I − I_f) − g + Cᵀq̇
    warnings: list[str]


def log_terms(model: Any, log: Any) -> Terms:
    """The model's terms at every sample of ``log`` (dragd.identify.data.Log: t, q, i, optional dq)."""
    warnings: list[str] = []
    dq = log.dq
    if dq is None:
        dq = causal_velocity(log.t, log.q)
        warnings.append(f"{log.path}: no velocity column: q̇ is the backward difference of q low-passed at "
                        f"{VELOCITY_CUTOFF_HZ:g} Hz (causal, as in the cycle)")
    P, T = model.log_terms(log.q, dq, log.i)
    return Terms(log.t, dq, P, T, warnings)


def run_log(model: Any, bands: ContactBands, settings: ContactSettings, log: Any, compiled: bool = True,
            terms: Terms | None = None) -> Run:
    """The detector over every sample of ``log`` (or of its precomputed ``terms``)."""
    terms = terms if terms is not None else log_terms(model, log)
    dq, P, T, warnings = terms.dq, terms.p, terms.tau_in, list(terms.warnings)
    det = ContactDetector(model.kt_Nm_per_A, bands, settings)
    if compiled and (k := contact_kernel()) is not None:
        det.use_kernel(k)
    t = terms.t
    N, n = P.shape
    e, d, band = (np.empty((N, n)) for _ in range(3))
    feats = np.empty((N, n, 4))
    state = np.empty((N, n), dtype=np.int64)
    over = np.empty((N, n), dtype=bool)
    det.arm(P[0], float(t[0]))
    for k in range(N):
        det.update(float(t[k]), dq[k], P[k], T[k])
        e[k], d[k], band[k], state[k], over[k] = det.e, det.d, det.band, det.state, det.over
        feats[k, :, 0], feats[k, :, 1], feats[k, :, 2], feats[k, :, 3] = det.f_low, det.f_speed, det.f_acc, det.f_arm
    band[t - t[0] < settings.arm_s] = np.nan
    det.disarm()
    return Run(t, e, d, band, state, over, np.abs(dq), feats, det.events, warnings)
