"""The planner worker: a separate Python process that plans replays and writes programs for the daemon.

Planning a replay (inverse kinematics along a circle, re-timing, feed-forward torques) is seconds of Python; in
the daemon's process it would hold the GIL against the 1 kHz cycle. The daemon talks to one long-lived worker
(``python -m dragd.teach.worker``) over its stdin/stdout with pickled ``(function, args)`` → ``("ok", result)`` or
``("error", message)``. The worker is started from a normal-priority helper thread, so it never inherits the
cycle's real-time policy; it also demotes itself off the cycle's CPUs.
"""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
import threading
from typing import Any


class WorkerError(RuntimeError):
    """The worker process failed (crashed, or could not be started)."""


def trajectory(dt_s: float, label: str, file: str | None = None, t_s: Any = None, q_rad: Any = None) -> Any:
    """A TRACK trajectory from a file or samples (the spline's seconds and its scipy stay out of the daemon)."""
    from dragd.control.trajectory import Trajectory

    if file is not None:
        return Trajectory.load(file, dt_s, label)
    return Trajectory(t_s, q_rad, dt_s, label)


def _functions() -> dict[str, Any]:
    from dragd.teach.keyframes import extract_keyframes
    from dragd.teach.plan import plan_replay, rigid_body_effort, warm_up
    from dragd.teach.program import list_programs
    from dragd.teach.recorder import write_program

    return {"plan_replay": plan_replay, "write_program": write_program, "warm_up": warm_up,
            "extract_keyframes": extract_keyframes, "list_programs": list_programs,
            "rigid_body_effort": rigid_body_effort, "trajectory": trajectory}


def main() -> int:
    from dragd.realtime import demote_current_thread

    avoid = {int(c) for c in os.environ.get("DRAGD_WORKER_AVOID_CPUS", "").split(",") if c.strip()}
    demote_current_thread(avoid or None)
    try:
        os.nice(5)
    except OSError:
        pass
    inp, out = sys.stdin.buffer, sys.stdout.buffer
    sys.stdout = sys.stderr  # stdout carries the protocol only
    funcs = _functions()
    while True:
        try:
            name, args, kwargs = pickle.load(inp)
        except EOFError:
            return 0
        try:
            result: tuple[str, Any] = ("ok", funcs[name](*args, **kwargs))
        except (ValueError, KeyError, FileNotFoundError, OSError) as exc:
            result = ("error", str(exc) or type(exc).__name__)
        except Exception as exc:  # noqa: BLE001 - reported to the daemon, the worker lives on
            result = ("error", f"{type(exc).__name__}: {exc}")
        pickle.dump(result, out, protocol=pickle.HIGHEST_PROTOCOL)
        out.flush()


class Worker:
    """Client side: ``call`` blocks (run it in a helper thread, never in the cycle's thread)."""

    def __init__(self, avoid_cpus: set[int] | None = None) -> None:
        self.avoid_cpus = avoid_cpus or set()
        self.proc: subprocess.Popen | None = None
        self._lock = threading.Lock()

    def _start(self) -> subprocess.Popen:
        env = {**os.environ, "DRAGD_WORKER_AVOID_CPUS": ",".join(str(c) for c in sorted(self.avoid_cpus))}
        return subprocess.Popen([sys.executable, "-m", "dragd.teach.worker"], stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, stderr=None, env=env)

    def call(self, name: str, *args: Any, **kwargs: Any) -> Any:
        with self._lock:
            if self.proc is None or self.proc.poll() is not None:
                self.proc = self._start()
            proc = self.proc
            try:
                assert proc.stdin is not None and proc.stdout is not None
                pickle.dump((name, args, kwargs), proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
                proc.stdin.flush()
                status, value = pickle.load(proc.stdout)
            except (EOFError, BrokenPipeError, pickle.UnpicklingError, OSError) as exc:
                self.proc = None
                raise WorkerError(f"the planner worker died ({exc.__class__.__name__}); try again") from None
        if status != "ok":
            raise ValueError(value)
        return value

    def close(self) -> None:
        proc, self.proc = self.proc, None
        if proc is None:
            return
        try:
            if proc.stdin is not None:
                proc.stdin.close()
            proc.wait(2.0)
        except (OSError, subprocess.TimeoutExpired):
            proc.kill()
            proc.wait(2.0)


if __name__ == "__main__":
    sys.exit(main())
