"""Identification logs: loading (daemon MCAP or CSV), validation, zero-phase filtering, derivatives, masks.

Inputs
- MCAP telemetry of the daemon (topic ``/dragd/cycle``: ``t_s``, ``mode``, ``q_rad``, ``current_measured_A``);
  only rows in mode ``track`` are used (the drives follow the excitation in CSP, the measured current is the
  whole motor current). Read by dragd/telemetry/reader.py: a file whose writer was killed is used up to its last
  complete chunk, with a warning naming it.
- CSV ``t,q1..qN,i1..iN`` with optional ``dq1..dqN``, ``i_target1..N``, ``tau_target1..N`` (s, rad, A, rad/s,
  A, N·m) from any arm; headerless: 1+5N columns = the UR RTDE recording (t,q,qd,i,i_target,tau_target), 1+3N =
  t,q,dq,i, 1+2N = t,q,i (N = the robot's joints). A name without extension is sniffed (or NAME.csv/.mcap).

Problems are errors naming the file, the column and the line (missing columns, NaN/inf values, time not strictly
increasing, malformed rows, angles in degrees, no usable rows, a joint count that differs from the robot's) —
``drop_bad_rows`` skips NaN/malformed/out-of-sequence rows instead, naming them in a warning; a truncated last row
(writer stopped) is skipped with a warning; gaps are split with a warning. See docs/IDENTIFICATION.md.

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
    i_target: np.ndarray | None = None  # (N, n) A: the controller's current setpoint (UR RTDE logs)
    tau_target: np.ndarray | None = None  # (N, n) N·m: the controller's torque setpoint (UR RTDE logs)
    columns: list[str] | None = None  # the columns as read (header or layout)
    lines: np.ndarray | None = None  # (N,) file line (CSV) or message number (MCAP) of each row, for messages
    row_word: str = "line"

    @property
    def n(self) -> int:
        return int(self.q.shape[1])

    @property
    def rate_Hz(self) -> float:
        d = np.diff(self.t)
        return float(1.0 / np.median(d)) if d.size else 0.0

    @property
    def from_mcap(self) -> bool:
        """Read from dragd telemetry (columns named as its fields, rows as message numbers)."""
        return self.columns is not None and self.columns[0] != "t"

    def q_names(self) -> list[str]:
        return [f"q_rad[{k}]" if self.from_mcap else f"q{k + 1}" for k in range(self.n)]

    def dq_names(self) -> list[str]:
        return [f"dq{k + 1}" for k in range(self.n)]

    def named_columns(self) -> list[tuple[str, np.ndarray]]:
        """(column name, values) of every array read, in file order where known."""
        mcap = self.from_mcap
        out = [("t_s" if mcap else "t", self.t)]
        for pre, arr in (("q", self.q), ("i", self.i), ("dq", self.dq), ("i_target", self.i_target),
                         ("tau_target", self.tau_target)):
            if arr is not None:
                for k in range(self.n):
                    nm = {"q": f"q_rad[{k}]", "i": f"current_measured_A[{k}]"}.get(pre, f"{pre}{k + 1}") if mcap \
                        else f"{pre}{k + 1}"
                    out.append((nm, arr[:, k]))
        return out

    def describe_columns(self) -> str:
        """'t, q1..q5, i1..i5' (runs of a prefix with consecutive numbers compressed)."""
        if not self.columns:
            return f"t, q1..q{self.n}, i1..i{self.n}"
        out: list[str] = []
        run: list[str] = []
        for c in self.columns + [""]:
            m = re.fullmatch(r"(\D+)(\d+)", c)
            last = re.fullmatch(r"(\D+)(\d+)", run[-1]) if run else None
            if m and last and last.group(1) == m.group(1) and int(m.group(2)) == int(last.group(2)) + 1:
                run.append(c)
                continue
            if run:
                out.append(run[0] if len(run) == 1 else f"{run[0]}..{run[-1]}")
            run = [c] if m else []
            if c and not m:
                out.append(c)
        return ", ".join(out)

    def check_robot(self, joint_names: tuple[str, ...] | list[str], robot: str) -> None:
        if self.n != len(joint_names):
            raise LogError(f"{self.path}: joints: the log has {self.n} joints (q1..q{self.n}), the robot {robot} has "
                           f"{len(joint_names)} ({', '.join(joint_names)}); columns found: {self.describe_columns()}")

    def select(self, mask: np.ndarray) -> Log:
        def s(a: np.ndarray | None) -> np.ndarray | None:
            return None if a is None else a[mask]

        return Log(self.path, self.t[mask], self.q[mask], self.i[mask], s(self.dq), list(self.warnings),
                   dict(self.modes), s(self.i_target), s(self.tau_target), self.columns, s(self.lines), self.row_word)


# ------------------------------------------------------------------------------------------ loading

_MCAP_MAGIC = b"\x89MCAP"
# headerless layouts by column count for n joints (the UR RTDE recording first: 1+5n)
_UR_LAYOUT = ("q", "dq", "i", "i_target", "tau_target")
_HEADERLESS = {5: _UR_LAYOUT, 3: ("q", "dq", "i"), 2: ("q", "i")}
_DEG_SPAN_RAD = 1.5 * 2.0 * np.pi  # a revolute joint's log beyond this span (or |q| beyond it) is not radians


def load_log(path: str | Path, modes: tuple[str, ...] = ("track",), joints: tuple[str, ...] | list[str] | None = None,
             robot: str = "robot", drop_bad_rows: bool = False, layout: tuple[str, ...] | None = None) -> Log:
    """Read a daemon MCAP (rows in ``modes``) or a CSV log (header ``t,q1..`` or a headerless layout); validate.

    ``joints`` (the robot's joint names) picks the layout of a headerless CSV and checks the joint count;
    ``layout`` names a headerless CSV's blocks of N columns after t instead (``parse_layout``: e.g. q,dq,i,- where
    ``-`` is a block that is not read); ``drop_bad_rows`` skips NaN/inf, malformed and out-of-sequence rows with a
    warning naming them (else: error).
    """
    path = Path(path)
    found = ""
    if not path.is_file() and not path.suffix:  # a log named without its extension (as datasets list them)
        alt = [path.with_name(path.name + s) for s in (".csv", ".mcap") if path.with_name(path.name + s).is_file()]
        if len(alt) == 1:
            path, found = alt[0], f"{path} not found: read {alt[0].name}"
    if not path.is_file():
        raise LogError(f"{path}: file not found")
    suffix = path.suffix.lower()
    if suffix == ".mcap":
        kind = "mcap"
    elif suffix in (".csv", ".txt"):
        kind = "csv"
    else:  # no/unknown extension (e.g. the UR10e dataset's names as given): sniff the content
        with path.open("rb") as fh:
            head = fh.read(4096)
        if head.startswith(_MCAP_MAGIC):
            kind = "mcap"
        elif head and b"\x00" not in head and re.match(rb"^[\s\w.,+\-]*$", head.split(b"\n")[0]):
            kind = "csv"
        else:
            raise LogError(f"{path}: expected a .mcap (dragd telemetry) or .csv (t,q1..qN,i1..iN[,dq1..dqN]) file; "
                           "the content is neither")
    n_joints = None if joints is None else len(joints)
    log = _load_mcap(path, modes) if kind == "mcap" else _load_csv(path, n_joints, drop_bad_rows, layout)
    if found:
        log.warnings.insert(0, found)
    log = _validate(log, drop_bad_rows)
    if joints is not None:
        log.check_robot(joints, robot)
    return log


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
    counts = {str(m): int(c) for m, c in zip(*np.unique(mode, return_counts=True), strict=True)}
    keep = np.isin(mode, modes)
    if not keep.any():
        raise LogError(f"{path}: no rows in mode {'/'.join(modes)} (rows per mode: "
                       f"{', '.join(f'{k} {v}' for k, v in counts.items())}); identification uses tracked excitation")
    t, q, i = rows["t_s"][keep], rows["q_rad"][keep], rows["current_measured_A"][keep]
    if q.ndim != 2 or i.shape != q.shape:
        raise LogError(f"{path}: /dragd/cycle: q_rad and current_measured_A must have one value per joint, got "
                       f"shapes {q.shape} and {i.shape}")
    n = q.shape[1]
    log = Log(str(path), t, q, i, None, [], counts, columns=["t_s", *[f"q_rad[{k}]" for k in range(n)],
                                                              *[f"current_measured_A[{k}]" for k in range(n)]],
              lines=np.nonzero(keep)[0] + 1, row_word="message")
    if tl.warning:
        log.warnings.append(tl.warning)
    dropped = int(mode.shape[0] - t.shape[0])
    if dropped:
        log.warnings.append(f"{dropped} rows not in mode {'/'.join(modes)} ignored (rows per mode: "
                            f"{', '.join(f'{k} {v}' for k, v in counts.items())})")
    return log


_COL = re.compile(r"^(t|q\d+|i\d+|dq\d+|i_target\d+|tau_target\d+)$")


def _is_number(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


def _ranges(lines: list[int] | np.ndarray) -> str:
    """'2–10, 57' from sorted line numbers."""
    out: list[str] = []
    ls = [int(x) for x in lines]
    k = 0
    while k < len(ls):
        a = b = ls[k]
        while k + 1 < len(ls) and ls[k + 1] == b + 1:
            k += 1
            b = ls[k]
        out.append(str(a) if a == b else f"{a}–{b}")
        k += 1
    return ", ".join(out)


def _first(lines: np.ndarray, k: int = 5) -> str:
    return ", ".join(str(int(x)) for x in lines[:k]) + (" ..." if lines.size > k else "")


LAYOUT_KINDS = ("q", "dq", "i", "i_target", "tau_target", "-")


def parse_layout(text: str) -> tuple[str, ...]:
    """``--columns q,dq,i,-`` → the blocks of a headerless CSV after t (each N columns; ``-`` not read)."""
    kinds = tuple(k.strip() for k in text.split(",") if k.strip())
    bad = [k for k in kinds if k not in LAYOUT_KINDS]
    if bad or not kinds:
        raise LogError(f"--columns: expected blocks among {', '.join(LAYOUT_KINDS)} ('-': N columns not read), "
                       f"comma-separated after t, e.g. q,dq,i,-; got {text!r}")
    for need in ("q", "i"):
        if need not in kinds:
            raise LogError(f"--columns: the layout needs a '{need}' block, got {text!r}")
    twice = sorted({k for k in kinds if k != "-" and kinds.count(k) > 1})
    if twice:
        raise LogError(f"--columns: each block once (except '-'), got {', '.join(twice)} twice in {text!r}")
    return kinds


def _load_csv(path: Path, n_joints: int | None, drop_bad_rows: bool, layout: tuple[str, ...] | None = None) -> Log:
    raw = path.read_text(errors="replace").splitlines()
    numbered = [(k + 1, s.strip()) for k, s in enumerate(raw) if s.strip()]
    if not numbered:
        raise LogError(f"{path}: empty file; expected CSV t,q1..qN,i1..iN[,dq1..dqN]")
    first = [c.strip() for c in numbered[0][1].rstrip(",").split(",")]
    warnings: list[str] = []
    if all(_is_number(c) for c in first):  # headerless: the layout follows from the column count
        ncols = len(first)
        cols, kinds = _headerless_columns(path, ncols, n_joints, layout)
        warnings.append(f"headerless {ncols} columns: read as " + (
            "UR RTDE layout t,q,qd,i,i_target,tau_target" if kinds == _UR_LAYOUT else ",".join(["t", *kinds]))
            + f" ({(ncols - 1) // len(kinds)} joints; s, rad, rad/s, A, N·m)")
        body = numbered
    else:
        cols = [c.lower() for c in first]
        if not any(c in ("t", "q1", "i1") for c in cols):
            raise LogError(f"{path}: expected a header line t,q1..qN,i1..iN[,dq1..dqN] (or a headerless UR RTDE "
                           f"log), got {numbered[0][1][:80]!r}")
        unknown = [c for c in cols if not _COL.match(c)]
        if unknown:
            raise LogError(f"{path}: columns: unknown {', '.join(unknown)}; expected t, q1..qN, i1..iN, optional "
                           "dq1..dqN, i_target1..N, tau_target1..N")
        body = numbered[1:]
    n = max([int(c[1:]) for c in cols if re.fullmatch(r"q\d+", c)] + [int(c[1:]) for c in cols
                                                                      if re.fullmatch(r"i\d+", c)] + [0])
    want = ["t"] + [f"q{k}" for k in range(1, n + 1)] + [f"i{k}" for k in range(1, n + 1)]
    missing = [c for c in want if c not in cols]
    if n == 0 or missing:
        raise LogError(f"{path}: columns: missing {', '.join(missing) if missing else 'q1, i1'}; expected t, q1..qN, "
                       f"i1..iN (optional dq1..dqN), got {', '.join(cols)}")
    opt: dict[str, list[str] | None] = {}
    for pre in ("dq", "i_target", "tau_target"):
        names = [f"{pre}{k}" for k in range(1, n + 1)]
        have = [c for c in names if c in cols]
        if have and len(have) != n:
            raise LogError(f"{path}: columns: {pre} columns incomplete: have {', '.join(have)}, expected "
                           f"{pre}1..{pre}{n} or none")
        opt[pre] = names if have else None
    if not body:
        raise LogError(f"{path}: no data rows")
    lines = np.array([ln for ln, _ in body], dtype=np.int64)
    try:  # fast path: every row complete and numeric
        data = np.loadtxt([s.rstrip(",") for _, s in body], delimiter=",", ndmin=2, dtype=float)
        if data.shape[1] != len(cols):
            raise ValueError("column count")
    except ValueError:
        data, lines, warnings_bad = _parse_rows(path, body, len(cols), drop_bad_rows)
        warnings += warnings_bad
    idx = {c: k for k, c in enumerate(cols)}

    def take(names: list[str] | None) -> np.ndarray | None:
        return None if names is None else data[:, [idx[c] for c in names]]

    def block(names: list[str]) -> np.ndarray:
        return data[:, [idx[c] for c in names]]

    return Log(str(path), data[:, idx["t"]], block(want[1:n + 1]), block(want[n + 1:]), take(opt["dq"]), warnings,
               i_target=take(opt["i_target"]), tau_target=take(opt["tau_target"]), columns=cols, lines=lines)


def _headerless_columns(path: Path, ncols: int, n_joints: int | None,
                        layout: tuple[str, ...] | None = None) -> tuple[list[str], tuple[str, ...]]:
    """Column names of a headerless CSV: 1+5n = UR RTDE, 1+3n = t,q,dq,i, 1+2n = t,q,i (n from the robot), or the
    given ``layout`` (blocks of n; a '-' block's columns are named skip1.. and not read)."""
    def names(kinds: tuple[str, ...], n: int) -> tuple[list[str], tuple[str, ...]]:
        cols = ["t"]
        for b, k in enumerate(kinds):
            cols += [f"skip{b}_{j}" if k == "-" else f"{k}{j}" for j in range(1, n + 1)]
        return cols, kinds

    if layout is not None:
        n = (ncols - 1) // len(layout)
        if n * len(layout) + 1 != ncols or (n_joints is not None and n != n_joints):
            want = f"{1 + len(layout) * n_joints}" if n_joints is not None else f"1 + {len(layout)}·N"
            raise LogError(f"{path}: headerless CSV with {ncols} columns does not fit --columns {','.join(layout)}: "
                           f"expected {want} (t + {len(layout)} blocks of one column per joint)")
        return names(layout, n)

    if n_joints is not None:
        for k, kinds in _HEADERLESS.items():
            if ncols == 1 + k * n_joints:
                return names(kinds, n_joints)
        raise LogError(f"{path}: headerless CSV with {ncols} columns does not fit the robot's {n_joints} joints: "
                       f"expected {1 + 5 * n_joints} (UR RTDE t,q,qd,i,i_target,tau_target), {1 + 3 * n_joints} "
                       f"(t,q,dq,i) or {1 + 2 * n_joints} (t,q,i) columns, or a header line t,q1..qN,i1..iN "
                       "(dragd contact also takes the layout as --columns, e.g. q,dq,i,-)")
    if ncols > 1 and (ncols - 1) % 5 == 0:
        return names(_UR_LAYOUT, (ncols - 1) // 5)
    raise LogError(f"{path}: headerless CSV with {ncols} columns: the layout is ambiguous without the robot's joint "
                   "count; add a header line t,q1..qN,i1..iN[,dq1..dqN] (or give the robot)")


def _parse_rows(path: Path, body: list[tuple[int, str]], ncols: int,
                drop_bad_rows: bool) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Row by row: a truncated LAST row (a writer stopped mid-line) is skipped with a warning; malformed rows
    elsewhere are an error naming the line, or skipped and named with ``drop_bad_rows``."""
    rows: list[list[float]] = []
    keep: list[int] = []
    bad: list[tuple[int, str]] = []
    warnings: list[str] = []
    last = body[-1][0]
    for ln, s in body:
        p = [v.strip() for v in s.rstrip(",").split(",")]
        if len(p) != ncols:
            if ln == last and len(p) < ncols:
                warnings.append(f"line {ln}: last row truncated ({len(p)} of {ncols} fields; the writer was "
                                "stopped mid-row) skipped")
                continue
            bad.append((ln, f"{len(p)} fields, expected {ncols}"))
            continue
        try:
            rows.append([float(v) for v in p])
            keep.append(ln)
        except ValueError:
            v = next(v for v in p if not _is_number(v))
            bad.append((ln, f"{v[:20]!r} is not a number"))
    if bad:
        if not drop_bad_rows:
            ln, why = bad[0]
            more = f" ({len(bad)} such rows at lines {_ranges([b[0] for b in bad])})" if len(bad) > 1 else ""
            raise LogError(f"{path}: line {ln}: {why}{more}; fix the log or pass --drop-bad-rows to skip "
                           "malformed rows")
        warnings.append(f"--drop-bad-rows: {len(bad)} malformed rows skipped at lines {_ranges([b[0] for b in bad])} "
                        f"(line {bad[0][0]}: {bad[0][1]})")
    if not rows:
        raise LogError(f"{path}: no data rows")
    return np.array(rows, dtype=float), np.array(keep, dtype=np.int64), warnings


def _in_sequence(t: np.ndarray, min_run: int = 10, window: int = 32) -> np.ndarray:
    """Rows in sequence: the longest chain of rows (each within ``window`` rows of the last) whose time steps are
    regular (0 < Δt ≤ G, G = max(1 s, 50 median steps)) or a longer gap between two regular runs of ≥ ``min_run``
    steps (a pause); the rest — the fewest rows — is out of sequence (a garbage block, a row written twice)."""
    n = t.shape[0]
    d = np.diff(t)
    pos = d[d > 0]
    G = max(1.0, 50.0 * float(np.median(pos))) if pos.size else 1.0
    ok = (d > 0) & (d <= G)
    fwd = np.zeros(n, dtype=np.int64)  # regular steps starting at row k
    bwd = np.zeros(n, dtype=np.int64)  # regular steps ending at row k
    for k in range(n - 2, -1, -1):
        fwd[k] = fwd[k + 1] + 1 if ok[k] else 0
    for k in range(1, n):
        bwd[k] = bwd[k - 1] + 1 if ok[k - 1] else 0
    best = np.ones(n, dtype=np.int64)
    prev = np.full(n, -1, dtype=np.int64)
    for k in range(1, n):
        lo = max(0, k - window)
        dt = t[k] - t[lo:k]
        can = (dt > 0) & ((dt <= G) | ((bwd[lo:k] >= min_run) & (fwd[k] >= min_run)))
        if can.any():
            cand = np.where(can, best[lo:k], 0)
            j = lo + (k - lo - 1 - int(np.argmax(cand[::-1])))  # the latest of the best predecessors
            best[k] = best[j] + 1
            prev[k] = j
    keep = np.zeros(n, dtype=bool)
    k = int(n - 1 - np.argmax(best[::-1]))
    while k >= 0:
        keep[k] = True
        k = int(prev[k])
    return keep


STACK_GAP_S = 10.0  # the time gap put between stacked logs: far above prepare()'s max gap, so each is its own stretch


def stack_logs(logs: list[Log], max_rate_mismatch: float = 0.1) -> Log:
    """Several logs of one robot as one: each keeps its own samples and is preprocessed as its own stretch.

    The logs are placed one after another on a common time axis with a gap of ``STACK_GAP_S`` between them, so
    :func:`prepare` filters and differentiates each separately (no filter runs across a file boundary) and the
    regressions stack their rows. The logs must have the same joints and sampling rates within 10 %.
    """
    if not logs:
        raise LogError("no log given")
    if len(logs) == 1:
        return logs[0]
    first = logs[0]
    for lg in logs[1:]:
        if lg.n != first.n:
            raise LogError(f"{lg.path}: {lg.n} joints, but {first.path} has {first.n}; stacked "
                           "logs must be of one robot")
        if abs(lg.rate_Hz - first.rate_Hz) > max_rate_mismatch * first.rate_Hz:
            raise LogError(f"{lg.path}: sampled at {lg.rate_Hz:.1f} Hz, {first.path} at "
                           f"{first.rate_Hz:.1f} Hz; stacked "
                           f"logs must share a rate within {max_rate_mismatch:.0%}")
    ts, offset = [], 0.0
    for lg in logs:
        ts.append(lg.t - lg.t[0] + offset)
        offset = ts[-1][-1] + STACK_GAP_S

    def cat(name: str) -> np.ndarray | None:
        arrs = [getattr(lg, name) for lg in logs]
        return None if any(a is None for a in arrs) else np.concatenate(arrs)

    def cat_all(name: str) -> np.ndarray:  # (every log has q and i)
        return np.concatenate([getattr(lg, name) for lg in logs])

    warnings = [f"{lg.path}: {w}" for lg in logs for w in lg.warnings]
    warnings.append(f"{len(logs)} logs stacked ({', '.join(str(lg.t.shape[0]) for lg in logs)} rows): each is "
                    "filtered and differentiated as its own stretch")
    modes: dict[str, int] = {}
    for lg in logs:
        for k, v in lg.modes.items():
            modes[k] = modes.get(k, 0) + v
    return Log(" + ".join(lg.path for lg in logs), np.concatenate(ts), cat_all("q"), cat_all("i"), cat("dq"), warnings,
               modes, cat("i_target"), cat("tau_target"), first.columns, cat("lines"), first.row_word)


def _validate(log: Log, drop_bad_rows: bool = False) -> Log:
    """Finite values per column, strictly increasing time, radians — errors name the file, column and line."""
    where = log.row_word
    lines = log.lines if log.lines is not None else np.arange(log.t.shape[0]) + 1
    named = log.named_columns()
    bad = np.zeros(log.t.shape[0], dtype=bool)
    per_col: list[tuple[str, np.ndarray]] = []
    for name, col in named:
        nf = ~np.isfinite(col)
        if nf.any():
            per_col.append((name, lines[nf]))
            bad |= nf
    if per_col:
        def at(ls: np.ndarray) -> str:
            return f"{where}{'s' if ls.size > 1 else ''} {_first(ls)}"

        desc = "; ".join(f"{c}: {ls.size} row{'s' if ls.size > 1 else ''} ({at(ls)})" for c, ls in per_col)
        if not drop_bad_rows:
            raise LogError(f"{log.path}: {per_col[0][0]}: NaN or infinite values at {at(per_col[0][1])} "
                           f"({desc}); expected finite numbers — fix the log or pass --drop-bad-rows to skip such rows")
        if bad.all():
            raise LogError(f"{log.path}: every row has NaN or infinite values ({desc})")
        log = log.select(~bad)
        lines = lines[~bad]
        log.warnings.append(f"--drop-bad-rows: {int(bad.sum())} rows with NaN or infinite values dropped ({desc})")
    d = np.diff(log.t)
    if np.any(d <= 0):
        k = int(np.nonzero(d <= 0)[0][0])
        seq = _in_sequence(log.t)
        out = lines[~seq]
        msg = (f"{log.path}: t: expected strictly increasing time, got t = {log.t[k + 1]:.6f} s after "
               f"{log.t[k]:.6f} s at {where} {lines[k + 1]}")
        if not drop_bad_rows:
            extra = f"; {out.size} rows out of sequence at {where}s {_ranges(out)}" if out.size > 1 else ""
            raise LogError(msg + extra + " — fix the log or pass --drop-bad-rows to skip rows out of sequence")
        log = log.select(seq)
        lines = lines[seq]
        log.warnings.append(f"--drop-bad-rows: {out.size} row{'s' if out.size > 1 else ''} with time out of "
                            f"sequence dropped ({where}{'s' if out.size > 1 else ''} {_ranges(out)})")
    if log.t.shape[0] < 50:
        raise LogError(f"{log.path}: only {log.t.shape[0]} usable rows; expected a log of at least a few seconds")
    _check_radians(log)
    return log


def _check_radians(log: Log) -> None:
    """Angles that look like degrees: a joint spanning more than 1.5 turns (or |q| beyond), or a velocity
    column ≈ 57.3× (or 1/57.3×) the derivative of the position."""
    qn = log.q_names()
    for j in range(log.n):
        q = log.q[:, j]
        lo, hi = float(q.min()), float(q.max())
        if hi - lo > _DEG_SPAN_RAD or max(abs(lo), abs(hi)) > _DEG_SPAN_RAD:
            raise LogError(f"{log.path}: looks like degrees: column {qn[j]} spans {lo:.4g}..{hi:.4g}; expected "
                           f"radians (|q| ≤ {_DEG_SPAN_RAD:.3g} rad over a log; multiply degrees by π/180)")
    if log.dq is None or log.t.shape[0] < 10:
        return
    dqn = log.dq_names()
    dq_num = np.gradient(log.q, log.t, axis=0)
    for j in range(log.n):
        a, b = dq_num[:, j], log.dq[:, j]
        m = np.abs(b) > 0.05 * max(float(np.abs(b).max()), 1e-12)
        if m.sum() < 20 or float(np.abs(b).max()) < 1e-6:
            continue
        ratio = float(np.dot(a[m], b[m]) / max(float(np.dot(b[m], b[m])), 1e-300))
        if 40.0 < ratio < 80.0:
            raise LogError(f"{log.path}: looks like degrees: column {qn[j]} changes {ratio:.1f}× faster than "
                           f"{dqn[j]} (rad/s); expected radians (multiply degrees by π/180)")
        if 1 / 80.0 < ratio < 1 / 40.0:
            raise LogError(f"{log.path}: looks like degrees: column {dqn[j]} is {1 / ratio:.1f}× the rate of "
                           f"{qn[j]} (rad); expected rad/s (multiply deg/s by π/180)")


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
        out = [np.arange(s.start + edge, s.stop - edge, step) for s in self.segments
               if s.stop - s.start > 2 * edge + step]
        return np.concatenate(out) if out else np.zeros(0, dtype=int)


def _segments(t: np.ndarray, max_gap_s: float) -> list[Segment]:
    gaps = np.nonzero(np.diff(t) > max_gap_s)[0]
    starts = np.concatenate([[0], gaps + 1])
    stops = np.concatenate([gaps + 1, [t.shape[0]]])
    return [Segment(int(a), int(b)) for a, b in zip(starts, stops, strict=True)]


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
    T, Q, CUR, DQ, out_segs = [], [], [], [], []
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
        CUR.append(i)
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
    i = np.concatenate(CUR)
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
