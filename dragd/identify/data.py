"""Identification logs: loading (daemon MCAP or CSV), validation, zero-phase filtering, derivatives, masks.

Inputs
- MCAP telemetry of the daemon (topic ``/dragd/cycle``: ``t_s``, ``mode``, ``q_rad``, ``current_measured_A``);
  only rows in mode ``track`` are used (the drives follow the excitation in CSP, the measured current is the
  whole motor current). Read by dragd/telemetry/reader.py: a file whose writer was killed is used up to its last
  complete chunk, with a warning naming it.
- CSV ``t,q1..qN,i1..iN`` with optional ``dq1..dqN`` (s, rad, A, rad/s) from any arm.

Problems are errors naming the file and what is wrong (missing columns, non-monotonic time, no usable rows,
a joint count that differs from the robot's) or warnings (rows with NaN dropped, gaps split).

Signal processing (applied the same way to both sides of every regression):
1. contiguous stretches ("segments") are split at gaps; each is resampled on a uniform grid;
2. a zero-phase anti-alias low-pass brings the log to the work rate (≤ 200 Hz) — on q and i alike;
3. q̃ = zero-phase low-pass of q (``deriv_cutoff_Hz``); q̇, q̈ by central differences of q̃ (or the
   log's dq, filtered the same way, when it has one);
4. the regression filter H (zero-phase Butterworth, ``cutoff_Hz``) is applied to the current *and* to every
   regressor column computed from (q̃, q̇, q̈); rows are then decimated to ~2.5·cutoff (residuals ≈ white).
"""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.ndimage import minimum_filter1d
from scipy.signal import butter, sosfiltfilt


class LogError(ValueError):
    """A log that cannot be used; the message names the file and what is wrong."""


@dataclass
class Log:
    path: str
    t: np.ndarray  # (N,) s
    q: np.ndarray  # (N, n) rad
    i: np.ndarray  # (N, n) A
    dq: np.ndarray | None = None  # (N, n) rad/s when the log has a velocity column
    warnings: list[str] = field(default_factory=list)
    modes: dict[str, int] = field(default_factory=dict)

    @property
    def n(self) -> int:
        return int(self.q.shape[1])

    @property
    def rate_Hz(self) -> float:
        d = np.diff(self.t)
        return float(1.0 / np.median(d)) if d.size else 0.0

    def check_robot(self, joint_names: tuple[str, ...] | list[str], robot: str) -> None:
        if self.n != len(joint_names):
            raise LogError(f"{self.path}: joints: the log has {self.n} joints (q1..q{self.n}), the robot {robot} has "
                           f"{len(joint_names)} ({', '.join(joint_names)})")

    def select(self, mask: np.ndarray) -> Log:
        return Log(self.path, self.t[mask], self.q[mask], self.i[mask], None if self.dq is None else self.dq[mask],
                   list(self.warnings), dict(self.modes))


# ------------------------------------------------------------------------------------------ loading


def load_log(path: str | Path, modes: tuple[str, ...] = ("track",)) -> Log:
    """Read a daemon MCAP (rows in ``modes``) or a CSV log; validate time and values."""
    path = Path(path)
    if not path.is_file():
        raise LogError(f"{path}: file not found")
    if path.suffix.lower() == ".mcap":
        log = _load_mcap(path, modes)
    elif path.suffix.lower() in (".csv", ".txt"):
        log = _load_csv(path)
    else:
        raise LogError(f"{path}: expected a .mcap (dragd telemetry) or .csv (t,q1..qN,i1..iN[,dq1..dqN]) file")
    return _validate(log)


def _load_mcap(path: Path, modes: tuple[str, ...]) -> Log:
    from dragd.telemetry.reader import TelemetryFileError, read_log

    try:
        tl = read_log(path, ("t_s", "mode", "q_rad", "current_measured_A"))
    except TelemetryFileError as exc:
        raise LogError(str(exc)) from None
    if tl.n_rows == 0:
        raise LogError(f"{path}: no /dragd/cycle messages (expected dragd telemetry)")
    rows = tl.rows
    mode = rows["mode"]
    counts = {str(m): int(c) for m, c in zip(*np.unique(mode, return_counts=True))}
    keep = np.isin(mode, modes)
    if not keep.any():
        raise LogError(f"{path}: no rows in mode {'/'.join(modes)} (rows per mode: "
                       f"{', '.join(f'{k} {v}' for k, v in counts.items())}); identification uses tracked excitation")
    t, q, i = rows["t_s"][keep], rows["q_rad"][keep], rows["current_measured_A"][keep]
    if q.ndim != 2 or i.shape != q.shape:
        raise LogError(f"{path}: /dragd/cycle: q_rad and current_measured_A must have one value per joint, got "
                       f"shapes {q.shape} and {i.shape}")
    log = Log(str(path), t, q, i, None, [], counts)
    if tl.warning:
        log.warnings.append(tl.warning)
    dropped = int(mode.shape[0] - t.shape[0])
    if dropped:
        log.warnings.append(f"{dropped} rows not in mode {'/'.join(modes)} ignored (rows per mode: "
                            f"{', '.join(f'{k} {v}' for k, v in counts.items())})")
    return log


_COL = re.compile(r"^(t|q\d+|i\d+|dq\d+)$")


def _load_csv(path: Path) -> Log:
    with path.open() as fh:
        header = fh.readline().strip()
    cols = [c.strip().lower() for c in header.split(",")]
    if not header or not any(c in ("t", "q1", "i1") for c in cols):
        raise LogError(f"{path}: expected a header line t,q1..qN,i1..iN[,dq1..dqN], got {header[:80]!r}")
    unknown = [c for c in cols if not _COL.match(c)]
    if unknown:
        raise LogError(f"{path}: columns: unknown {', '.join(unknown)}; expected t, q1..qN, i1..iN, optional dq1..dqN")
    n = max([int(c[1:]) for c in cols if c.startswith("q") and c[1:].isdigit()] + [0])
    n = max([n] + [int(c[1:]) for c in cols if c.startswith("i")])
    want = ["t"] + [f"q{k}" for k in range(1, n + 1)] + [f"i{k}" for k in range(1, n + 1)]
    missing = [c for c in want if c not in cols]
    if n == 0 or missing:
        raise LogError(f"{path}: columns: missing {', '.join(missing) if missing else 'q1, i1'}; expected t, q1..qN, "
                       f"i1..iN (optional dq1..dqN), got {', '.join(cols)}")
    dq_cols = [f"dq{k}" for k in range(1, n + 1)]
    have_dq = [c for c in dq_cols if c in cols]
    if have_dq and len(have_dq) != n:
        raise LogError(f"{path}: columns: dq columns incomplete: have {', '.join(have_dq)}, expected dq1..dq{n} or none")
    try:
        data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2, dtype=float)
    except ValueError as exc:
        raise LogError(f"{path}: not a numeric CSV: {_csv_error(path, exc)}") from None
    if data.shape[0] == 0:
        raise LogError(f"{path}: no data rows")
    if data.shape[1] != len(cols):
        raise LogError(f"{path}: rows have {data.shape[1]} values, the header {len(cols)} columns")
    idx = {c: k for k, c in enumerate(cols)}
    t = data[:, idx["t"]]
    q = data[:, [idx[f"q{k}"] for k in range(1, n + 1)]]
    i = data[:, [idx[f"i{k}"] for k in range(1, n + 1)]]
    dq = data[:, [idx[c] for c in dq_cols]] if have_dq else None
    return Log(str(path), t, q, i, dq, [])


def _csv_error(path: Path, exc: Exception) -> str:
    """Find the first bad line for a helpful message (loadtxt's own is terse)."""
    with path.open() as fh:
        next(fh)
        for lineno, line in enumerate(fh, start=2):
            for v in line.strip().split(","):
                try:
                    float(v)
                except ValueError:
                    return f"line {lineno}: {v.strip()!r} is not a number"
    return str(exc)


def _validate(log: Log) -> Log:
    arrays = [log.t[:, None], log.q, log.i] + ([log.dq] if log.dq is not None else [])
    bad = ~np.all(np.isfinite(np.hstack(arrays)), axis=1)
    if bad.any():
        rows = np.nonzero(bad)[0]
        where = ", ".join(str(r + 1) for r in rows[:5]) + (" ..." if rows.size > 5 else "")
        if bad.all():
            raise LogError(f"{log.path}: every row has NaN or infinite values")
        log = log.select(~bad)
        log.warnings.append(f"{rows.size} rows with NaN or infinite values dropped (data rows {where})")
    if log.t.shape[0] < 50:
        raise LogError(f"{log.path}: only {log.t.shape[0]} usable rows; expected a log of at least a few seconds")
    d = np.diff(log.t)
    if np.any(d <= 0):
        k = int(np.nonzero(d <= 0)[0][0])
        raise LogError(f"{log.path}: t: expected strictly increasing time, got t = {log.t[k + 1]:.6f} s after "
                       f"{log.t[k]:.6f} s at data row {k + 2}")
    return log


# ------------------------------------------------------------------------------------------ processing


@functools.lru_cache(maxsize=64)
def _butter_sos(order: int, cutoff_Hz: float, fs_Hz: float) -> np.ndarray:
    return butter(order, cutoff_Hz, fs=fs_Hz, output="sos")


def lowpass(x: np.ndarray, cutoff_Hz: float, fs_Hz: float, order: int = 4) -> np.ndarray:
    """Zero-phase Butterworth low-pass along axis 0 (no-op when the cutoff is at/above Nyquist)."""
    if cutoff_Hz >= 0.45 * fs_Hz:
        return x.copy()
    sos = _butter_sos(order, float(cutoff_Hz), float(fs_Hz))
    padlen = min(x.shape[0] - 1, 3 * (2 * sos.shape[0] + 1) * 10)
    return sosfiltfilt(sos, x, axis=0, padlen=padlen)


@dataclass
class Segment:
    start: int
    stop: int  # exclusive


@dataclass
class Prepared:
    """A log at the work rate: uniform samples per segment, filtered positions and derivatives."""

    path: str
    fs: float
    t: np.ndarray
    q: np.ndarray  # zero-phase filtered positions
    dq: np.ndarray
    ddq: np.ndarray
    i: np.ndarray  # current after the anti-alias filter (not yet the regression filter)
    segments: list[Segment]
    cutoff_Hz: float
    deriv_cutoff_Hz: float
    warnings: list[str]
    source_rate_Hz: float
    q_raw: np.ndarray | None = None  # positions after the anti-alias filter only (stick detection)

    @property
    def n(self) -> int:
        return int(self.q.shape[1])

    def regfilter(self, x: np.ndarray, cutoff_Hz: float | None = None) -> np.ndarray:
        """The regression filter H, per segment (zero-phase): apply it to the current and to every column."""
        out = np.empty_like(x, dtype=float)
        fc = cutoff_Hz or self.cutoff_Hz
        for s in self.segments:
            out[s.start:s.stop] = lowpass(x[s.start:s.stop], fc, self.fs)
        return out

    def rows(self, cutoff_Hz: float | None = None) -> np.ndarray:
        """Decimated row indices for regressions (~2.5·cutoff), away from segment edges (filter transients)."""
        fc = cutoff_Hz or self.cutoff_Hz
        step = max(1, int(self.fs / (2.5 * fc)))
        edge = int(round(self.fs / fc))
        out = [np.arange(s.start + edge, s.stop - edge, step) for s in self.segments if s.stop - s.start > 2 * edge + step]
        return np.concatenate(out) if out else np.zeros(0, dtype=int)


def _segments(t: np.ndarray, max_gap_s: float) -> list[Segment]:
    gaps = np.nonzero(np.diff(t) > max_gap_s)[0]
    starts = np.concatenate([[0], gaps + 1])
    stops = np.concatenate([gaps + 1, [t.shape[0]]])
    return [Segment(int(a), int(b)) for a, b in zip(starts, stops)]


def prepare(log: Log, cutoff_Hz: float = 5.0, deriv_cutoff_Hz: float = 20.0, work_rate_Hz: float = 200.0,
            min_segment_s: float = 2.0, max_gap_s: float = 0.05) -> Prepared:
    """Uniform, anti-aliased, zero-phase filtered data at ≤ ``work_rate_Hz`` (see the module docstring)."""
    fs_in = log.rate_Hz
    dt = 1.0 / fs_in
    warnings = list(log.warnings)
    # short gaps (missed cycles of a loaded controller) are interpolated over; long ones split the log
    max_gap = max(5.5 * dt, max_gap_s)
    short_gaps = int(np.sum((np.diff(log.t) > 1.5 * dt) & (np.diff(log.t) <= max_gap)))
    if short_gaps:
        warnings.append(f"{short_gaps} short gaps (missed samples, ≤ {max_gap * 1e3:.0f} ms) interpolated over")
    segs = _segments(log.t, max_gap)
    if len(segs) > 1:
        warnings.append(f"{len(segs) - 1} gaps longer than {max_gap * 1e3:.0f} ms: the log is processed as "
                        f"{len(segs)} separate stretches")
    k = max(1, int(round(fs_in / work_rate_Hz)))
    fs = fs_in / k
    T, Q, I, DQ, out_segs = [], [], [], [], []
    pos = 0
    short = 0
    for s in segs:
        t = log.t[s.start:s.stop]
        if t[-1] - t[0] < min_segment_s:
            short += 1
            continue
        grid = np.arange(t[0], t[-1] + dt / 2, dt)
        q = np.column_stack([np.interp(grid, t, log.q[s.start:s.stop, j]) for j in range(log.n)])
        i = np.column_stack([np.interp(grid, t, log.i[s.start:s.stop, j]) for j in range(log.n)])
        dq = None if log.dq is None else np.column_stack(
            [np.interp(grid, t, log.dq[s.start:s.stop, j]) for j in range(log.n)])
        if k > 1:  # zero-phase anti-alias low-pass, then every k-th sample — the same on q, i (and dq)
            q = lowpass(q, 0.4 * fs, fs_in)[::k]
            i = lowpass(i, 0.4 * fs, fs_in)[::k]
            dq = None if dq is None else lowpass(dq, 0.4 * fs, fs_in)[::k]
            grid = grid[::k]
        T.append(grid)
        Q.append(q)
        I.append(i)
        if dq is not None:
            DQ.append(dq)
        out_segs.append(Segment(pos, pos + grid.shape[0]))
        pos += grid.shape[0]
    if short:
        warnings.append(f"{short} stretches shorter than {min_segment_s:g} s ignored")
    if not out_segs:
        raise LogError(f"{log.path}: no stretch of at least {min_segment_s:g} s of contiguous samples")
    t = np.concatenate(T)
    qr = np.concatenate(Q)
    i = np.concatenate(I)
    qf = np.empty_like(qr)
    dq = np.empty_like(qr)
    ddq = np.empty_like(qr)
    dq_log = np.concatenate(DQ) if DQ else None
    for s in out_segs:
        sl = slice(s.start, s.stop)
        qf[sl] = lowpass(qr[sl], deriv_cutoff_Hz, fs)
        if dq_log is not None:
            dq[sl] = lowpass(dq_log[sl], deriv_cutoff_Hz, fs)
        else:
            dq[sl] = np.gradient(qf[sl], 1.0 / fs, axis=0)
        ddq[sl] = np.gradient(dq[sl], 1.0 / fs, axis=0)
    return Prepared(log.path, fs, t, qf, dq, ddq, i, out_segs, cutoff_Hz, deriv_cutoff_Hz, warnings, fs_in, qr)


# ------------------------------------------------------------------------------------------ masks


def sliding(dq: np.ndarray, v_rest: float, guard: int) -> np.ndarray:
    """|q̇| > v_rest at every sample within ±guard (a joint sliding, not in or near a stick/reversal)."""
    m = np.abs(dq) > v_rest
    if guard > 0:
        m = minimum_filter1d(m.astype(np.uint8), size=2 * guard + 1, axis=0, mode="constant").astype(bool)
    return m


def motion_summary(p: Prepared) -> list[dict[str, float]]:
    """Per joint: position range, max speed, sliding fraction (for 'never moves' and excitation reports)."""
    out = []
    for j in range(p.n):
        out.append({"range_rad": float(np.ptp(p.q[:, j])), "max_speed_rad_s": float(np.abs(p.dq[:, j]).max()),
                    "moving_fraction": float(np.mean(np.abs(p.dq[:, j]) > 0.01))})
    return out
