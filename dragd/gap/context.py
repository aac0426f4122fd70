"""The measured log prepared for the gap workflow: dragd/identify's loading and filtering, plus the rigid-body terms,
the evaluation mask, the passes (cross-validation groups) and the noise level of each joint's current.

Rates: the log is brought to the work rate (≤ 200 Hz, anti-aliased, dragd.identify.data.prepare); fits use the
regression filter H (zero-phase, 5 Hz) on both sides and decimated rows, as identification does; RMSE figures
are against the **raw** current at the log's own rate (the prediction interpolated onto its samples).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pinocchio as pin

from dragd.identify.data import Log, Prepared, prepare, sliding
from dragd.identify.regressors import RegressorModel

V_SLIDE = 0.01  # rad/s: a joint slides above this (evaluation mask)
GUARD_S = 0.1  # ... for ± this long (stiction, reversal instants and rests are not evaluated)
V_REST = 0.01  # rad/s: the arm rests when every joint is below this (pass boundaries)
MISSED_MAX_SHARE = 0.3  # beyond this share of samples near missed cycles, only MISSED_GUARD_DENSE_S around each
MISSED_GUARD_DENSE_S = 0.02
MISSED_GUARD_S = 0.1  # samples this close to a missed cycle of the log are not evaluated (the drive saw a jerky target)
FOLDS = 5


@dataclass
class GapData:
    """A log at the work rate with everything the catalogue's regressors are built from."""

    log: Log
    p: Prepared
    names: list[str]
    robot: Any
    G: np.ndarray  # (T, n) gravity torque of the URDF [N·m]
    tau_dyn: np.ndarray  # (T, n) URDF rigid-body torque minus gravity: M(q)q̈ + C(q, q̇)q̇ [N·m]
    t_rel: np.ndarray  # (T,) s since the log's first sample
    slide: np.ndarray  # (T, n) bool: the joint slides (evaluation and fit mask)
    steady: np.ndarray  # (T, n) bool: ... and no stop or reversal of the joint within the regression filter's reach
    rows: np.ndarray  # decimated row indices for regressions (away from stretch edges)
    pass_id: np.ndarray  # (T,) pass number (a move between two rests of the arm)
    fold: np.ndarray  # (T,) cross-validation fold of each sample (whole passes)
    noise_A: np.ndarray  # (n,) white-noise level of the raw current (robust first-difference estimate)
    iH: np.ndarray  # (T, n) H(current)
    warnings: list[str] = field(default_factory=list)
    cache: dict[Any, Any] = field(default_factory=dict)  # per-log results of expensive candidate fits
    _payload: np.ndarray | None = None
    _inertia_diag: np.ndarray | None = None

    @property
    def n(self) -> int:
        return len(self.names)

    @property
    def T(self) -> int:
        return int(self.p.t.shape[0])

    def H(self, x: np.ndarray) -> np.ndarray:
        """The regression filter (zero-phase, per stretch) applied along time."""
        return self.p.regfilter(x)

    def fit_rows(self, j: int) -> np.ndarray:
        """Decimated rows where joint j slides."""
        return self.rows[self.slide[self.rows, j]]

    def payload_regressor(self) -> np.ndarray:
        """(T, n, 4): joint torques per unit of the flange body's [m, m·cx, m·cy, m·cz] (gravity and dynamics)."""
        if self._payload is None:
            m = self.robot.model
            d = m.createData()
            n = self.n
            out = np.empty((self.T, n, 4))
            lo = 10 * (n - 1)
            q, dq, ddq = self.p.q, self.p.dq, self.p.ddq
            f = pin.computeJointTorqueRegressor
            for k in range(self.T):
                out[k] = f(m, d, q[k], dq[k], ddq[k])[:, lo:lo + 4]
            self._payload = out
        return self._payload

    def inertia_diag(self, every: int = 8) -> np.ndarray:
        """(T, n): the URDF's joint-space inertia diagonal M_jj(q) [kg·m²] (computed every ``every`` samples and
        interpolated: it changes with the pose, slowly)."""
        if self._inertia_diag is None:
            m = self.robot.model
            data = m.createData()
            rows = np.unique(np.r_[np.arange(0, self.T, every), self.T - 1])
            diag = np.array([np.diag(pin.crba(m, data, self.p.q[k])) for k in rows])
            idx = np.arange(self.T)
            self._inertia_diag = np.column_stack([np.interp(idx, rows, diag[:, j]) for j in range(self.n)])
        return self._inertia_diag

    def raw_rmse(self, pred: np.ndarray) -> tuple[np.ndarray, float]:
        """Per-joint and overall RMSE of the raw current against a work-rate prediction, on the sliding mask."""
        t_raw, i_raw = self.log.t, self.log.i
        sq = np.zeros(self.n)
        cnt = np.zeros(self.n)
        for s in self.p.segments:
            t = self.p.t[s.start:s.stop]
            inside = (t_raw >= t[0]) & (t_raw <= t[-1])
            tr = t_raw[inside]
            for j in range(self.n):
                m = np.interp(tr, t, self.slide[s.start:s.stop, j].astype(float)) > 0.999
                e = i_raw[inside, j][m] - np.interp(tr[m], t, pred[s.start:s.stop, j])
                sq[j] += float(e @ e)
                cnt[j] += e.size
        per = np.sqrt(sq / np.maximum(cnt, 1))
        per[cnt == 0] = np.nan
        return per, float(math.sqrt(sq.sum() / max(cnt.sum(), 1)))


def _noise(i_raw: np.ndarray) -> np.ndarray:
    """Robust white-noise level per column: 1.4826·MAD of the first difference / √2."""
    d = np.diff(i_raw, axis=0)
    mad = np.median(np.abs(d - np.median(d, axis=0)), axis=0)
    return 1.4826 * mad / math.sqrt(2.0)


def _to_missed_s(log: Log, t: np.ndarray) -> np.ndarray:
    """Per work-rate sample, the time to the nearest missed cycle of the log (a gap of 1.5–5.5 periods,
    interpolated) [s]; inf without any."""
    d = np.diff(log.t)
    med = float(np.median(d))
    k = np.nonzero((d > 1.5 * med) & (d <= 5.5 * med))[0]
    if k.size == 0:
        return np.full(t.shape[0], np.inf)
    centres = 0.5 * (log.t[k] + log.t[k + 1])
    idx = np.searchsorted(centres, t)
    left = np.abs(t - centres[np.clip(idx - 1, 0, centres.size - 1)])
    right = np.abs(centres[np.clip(idx, 0, centres.size - 1)] - t)
    return np.minimum(left, right)


def _passes(p: Prepared, rest_s: float = 0.1, block_s: float = 10.0) -> tuple[np.ndarray, list[str]]:
    """A pass = a move of the arm between two rests (every joint below V_REST for ≥ rest_s); without rests, blocks."""
    moving = np.any(np.abs(p.dq) > V_REST, axis=1)
    guard = max(1, int(round(rest_s * p.fs / 2)))
    rest = sliding((~moving).astype(float)[:, None], 0.5, guard)[:, 0]
    starts = np.zeros(p.t.shape[0], dtype=bool)
    starts[1:] = rest[:-1] & ~rest[1:]
    for s in p.segments:
        starts[s.start] = True
    pid = np.cumsum(starts) - 1
    notes = []
    if np.unique(pid[~rest]).size < 2 * FOLDS:
        block_s = min(block_s, float(p.t[-1] - p.t[0]) / (2 * FOLDS))
        pid = np.floor((p.t - p.t[0]) / block_s).astype(int)
        notes.append(f"fewer than {2 * FOLDS} moves between rests: cross-validation leaves out {block_s:.3g} s blocks")
    return pid, notes


def load_gap_data(log: Log, robot: Any, cutoff_Hz: float = 5.0) -> GapData:
    """Prepare a log for the gap workflow (see the module docstring)."""
    names = list(robot.joint_names)
    log.check_robot(names, str(robot.urdf_path or "robot"))
    p = prepare(log, cutoff_Hz=cutoff_Hz, deriv_cutoff_Hz=20.0)
    rm = RegressorModel(robot, samples=20)
    G = rm.gravity(p.q)
    tau_dyn = rm.rnea(p.q, p.dq, p.ddq) - G
    guard = int(round(GUARD_S * p.fs))
    slide = np.column_stack([sliding(p.dq[:, j:j + 1], V_SLIDE, guard)[:, 0] for j in range(len(names))])
    to_missed = _to_missed_s(log, p.t)
    notes = []
    guard_s = MISSED_GUARD_S
    if np.mean(to_missed <= guard_s) > MISSED_MAX_SHARE:
        # missed cycles throughout the log (a loaded host): the full guard would leave too little; the drive's
        # position loop settles from a late target within MISSED_GUARD_DENSE_S — only that much is left out
        guard_s = MISSED_GUARD_DENSE_S
        notes.append(f"missed cycles throughout the log: only samples within {guard_s:g} s of one left out (not "
                     f"{MISSED_GUARD_S:g} s); figures noisier, timing artefacts may be named — record on a quieter "
                     "controller")
    missed = to_missed <= guard_s
    if missed.any():
        slide &= ~missed[:, None]
        notes.append(f"{int(missed.sum())} work-rate samples within {guard_s:g} s of missed cycles not evaluated "
                     "(the drive followed a jerky target there)")
    # steady rows: no zero crossing of the joint's q̇ within H's reach (1/cutoff: beyond it the filter's impulse
    # response stays < 4 % of its peak; at the 0.1 s guard it is still 13 %). Friction steps where q̇ changes sign
    # (breakaway, stop, reversal), and the model puts the step where the *estimated* q̇ (20 Hz position filter)
    # crosses zero, milliseconds off the true instant: that error (the step × the timing error, an impulse at each
    # stop or reversal) comes through H spread over the filter's reach and reads on the rows nearby as a
    # direction-odd level
    reach = max(guard, int(round(p.fs / p.cutoff_Hz)))
    steady = slide & np.column_stack([sliding(p.dq[:, j:j + 1], V_SLIDE, reach)[:, 0] for j in range(len(names))])
    pid, pass_notes = _passes(p)
    notes += pass_notes
    # folds: passes round-robin, so a pass and its return (the same positions, the other direction) differ
    uniq = np.unique(pid)
    fold = np.empty_like(pid)
    for k, u in enumerate(uniq):
        fold[pid == u] = k % FOLDS
    return GapData(log=log, p=p, names=names, robot=robot, G=G, tau_dyn=tau_dyn, t_rel=p.t - p.t[0], slide=slide,
                   steady=steady, rows=p.rows(), pass_id=pid, fold=fold, noise_A=_noise(log.i), iH=p.regfilter(p.i),
                   warnings=list(p.warnings) + notes)
