"""``python -m dragd ARGS`` as a real process, forked from a server that has imported the package already.

A CLI test pays ~1.5 s of CPU before ``main`` runs (numpy, scipy.optimize, pinocchio, canopen, numba, mcap, the
schema) and the unit tier starts a few hundred of them: most of the tier's CPU. One server per test process (each
xdist worker) imports those once; each call forks it and the child runs the ``dragd`` entry point exactly as
``python -m dragd`` does (``runpy``: ``dragd.__main__`` as ``__main__``, ``sys.argv``), in the caller's working
directory and environment, with its own stdout and stderr (files), exit status (``sys.exit``, an uncaught exception:
its traceback on stderr and status 1, a signal: minus its number) and atexit handlers. What the child does not
repeat is the interpreter's start and the imports: anything read at import time comes from the server's start, so
a call whose environment differs from the server's runs as a fresh interpreter instead (``run`` decides), as does
every call when ``DRAGD_TEST_CLI=exec`` (a whole tier through real ``python -m dragd`` processes).
The CLI's own process-level properties (what a command imports, the installed entry point) are tested with fresh
interpreters: tests/test_cli.py, tests/test_import_graph.py.
"""

from __future__ import annotations

import atexit
import contextlib
import json
import os
import select
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

# What the CLI's commands import (their own modules import the rest in the child). Only libraries and dragd's
# modules without side effects at import: no rclpy, no rerun (the child imports them when a command needs them).
PRELOAD = ("numpy", "scipy.optimize", "scipy.signal", "pinocchio", "canopen", "can", "mcap", "numba", "yaml",
           "dragd.cli.app", "dragd.config", "dragd.model", "dragd.robots.gravity", "dragd.hardware.plan")

_SERVER = r'''
import importlib, json, os, sys, traceback
reply_fd = int(sys.argv[1])
for name in sys.argv[2:]:
    try:
        importlib.import_module(name)
    except ImportError:
        pass
out = os.fdopen(reply_fd, "w", buffering=1)
out.write("ready\n")
for line in sys.stdin:
    req = json.loads(line)
    pid = os.fork()
    if pid == 0:
        code = 1
        try:
            os.setsid()
            fd0 = os.open(os.devnull, os.O_RDONLY)
            os.dup2(fd0, 0)
            for fd, path in ((1, req["stdout"]), (2, req["stderr"])):
                f = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
                os.dup2(f, fd)
                os.close(f)
            os.close(reply_fd)
            os.chdir(req["cwd"])
            os.environ.clear()
            os.environ.update(req["env"])
            sys.stdin = open(0, closefd=False)
            sys.stdout = open(1, "w", closefd=False)
            sys.stderr = open(2, "w", closefd=False)
            sys.argv = ["-m", *req["args"]]  # runpy sets argv[0] to the module's file, as python -m does
            import runpy
            try:
                runpy.run_module(req["module"], run_name="__main__", alter_sys=True)
                code = 0
            except SystemExit as exc:
                c = exc.code
                if c is None:
                    code = 0
                elif isinstance(c, int):
                    code = c & 0xFF
                else:
                    print(c, file=sys.stderr)
                    code = 1
            except BaseException:
                traceback.print_exc()
                code = 1
            import atexit, threading
            threading._shutdown()
            atexit._run_exitfuncs()
            for s in (sys.stdout, sys.stderr):
                try:
                    s.flush()
                except Exception:
                    pass
        finally:
            os._exit(code)
    out.write(json.dumps({"pid": pid}) + "\n")
    _, status = os.waitpid(pid, 0)
    out.write(json.dumps({"status": os.waitstatus_to_exitcode(status)}) + "\n")
'''


# The environment the server starts with: tests/conftest.py's at import (after its own settings), else this
# process's at the first call.
BASE_ENV: dict[str, str] | None = None


class _Server:
    def __init__(self, env: dict[str, str]) -> None:
        self.env = env
        r, w = os.pipe()
        self.proc = subprocess.Popen([sys.executable, "-c", _SERVER, str(w), *PRELOAD], stdin=subprocess.PIPE,
                                     text=True, pass_fds=(w,), env=self.env, cwd="/", start_new_session=True)
        os.close(w)
        self.fd, self.buf = r, b""
        if self._line(None) != "ready":
            raise RuntimeError("the dragd fork server did not start")

    def _line(self, timeout: float | None) -> str | None:
        """The server's next reply line; None after ``timeout`` wall seconds without one (unbuffered: select sees
        what the pipe holds)."""
        while b"\n" not in self.buf:
            if timeout is not None and not select.select([self.fd], [], [], timeout)[0]:
                return None
            chunk = os.read(self.fd, 4096)
            if not chunk:
                raise RuntimeError("the dragd fork server exited")
            self.buf += chunk
        line, self.buf = self.buf.split(b"\n", 1)
        return line.decode()

    def alive(self) -> bool:
        return self.proc.poll() is None

    def run(self, module: str, args: tuple[str, ...], env: dict[str, str], cwd: Path,
            timeout: float) -> subprocess.CompletedProcess[str]:
        with tempfile.TemporaryDirectory(prefix="dragd-cli-") as tmp:
            out, err = Path(tmp) / "stdout", Path(tmp) / "stderr"
            req = {"module": module, "args": list(args), "cwd": str(cwd), "env": env, "stdout": str(out),
                   "stderr": str(err)}
            assert self.proc.stdin is not None
            self.proc.stdin.write(json.dumps(req) + "\n")
            self.proc.stdin.flush()
            pid = json.loads(self._line(None) or "")["pid"]
            reply = self._line(timeout)
            if reply is None:  # a hang guard, as subprocess.run's timeout: kill the child (and its group), name it
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(pid, signal.SIGKILL)
                self._line(None)
                raise subprocess.TimeoutExpired(["python", "-m", module, *args], timeout)
            status = json.loads(reply)["status"]
            return subprocess.CompletedProcess(["python", "-m", module, *args], status,
                                               out.read_text(errors="replace"), err.read_text(errors="replace"))

    def close(self) -> None:
        if self.proc.stdin is not None:
            self.proc.stdin.close()
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        os.close(self.fd)


_server: _Server | None = None

# Set for each test (pytest's phase; tests/conftest.py's rig clock of the test's tier); nothing reads them at import
# (the child gets the caller's values). (Without DRAGD_RIG_CLOCK here every call differed from the server's
# environment and ran as a fresh interpreter.)
_PER_CALL = ("PYTEST_CURRENT_TEST", "DRAGD_RIG_CLOCK")


def _imported(env: dict[str, str]) -> dict[str, str]:
    """The part of an environment the server's imports could have read: all but ``_PER_CALL``."""
    return {k: v for k, v in env.items() if k not in _PER_CALL}


def run(args: tuple[str, ...], env: dict[str, str] | None, cwd: Path | None, timeout: float,
        module: str = "dragd") -> subprocess.CompletedProcess[str] | None:
    """The CompletedProcess of ``python -m MODULE ARGS`` (``dragd``, or ``sim``) forked from the server, or None
    where it must be a fresh interpreter: ``DRAGD_TEST_CLI=exec``, or an environment other than the server's
    (``env``, or this process's own changed since the server started: a test's monkeypatch)."""
    global _server
    if os.environ.get("DRAGD_TEST_CLI") == "exec":
        return None
    want = dict(os.environ) if env is None else env
    if _server is not None and not _server.alive():
        _server = None
    base = BASE_ENV if BASE_ENV is not None else dict(os.environ)
    if _imported(want) != _imported(base):
        return None
    if _server is None:
        _server = _Server(base)
    return _server.run(module, args, want, Path.cwd() if cwd is None else Path(cwd), timeout)


def close() -> None:
    global _server
    if _server is not None:
        _server.close()
        _server = None


atexit.register(close)
