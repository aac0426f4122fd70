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
import threading
import time
from pathlib import Path

# What the CLI's commands import (their own modules import the rest in the child). Only libraries and dragd's
# modules without side effects at import: no rclpy, no rerun (the child imports them when a command needs them).
PRELOAD = ("numpy", "scipy.optimize", "scipy.signal", "pinocchio", "canopen", "can", "mcap", "numba", "yaml",
           "dragd.cli.app", "dragd.config", "dragd.model", "dragd.robots.gravity", "dragd.hardware.plan")

# In a forked child whose fds 0, 1, 2 are set (and nothing else of the server's open): the entry point as
# ``python -m MODULE ARGS`` runs it, in the request's folder and environment; never returns (its exit status).
_RUN_ENTRY = r'''
def run_entry(req):
    import atexit, os, runpy, sys, threading, traceback
    code = 1
    try:
        # (Python 3.11 keeps the parent's native id after a fork: what a daemon reports of its threads,
        # dragd/realtime.py, would be the server's main thread's)
        threading.current_thread()._set_native_id()
        os.chdir(req["cwd"])
        os.environ.clear()
        os.environ.update(req["env"])
        sys.stdin = open(0, closefd=False)
        sys.stdout = open(1, "w", closefd=False)
        sys.stderr = open(2, "w", closefd=False)
        sys.argv = ["-m", *req["args"]]  # runpy sets argv[0] to the module's file, as python -m does
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
        threading._shutdown()
        atexit._run_exitfuncs()
        for s in (sys.stdout, sys.stderr):
            try:
                s.flush()
            except Exception:
                pass
    finally:
        os._exit(code)
'''

_SERVER = _RUN_ENTRY + r'''
import importlib, json, os, sys
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
        try:
            os.setsid()
            fd0 = os.open(os.devnull, os.O_RDONLY)
            os.dup2(fd0, 0)
            for fd, path in ((1, req["stdout"]), (2, req["stderr"])):
                f = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
                os.dup2(f, fd)
                os.close(f)
            os.close(reply_fd)
        except BaseException:
            os._exit(1)
        run_entry(req)
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


# --------------------------------------------------------------------------------------------- the rig's processes

# The lockstep tier's simulator and daemon (dragd/lab/rig.py ``Child``: ``python -m sim run ...``, ``python -m dragd
# run ...``) fork from a server per module and test process that has imported what that process imports and loaded
# its numba kernels (dragd/jit.py keeps them per process): a rig's start costs ~1 s of CPU instead of ~2.8. Unlike
# the CLI's server it answers at once with the child's pid and reports each exit when it happens (a pidfd per
# child), so a simulator and a daemon run side by side. The child is the entry point as ``python -m`` runs it, in the
# rig's folder and environment, its output appended to the rig's log; it gets SIGTERM if its server dies. A server
# preloads only what its process would load: the daemon's must never see scipy (tests/test_daemon_track.py reads
# its memory map), so numba's kernels are loaded as dragd/jit.py loads them in the daemon.
SPAWN_PRELOAD = {
    "dragd": ("dragd.cli.app", "dragd.cli.daemon", "dragd.daemon.core", "dragd.control.contact",
              "dragd.control.contact_watch", "dragd.control.fused", "dragd.control.guard", "dragd.control.safety",
              "dragd.daemon.kernels"),
    "sim": ("dragd.realtime", "sim.runner", "sim.kernels"),
}
SPAWN_WARM = {  # (module, function): each loads its module's kernels (tests/conftest.py ``_compile_kernels``)
    "dragd": (("dragd.control.fused", "_compiled"), ("dragd.control.guard", "_kernels"),
              ("dragd.control.safety", "safety_kernel"), ("dragd.control.contact", "contact_kernel"),
              ("dragd.control.contact_watch", "_kernels"), ("dragd.daemon.kernels", "kernels")),
    "sim": (("sim.kernels", "hold_kernel"),),
}

_SPAWN_SERVER = _RUN_ENTRY + r'''
import ctypes, importlib, json, os, select, signal, sys, time
reply_fd, module = int(sys.argv[1]), sys.argv[2]
preload, warm = json.loads(sys.argv[3]), json.loads(sys.argv[4])
if module == "sim":
    from dragd.realtime import single_threaded_blas  # (as sim/__main__.py does before numpy)
    single_threaded_blas()
for name in preload:
    importlib.import_module(name)
for name, fn in warm:
    getattr(importlib.import_module(name), fn)()
if "scipy" in sys.modules and sys.modules["scipy"] is not None and module == "dragd":
    raise SystemExit("the daemon's fork server loaded scipy, which the daemon never does")
out = os.fdopen(reply_fd, "w", buffering=1)
out.write("ready\n")
libc = ctypes.CDLL(None, use_errno=True)
children = {}  # pidfd -> pid
inbox = b""
stdin_fd = sys.stdin.fileno()


def start(req):
    pid = os.fork()
    if pid:
        return pid
    try:
        libc.prctl(1, int(signal.SIGTERM))  # PR_SET_PDEATHSIG: a child outlives no server
        os.close(reply_fd)
        for fd in children:
            os.close(fd)
        fd0 = os.open(os.devnull, os.O_RDONLY)
        os.dup2(fd0, 0)
        log = os.open(req["log"], os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        os.dup2(log, 1)
        os.dup2(log, 2)
        for fd in (fd0, log):
            os.close(fd)
    except BaseException:
        os._exit(1)
    run_entry(req)


def reap(fd):
    pid = children.pop(fd)
    os.close(fd)
    _, status = os.waitpid(pid, 0)
    out.write(json.dumps({"exit": pid, "status": os.waitstatus_to_exitcode(status)}) + "\n")


while True:
    ready = select.select([stdin_fd, *children], [], [])[0]
    for fd in ready:
        if fd != stdin_fd:
            reap(fd)
            continue
        chunk = os.read(stdin_fd, 65536)
        if not chunk:  # the test process is gone: its children are ended as a rig's close() ends them
            for pid in children.values():
                try:
                    os.kill(pid, signal.SIGTERM)
                except ProcessLookupError:
                    pass
            end = time.monotonic() + 30.0
            while children and time.monotonic() < end:
                for fd in select.select(list(children), [], [], 0.5)[0]:
                    reap(fd)
            for pid in children.values():
                try:
                    os.kill(pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
            raise SystemExit(0)
        inbox += chunk
        while b"\n" in inbox:
            line, inbox = inbox.split(b"\n", 1)
            pid = start(json.loads(line))
            children[os.pidfd_open(pid)] = pid
            out.write(json.dumps({"pid": pid}) + "\n")
'''


class _Spawner:
    """One module's fork server (``python -m MODULE``'s children, run side by side)."""

    def __init__(self, module: str, env: dict[str, str]) -> None:
        r, w = os.pipe()
        self.module, self.env = module, env
        self.proc = subprocess.Popen(
            [sys.executable, "-c", _SPAWN_SERVER, str(w), module, json.dumps(SPAWN_PRELOAD[module]),
             json.dumps(SPAWN_WARM[module])], stdin=subprocess.PIPE, pass_fds=(w,), env=env, cwd="/",
            start_new_session=True)
        os.close(w)
        self.fd, self.buf = r, b""
        self.exits: dict[int, int] = {}
        self.lock = threading.Lock()
        if self._line(None) != "ready":
            raise RuntimeError(f"the {module} fork server did not start")

    def _line(self, timeout: float | None) -> str | None:
        while b"\n" not in self.buf:
            if timeout is not None and not select.select([self.fd], [], [], max(0.0, timeout))[0]:
                return None
            chunk = os.read(self.fd, 4096)
            if not chunk:
                raise RuntimeError(f"the {self.module} fork server exited")
            self.buf += chunk
        line, self.buf = self.buf.split(b"\n", 1)
        return line.decode()

    def _take(self, line: str) -> int | None:
        """An exit report is kept; a pid reply is returned."""
        msg = json.loads(line)
        if "exit" in msg:
            self.exits[int(msg["exit"])] = int(msg["status"])
            return None
        return int(msg["pid"])

    def alive(self) -> bool:
        return self.proc.poll() is None

    def spawn(self, args: list[str], cwd: Path, env: dict[str, str], log: Path) -> ForkedProcess:
        req = {"module": self.module, "args": args, "cwd": str(cwd), "env": env, "log": str(log)}
        with self.lock:
            assert self.proc.stdin is not None
            self.proc.stdin.write((json.dumps(req) + "\n").encode())
            self.proc.stdin.flush()
            while True:
                pid = self._take(self._line(None) or "")
                if pid is not None:
                    return ForkedProcess(self, pid, [sys.executable, "-m", self.module, *args])

    def status(self, pid: int, timeout: float | None) -> int | None:
        """``pid``'s exit status once the server reported it; waits up to ``timeout`` wall seconds (None: for ever)."""
        end = None if timeout is None else time.monotonic() + timeout
        with self.lock:
            while pid not in self.exits:
                line = self._line(None if end is None else max(0.0, end - time.monotonic()))
                if line is None:
                    return None
                self._take(line)
            return self.exits[pid]

    def close(self) -> None:
        if self.proc.stdin is not None:
            self.proc.stdin.close()
        try:
            self.proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        os.close(self.fd)


class ForkedProcess:
    """What dragd/lab/rig.py's Child uses of a Popen, for a child of a fork server."""

    def __init__(self, server: _Spawner, pid: int, args: list[str]) -> None:
        self.server, self.pid, self.args = server, pid, args
        self.returncode: int | None = None

    def poll(self) -> int | None:
        if self.returncode is None:
            self.returncode = self.server.status(self.pid, 0.0)
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        if self.returncode is None:
            self.returncode = self.server.status(self.pid, timeout)
            if self.returncode is None:
                raise subprocess.TimeoutExpired(self.args, timeout or 0.0)
        return self.returncode

    def send_signal(self, sig: int) -> None:
        if self.poll() is None:  # (as Popen: never a signal to a pid already reaped)
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.pid, sig)

    def terminate(self) -> None:
        self.send_signal(signal.SIGTERM)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)


_spawners: dict[str, _Spawner] = {}


def launch(argv: list[str], cwd: Path, env: dict[str, str], log: Path) -> ForkedProcess | None:
    """dragd/lab/rig.py's ``LAUNCHER``: ``python -m sim|dragd ARGS`` forked from that module's server, or None where
    it must be a fresh interpreter (``DRAGD_TEST_CLI=exec``, another interpreter or module, an environment other
    than the server's)."""
    if os.environ.get("DRAGD_TEST_CLI") == "exec" or len(argv) < 3 or argv[0] != sys.executable or argv[1] != "-m":
        return None
    if not hasattr(os, "pidfd_open"):  # (Linux >= 5.3: the server waits on its children's pidfds)
        return None
    module = argv[2]
    if module not in SPAWN_PRELOAD:
        return None
    base = BASE_ENV if BASE_ENV is not None else dict(os.environ)
    if _imported(env) != _imported(base):
        return None
    server = _spawners.get(module)
    if server is None or not server.alive():
        server = _spawners[module] = _Spawner(module, base)
    return server.spawn(argv[3:], cwd, env, log)


def close_spawners() -> None:
    for server in _spawners.values():
        server.close()
    _spawners.clear()


atexit.register(close_spawners)
