"""Forward selection of effects with pass-wise cross-validation and an information criterion.

Per joint j the model is y = H(i_j − fixed_j) ≈ H(X_j)·θ_j on decimated rows where the joint slides (H the
regression filter on both sides). A candidate effect adds its columns (and, for some, a fixed part; backlash is only a
fixed part: a physical predictor whose parameters are its hyperparameters); it is scored by

- the **held-out** error: K-fold cross-validation whose folds are whole passes (moves between rests of the arm,
  assigned round-robin, so a pass and its return through the same positions are in different folds) — never single
  samples, whose neighbours would leak through the filter;
- **BIC** on all rows: N·ln(SSE'/SSE) + (k + hyperparameters)·ln N < 0.

An effect is *real* on a joint when the held-out MSE falls by at least ``REL_MIN`` **and** the held-out error it
explains, √(ΔSSE/N), is at least ``ABS_MIN`` × that joint's current noise (the raw Hall noise estimate), and BIC
agrees. Each round adds the effect with the largest held-out gain (summed over the joints where it is real) on those
joints, with each joint's best hyperparameter; the rounds stop when no effect is real anywhere. The payload is one
shared parameter vector across joints (fitted jointly, the joints' other columns eliminated). An effect may mark
samples where its prediction stays uncertain beyond the noise (a play's crossings, where the current follows the
drive's unobserved reference): they leave that joint's rows for every later fit and score.

Effects are judged on the joint's *steady* rows (no stop or reversal within the regression filter's reach, where the
model's misplaced friction steps leak through H as a direction-odd level) unless their signature lives in the
transients (``Effect.transient``: inertia, K_t, the play); the model is fitted on every row.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from dragd.gap.baseline import Baseline, update_seed000
from dragd.gap.context import FOLDS, GapData
from dragd.gap.effects import CATALOGUE, Cols, Effect

KT_PAYLOAD_ROUNDS = 8  # payload ↔ K_t alternating refits: the gains settle ~5× per round (0.12 → 1e-4 in 5)
AMBIGUOUS = 0.3  # another real effect whose held-out RMS is within this × the joint's noise explains it as well
REL_MIN = 0.05  # held-out MSE must fall by 5 %
ABS_MIN = 0.3  # ... and the explained held-out RMS must reach 0.3 × the joint's noise
MAX_ROUNDS = 8
MIN_STEADY_ROWS = 30  # fewer steady rows than this: an effect is judged on all the joint's rows
RIDGE = 1e-9


@dataclass
class Term:
    effect: str
    hyper: Any
    cols: Cols
    XH: np.ndarray  # (R, k) filtered free columns on the joint's fit rows
    offH: np.ndarray | None  # (R,) filtered fixed part on the fit rows


@dataclass
class JointModel:
    j: int
    rows: np.ndarray
    y: np.ndarray  # filtered target on rows (current − fixed)
    base: np.ndarray  # (R, k0) filtered free base columns (seed 000) or (R, 0)
    terms: list[Term] = field(default_factory=list)
    theta: np.ndarray | None = None

    def design(self, extra: Term | None = None) -> tuple[np.ndarray, np.ndarray]:
        ts = self.terms + ([extra] if extra is not None else [])
        X = np.hstack([self.base] + [t.XH for t in ts]) if ts or self.base.shape[1] else np.zeros((self.y.size, 0))
        y = self.y.copy()
        for t in ts:
            if t.offH is not None:
                y -= t.offH
        return X, y

    def col(self, t: Term) -> int:
        """The first column of term ``t`` in :meth:`design` (the base columns first, then each term's in order)."""
        return self.base.shape[1] + sum(tt.XH.shape[1] for tt in self.terms[:self.terms.index(t)])

    def kt_col(self) -> int | None:
        """The column of the joint's torque_constant term, if it has one."""
        t = next((tt for tt in self.terms if tt.effect == "torque_constant"), None)
        return None if t is None else self.col(t)


@dataclass
class Step:
    effect: str
    joints: list[str]
    hypers: dict[str, Any]
    gain: dict[str, dict[str, float]]  # per joint: held-out RMS before/after, BIC change
    # effects that explain the same joints as well in the final model (swapped in, held-out RMS within AMBIGUOUS ×
    # noise of this one's): effect → {joint: {cv_rmse_after_A of the alternative, of this effect}}
    ambiguous: dict[str, dict[str, dict[str, float]]] = field(default_factory=dict)


def _cv_sse(X: np.ndarray, y: np.ndarray, fold: np.ndarray) -> float:
    """Sum of held-out squared errors over the folds (least squares on the others)."""
    if X.shape[1] == 0:
        return float(y @ y)
    sse = 0.0
    G = X.T @ X
    b = X.T @ y
    lam = RIDGE * max(1.0, float(np.trace(G)) / X.shape[1])
    for f in range(FOLDS):
        m = fold == f
        if not m.any():
            continue
        Xf, yf = X[m], y[m]
        Gf, bf = Xf.T @ Xf, Xf.T @ yf
        try:
            th = np.linalg.solve(G - Gf + lam * np.eye(G.shape[0]), b - bf)
        except np.linalg.LinAlgError:
            return float("inf")
        e = yf - Xf @ th
        sse += float(e @ e)
    return sse


def _fit(X: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, float]:
    if X.shape[1] == 0:
        return np.zeros(0), float(y @ y)
    th, *_ = np.linalg.lstsq(X, y, rcond=None)
    e = y - X @ th
    return th, float(e @ e)


def _adds(X: np.ndarray, t: Term) -> bool:
    """The candidate brings something the model lacks: regressors outside X's span, or (a fixed-current effect
    without columns, e.g. the backlash predictor) a current that is not zero."""
    if t.XH.shape[1]:
        return _independent(X, t.XH)
    return t.offH is not None and bool(np.any(t.offH))


def _independent(X: np.ndarray, C: np.ndarray, tol: float = 1e-3) -> bool:
    """C's columns are not (nearly) in X's span (else the effect is absorbed by what the model already has)."""
    if C.shape[1] == 0 or np.linalg.norm(C) == 0:
        return False
    if X.shape[1] == 0:
        return True
    Q, _ = np.linalg.qr(X)
    R = C - Q @ (Q.T @ C)
    return bool(np.all(np.linalg.norm(R, axis=0) > tol * np.maximum(np.linalg.norm(C, axis=0), 1e-300)))


class Selector:
    """The forward selection over the catalogue on one prepared log and baseline."""

    def __init__(self, d: GapData, base: Baseline, effects: tuple[str, ...] | None = None) -> None:
        self.d = d
        self.base = base
        self.effects = [CATALOGUE[e] for e in (effects or CATALOGUE)]
        self.joints: list[JointModel] = []
        for j in range(d.n):
            r = d.fit_rows(j)
            y = (d.iH[:, j] - d.H(base.fixed[:, j:j + 1])[:, 0])[r]
            fb = base.free[j]
            B = d.H(fb)[r] if fb is not None else np.zeros((r.size, 0))
            self.joints.append(JointModel(j, r, y, B))
        self.payload: Term | None = None  # shared: columns per joint in a dict
        self.payload_cols: dict[int, Term] = {}
        self.payload_theta: np.ndarray | None = None
        # a joint's K_t error scales its whole torque current, the payload's too: (1 + gain) on its payload columns
        self.payload_scale = np.ones(d.n)
        self.steps: list[Step] = []
        self.snapshots: list[np.ndarray] = []  # work-rate prediction after the baseline and after each step
        self._refit()
        self.snapshots.append(self.predict())

    # ------------------------------------------------------------------------------------ fitting

    def _payload_y(self, jm: JointModel) -> np.ndarray:
        """Joint target with the shared payload's current removed."""
        X, y = jm.design()
        if self.payload_theta is not None and jm.j in self.payload_cols:
            y = y - (self.payload_cols[jm.j].XH @ self.payload_theta) * self.payload_scale[jm.j]
        return y

    def _refit(self) -> None:
        """Fit every joint (and the shared payload) on all rows; update the seed-000 baseline's K_t/levels. A K_t error
        on one of the payload's joints scales the payload's current there too (i = (1 + g)·(τ_model + τ_payload)/K_t):
        alternating least squares — the payload with each joint's columns scaled by 1 + g, then each joint with its
        gain's column the whole torque current (the model's and the payload's) — until the gains settle."""
        for _ in range(KT_PAYLOAD_ROUNDS):
            if self.payload_cols:
                self.payload_theta = self._shared_fit(self.payload_cols, None)[0]
            for jm in self.joints:
                X, y = jm.design()
                k = self._kt_index(jm)
                if k is None:
                    y = self._payload_y(jm)
                else:  # the gain scales the payload's current too: its column carries it, the target loses it unscaled
                    pay = self.payload_cols[jm.j].XH @ self.payload_theta
                    X = X.copy()
                    X[:, k] += pay
                    y = y - pay
                jm.theta, _ = _fit(X, y)
                if self.base.kind == "seed000" and jm.theta.size:
                    update_seed000(self.base, self.d, jm.j, jm.theta)
            scale = self._kt_scales()
            settled = np.allclose(scale, self.payload_scale, rtol=0.0, atol=1e-4)
            self.payload_scale = scale  # (what the joints' fits above imply: X·θ + (1 + g)·P·θ_p is their prediction)
            if not self.payload_cols or settled:
                break

    def _kt_index(self, jm: JointModel) -> int | None:
        """The column of the joint's torque_constant term in its design, when a payload is fitted on the joint."""
        if self.payload_theta is None or jm.j not in self.payload_cols:
            return None
        return jm.kt_col()

    def _kt_scales(self) -> np.ndarray:
        """(1 + the fitted K_t gain change) on the joints that carry a torque_constant term, else 1: the factor on
        their payload columns (a payload candidate's too). (≥ 0.2: the term's physical range, K_t within ×5.)"""
        scale = np.ones(self.d.n)
        for jm in self.joints:
            k = jm.kt_col()
            if k is not None and jm.theta is not None and jm.theta.size > k:
                scale[jm.j] = max(1.0 + float(jm.theta[k]), 0.2)
        return scale

    @contextmanager
    def _without(self, jm: JointModel, t: Term) -> Iterator[None]:
        """Term ``t`` taken out of joint ``jm`` for a comparison (a K_t term's gain no longer scales the joint's
        payload columns meanwhile); put back as it was."""
        idx, scale = jm.terms.index(t), self.payload_scale[jm.j]
        jm.terms.remove(t)
        if t.effect == "torque_constant":
            self.payload_scale[jm.j] = 1.0
        try:
            yield
        finally:
            jm.terms.insert(idx, t)
            self.payload_scale[jm.j] = scale

    def _shared_fit(self, terms: dict[int, Term], fold: int | None) -> tuple[np.ndarray, dict[int, float]]:
        """Shared θ_p over joints (their own columns eliminated); returns θ_p and per-joint held-out SSE for
        ``fold``."""
        A = np.zeros((4, 4))
        b = np.zeros(4)
        parts = []
        for j, t in terms.items():
            jm = self.joints[j]
            X, y = jm.design()
            f = self.d.fold[jm.rows]
            tr = np.ones(y.size, bool) if fold is None else f != fold
            C = t.XH * self.payload_scale[j]
            if X.shape[1]:
                Q, _ = np.linalg.qr(X[tr])
                Ct = C[tr] - Q @ (Q.T @ C[tr])
                yt = y[tr] - Q @ (Q.T @ y[tr])
            else:
                Ct, yt = C[tr], y[tr]
            A += Ct.T @ Ct
            b += Ct.T @ yt
            parts.append((jm, X, y, C, tr))
        th = np.linalg.solve(A + RIDGE * max(1.0, np.trace(A)) * np.eye(4), b)
        sse = {}
        if fold is not None:
            for jm, X, y, C, tr in parts:
                r = y - C @ th
                beta, _ = _fit(X[tr], r[tr])
                e = r[~tr] - X[~tr] @ beta if X.shape[1] else r[~tr]
                sse[jm.j] = float(e @ e)
        return th, sse

    # ------------------------------------------------------------------------------------ candidates

    def _term(self, eff: Effect, jm: JointModel, hyper: Any) -> Term | None:
        cols = eff.columns(self.d, jm.j, hyper, self.base.info())
        if cols is None:
            return None
        XH = self.d.H(cols.X)[jm.rows] if cols.X.shape[1] else np.zeros((jm.rows.size, 0))
        offH = None if cols.offset is None else self.d.H(cols.offset[:, None])[jm.rows, 0]
        return Term(eff.name, hyper, cols, XH, offH)

    def _residual(self, jm: JointModel) -> np.ndarray:
        """Work-rate residual of joint j under the current model (for spectra)."""
        return self.d.p.i[:, jm.j] - self.predict()[:, jm.j]

    def _judged_on(self, eff: Effect, jm: JointModel) -> np.ndarray:
        """The joint's rows (a mask over ``jm.rows``) an effect is judged on: the steady ones (no stop or reversal
        within the regression filter's reach: GapData.steady) unless its signature lives in the transients
        (``Effect.transient``) or too few are steady. Fits of the model itself use every row."""
        every = np.ones(jm.rows.size, dtype=bool)
        if eff.transient or eff.shared:
            return every
        m = self.d.steady[jm.rows, jm.j]
        return m if m.sum() >= MIN_STEADY_ROWS else every

    def _score_joint(self, eff: Effect, jm: JointModel, resid: np.ndarray | None) -> tuple[float, dict, Term] | None:
        X, y = jm.design()
        y = self._payload_y(jm) if self.payload_theta is not None else y
        m = self._judged_on(eff, jm)
        X, y = X[m], y[m]
        fold = self.d.fold[jm.rows][m]
        n = y.size
        if n < 30:
            return None
        cv0 = _cv_sse(X, y, fold)
        _, sse0 = _fit(X, y)

        def with_term(tt: Term) -> tuple[np.ndarray, np.ndarray]:
            return np.hstack([X, tt.XH[m]]), (y - tt.offH[m] if tt.offH is not None else y)

        best = None
        for h in eff.hypers(self.d, jm.j, resid if resid is not None else np.zeros(self.d.T), self.base.info()):
            t = self._term(eff, jm, h)
            if t is None or not _adds(X, Term(t.effect, t.hyper, t.cols, t.XH[m],
                                              None if t.offH is None else t.offH[m])):
                continue
            X1, y1 = with_term(t)
            cv1 = _cv_sse(X1, y1, fold)
            if best is None or cv1 < best[0]:
                best = (cv1, t, X1, y1)
        if best is None:
            return None
        if hasattr(eff, "refine") and cv0 - best[0] >= REL_MIN * cv0:  # refine a promising shape only
            def sse(h: Any) -> float:
                tt = self._term(eff, jm, h)
                if tt is None:
                    return float("inf")
                return _fit(*with_term(tt))[1]

            h2 = eff.refine(sse, best[1].hyper)
            t2 = self._term(eff, jm, h2)
            if t2 is not None and _independent(X, t2.XH[m]):
                X2, y2 = with_term(t2)
                cv2 = _cv_sse(X2, y2, fold)
                if cv2 < best[0]:
                    best = (cv2, t2, X2, y2)
        cv1, t, X1, y1 = best
        th1, sse1 = _fit(X1, y1)
        k = t.XH.shape[1] + eff.extra_params
        dbic = n * math.log(max(sse1, 1e-300) / max(sse0, 1e-300)) + k * math.log(n)
        gain = cv0 - cv1
        sigma = float(self.d.noise_A[jm.j])
        physical = eff.physical(th1[th1.size - t.XH.shape[1]:], self.base.info(), jm.j)
        real = gain > 0 and gain >= REL_MIN * cv0 and math.sqrt(gain / n) >= ABS_MIN * sigma and dbic < 0 and physical
        info = {"physical": physical, "cv_rmse_before_A": math.sqrt(cv0 / n),
                "cv_rmse_after_A": math.sqrt(max(cv1, 0.0) / n),
                "explained_rms_A": math.sqrt(max(gain, 0.0) / n), "delta_bic": dbic, "real": real}
        return (gain / n if real else 0.0), info, t

    def _score_payload(self, eff: Effect) -> tuple[float, dict, dict[int, Term]] | None:
        terms: dict[int, Term] = {}
        for jm in self.joints:
            t = self._term(eff, jm, None)
            if t is not None and jm.rows.size >= 30:
                terms[jm.j] = t
        if len(terms) < 2:
            return None
        per_cv1 = {j: 0.0 for j in terms}
        for f in range(FOLDS):
            _, sse = self._shared_fit(terms, f)
            for j, v in sse.items():
                per_cv1[j] += v
        th, _ = self._shared_fit(terms, None)
        per_cv0, n_tot, sse0, sse1 = {}, 0, 0.0, 0.0
        for j, t in terms.items():
            jm = self.joints[j]
            X, y = jm.design()
            per_cv0[j] = _cv_sse(X, y, self.d.fold[jm.rows])
            _, s0 = _fit(X, y)
            _, s1 = _fit(X, y - (t.XH @ th) * self.payload_scale[j])
            sse0 += s0
            sse1 += s1
            n_tot += y.size
        cv0, cv1 = sum(per_cv0.values()), sum(per_cv1.values())
        gain = cv0 - cv1
        dbic = n_tot * math.log(max(sse1, 1e-300) / max(sse0, 1e-300)) + 4 * math.log(n_tot)
        sigma = float(np.mean(self.d.noise_A[list(terms)]))
        real = (gain > 0 and gain >= REL_MIN * cv0 and math.sqrt(gain / n_tot) >= ABS_MIN * sigma and dbic < 0
                and eff.physical(th, self.base.info(), 0))
        info = {"cv_rmse_before_A": math.sqrt(cv0 / n_tot), "cv_rmse_after_A": math.sqrt(max(cv1, 0) / n_tot),
                "explained_rms_A": math.sqrt(max(gain, 0) / n_tot), "delta_bic": dbic, "real": real,
                "per_joint_explained_rms_A": {self.d.names[j]: math.sqrt(max(per_cv0[j] - per_cv1[j], 0) /
                                                                         self.joints[j].rows.size) for j in terms}}
        score = sum(max(per_cv0[j] - per_cv1[j], 0.0) / self.joints[j].rows.size for j in terms)
        return (score if real else 0.0), info, terms

    # ------------------------------------------------------------------------------------ the loop

    def run(self) -> list[Step]:
        used: dict[str, set[int]] = {e.name: set() for e in self.effects}
        for _ in range(MAX_ROUNDS):
            resid = {jm.j: self._residual(jm) for jm in self.joints}
            best: tuple[float, Effect, dict, Any] | None = None
            for eff in self.effects:
                if eff.shared:
                    if self.payload_cols:
                        continue
                    sc = self._score_payload(eff)
                    if sc is not None and sc[0] > 0 and (best is None or sc[0] > best[0]):
                        best = (sc[0], eff, {"_shared": sc[1]}, sc[2])
                    continue
                found: dict[int, tuple[float, dict, Term]] = {}
                total = 0.0
                for jm in self.joints:
                    if jm.j in used[eff.name]:
                        continue
                    scj = self._score_joint(eff, jm, resid[jm.j])
                    if scj is not None and scj[0] > 0:
                        found[jm.j] = scj
                        total += scj[0]
                if found and (best is None or total > best[0]):
                    best = (total, eff, {j: v[1] for j, v in found.items()}, {j: v[2] for j, v in found.items()})
            if best is None:
                break
            _, eff, infos, terms = best
            ambiguous: dict[str, dict[str, dict[str, float]]] = {}  # judged on the final model (_settle_ambiguity)
            if eff.shared:
                self.payload_cols = terms
                joints = [nm for nm, v in infos["_shared"]["per_joint_explained_rms_A"].items()
                          if v >= ABS_MIN * self.d.noise_A[self.d.names.index(nm)]]
                self.steps.append(Step(eff.name, joints, {}, {"all": infos["_shared"]}))
            else:
                for j, t in terms.items():
                    self.joints[j].terms.append(t)
                    used[eff.name].add(j)
                    if t.cols.exclude is not None:
                        self._restrict(self.joints[j], t.cols.exclude)
                self.steps.append(Step(eff.name, [self.d.names[j] for j in sorted(terms)],
                                       {self.d.names[j]: t.hyper for j, t in terms.items()},
                                       {self.d.names[j]: infos[j] for j in sorted(terms)}, ambiguous))
            self._refit()
            self.snapshots.append(self.predict())
        self._prune()
        self._settle_ambiguity()
        return self.steps

    def _settle_ambiguity(self) -> None:
        """Which added effects the data cannot tell from another catalogue effect, judged on the final model: on each
        joint, the added effect is swapped for each other per-joint candidate (its best hyperparameter); when the
        swapped model is real against the model without the effect (the selection's tests, physical sign) and its
        held-out RMS is within AMBIGUOUS × the joint's noise of the final model's, both explain the data equally and
        the alternative is reported (``Step.ambiguous``). The shared payload and the play's predictor are not
        swapped."""
        info = self.base.info()
        for st in self.steps:
            st.ambiguous = {}
            if CATALOGUE[st.effect].shared:
                continue
            for nm in st.joints:
                jm = self.joints[self.d.names.index(nm)]
                t = next(tt for tt in jm.terms if tt.effect == st.effect and tt.hyper == st.hypers.get(nm))
                if t.cols.exclude is not None or jm.theta is None:
                    continue
                m = self._judged_on(CATALOGUE[st.effect], jm)  # the alternatives on the rows this one was judged on
                fold = self.d.fold[jm.rows][m]
                X1, _ = jm.design()
                y1 = self._payload_y(jm)
                X1, y1 = X1[m], y1[m]
                cv1, n = _cv_sse(X1, y1, fold), y1.size
                k = jm.col(t)
                own = t.cols.X @ jm.theta[k:k + t.cols.X.shape[1]] + (t.cols.offset if t.cols.offset is not None else 0)
                resid = self._residual(jm) + own  # the residual of the model without this effect (for spectra)
                with self._without(jm, t):
                    X0, _ = jm.design()
                    y0 = self._payload_y(jm)
                    X0, y0 = X0[m], y0[m]
                    cv0 = _cv_sse(X0, y0, fold)
                    sigma = float(self.d.noise_A[jm.j])
                    have = {tt.effect for tt in jm.terms}
                    for eff in self.effects:
                        if eff.shared or eff.name in have or eff.name in (st.effect, "backlash"):
                            continue
                        best = None
                        for h in eff.hypers(self.d, jm.j, resid, info):
                            ta = self._term(eff, jm, h)
                            if ta is None:
                                continue
                            ta = Term(ta.effect, ta.hyper, ta.cols, ta.XH[m], None if ta.offH is None else ta.offH[m])
                            if not _adds(X0, ta):
                                continue
                            Xa = np.hstack([X0, ta.XH])
                            ya = y0 - ta.offH if ta.offH is not None else y0
                            cva = _cv_sse(Xa, ya, fold)
                            if best is None or cva < best[0]:
                                best = (cva, ta, Xa, ya)
                        if best is None:
                            continue
                        cva, ta, Xa, ya = best
                        tha, _ = _fit(Xa, ya)
                        gain = cv0 - cva
                        real = (gain >= REL_MIN * cv0 and math.sqrt(max(gain, 0.0) / n) >= ABS_MIN * sigma
                                and eff.physical(tha[tha.size - ta.XH.shape[1]:], info, jm.j))
                        if real and math.sqrt(max(cva - cv1, 0.0) / n) < AMBIGUOUS * sigma:
                            st.ambiguous.setdefault(eff.name, {})[nm] = {
                                "cv_rmse_after_A": math.sqrt(max(cva, 0.0) / n),
                                "chosen_cv_rmse_after_A": math.sqrt(max(cv1, 0.0) / n)}

    def _restrict(self, jm: JointModel, exclude: np.ndarray) -> None:
        """Drop the joint's fit rows inside ``exclude`` (an effect's uncertain samples) from every later fit and score
        (the joint's own terms and its columns of a shared payload alike)."""
        keep = ~exclude[jm.rows]
        jm.rows = jm.rows[keep]
        jm.y = jm.y[keep]
        jm.base = jm.base[keep]
        shared = [self.payload_cols[jm.j]] if jm.j in self.payload_cols else []
        for t in jm.terms + shared:
            t.XH = t.XH[keep]
            if t.offH is not None:
                t.offH = t.offH[keep]

    def _prune(self) -> None:
        """Backward elimination: while some added effect (on a joint) is no longer real given the others, drop the
        weakest such one and refit — least useful first, so that a term the others only stood in for goes before the
        one they stood in for (a K_t error and a payload explain part of each other). An effect that took its
        uncertain samples out of the joint's rows cannot be re-scored on them and stays."""
        changed = False
        while True:
            weakest: tuple[float, Step, str, JointModel, Term] | None = None
            for st in self.steps:
                if CATALOGUE[st.effect].shared:
                    continue
                for nm in st.joints:
                    jm = self.joints[self.d.names.index(nm)]
                    t = next(tt for tt in jm.terms if tt.effect == st.effect and tt.hyper == st.hypers.get(nm))
                    if t.cols.exclude is not None:
                        continue
                    real, explained = self._still_real(jm, t)
                    if not real and (weakest is None or explained < weakest[0]):
                        weakest = (explained, st, nm, jm, t)
            if weakest is None:
                break
            _, st, nm, jm, t = weakest
            jm.terms.remove(t)
            st.joints = [x for x in st.joints if x != nm]
            for alt in list(st.ambiguous):
                st.ambiguous[alt] = {x: v for x, v in st.ambiguous[alt].items() if x != nm}
                if not st.ambiguous[alt]:
                    del st.ambiguous[alt]
            if not st.joints:
                self.steps.remove(st)
            self._refit()
            changed = True
        if changed:
            self.snapshots = self.snapshots[:1] + [self.predict()] * len(self.steps)

    def _still_real(self, jm: JointModel, t: Term) -> tuple[bool, float]:
        """Whether term ``t`` of joint ``jm`` passes the selection's tests against the model without it (the shared
        payload refitted too where it couples the joint), and the held-out RMS it explains [A]."""
        coupled = jm.j in self.payload_cols  # the shared payload was fitted with this term: refit it without
        # judged on the rows selection judged it on (all of them where the payload couples the joints)
        m = np.ones(jm.rows.size, dtype=bool) if coupled else self._judged_on(CATALOGUE[t.effect], jm)
        fold = self.d.fold[jm.rows][m]
        X1, _ = jm.design()
        y1 = self._payload_y(jm)
        X1, y1 = X1[m], y1[m]
        k = jm.col(t)
        cv1 = self._cv_payload() if coupled else _cv_sse(X1, y1, fold)
        with self._without(jm, t):
            X0, _ = jm.design()
            y0 = self._payload_y(jm)
            X0, y0 = X0[m], y0[m]
            cv0_own = _cv_sse(X0, y0, fold)
            cv0 = self._cv_payload() if coupled else cv0_own
        n = y1.size
        gain = cv0 - cv1  # over every joint the payload couples, against this joint's own error
        # the effect's own fitted current (filtered, on the fit rows) must reach what selection asks it to explain: a
        # term that the later ones reduced to a sliver is not named
        th1, _ = _fit(X1, y1)
        own = t.XH[m] @ th1[k:k + t.XH.shape[1]] + (t.offH[m] if t.offH is not None else 0.0)
        sigma = self.d.noise_A[jm.j]
        explained = math.sqrt(max(gain, 0.0) / n)
        big = math.sqrt(float(np.mean(np.square(own)))) >= ABS_MIN * sigma
        return bool(big and gain >= REL_MIN * cv0_own and explained >= ABS_MIN * sigma), explained

    def _cv_payload(self) -> float:
        """Held-out SSE summed over the payload's joints, the shared payload refitted on each fold's training rows
        with the joints' present columns (what dropping a term from one of them does to all)."""
        sse = 0.0
        for f in range(FOLDS):
            sse += sum(self._shared_fit(self.payload_cols, f)[1].values())
        return sse

    # ------------------------------------------------------------------------------------ results

    def predict(self) -> np.ndarray:
        """The current model's current at the work rate (T, n)."""
        d = self.d
        out = self.base.fixed.copy()
        for jm in self.joints:
            th = jm.theta if jm.theta is not None else np.zeros(0)
            k = 0
            fb = self.base.free[jm.j]
            if fb is not None:
                out[:, jm.j] += fb @ th[:fb.shape[1]]
                k = fb.shape[1]
            for t in jm.terms:
                kk = t.cols.X.shape[1]
                out[:, jm.j] += t.cols.X @ th[k:k + kk]
                if t.cols.offset is not None:
                    out[:, jm.j] += t.cols.offset
                k += kk
        if self.payload_theta is not None:
            for j, t in self.payload_cols.items():
                out[:, j] += (t.cols.X @ self.payload_theta) * self.payload_scale[j]
        del d
        return out

    def effect_params(self) -> list[tuple[str, list[str], dict[str, Any]]]:
        """(effect, joints, params per joint or shared) in the order added, from the final fit."""
        out = []
        info = self.base.info()
        for st in self.steps:
            eff = CATALOGUE[st.effect]
            if eff.shared:
                j0 = next(iter(self.payload_cols))
                if self.payload_theta is None:
                    raise RuntimeError(f"gap: the shared effect '{st.effect}' was chosen without a payload fit")
                out.append((st.effect, st.joints, eff.params(self.payload_theta, None, self.d, j0, info)))
                continue
            prm = {}
            for nm in st.joints:
                jm = self.joints[self.d.names.index(nm)]
                if jm.theta is None:
                    raise RuntimeError(f"gap: joint {nm} has a step of '{st.effect}' but no fit")
                fb = self.base.free[jm.j]
                k = fb.shape[1] if fb is not None else 0
                for t in jm.terms:
                    kk = t.cols.X.shape[1]
                    if t.effect == st.effect and t.hyper == st.hypers.get(nm):
                        prm[nm] = eff.params(jm.theta[k:k + kk], t.hyper, self.d, jm.j, info)
                    k += kk
            out.append((st.effect, st.joints, prm))
        return out
