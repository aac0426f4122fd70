"""A joint trajectory for TRACK mode as a table at the loop period: what the cycle samples in O(1).

Built off the loop (a clamped cubic spline through samples, or a replay plan's table with velocity and
feed-forward tables); the cycle only indexes rows and interpolates between two of them. The daemon builds it in
its planner process (dragd/teach/worker.py ``trajectory``): the spline's scipy is never imported beside the cycle.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np


class Trajectory:
    """A joint trajectory for TRACK mode, resampled once (off the loop) at the loop period.

    From samples t [s] (from 0, increasing) and q [rad] with a clamped cubic spline; the cycle then indexes the
    table (O(1), no allocation). ``load`` reads the same from a .npz (arrays ``t_s``, ``q_rad``) or CSV file
    (``t,q1..qN``). ``from_table`` takes a table already at the loop period (replay plans) with optional velocity
    and feed-forward torque tables, a repeated part (rows ``body_row`` to the end) and the waypoint marks.
    """

    def __init__(self, t_s: np.ndarray, q_rad: np.ndarray, dt_s: float, label: str = "track") -> None:
        t_s = np.asarray(t_s, dtype=float)
        q_rad = np.asarray(q_rad, dtype=float)
        if t_s.ndim != 1 or q_rad.ndim != 2 or q_rad.shape[0] != t_s.shape[0] or t_s.shape[0] < 2:
            raise ValueError(f"trajectory: expected t (N ≥ 2,) and q (N, joints), got {t_s.shape} and {q_rad.shape}")
        if not (np.all(np.isfinite(t_s)) and np.all(np.isfinite(q_rad))):
            raise ValueError("trajectory: t and q must be finite numbers")
        if np.any(np.diff(t_s) <= 0):
            raise ValueError("trajectory: t must increase strictly")
        if t_s[0] != 0.0:
            raise ValueError(f"trajectory: t must start at 0, got {t_s[0]}")
        self.label = label
        self.dt_s = dt_s
        self.duration_s = float(t_s[-1])
        from scipy.interpolate import CubicSpline  # in the planner process (the daemon never builds one itself)

        grid = np.arange(0.0, self.duration_s + dt_s / 2, dt_s)
        self.table = np.ascontiguousarray(CubicSpline(t_s, q_rad, bc_type="clamped")(grid))
        self.start_q = self.table[0].copy()
        self._init_tables(None, None, 0, [], {})

    def _init_tables(self, dq: np.ndarray | None, ff: np.ndarray | None, body_row: int,
                     marks: list[dict[str, Any]], info: dict[str, Any]) -> None:
        self.dq_table = dq  # rad/s at rate 1 (None: the cycle differentiates q_ref)
        self.ff_table = ff  # N·m of M(q)q̈ + C(q,q̇)q̇ at rate 1 (None: no inertial feed-forward)
        self.pred_table: np.ndarray | None = None  # the same for the residual monitor only (not commanded)
        self.residual_monitor = True
        self.body_row = int(body_row)
        self.body_start_s = self.body_row * self.dt_s
        self.marks = marks
        self.info = info
        self.outcome = "done"  # what Track reports when the path ends (a stream says why it ended)
        self._d = np.zeros(self.table.shape[1])
        self.k = 0  # row and fraction of the last sample()
        self.f = 0.0

    @classmethod
    def from_table(cls, q: np.ndarray, dt_s: float, label: str = "replay", *, dq: np.ndarray | None = None,
                   ff_Nm: np.ndarray | None = None, body_row: int = 0, marks: list[dict[str, Any]] | None = None,
                   info: dict[str, Any] | None = None) -> Trajectory:
        q = np.ascontiguousarray(q, dtype=float)
        if q.ndim != 2 or q.shape[0] < 2 or not np.all(np.isfinite(q)):
            raise ValueError(f"trajectory: expected a finite table (N ≥ 2, joints), got {q.shape}")
        for name, a in (("dq", dq), ("ff_Nm", ff_Nm)):
            if a is not None and (a.shape != q.shape or not np.all(np.isfinite(a))):
                raise ValueError(f"trajectory: {name}: expected a finite table of shape {q.shape}, got {a.shape}")
        if not 0 <= body_row < q.shape[0] - 1:
            raise ValueError(f"trajectory: body_row: expected 0..{q.shape[0] - 2}, got {body_row}")
        self = cls.__new__(cls)
        self.label = label
        self.dt_s = dt_s
        self.table = q
        self.duration_s = (q.shape[0] - 1) * dt_s
        self.start_q = q[0].copy()
        self._init_tables(None if dq is None else np.ascontiguousarray(dq, dtype=float),
                          None if ff_Nm is None else np.ascontiguousarray(ff_Nm, dtype=float), body_row,
                          list(marks or []), dict(info or {}))
        return self

    @classmethod
    def load(cls, path: str | Path, dt_s: float, label: str = "track") -> Trajectory:
        path = Path(path)
        if not path.is_file():
            raise ValueError(f"trajectory file {path}: not found")
        try:
            if path.suffix == ".npz":
                with np.load(path) as z:
                    return cls(z["t_s"], z["q_rad"], dt_s, label)
            data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
        except (KeyError, ValueError, OSError) as exc:
            raise ValueError(f"trajectory file {path}: expected .npz with t_s, q_rad or CSV t,q1..qN: {exc}") from None
        return cls(data[:, 0], data[:, 1:], dt_s, label)

    def sample(self, t: float, out: np.ndarray) -> np.ndarray:
        """q at time ``t`` (linear interpolation between the table's rows; clamped to the ends)."""
        last = self.table.shape[0] - 1
        x = t / self.dt_s
        if x <= 0.0:
            k, f = 0, 0.0
        elif x >= last:
            k, f = last, 0.0
        else:
            k = int(x)
            f = x - k
        self.k, self.f = k, f
        return self.row(self.table, out)

    def row(self, table: np.ndarray, out: np.ndarray) -> np.ndarray:
        """Another table (velocity, feed-forward) at the time of the last ``sample``."""
        k, f = self.k, self.f
        out[:] = table[k]
        if f > 0.0:
            np.subtract(table[k + 1], table[k], out=self._d)
            self._d *= f
            out += self._d
        return out
