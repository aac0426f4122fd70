"""Periodic tick for asyncio from a Linux timerfd with absolute deadlines.

``asyncio.sleep`` rounds timeouts up to whole milliseconds on epoll and drifts by
the cycle's own run time; a timerfd armed with an absolute CLOCK_MONOTONIC
deadline and a fixed interval fires on a drift-free grid and counts the
expirations the loop slept through (missed ticks).

GIL note for the daemon: after the timer fires, the cycle thread must take the GIL;
a busy Python thread that never blocks holds it for up to ``sys.getswitchinterval()``
(5 ms by default, measured +5.2 ms wake-up latency). Helper threads should block
often (the telemetry writer sleeps every few rows), and the daemon should lower
the interval at 1 kHz (``sys.setswitchinterval(5e-4)``: +0.36 ms at 2e-4, +1.1 ms
at 1e-3 with a spinning thread on the test VM).
"""

from __future__ import annotations

import asyncio
import ctypes
import ctypes.util
import errno
import os
import platform
import resource
import struct
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

__all__ = ["Ticker", "set_realtime", "scheduler_label", "demote_current_thread", "HELPER_PRIORITY",
           "CpuLatencyRequest", "thread_policy", "thread_policies"]

_CLOCK_MONOTONIC = 1
_TFD_NONBLOCK = os.O_NONBLOCK
_TFD_CLOEXEC = os.O_CLOEXEC
_TFD_TIMER_ABSTIME = 1


class _Timespec(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


class _Itimerspec(ctypes.Structure):
    _fields_ = [("it_interval", _Timespec), ("it_value", _Timespec)]


_libc: ctypes.CDLL | None = None


def _get_libc() -> ctypes.CDLL:
    global _libc
    if _libc is None:
        if not sys.platform.startswith("linux"):
            raise OSError(f"Ticker needs Linux timerfd; this platform is {sys.platform!r}")
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        libc.timerfd_create.argtypes = [ctypes.c_int, ctypes.c_int]
        libc.timerfd_create.restype = ctypes.c_int
        libc.timerfd_settime.argtypes = [
            ctypes.c_int,
            ctypes.c_int,
            ctypes.POINTER(_Itimerspec),
            ctypes.POINTER(_Itimerspec),
        ]
        libc.timerfd_settime.restype = ctypes.c_int
        libc.mlockall.argtypes = [ctypes.c_int]
        libc.mlockall.restype = ctypes.c_int
        _libc = libc
    return _libc


def _oserror(call: str) -> OSError:
    err = ctypes.get_errno()
    return OSError(err, f"{call} failed: {os.strerror(err)}")


class Ticker:
    """Drift-free periodic tick: ``n = await ticker.wait()`` once per period, or ``on_tick(n)`` called by the loop
    (``call_each``: the 1 kHz cycle's way, no future and no task wake-up per tick).

    The timer is armed on the first `wait` (first deadline one period later) or
    explicitly with `start`. ``wait`` returns the number of periods elapsed since
    the previous return (1 normally, >1 when ticks were missed); ``deadline_ns`` is
    the CLOCK_MONOTONIC deadline of the tick just returned, so
    ``time.monotonic_ns() - ticker.deadline_ns`` is the wake-up latency.
    """

    def __init__(self, period_s: float, loop: asyncio.AbstractEventLoop | None = None) -> None:
        if not (period_s > 0 and period_s < 3600):
            raise ValueError(f"Ticker period_s must be in (0, 3600) seconds; got {period_s!r}")
        self.period_ns = int(round(period_s * 1e9))
        if self.period_ns < 10_000:
            raise ValueError(f"Ticker period {period_s} s is below 10 us; expected >= 1e-5 s")
        self._libc = _get_libc()
        fd = self._libc.timerfd_create(_CLOCK_MONOTONIC, _TFD_NONBLOCK | _TFD_CLOEXEC)
        if fd < 0:
            raise _oserror("timerfd_create(CLOCK_MONOTONIC)")
        self._fd = fd
        self._loop = loop
        self._reader_loop: asyncio.AbstractEventLoop | None = None
        self._waiter: asyncio.Future[None] | None = None
        self._pending = 0
        self._start_ns = 0
        self._armed = False
        self.ticks = 0
        """Periods elapsed since start (sum of `wait` results)."""
        self.missed = 0
        """Ticks skipped in total (sum of ``n - 1`` over all waits)."""

    # -- arming -----------------------------------------------------------------------------
    def start(self, first_deadline_ns: int | None = None) -> None:
        """Arm the timer: first tick at ``first_deadline_ns`` (default now + period)."""
        if self._fd < 0:
            raise RuntimeError("Ticker is closed")
        if first_deadline_ns is None:
            first_deadline_ns = time.monotonic_ns() + self.period_ns
        spec = _Itimerspec()
        spec.it_value.tv_sec, spec.it_value.tv_nsec = divmod(first_deadline_ns, 1_000_000_000)
        spec.it_interval.tv_sec, spec.it_interval.tv_nsec = divmod(self.period_ns, 1_000_000_000)
        if self._libc.timerfd_settime(self._fd, _TFD_TIMER_ABSTIME, ctypes.byref(spec), None) != 0:
            raise _oserror("timerfd_settime(TFD_TIMER_ABSTIME)")
        self._start_ns = first_deadline_ns
        self._pending = 0
        self.ticks = 0
        self.missed = 0
        self._armed = True

    @property
    def fileno(self) -> int:
        return self._fd

    @property
    def deadline_ns(self) -> int:
        """CLOCK_MONOTONIC deadline of the tick most recently returned by `wait`."""
        return self._start_ns + (self.ticks - 1) * self.period_ns

    @property
    def next_deadline_ns(self) -> int:
        return self._start_ns + self.ticks * self.period_ns

    # -- waiting ----------------------------------------------------------------------------
    def _drain(self) -> int:
        try:
            data = os.read(self._fd, 8)
        except BlockingIOError:
            return 0
        n = int.from_bytes(data, sys.byteorder)
        self._pending += n
        return n

    def _on_readable(self) -> None:
        if self._drain() and self._waiter is not None and not self._waiter.done():
            self._waiter.set_result(None)

    def call_each(self, loop: asyncio.AbstractEventLoop, on_tick: Callable[[int], None]) -> None:
        """Call ``on_tick(n)`` from ``loop`` at each tick (n: periods since the previous call; >1 after missed
        ticks), until `close`. Arms the timer if `start` was not called. The loop runs its other ready callbacks
        between two calls however late the ticks are."""
        if self._fd < 0:
            raise RuntimeError("Ticker is closed")
        if self._reader_loop is not None:
            raise RuntimeError("Ticker already delivers its ticks (wait or call_each)")
        fd = self._fd

        def on_readable() -> None:
            try:
                n = int.from_bytes(os.read(fd, 8), sys.byteorder)
            except BlockingIOError:
                return
            self.ticks += n
            self.missed += n - 1
            on_tick(n)

        if not self._armed:
            self.start()
        loop.add_reader(fd, on_readable)
        self._reader_loop = loop

    def _register(self) -> asyncio.AbstractEventLoop:
        running = asyncio.get_running_loop()
        if self._loop is not None and self._loop is not running:
            raise RuntimeError("Ticker.wait() called from a loop other than the one it was given")
        if self._reader_loop is None:
            running.add_reader(self._fd, self._on_readable)
            self._reader_loop = running
        elif self._reader_loop is not running:
            raise RuntimeError("Ticker.wait() called from a different event loop than before")
        return running

    async def wait(self) -> int:
        """Wait for the next tick; return the number of periods since the last return.

        When ticks are already overdue it returns at once but still yields to the
        loop once, so other tasks (control socket, watchdog) run even if the cycle
        overruns continuously.
        """
        if self._fd < 0:
            raise RuntimeError("Ticker is closed")
        loop = self._register()
        if not self._armed:
            self.start()
        if self._pending == 0 and time.monotonic_ns() >= self.next_deadline_ns:
            self._drain()
        if self._pending == 0:
            waiter = loop.create_future()
            self._waiter = waiter
            try:
                await waiter
            finally:
                self._waiter = None
        else:
            await asyncio.sleep(0)
        n = self._pending
        self._pending = 0
        self.ticks += n
        self.missed += n - 1
        return n

    # -- teardown ---------------------------------------------------------------------------
    def close(self) -> None:
        """Stop the timer, unregister it from the loop and close the fd (idempotent)."""
        if self._fd < 0:
            return
        if self._reader_loop is not None and not self._reader_loop.is_closed():
            self._reader_loop.remove_reader(self._fd)
        self._reader_loop = None
        if self._waiter is not None and not self._waiter.done():
            self._waiter.cancel()
        os.close(self._fd)
        self._fd = -1

    def __enter__(self) -> Ticker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        if getattr(self, "_fd", -1) >= 0:
            try:
                os.close(self._fd)
            except OSError:
                pass


# -- real-time scheduling -------------------------------------------------------------------

def _mcl_flags() -> int:
    # MCL_CURRENT | MCL_FUTURE; values differ on a few architectures.
    if platform.machine().lower().startswith(("ppc", "powerpc", "sparc", "alpha")):
        return 0x2000 | 0x4000
    return 1 | 2


def _rtprio_limit() -> str:
    soft, _hard = resource.getrlimit(resource.RLIMIT_RTPRIO)
    return "unlimited" if soft == resource.RLIM_INFINITY else str(soft)


def set_realtime(
    priority: int | None,
    cpus: set[int] | None,
    *,
    lock_memory: bool = False,
) -> dict[str, Any]:
    """Pin the calling thread to ``cpus`` and make it SCHED_FIFO at ``priority``.

    Applies to the *calling thread* only; threads started afterwards inherit the
    policy and affinity (threads that must not run real-time should call
    `demote_current_thread`). ``lock_memory`` also calls ``mlockall(MCL_CURRENT |
    MCL_FUTURE)``. Never raises for missing permission: the returned dict tells, per
    item, what was applied and why not. Raises ValueError for invalid arguments.
    """
    result: dict[str, Any] = {}

    if cpus is None:
        result["affinity"] = {
            "requested": None,
            "applied": False,
            "cpus": sorted(os.sched_getaffinity(0)),
            "reason": "not requested",
        }
    else:
        wanted = {int(c) for c in cpus}
        if not wanted or min(wanted) < 0:
            raise ValueError(f"cpus must be a non-empty set of CPU numbers >= 0; got {cpus!r}")
        try:
            os.sched_setaffinity(0, wanted)
            result["affinity"] = {
                "requested": sorted(wanted),
                "applied": True,
                "cpus": sorted(os.sched_getaffinity(0)),
                "reason": None,
            }
        except OSError as e:
            result["affinity"] = {
                "requested": sorted(wanted),
                "applied": False,
                "cpus": sorted(os.sched_getaffinity(0)),
                "reason": f"sched_setaffinity({sorted(wanted)}) failed: {e.strerror}; "
                f"this process may use CPUs {sorted(os.sched_getaffinity(0))} "
                f"of {os.cpu_count()} online",
            }

    if priority is None:
        result["scheduler"] = {
            "requested_priority": None,
            "applied": False,
            "policy": _policy_name(os.sched_getscheduler(0)),
            "reason": "not requested",
        }
    else:
        lo = os.sched_get_priority_min(os.SCHED_FIFO)
        hi = os.sched_get_priority_max(os.SCHED_FIFO)
        if not (isinstance(priority, int) and lo <= priority <= hi):
            raise ValueError(f"SCHED_FIFO priority must be an integer in {lo}..{hi}; got {priority!r}")
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
            global _REALTIME_PRIORITY
            with _HELPERS_LOCK:  # (a helper demoting itself right now sees the priority, or is re-demoted here)
                _REALTIME_PRIORITY = priority
                helpers = _demote_started_helpers()  # helpers started before: below the cycle from now on
            result["scheduler"] = {
                "requested_priority": priority,
                "applied": True,
                "policy": _policy_name(os.sched_getscheduler(0)),
                "reason": None,
                "helpers": helpers,
            }
        except PermissionError:
            result["scheduler"] = {
                "requested_priority": priority,
                "applied": False,
                "policy": _policy_name(os.sched_getscheduler(0)),
                "reason": f"SCHED_FIFO priority {priority} not permitted: needs CAP_SYS_NICE or "
                f"RLIMIT_RTPRIO >= {priority} (current soft limit {_rtprio_limit()}); "
                "under systemd set LimitRTPRIO= in the unit",
            }
        except OSError as e:
            result["scheduler"] = {
                "requested_priority": priority,
                "applied": False,
                "policy": _policy_name(os.sched_getscheduler(0)),
                "reason": f"sched_setscheduler(SCHED_FIFO, {priority}) failed: {e.strerror}",
            }

    if not lock_memory:
        result["memory_lock"] = {"requested": False, "applied": False, "reason": "not requested"}
    elif _get_libc().mlockall(_mcl_flags()) == 0:
        result["memory_lock"] = {"requested": True, "applied": True, "reason": None}
    else:
        err = ctypes.get_errno()
        soft, _ = resource.getrlimit(resource.RLIMIT_MEMLOCK)
        limit = "unlimited" if soft == resource.RLIM_INFINITY else f"{soft} bytes"
        result["memory_lock"] = {
            "requested": True,
            "applied": False,
            "reason": f"mlockall(MCL_CURRENT|MCL_FUTURE) failed: {os.strerror(err)} "
            f"(RLIMIT_MEMLOCK {limit}; under systemd set LimitMEMLOCK=infinity)",
        }
    return result


CPU_LATENCY_DEVICE = "/dev/cpu_dma_latency"
_INT32 = struct.Struct("=i")


class CpuLatencyRequest:
    """A PM QoS request: every CPU wakes from idle within ``latency_us`` while this request is held (Linux
    ``/dev/cpu_dma_latency``, as cyclictest makes it). 0 keeps idle CPUs in their polling state: no deep C-state to
    leave, and in a virtual machine no halted vCPU for the host to wake, so a cycle's wake-ups start sooner and with
    warm caches. The price is power: idle CPUs spin. Held while the descriptor is open: ``close`` withdraws it, and
    the kernel does when the process ends, however it ends. Never raises for a missing device or permission:
    ``info`` tells what applied and why not."""

    def __init__(self, latency_us: int, device: str = CPU_LATENCY_DEVICE) -> None:
        if not 0 <= latency_us <= 2_000_000_000:
            raise ValueError(f"cpu latency: expected 0..2000000000 µs, got {latency_us}")
        self.device = device
        self._fd: int | None = None
        self.info: dict[str, Any] = {"requested_us": int(latency_us), "applied": False, "reason": None}
        try:
            fd = os.open(device, os.O_RDWR | os.O_CLOEXEC)
        except OSError as e:
            # (ENOENT: the shipped unit's PrivateDevices=yes hides the device; EACCES: root's by default)
            self.info["reason"] = (f"open {device} failed: {e.strerror}" + (
                "; under systemd install the drop-in systemd/dragd-cpu-latency.conf and the udev rule "
                "systemd/70-dragd-cpu-latency.rules (docs/SYSTEMD.md)"
                if e.errno in (errno.EACCES, errno.EPERM, errno.ENOENT) else ""))
            return
        try:
            os.write(fd, _INT32.pack(int(latency_us)))
        except OSError as e:
            os.close(fd)
            self.info["reason"] = f"write {device} failed (a 4-byte int, {latency_us} µs): {e.strerror}"
            return
        self._fd = fd
        self.info["applied"] = True

    def effective_us(self) -> int | None:
        """The latency every CPU is held to now (the strictest request of all processes), or None without one."""
        if self._fd is None:
            return None
        try:
            raw = os.pread(self._fd, _INT32.size, 0)
        except OSError:
            return None
        return _INT32.unpack(raw)[0] if len(raw) == _INT32.size else None

    @property
    def held(self) -> bool:
        return self._fd is not None

    def close(self) -> None:
        """Withdraw the request."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
            self.info["applied"] = False
            self.info["reason"] = "withdrawn"

    def status(self) -> dict[str, Any]:
        """``info`` and the latency every CPU is held to now (``effective_us``, None without a request held)."""
        return {**self.info, "effective_us": self.effective_us()}


def scheduler_label(info: dict[str, Any], priority: int | None) -> str:
    """One line for status reports from `set_realtime`'s result: "SCHED_FIFO 70", "SCHED_OTHER", or
    "SCHED_OTHER (SCHED_FIFO 70 refused: <reason>)" when a priority was asked for and not granted."""
    sched = info.get("scheduler") or {}
    if sched.get("applied"):
        return f"{sched.get('policy')} {priority}"
    policy = str(sched.get("policy") or "SCHED_OTHER")
    return policy if priority is None else f"{policy} (SCHED_FIFO {priority} refused: {sched.get('reason')})"


HELPER_PRIORITY = 1  # SCHED_FIFO priority of a real-time process's helper threads: below every cycle thread
_REALTIME_PRIORITY: int | None = None  # the SCHED_FIFO priority set_realtime applied in this process (None: none)
# every thread that called demote_current_thread: native id → (thread, CPUs to avoid); set_realtime re-applies
_HELPERS: dict[int, tuple[threading.Thread, set[int] | None]] = {}
_HELPERS_LOCK = threading.Lock()


def demote_current_thread(avoid_cpus: set[int] | None = None) -> dict[str, Any]:
    """Put the calling helper thread (telemetry writer, executors, control socket) below the cycle and, if possible,
    off ``avoid_cpus``.

    In a real-time process a helper runs SCHED_FIFO at the lowest priority (``HELPER_PRIORITY``), not
    SCHED_OTHER: every cycle thread preempts it, and no normal task does — a SCHED_OTHER helper preempted by the
    host's other work *while it holds the GIL* would stall the cycle thread waiting for the GIL for as long as the
    scheduler keeps it off a CPU (milliseconds; the RPDO watchdogs fault the arm at 50). The thread is remembered: a
    helper started before `set_realtime` (the daemon's SDO worker and telemetry forwarder start during boot) is put
    at ``HELPER_PRIORITY`` when the process turns real-time, not left SCHED_OTHER. The policy carries
    SCHED_RESET_ON_FORK: processes the helper starts (the telemetry encoder, the planner) run SCHED_OTHER — and so do
    threads it starts, which call this in turn. A cycle at priority ``HELPER_PRIORITY`` or below has SCHED_OTHER
    helpers (never beside it), and so has a process `set_realtime` did not make real-time. Never raises.
    """
    with _HELPERS_LOCK:
        for tid in [tid for tid, (t, _) in _HELPERS.items() if not t.is_alive()]:  # (record windows' writers, ...)
            del _HELPERS[tid]
        _HELPERS[threading.get_native_id()] = (threading.current_thread(), set(avoid_cpus) if avoid_cpus else None)
        return _demote(0, avoid_cpus)


def _demote(tid: int, avoid_cpus: set[int] | None) -> dict[str, Any]:
    """`demote_current_thread` for thread ``tid`` (0: the calling one). Never raises."""
    out: dict[str, Any] = {"policy": None, "cpus": None, "reason": None}
    reasons: list[str] = []
    reset = getattr(os, "SCHED_RESET_ON_FORK", 0)
    try:
        if _REALTIME_PRIORITY is not None and _REALTIME_PRIORITY > HELPER_PRIORITY:
            try:
                os.sched_setscheduler(tid, os.SCHED_FIFO | reset, os.sched_param(HELPER_PRIORITY))
            except OSError as e:  # (RLIMIT_RTPRIO lowered since, a kernel without RESET_ON_FORK): SCHED_OTHER
                reasons.append(f"sched_setscheduler(SCHED_FIFO {HELPER_PRIORITY}) failed: {e.strerror}")
                os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
        elif os.sched_getscheduler(tid) & ~reset != os.SCHED_OTHER:
            os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
        out["policy"] = thread_policy(tid)
    except OSError as e:
        reasons.append(f"sched_getscheduler/sched_setscheduler failed: {e.strerror}")
    try:
        allowed = os.sched_getaffinity(tid)
        if avoid_cpus:
            rest = set(range(os.cpu_count() or 1)) - set(avoid_cpus)
            if rest:
                os.sched_setaffinity(tid, rest)
            else:
                reasons.append(f"no CPU left outside {sorted(avoid_cpus)}; affinity unchanged")
            allowed = os.sched_getaffinity(tid)
        out["cpus"] = sorted(allowed)
    except OSError as e:
        reasons.append(f"sched_setaffinity failed: {e.strerror}")
    out["reason"] = "; ".join(reasons) or None
    return out


def _demote_started_helpers() -> dict[str, Any]:
    """Put every live helper thread that called `demote_current_thread` before the process turned real-time at
    ``HELPER_PRIORITY`` (their name → what `_demote` reports); forget the ones that ended. Holding _HELPERS_LOCK."""
    done: dict[str, Any] = {}
    for tid, (thread, avoid) in list(_HELPERS.items()):
        if not thread.is_alive() or thread.native_id != tid:
            del _HELPERS[tid]
            continue
        done[thread.name] = _demote(tid, avoid)
    return done


def thread_policy(tid: int = 0) -> str:
    """Thread ``tid``'s (0: the calling thread's) scheduling policy as status reports it: "SCHED_FIFO 1",
    "SCHED_OTHER"."""
    reset = getattr(os, "SCHED_RESET_ON_FORK", 0)
    name = _policy_name(os.sched_getscheduler(tid) & ~reset)
    return f"{name} {os.sched_getparam(tid).sched_priority}" if name in ("SCHED_FIFO", "SCHED_RR") else name


def thread_policies() -> dict[str, str]:
    """Every live thread of this process (by name; its native id where two share one) → its scheduling policy."""
    out: dict[str, str] = {}
    for t in threading.enumerate():
        tid = t.native_id
        if tid is None:
            continue
        try:
            policy = thread_policy(tid)
        except OSError:  # (ended since)
            continue
        out[t.name if t.name not in out else f"{t.name} ({tid})"] = policy
    return out


def _policy_name(policy: int) -> str:
    names = {
        os.SCHED_OTHER: "SCHED_OTHER",
        os.SCHED_FIFO: "SCHED_FIFO",
        os.SCHED_RR: "SCHED_RR",
        getattr(os, "SCHED_BATCH", -10): "SCHED_BATCH",
        getattr(os, "SCHED_IDLE", -11): "SCHED_IDLE",
    }
    return names.get(policy, f"policy {policy}")


BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def single_threaded_blas() -> None:
    """One BLAS thread in this process: call before numpy is imported (a real-time process's first lines).

    OpenBLAS keeps worker threads (SCHED_OTHER) that spin-wait for work; a SCHED_FIFO thread that hands them a
    share of a matrix product and waits for it can wait until the scheduler finds a worker a free core: 80–100 ms
    measured here (the daemon's cycle stalled, the drives' RPDO watchdogs fired). The cycle's
    matrices are a few joints wide: one thread loses nothing. A value the user set is kept.
    """
    if "numpy" in sys.modules:
        raise RuntimeError("single_threaded_blas() must run before numpy is imported")
    for name in BLAS_THREAD_VARIABLES:
        os.environ.setdefault(name, "1")
