"""Running the simulated robot and the daemon as separate processes (demo, benchmarks, integration tests).

dragd never imports ``sim``: the simulator is started as ``python -m sim run`` and driven through its
control socket.

The rig owns the arm's time: ``Rig.sleep(s)`` lets the arm run ``s`` seconds, ``Rig.wait_for(cond, timeout_s, what)``
runs it until ``cond()`` holds. On the wall clock (``lockstep=False``) that is real time. On the lockstep clock
(``lockstep=True``: both processes with ``--lockstep``, dragd/clock.py, sim/lockstep.py) the arm's time stands still
between the rig's calls: ``sleep`` grants exactly ``s`` of simulated time (``round(s / period)`` cycles) and returns
once they ran, ``wait_for`` grants ``LOCKSTEP_STEP_S`` at a time and looks at ``cond`` after each; what the test does
in between (a sim ``operator`` scenario, an injected fault, a daemon command) happens at a cycle the run determines,
so a test's verdict does not depend on how the host schedules the two processes.

Drag: a rig starts the daemon with ``--lab-unguarded-drag`` unless ``drag_guard="config"`` (then drag needs what the
configuration's ``drag.require`` says). ``Rig.drag()`` holds a drag lease as a client does (docs/HAND.md): on the
lockstep clock it is renewed between grants (``sleep`` and ``wait_for`` grant at most a third of its period at a
time), on the wall clock by a thread; ``drop_lease(close=False)`` stops renewing (a client that died).
"""

from __future__ import annotations

import hashlib
import math
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from dragd.hardware.cia402 import EMCY_HEARTBEAT, EMCY_RPDO_TIMEOUT
from dragd.lease import LeaseHolder
from dragd.protocol import ControlClient, DaemonUnavailable

# faults a host that starves the daemon or the simulator can cause on the wall clock (a drive's reception deadline or
# heartbeat consumer, the daemon's lost feedback or heartbeats): the real-time path's outcome, which the wall clock's
# demo and loop benchmarks report beside the machine's stalls; any other fault is the software's
TIMING_FAULT_CODES = (EMCY_RPDO_TIMEOUT, EMCY_HEARTBEAT)
TIMING_FAULT_TEXTS = ("feedback lost: no TPDO", "no heartbeat from node", "bus outage: no heartbeat")


def timing_fault(entry: dict[str, Any]) -> bool:
    """Whether a fault entry (the daemon's status ``faults``) is a communication deadline that passed."""
    text = str(entry.get("text", ""))
    return entry.get("code") in TIMING_FAULT_CODES or any(t in text for t in TIMING_FAULT_TEXTS)


class ProcessError(RuntimeError):
    """A child process that failed to start or answer; the message carries its output's tail."""


_GROUPS = 255 * 254  # 239.74.X.Y, X 0..255 but 163 (the docs' and examples' 239.74.163.2), Y 1..254
_groups_taken: set[int] = set()
_groups_lock = threading.Lock()
_group_claims: list[socket.socket] = []  # held until this process exits


def _claim_group(k: int) -> bool:
    """Claim group ``k`` for this process on the whole machine (its network namespace, where the group's traffic
    goes): an abstract Unix socket named for it, which the kernel frees when the process exits, however it ends.
    False: another process (another test run's worker, a demo) holds it."""
    claim = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    try:
        claim.bind(f"\0dragd-udp-multicast-group-{k}")
    except OSError:
        claim.close()
        return False
    _group_claims.append(claim)
    return True


def multicast_group(tag: str) -> str:
    """A private udp_multicast group 239.74.X.Y derived from ``tag``, the pid and the time, and claimed for this
    process machine-wide (`_claim_group`): no cross-talk between runs (two checkouts testing at once, xdist workers);
    two groups of one process always differ (the next free one where the derived one was given already)."""
    h = hashlib.sha256(f"{tag}:{os.getpid()}:{time.monotonic_ns()}".encode()).digest()
    k = int.from_bytes(h[:4], "big") % _GROUPS
    with _groups_lock:
        for _ in range(_GROUPS):
            if k not in _groups_taken:
                _groups_taken.add(k)  # (given out or held elsewhere: never tried again by this process)
                if _claim_group(k):
                    x = k // 254
                    return f"239.74.{x + (x >= 163)}.{1 + k % 254}"
            k = (k + 1) % _GROUPS
        raise RuntimeError(f"multicast_group: all {_GROUPS} groups of 239.74.0.0/16 are given out by this process "
                           "or held by others")


# How a Child's process starts: None (the default) is subprocess.Popen. A test harness may set a launcher
# ``(argv, cwd, env, log_path) -> process or None`` whose process has Popen's ``pid``, ``returncode``, ``poll``,
# ``wait(timeout)``, ``send_signal`` and ``kill``, its stdout and stderr appended to ``log_path`` (None: Popen starts
# it). tests/conftest.py: the lockstep tier's ``python -m sim`` / ``python -m dragd`` fork from a server that has
# imported them (tests/cli_fork.py).
LAUNCHER: Callable[[list[str], Path, dict[str, str], Path], Any] | None = None


class Child:
    """A child process whose stdout/stderr go to a log file; ``tail()`` for error messages."""

    def __init__(self, name: str, argv: list[str], workdir: Path, env: dict[str, str] | None = None) -> None:
        self.name = name
        self.argv = argv
        self.log_path = workdir / f"{name}.log"
        self._log = self.log_path.open("wb")
        full_env = {**os.environ, **(env or {})}
        proc = LAUNCHER(argv, workdir, full_env, self.log_path) if LAUNCHER is not None else None
        self.proc = proc if proc is not None else subprocess.Popen(
            argv, stdout=self._log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=full_env, cwd=str(workdir))

    def alive(self) -> bool:
        return self.proc.poll() is None

    def tail(self, lines: int = 25) -> str:
        try:
            text = self.log_path.read_text(errors="replace").splitlines()
        except OSError:
            return ""
        return "\n".join(text[-lines:])

    def terminate(self, timeout_s: float = 10.0, sig: int = signal.SIGTERM) -> int:
        """Send ``sig`` and wait; SIGKILL after ``timeout_s``. Returns the exit status."""
        if self.alive():
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self._log.close()
        return int(self.proc.returncode)

    def output(self) -> str:
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""


def wait_until(cond: Callable[[], bool], timeout_s: float, what: str, child: Child | None = None,
               interval_s: float = 0.05) -> None:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if child is not None and not child.alive():
            raise ProcessError(f"{child.name} exited ({child.proc.returncode}) while waiting for {what}:\n"
                               f"{child.tail()}")
        try:
            if cond():
                return
        except DaemonUnavailable:
            pass
        time.sleep(interval_s)
    tail = f":\n{child.tail()}" if child is not None else ""
    raise ProcessError(f"timed out after {timeout_s:.0f} s waiting for {what}{tail}")


DEPLOYED_PRIORITY = 70  # the cycle thread's SCHED_FIFO priority in the shipped unit (config loop.realtime_priority)
START_GUARD_S = 120.0  # a process that has not come up (imports, boot) by then is hung; a loaded 2-core host takes 30+
LOCKSTEP_CALL_S = 120.0  # the wall-clock guard of a daemon command (or SIGTERM's ramp down) on the lockstep clock
LOCKSTEP_STEP_S = 0.01  # Rig.wait_for on the lockstep clock: the condition is looked at every 10 ms of arm time
LOCKSTEP_WALL_S_PER_S = 20.0  # a grant's wall-clock guard: this much wall time per simulated second (+ 60 s)


def config_rate_Hz(config: Path | None) -> float:
    """The loop rate of a dragd configuration file (its loop.rate_Hz; 1000 when it names none)."""
    if config is None:
        return 1000.0
    import yaml

    data = yaml.safe_load(Path(config).read_text()) or {}
    return float((data.get("loop") or {}).get("rate_Hz", 1000.0))


class Periodic:
    """A test's action every period of the rig's clock (``Rig.every``); ``stop()`` holds once it returns. (#31)"""

    def __init__(self, period_s: float, fn: Callable[[], None]) -> None:
        self.period_s, self.fn, self.on = period_s, fn, True
        self.ticks = self.next_tick = 0  # lockstep: the period and the next due tick
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()

    def start_thread(self) -> None:
        def run() -> None:
            due = time.monotonic()
            while True:
                with self._lock:
                    if not self.on:
                        return
                    self.fn()
                due += self.period_s
                time.sleep(max(0.0, due - time.monotonic()))

        self._thread = threading.Thread(target=run, name="rig-every", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        with self._lock:
            self.on = False


class Rig:
    """The simulated robot and (optionally) the daemon, each its own process, on a private multicast group.

    ``bus`` ("INTERFACE:CHANNEL", e.g. ``socketcan:vcan0``) puts both on that bus instead of a multicast group.
    ``as_deployed``: the daemon's cycle thread asks for SCHED_FIFO ``DEPLOYED_PRIORITY`` and the simulator's threads
    for 10 below, as the systemd unit runs it (docs/SYSTEMD.md); applied where the system permits it, otherwise
    both run SCHED_OTHER and ``schedulers()`` says why (no root assumed). ``lockstep``: both on the lockstep clock
    (module doc; None: as ``$DRAGD_RIG_CLOCK`` says, ``lockstep`` or ``wall``, the default; the test tiers set it);
    the simulator's period follows the configuration's loop.rate_Hz.
    """

    def __init__(self, tag: str = "rig", workdir: Path | None = None, config: Path | None = None,
                 sim_config: Path | None = None, telemetry: Path | None = None, group: str | None = None,
                 sim_args: list[str] | None = None, daemon_args: list[str] | None = None,
                 env: dict[str, str] | None = None, bus: str | None = None,
                 allow_dirs: list[Path] | None = None, as_deployed: bool = False, lockstep: bool | None = None,
                 drag_guard: str = "lab") -> None:
        # absolute paths: the processes run in the work folder (cwd), where a relative path would name another file
        self.workdir = Path(workdir or tempfile.mkdtemp(prefix=f"dragd-{tag}-")).resolve()
        self.workdir.mkdir(parents=True, exist_ok=True)
        config, sim_config, telemetry = (None if p is None else Path(p).resolve()
                                         for p in (config, sim_config, telemetry))
        if bus is not None and group is not None:
            raise ValueError(f"Rig: give either bus ({bus!r}) or group ({group!r}), not both")
        self.group = None if bus is not None else (group or multicast_group(tag))
        self.bus = bus if bus is not None else f"udp_multicast:{self.group}"
        self.config = config
        self.sim_config = sim_config
        self.telemetry = telemetry
        self.sim_socket = str(self.workdir / "sim.sock")
        self.socket = str(self.workdir / "dragd.sock")
        self.sim_args = list(sim_args or [])
        self.daemon_args = list(daemon_args or [])
        if as_deployed:
            if "--realtime-priority" not in self.daemon_args:
                self.daemon_args += ["--realtime-priority", str(DEPLOYED_PRIORITY)]
            if "--realtime-priority" not in self.sim_args:
                self.sim_args += ["--realtime-priority", str(DEPLOYED_PRIORITY - 10)]
        if lockstep is None:
            lockstep = os.environ.get("DRAGD_RIG_CLOCK", "wall") == "lockstep"
        self.lockstep = lockstep
        if lockstep:
            if "--lockstep" not in self.sim_args:
                self.sim_args += ["--lockstep", "--period-ms", f"{1000.0 / config_rate_Hz(config):g}"]
            if "--lockstep" not in self.daemon_args:
                self.daemon_args.append("--lockstep")
        if drag_guard not in ("lab", "config"):
            raise ValueError(f"Rig: drag_guard: expected 'lab' or 'config', got {drag_guard!r}")
        if drag_guard == "lab" and "--lab-unguarded-drag" not in self.daemon_args:
            self.daemon_args.append("--lab-unguarded-drag")
        self.lease: LeaseHolder | None = None  # a drag lease the rig holds (drag())
        self._lease_t = 0.0  # lockstep: the simulated time of its last renewal
        self.lease_error: str | None = None  # why the wall clock's renewal thread stopped
        # where the daemon may write what the rig asks
        self.allow_dirs = [self.workdir, *(Path(d).resolve() for d in allow_dirs or [])]
        self.env = env
        self.sim: Child | None = None
        self.daemon: Child | None = None
        self._periodic: list[Periodic] = []  # (#31) a test's actions every period of the arm's time: every()

    # processes
    def start_sim(self, timeout_s: float = START_GUARD_S) -> None:
        argv = [sys.executable, "-m", "sim", "run", "--bus", self.bus, "--control", self.sim_socket, *self.sim_args]
        if self.bus.startswith("udp_multicast:") and "--batch-frames" not in argv:
            argv.append("--batch-frames")  # one datagram per SYNC answer: the rig's peers are dragd's own buses
        if self.sim_config is not None:
            argv += ["--config", str(self.sim_config)]
        self.sim = Child("sim", argv, self.workdir, self.env)
        wait_until(lambda: "q_rad" in self.sim_call("state"), timeout_s, "the simulator's control socket", self.sim)

    def start_daemon(self, timeout_s: float = START_GUARD_S) -> None:
        argv = [sys.executable, "-m", "dragd", "run", "--bus", self.bus, "--socket", self.socket, *self.daemon_args]
        if self.bus.startswith("udp_multicast:") and "--batch-frames" not in argv:
            argv.append("--batch-frames")  # the cycle's command frames ride with the next SYNC (the sim batches too)
        for d in self.allow_dirs:
            argv += ["--allow-dir", str(Path(d).absolute())]
        if self.config is not None:
            argv += ["--config", str(self.config)]
        if self.telemetry is not None:
            argv += ["--telemetry", str(self.telemetry)]
        self.daemon = Child("dragd", argv, self.workdir, self.env)
        if self.lockstep:  # up (booted, socket open), then the first cycles on the arm's time
            wait_until(lambda: "clock" in self.call("status"), timeout_s, "the daemon's control socket", self.daemon)
        self.wait_for(lambda: self.call("status").get("cycles", 0) > 10, timeout_s, "the daemon's first cycles")

    def __enter__(self) -> Rig:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> dict[str, int]:
        self._stop_lease_thread()
        codes = {}
        if self.daemon is not None:  # (lockstep: its ramp down runs on the simulated clock, at the machine's pace)
            codes["dragd"] = self.daemon.terminate(LOCKSTEP_CALL_S if self.lockstep else 10.0)
        if self.sim is not None:
            codes["sim"] = self.sim.terminate()
        return codes

    # control sockets
    def call(self, cmd: str, timeout_s: float | None = None, **args: Any) -> dict[str, Any]:
        """A daemon command; ``timeout_s`` of wall time (default 10 s; on the lockstep clock 120 s: a command that
        waits for the arm runs its simulated time first, however fast the machine runs it)."""
        if timeout_s is None:
            timeout_s = LOCKSTEP_CALL_S if self.lockstep else 10.0
        return ControlClient(self.socket, timeout_s).call(cmd, **args)

    def sim_call(self, cmd: str, timeout_s: float = 5.0, **args: Any) -> dict[str, Any]:
        return ControlClient(self.sim_socket, timeout_s).call(cmd, **args)

    def cli(self, *args: str, timeout_s: float = 60.0) -> subprocess.CompletedProcess:
        """Run ``dragd ARGS --socket <this rig's daemon>`` as a real process (lockstep: with the answer's wall-clock
        guard of ``call``, unless ARGS say ``--timeout``: a command that waits for the arm runs its time first)."""
        extra = ["--timeout", str(LOCKSTEP_CALL_S)] if self.lockstep and "--timeout" not in args else []
        return subprocess.run([sys.executable, "-m", "dragd", *args, "--socket", self.socket, *extra],
                              capture_output=True, text=True, timeout=max(timeout_s, LOCKSTEP_CALL_S + 30.0)
                              if extra else timeout_s, cwd=str(self.workdir))

    # a drag lease, as a client holds it (docs/HAND.md)
    def hold_lease(self, period_s: float | None = None, holder: str = "rig") -> LeaseHolder:
        """Open a drag lease and keep renewing it (lockstep: between grants; wall: a thread)."""
        if self.lease is not None:
            raise ProcessError(f"Rig: already holding lease {self.lease.lease}")
        def call(cmd: str, timeout_s: float | None = None, **kw: Any) -> dict[str, Any]:
            resp = self.call(cmd, timeout_s=timeout_s, **kw)
            if not resp.get("ok"):
                raise ProcessError(f"daemon refused {cmd} {kw}: {resp.get('error')}")
            return resp

        lease = LeaseHolder(call, holder, period_s)
        lease.open()
        self.lease = lease
        if self.lockstep:
            self._lease_t = float(self.must("clock")["clock"]["t_s"])
        else:
            lease.keep()  # paced by the daemon's clock
        return lease

    def drag(self, accept: bool = False, period_s: float | None = None) -> dict[str, Any]:
        """``mode drag`` with a drag lease the rig holds from now on (opened if none is held)."""
        if self.lease is None:
            self.hold_lease(period_s)
        assert self.lease is not None
        return self.lease.drag(**({"accept": True} if accept else {}))

    def drop_lease(self, close: bool = True) -> dict[str, Any] | None:
        """Stop renewing the lease; ``close``: close it too (the arm holds at once), else it lapses in the daemon."""
        lease, self.lease = self.lease, None
        self._stop_lease_thread(lease)
        if lease is None:
            return None
        return lease.close() if close else None

    def _stop_lease_thread(self, lease: LeaseHolder | None = None) -> None:
        lease = lease or self.lease
        if lease is not None and not self.lockstep:
            lease.stop_keeping()
            self.lease_error = lease.error

    def _renew_lockstep(self, t_s: float) -> None:
        lease = self.lease
        if lease is not None and t_s - self._lease_t >= lease.every_s - 1e-9:
            lease.renew()
            self._lease_t = t_s

    def ensure_hold(self, tries: int = 3) -> None:
        """Restart a daemon that faulted at rest (a loaded machine's missed cycles) until it holds."""
        for _ in range(tries):
            if self.must("status")["mode"] == "hold":
                return
            self.must("start")
            self.sleep(0.5)

    # the rig's clock: tests say how long the arm runs through these, never through time.sleep
    def sleep(self, seconds: float) -> None:
        """Let the arm run for ``seconds`` of the rig's clock (lockstep: exactly that much simulated time)."""
        if not self.lockstep:
            time.sleep(seconds)
            return
        if self.daemon is None:
            raise ProcessError("Rig.sleep on the lockstep clock needs the daemon (its SYNCs are the arm's time); "
                               "start_daemon first, or use lockstep=False")
        self.advance(seconds)

    def now(self) -> float:
        """The arm's time in seconds on the rig's clock (lockstep: the daemon's simulated time, which stands still
        between grants; wall: CLOCK_MONOTONIC): what a test stamps the samples it sends with."""
        if not self.lockstep:
            return time.monotonic()
        if self.daemon is None:
            raise ProcessError("Rig.now on the lockstep clock needs the daemon (its SYNCs are the arm's time)")
        return float(self.must("clock")["clock"]["t_s"])

    @contextmanager
    def running(self) -> Iterator[None]:
        """Lockstep: time runs on its own inside (``dragd clock run``, as fast as both processes go), paused again
        after; wall: nothing to do. For a client that paces itself on the wall clock (``dragd identify run`` polls
        the daemon every 0.2 s of wall time): what it makes the arm do runs on the daemon's clock from the tick its
        command lands at."""
        if not self.lockstep:
            yield
            return
        self.must("clock", action="run")
        try:
            yield
        finally:
            if self.daemon is not None and self.daemon.alive():
                self.must("clock", action="pause")

    def advance(self, seconds: float) -> dict[str, Any]:
        """Lockstep: grant ``seconds`` of simulated time and wait until they ran; the daemon's clock status. While
        the rig holds a drag lease, at most a third of its period per grant, renewed after each."""
        if any(p.on for p in self._periodic):  # (#31)
            return self._advance_periodic(seconds)
        lease = self.lease
        if lease is not None and seconds > lease.every_s:
            period = 1.0 / config_rate_Hz(self.config)  # (whole periods per grant: the total stays exact)
            left, chunk = round(seconds / period), max(1, int(lease.every_s / period + 1e-9))
            clock: dict[str, Any] = {}
            while left > 0:
                step = min(left, chunk)
                clock = self._grant(step * period)
                left -= step
            return clock
        return self._grant(seconds)

    # --- (#31) a test's periodic actions on the arm's time (a ROS client's keepalive, a stream of commands)
    def every(self, period_s: float, fn: Callable[[], None]) -> Periodic:
        """``fn()`` now and then every ``period_s`` of the rig's clock until the handle's ``stop()``. Lockstep: between
        grants, at exact simulated times (no grant runs past the next one due), so what ``fn`` sends lands at a
        cycle the run determines (``fn`` may wait, in wall time, for its effect before time goes on); wall: a
        thread on CLOCK_MONOTONIC's grid."""
        if not period_s > 0:
            raise ValueError(f"Rig.every: period_s: expected a positive number of seconds, got {period_s!r}")
        p = Periodic(period_s, fn)
        if not self.lockstep:
            p.start_thread()
            return p
        period = 1.0 / config_rate_Hz(self.config)
        p.ticks = max(1, round(period_s / period))
        p.next_tick = int(self.must("clock")["clock"]["ticks"]) + p.ticks
        self._periodic.append(p)
        fn()
        return p

    def _advance_periodic(self, seconds: float) -> dict[str, Any]:
        period = 1.0 / config_rate_Hz(self.config)
        left = round(seconds / period)
        if left <= 0:
            return self._grant(0.0)
        now = int(self.must("clock")["clock"]["ticks"])
        chunk = max(1, int(self.lease.every_s / period + 1e-9)) if self.lease is not None else left
        clock: dict[str, Any] = {}
        while left > 0:
            live = [p for p in self._periodic if p.on]
            step = min([left, chunk] + [max(1, p.next_tick - now) for p in live])
            clock = self._grant(step * period)
            now = int(clock["ticks"])
            left -= step
            for p in live:
                if p.on and now >= p.next_tick:
                    p.next_tick += p.ticks
                    p.fn()
        self._periodic = [p for p in self._periodic if p.on]
        return clock
    # --- (#31) end

    def _grant(self, seconds: float) -> dict[str, Any]:
        guard = 60.0 + LOCKSTEP_WALL_S_PER_S * seconds
        try:
            resp = self.call("clock", timeout_s=guard, action="advance", seconds=seconds)
        except DaemonUnavailable as exc:
            try:  # what held the clock: the peer (peer_time_s), a job off the cycle (offcycle), a gate (gate_waits)
                held = f"; its clock: {self.call('clock', timeout_s=5.0).get('clock')}"
            except DaemonUnavailable:
                held = ""
            raise ProcessError(f"lockstep: the daemon did not finish a grant of {seconds:g} s within {guard:.0f} s "
                               f"of wall time ({exc}){held}:\n{self._tails()}") from None
        if not resp.get("ok"):
            raise ProcessError(f"lockstep: clock advance {seconds:g} s refused: {resp.get('error')}\n{self._tails()}")
        if self.lease is not None:
            self._renew_lockstep(float(resp["clock"]["t_s"]))
        return resp["clock"]

    def wait_for(self, cond: Callable[[], bool], timeout_s: float, what: str) -> None:
        """Run the rig until ``cond()`` holds, at most ``timeout_s`` of its clock; ProcessError names ``what``."""
        if not self.lockstep or self.daemon is None:
            wait_until(cond, timeout_s, what, self.daemon or self.sim)
            return
        steps = max(1, math.ceil(timeout_s / LOCKSTEP_STEP_S - 1e-9))
        for _ in range(steps + 1):
            for child in (self.daemon, self.sim):
                if child is not None and not child.alive():
                    raise ProcessError(f"{child.name} exited ({child.proc.returncode}) while waiting for {what}:\n"
                                       f"{child.tail()}")
            try:
                if cond():
                    return
            except DaemonUnavailable:
                pass
            if _ < steps:
                self.advance(LOCKSTEP_STEP_S)
        raise ProcessError(f"timed out after {timeout_s:g} s of simulated time waiting for {what}:\n{self._tails()}")

    def _tails(self) -> str:
        return "\n".join(f"--- {c.name}:\n{c.tail()}" for c in (self.daemon, self.sim) if c is not None)

    def schedulers(self) -> dict[str, str]:
        """The scheduling policy each running process reports (e.g. "SCHED_FIFO 70", or SCHED_OTHER and why)."""
        got = {}
        if self.daemon is not None:
            got["daemon"] = str(self.must("status").get("scheduler"))
        if self.sim is not None:
            got["simulator"] = str(self.sim_call("state").get("scheduler"))
        return got

    def must(self, cmd: str, **args: Any) -> dict[str, Any]:
        resp = self.call(cmd, **args)
        if not resp.get("ok"):
            raise ProcessError(f"daemon refused {cmd} {args}: {resp.get('error')}\n"
                               f"{self.daemon.tail() if self.daemon else ''}")
        return resp
