"""``dragd identify run``: drive an excitation plan on the robot through the daemon (CSP) and record it to MCAP.

Sequence (control socket): status (the arm must be enabled: hold or drag) → a short approach ``track`` from the
current pose to the plan's start → ``record start`` → the plan as one or more ``track`` motions (long plans are
cut at rests into chunks of ≤ ``chunk_s``; between chunks the daemon holds briefly) → ``record stop``. The
daemon switches its drives to CSP, feeds gravity + believed friction forward, and logs every cycle; the measured
current in TRACK rows is the whole motor current (PD effort included), what identification wants.
Ctrl-C stops the motion along its path (``replay_stop``) and closes the recording.
"""

from __future__ import annotations

import itertools
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from dragd.identify.excitation import Plan


class RunError(RuntimeError):
    """The run could not be done; the message says why (and what the daemon said)."""


def _approach(q0: np.ndarray, q1: np.ndarray, speed: float = 0.2, dt: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """A quintic rest-to-rest move q0 → q1 at a peak joint speed of about ``speed``."""
    d = float(np.max(np.abs(q1 - q0)))
    T = max(1.0, 1.875 * d / speed)
    t = np.arange(0.0, T + dt / 2, dt)
    t[-1] = T
    s = t / T
    h = 10 * s**3 - 15 * s**4 + 6 * s**5
    return t, q0 + h[:, None] * (q1 - q0)[None, :]


def chunks(plan: Plan, chunk_s: float = 600.0) -> list[tuple[float, float]]:
    """Cut points (t0, t1) at rests (≥ 0.25 s without motion) so that each chunk lasts ≤ ``chunk_s`` if possible."""
    if plan.duration_s <= chunk_s:
        return [(0.0, plan.duration_s)]
    dq, _ = plan.derivatives()
    rest = np.all(np.abs(dq) < 1e-6, axis=1)
    dt = float(np.median(np.diff(plan.t_s)))
    need = max(2, int(0.25 / dt))
    # centres of rests long enough
    cand = []
    run = 0
    for k, r in enumerate(rest):
        run = run + 1 if r else 0
        if run == need:
            cand.append(k - need // 2)
    cuts = [0.0]
    for k in cand:
        t = float(plan.t_s[k])
        if t - cuts[-1] >= chunk_s * 0.8 and plan.duration_s - t > 5.0:
            cuts.append(t)
    cuts.append(plan.duration_s)
    return list(itertools.pairwise(cuts))


def motion_workdir(status: dict[str, Any]) -> Path:
    """A fresh folder for the motion files the daemon reads: in its spool folder when it has one this user may
    write (a daemon under systemd has a private /tmp), readable by the daemon's group; else a temporary folder."""
    spool = status.get("spool_dir")
    if spool and os.access(spool, os.W_OK | os.X_OK):
        work = Path(tempfile.mkdtemp(prefix="identify-", dir=spool))
        work.chmod(0o750)  # the spool is setgid dragd: the daemon reads through its group
        return work
    return Path(tempfile.mkdtemp(prefix="dragd-identify-"))


def run_plan(call: Callable[..., dict[str, Any]], plan: Plan, out: str | Path, *, chunk_s: float = 600.0,
             progress: bool = True, poll_s: float = 0.2, label: str | None = None,
             workdir: Path | None = None) -> dict[str, Any]:
    """Drive ``plan`` through the daemon (``call(cmd, **args)`` → response dict) and record ``out`` (MCAP)."""
    out = Path(out).expanduser().resolve()
    if out.exists():
        raise RunError(f"--out {out}: exists; choose a new file name")
    if out.suffix != ".mcap":
        raise RunError(f"--out {out}: expected an .mcap file name (the daemon records MCAP)")
    st = call("status")
    if st.get("mode") not in ("hold", "drag"):
        raise RunError(f"the arm is in mode {st.get('mode')}; enable it first ('dragd start'), then run again")
    since_s = float(st.get("t_s", 0.0))  # faults before the run (the daemon keeps a history) are not the run's
    q = np.array(st["q_rad"], dtype=float)
    if q.shape[0] != plan.n:
        raise RunError(f"plan {plan.name}: {plan.n} joints, the daemon's arm {q.shape[0]}")
    work, own = (Path(workdir), False) if workdir is not None else (motion_workdir(st), True)
    try:
        return _drive(call, plan, out, q, work, label or f"identify {plan.name}", since_s, chunk_s=chunk_s,
                      progress=progress, poll_s=poll_s)
    finally:
        if own:
            shutil.rmtree(work, ignore_errors=True)


def _drive(call: Callable[..., dict[str, Any]], plan: Plan, out: Path, q: np.ndarray, work: Path, label: str,
           since_s: float, *, chunk_s: float, progress: bool, poll_s: float) -> dict[str, Any]:
    """run_plan's motions: approach, record, the plan chunk by chunk, and what the daemon said."""
    t0 = time.monotonic()
    # 1. approach the plan's start
    if np.max(np.abs(plan.q_rad[0] - q)) > 0.005:
        ta, qa = _approach(q, plan.q_rad[0])
        _track(call, ta, qa, work / "approach.npz", "identify approach", progress=False, poll_s=poll_s)
    # 2. record the plan, chunk by chunk
    rec = call("record", action="start", path=str(out), label=label)
    if not rec.get("ok"):
        raise RunError(f"daemon refused to record to {out}: {rec.get('error')}")
    result: dict[str, Any] = {"log": str(out), "plan": plan.name, "plan_duration_s": plan.duration_s, "chunks": 0}
    try:
        parts = chunks(plan, chunk_s)
        for k, (a, b) in enumerate(parts):
            m = (plan.t_s >= a - 1e-9) & (plan.t_s <= b + 1e-9)
            t = plan.t_s[m] - plan.t_s[m][0]
            _track(call, t, plan.q_rad[m], work / f"chunk{k}.npz", f"{label} [{k + 1}/{len(parts)}]",
                   progress=progress, poll_s=poll_s, offset_s=a, total_s=plan.duration_s)
            result["chunks"] += 1
    except KeyboardInterrupt:
        call("replay_stop")
        result["interrupted"] = True
    finally:
        stats = call("record", action="stop")
        if not stats.get("ok", True):
            result["record_error"] = stats.get("error")
        result.update({"rows": stats.get("written"), "dropped_rows": stats.get("dropped"),
                       "wall_time_s": round(time.monotonic() - t0, 2)})
    end = call("status")
    faults = [f for f in end.get("faults", []) if float(f.get("t_s", since_s)) >= since_s]
    if faults:
        result["faults"] = faults
    return result


def _track(call: Callable[..., dict[str, Any]], t: np.ndarray, q: np.ndarray, path: Path, label: str, *,
           progress: bool, poll_s: float, offset_s: float = 0.0, total_s: float | None = None) -> None:
    np.savez(path, t_s=t, q_rad=q)
    resp = call("track", file=str(path), label=label)
    if not resp.get("ok"):
        st = call("status")
        faults = "; ".join(f["text"] for f in st.get("faults", [])[-3:])
        raise RunError(f"daemon refused the motion '{label}': {resp.get('error')}"
                       + (f" (faults: {faults})" if faults else ""))
    duration = float(resp.get("duration_s", t[-1]))
    total = total_s or duration
    bar = _Bar(total, label) if progress else None
    try:
        while True:
            time.sleep(poll_s)
            st = call("status")
            if st.get("mode") == "fault":
                raise RunError(f"the arm faulted during '{label}': "
                               + "; ".join(f["text"] for f in st.get("faults", [])[-3:]))
            tr = st.get("trajectory")
            if tr is None or st.get("mode") != "track":
                if bar:
                    bar.update(offset_s + duration)
                break
            if bar:
                bar.update(offset_s + float(tr.get("t_s", 0.0)))
    finally:
        if bar:
            bar.close()
    # wait for the drives back in CST (hold) before the next motion
    end = time.monotonic() + 5.0
    while time.monotonic() < end:
        st = call("status")
        if st.get("mode") == "hold" and st.get("drive_mode") == "cst" and st.get("trajectory") is None:
            return
        if st.get("mode") == "fault":
            raise RunError("the arm faulted at the end of the motion: "
                           + "; ".join(f["text"] for f in st.get("faults", [])[-3:]))
        time.sleep(0.05)
    raise RunError(f"the daemon did not return to hold/CST after '{label}'")


class _Bar:
    """A progress bar on stderr (rich when it is a terminal, a line every 10 % otherwise)."""

    def __init__(self, total: float, label: str) -> None:
        self.total = max(total, 1e-9)
        self.label = label
        self._rich = None
        self._last = -1
        if sys.stderr.isatty():
            try:
                from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

                self._rich = Progress(TextColumn("{task.description}"), BarColumn(),
                                      TextColumn("{task.percentage:>5.1f} %"), TimeRemainingColumn(), transient=False)
                self._rich.start()
                self._task = self._rich.add_task(label, total=self.total)
            except ImportError:  # pragma: no cover
                self._rich = None

    def update(self, t: float) -> None:
        if self._rich is not None:
            self._rich.update(self._task, completed=min(t, self.total))
            return
        pct = int(10 * min(t, self.total) / self.total)
        if pct != self._last:
            self._last = pct
            print(f"identify: {self.label}: {10 * pct:3d} % ({t:.0f} / {self.total:.0f} s)", file=sys.stderr,
                  flush=True)

    def close(self) -> None:
        if self._rich is not None:
            self._rich.stop()

