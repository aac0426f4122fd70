"""ROS 2 bridge benchmarks (docs/ROS2.md): the bridge's CPU, the latency from the daemon's socket to a subscriber,
and the highest command-stream rate the whole path carries without the daemon missing a cycle.

One session: simulator + daemon as deployed (SCHED_FIFO where permitted) + ``dragd ros2`` as processes, and a plain
rclpy node in this process (subscribing ``/joint_states``, publishing ``~/joint_commands`` as
topic_based_ros2_control does). Needs the ros2 extra.

The machine's own stalls are measured through the whole session as in the loop benchmarks (dragd/lab/bench/stalls.py:
a probe process per CPU above the cycle thread's priority): each window's missed ticks (the arm held with no stream,
then each stream rate) are split into those a probe's stall explains (the host's) and the daemon's own, exactly as
``loop_missed_ratio_own`` splits them; the stream rate counts only the daemon's own.

The stream at each rate: the publisher first holds the arm's pose until the bridge's stream runs (the first command
opens it, those until the drives are in CSP are not followed: by design), then publishes a smooth path for the window's
length, then ends the stream (``~/streaming false``: a clean close, the arm holds). The stream arrived whole when no
command was lost before the bridge nor gave way in it (its ``commands_lost`` and ``commands_coalesced`` from before the
stream to after its close), the daemon's stream took at least as many samples in the window as were published (the
window's count also has the pose's last commands, in flight as it began), none was refused, and the one stream ran
throughout and ended by the close. The rates: up the ladder ``RATES_HZ`` to the first that fails, then ``BISECT_STEPS``
halvings between it and the highest that passed (none below 100 Hz: the default ``stream.delay_s`` of 50 ms is for
100-500 Hz controllers; every rate's figures in the detail).
"""

from __future__ import annotations

import math
import os
import sys
import threading
import time
from collections.abc import Callable
from functools import lru_cache
from typing import Any

import numpy as np

from dragd.lab.bench import BenchError, benchmark
from dragd.lab.bench.loop import _missed_by_cause, process_cpu_s
from dragd.lab.bench.stalls import PROBE_PRIORITY, StallProbe

RATES_HZ = (100, 250, 500, 1000)
BISECT_STEPS = 2  # halvings between the highest rate that passed and the lowest that failed
PRIME_S = 30.0  # the longest the pose is held for the stream to open (the drives' switch to CSP)
LAND_S = 0.3  # after the last command, the longest its samples in flight may take to land (the deadline is 0.5 s)


def _env() -> dict[str, str]:
    return {"ROS_DOMAIN_ID": str(150 + os.getpid() % 80), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}


@lru_cache(maxsize=1)
def _session(seconds: float, config: Any) -> dict[str, Any]:
    from dragd.lab.rig import Child, Rig, wait_until
    from dragd.ros2 import unavailable

    reason = unavailable()
    if reason:
        raise BenchError(reason)
    env = _env()
    os.environ.update(env)
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile
    from sensor_msgs.msg import JointState
    from std_srvs.srv import SetBool

    from dragd.lab.rig import DEPLOYED_PRIORITY

    out: dict[str, Any] = {}
    windows: dict[Any, tuple[int, dict[str, Any]]] = {}  # window -> (missed ticks, the daemon's episodes of it)

    def missed_in(rig: Rig, before: dict[str, Any], after: dict[str, Any]) -> tuple[int, dict[str, Any]]:
        log = rig.must("missed_ticks", since=before["missed_episodes"])  # the window's episodes (as loop.py)
        n_new = after["missed_episodes"] - before["missed_episodes"]
        log["episodes"] = log["episodes"][:max(0, n_new - log["lost"])]
        return after["missed_cycles"] - before["missed_cycles"], log

    probe = StallProbe(min(99, max(PROBE_PRIORITY, DEPLOYED_PRIORITY + 10)))
    with Rig("bench-ros2", config=config, as_deployed=True) as rig:
        rig.start_sim()
        rig.start_daemon()
        rig.must("start")
        bridge = Child("bridge", [sys.executable, "-m", "dragd", "ros2", "--socket", rig.socket], rig.workdir, env)
        ctx = rclpy.Context()
        rclpy.init(context=ctx, domain_id=int(env["ROS_DOMAIN_ID"]))
        node = rclpy.create_node("dragd_bench", context=ctx)
        lat: list[float] = []
        lock = threading.Lock()

        def heard(msg: JointState) -> None:
            now = node.get_clock().now().nanoseconds
            with lock:
                lat.append((now - (msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec)) * 1e-6)

        node.create_subscription(JointState, "/joint_states", heard, 100)
        bridge_diag: dict[str, str] = {}

        def diagnosed(msg: DiagnosticArray) -> None:
            for st in msg.status:
                if st.name == "dragd: ros2 bridge":
                    with lock:
                        bridge_diag.update({kv.key: kv.value for kv in st.values})

        node.create_subscription(DiagnosticArray, "/diagnostics", diagnosed, 10)
        # reliable, depth 1: topic_based_ros2_control's command publisher (docs/ROS2.md)
        pub = node.create_publisher(JointState, "/dragd/joint_commands", QoSProfile(depth=1))
        streaming: Any = node.create_client(SetBool, "/dragd/streaming")
        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(node)
        spin = threading.Thread(target=ex.spin, daemon=True)
        spin.start()
        try:
            try:  # the machine's own stalls through the session
                probe.__enter__()
            except OSError as e:
                probe.errors.append(str(e))
            wait_until(lambda: "bridging the daemon" in bridge.output(), 30.0, "the bridge", bridge)
            wait_until(lambda: len(lat) > 50, 30.0, "joint states from the bridge", bridge)
            # bridge CPU and the latency of /joint_states (100 Hz), the arm held
            with lock:
                lat.clear()
            m0 = rig.must("status")
            c0, t0 = process_cpu_s(bridge.proc.pid), time.monotonic()
            rig.sleep(seconds)
            cpu = (process_cpu_s(bridge.proc.pid) - c0) / (time.monotonic() - t0) * 100.0
            windows["baseline"] = missed_in(rig, m0, rig.must("status"))  # the same time, no stream
            with lock:
                got = np.array(lat)
            out["bridge_cpu_pct"] = cpu
            out["latency_ms"] = got
            out["joint_states_Hz"] = len(got) / seconds
            # the command stream: a smooth path at each rate, through the bridge into the daemon's stream
            robot = rig.must("robot")
            names, out["loop_rate_Hz"] = robot["joint_names"], robot["rate_Hz"]
            rates: list[dict[str, Any]] = []

            def one_rate(rate: float) -> bool:
                """A stream at ``rate``: its figures in ``rates``; True if it arrived whole (the missed cycles' split
                comes after the session, when the probes' stalls are known)."""
                rig.wait_for(lambda: rig.must("status")["mode"] == "hold"
                             and rig.must("status")["drive_mode"] == "cst", 10.0, "hold in CST")
                _call(streaming, True)  # (the last rate's close latched the bridge: each rate starts afresh)
                q0 = np.array(rig.must("state")["q_rad"])
                opened = (rig.must("status")["stream"] or {}).get("opened") or 0
                with lock:
                    d0 = dict(bridge_diag)  # (the bridge's counters from before the stream to after its close)
                primed = _prime(node, pub, names, q0, rate, lambda: _running(rig, opened))
                s0 = rig.must("status")
                sid = (s0["stream"] or {}).get("stream")
                b0 = process_cpu_s(bridge.proc.pid)
                sent = _stream(node, pub, names, q0, rate, seconds)
                s1 = _landed(rig)  # the last commands in flight land (the stream must still run)
                b1 = process_cpu_s(bridge.proc.pid)
                _call(streaming, False)  # the stream ends cleanly (closed): the arm runs out its samples, holds
                rig.wait_for(lambda: (rig.must("status")["stream"] or {}).get("state") == "ended", 10.0,
                             "the stream's end")
                end = rig.must("status")
                time.sleep(1.5)  # (the bridge's next diagnostics, 1 Hz)
                with lock:
                    d1 = dict(bridge_diag)
                windows[rate] = missed_in(rig, s0, s1)
                st0, st1, ste = s0["stream"] or {}, s1["stream"] or {}, end["stream"] or {}
                got = (st1.get("samples") or 0) - (st0.get("samples") or 0)

                def delta(key: str) -> int | None:
                    try:
                        return int(d1[key]) - int(d0[key])
                    except (KeyError, ValueError):
                        return None

                # whole: none lost before the bridge nor given way in it (its counters), none refused, the one
                # stream running throughout and ended by the close, and at least every published command a sample
                # (the window's count also has the pose's last commands, in flight when it began)
                whole = (primed and st1.get("stream") == sid and st1.get("state") == "running" and got >= sent
                         and delta("commands_lost") == 0 and delta("commands_coalesced") == 0
                         and ste.get("end") == "closed" and ste.get("stream") == sid)

                rates.append({"rate_Hz": rate, "published": sent, "daemon_samples": got, "whole": whole,
                              "running_at_end": st1.get("state") == "running" and st1.get("stream") == sid,
                              "stream_end": ste.get("end"), "outcome": ste.get("outcome"),
                              "refused": (ste.get("refused") or 0) - (st0.get("refused") or 0),
                              "bridge_lost": delta("commands_lost"), "bridge_coalesced": delta("commands_coalesced"),
                              "bridge_forwarded": delta("commands_forwarded"),
                              "bridge_dropped": delta("commands_dropped"),
                              "dry_cycles": (st1.get("dry_cycles") or 0) - (st0.get("dry_cycles") or 0),
                              "min_buffer_s": st1.get("min_buffer_s"),
                              "missed_cycles": s1["missed_cycles"] - s0["missed_cycles"],
                              "period_max_us": s1["period_max_us"], "bridge_cpu_pct": (b1 - b0) / seconds * 100.0,
                              "faults": end["faults"][-1:] if end["mode"] == "fault" else []})
                if end["mode"] == "fault":
                    rig.must("start")
                return whole

            passed, failed = 0.0, None
            for rate in RATES_HZ:  # up the ladder to the first rate that fails
                if not one_rate(rate):
                    failed = rate
                    break
                passed = rate
            if failed is not None and passed > 0:  # then halvings between the highest that passed and it (never
                # below the ladder's first rate: slower streams need a longer stream.delay_s, docs/ROS2.md)
                lo, hi = passed, float(failed)
                for _ in range(BISECT_STEPS):
                    mid = round((lo + hi) / 2.0)
                    if mid in (lo, hi):
                        break
                    if one_rate(mid):
                        lo = mid
                    else:
                        hi = mid
            out["rates"] = rates
            out["schedulers"] = rig.schedulers()
        finally:
            try:
                probe.__exit__(None, None, None)
            except Exception as e:  # noqa: BLE001 - the probes' end must not hide the session's own error
                probe.errors.append(str(e))
            ex.shutdown(timeout_sec=2.0)
            node.destroy_node()
            rclpy.shutdown(context=ctx)
            bridge.terminate()
    dt = 1.0 / float(out["loop_rate_Hz"])  # the cycle's period (episodes are in ticks)
    out["stalls_measured"] = probe.complete
    out["probe_errors"] = probe.errors
    out["host_stall_max_ms"] = probe.summary()["late_max_ms"] if probe.complete else None
    for key, (missed, log) in windows.items():
        host, own = _missed_by_cause(missed, log, probe, dt) if probe.complete else (None, None)
        split = {"missed_cycles": missed, "missed_host": host, "missed_own": own}
        if key == "baseline":
            out["baseline"] = split
        else:
            next(r for r in out["rates"] if r["rate_Hz"] == key).update(split)
    return out


def _call(client: Any, on: bool) -> None:
    """``~/streaming true`` (the bridge follows commands again: a close or a refusal latches it until then) or
    ``false`` (the bridge closes its stream: the arm runs out the samples, then holds)."""
    from std_srvs.srv import SetBool

    if not client.wait_for_service(timeout_sec=30.0):
        raise BenchError("the bridge's ~/streaming service did not appear")
    done = threading.Event()
    fut = client.call_async(SetBool.Request(data=on))
    fut.add_done_callback(lambda _f: done.set())
    if not done.wait(30.0) or not fut.result().success:
        raise BenchError(f"~/streaming {str(on).lower()}: {fut.result() if fut.done() else 'no answer within 30 s'}")


def _landed(rig: Any) -> dict[str, Any]:
    """The daemon's status once its stream's sample count stood still for 50 ms (at most ``LAND_S``) after the last
    command: those in flight have landed (the stream still runs: its deadline is 0.5 s)."""
    end = time.monotonic() + LAND_S
    last = rig.must("status")
    while time.monotonic() < end:
        time.sleep(0.05)
        now = rig.must("status")
        if (now["stream"] or {}).get("samples") == (last["stream"] or {}).get("samples"):
            return now
        last = now
    return last


def _running(rig: Any, opened_before: int) -> bool:
    st = rig.must("status")["stream"] or {}
    return (st.get("opened") or 0) > opened_before and st.get("state") == "running" and (st.get("samples") or 0) > 0


def _prime(node: Any, pub: Any, names: list[str], q0: np.ndarray, rate: float, running: Any) -> bool:
    """Hold the pose at ``rate`` until the bridge's stream runs (its first command opens it); False if it did not
    within ``PRIME_S``."""
    from sensor_msgs.msg import JointState

    t0 = time.monotonic()
    k = 0
    while time.monotonic() - t0 < PRIME_S:
        msg = JointState()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(node.get_clock().now().nanoseconds), 10**9)
        msg.name = names
        msg.position = q0.tolist()
        pub.publish(msg)
        k += 1
        if k % max(1, int(rate / 20)) == 0 and running():  # (asked at ~20 Hz)
            return True
        time.sleep(max(0.0, t0 + k / rate - time.monotonic()))
    return False


def _stream(node: Any, pub: Any, names: list[str], q0: np.ndarray, rate: float, seconds: float) -> int:
    """Publish a slow sine path from ``q0`` at ``rate`` for ``seconds`` (absolute deadlines): the number published."""
    from sensor_msgs.msg import JointState

    step = np.array([0.1, -0.08, 0.1, 0.12, -0.1, 0.12])
    period = 1.0 / rate
    t0 = time.monotonic()
    k = 0
    while True:
        t = time.monotonic() - t0
        if t > seconds:
            break
        msg = JointState()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(node.get_clock().now().nanoseconds), 10**9)
        msg.name = names
        msg.position = (q0 + step * (1 - math.cos(2 * math.pi * t / seconds)) / 2).tolist()
        pub.publish(msg)
        k += 1
        time.sleep(max(0.0, t0 + k * period - time.monotonic()))
    return k


def _opts(opts: dict) -> tuple[float, Any]:
    return float(opts.get("seconds") or 5.0), opts.get("config")


@benchmark("ros2_bridge_cpu_pct", "%")
def ros2_bridge_cpu_pct(opts: dict) -> tuple[float, dict[str, Any]]:
    """The bridge's CPU time as a share of one core, publishing /joint_states at 100 Hz (and its diagnostics), the
    arm held."""
    s = _session(*_opts(opts))
    return float(s["bridge_cpu_pct"]), {"joint_states_Hz": round(s["joint_states_Hz"], 1),
                                        "schedulers": s["schedulers"]}


@benchmark("ros2_state_latency_ms", "ms")
def ros2_state_latency_ms(opts: dict) -> tuple[float, dict[str, Any]]:
    """Median age of a /joint_states message when a subscriber gets it: from the bridge's state request on the
    socket (its header stamp) through the daemon's answer, the publish and DDS (p99 and max in the detail)."""
    lat = _session(*_opts(opts))["latency_ms"]
    if lat.size == 0:
        raise BenchError("no joint states arrived")
    return float(np.median(lat)), {"p99_ms": round(float(np.percentile(lat, 99)), 3),
                                   "max_ms": round(float(lat.max()), 3), "messages": int(lat.size)}


@benchmark("ros2_stream_max_rate_Hz", "Hz")
def ros2_stream_max_rate_Hz(opts: dict) -> tuple[float, dict[str, Any]]:
    """The highest rate of ~/joint_commands whose stream arrived whole in the daemon (every command published in the
    window a sample of one running stream, none lost or coalesced by the bridge, none refused, ended by its close)
    with none of the daemon's own missed cycles in the window. Searched: 100, 250, 500, 1000 Hz up to the first rate
    not whole, then two halvings between it and the highest whole one (each rate one window of --seconds; 0 if 100 Hz
    was not). The detail has each rate's figures (published, the daemon's samples, the bridge's commands lost by the
    middleware and coalesced, missed cycles host/own) and the missed cycles of the same time with the arm held and no
    stream (the machine's own)."""
    s = _session(*_opts(opts))
    if not s["stalls_measured"]:
        raise BenchError(f"ros2_stream_max_rate_Hz: the machine's stalls were not measured "
                         f"({'; '.join(s['probe_errors'])}): the daemon's own missed cycles cannot be told from the "
                         "host's")
    rates = s["rates"]
    ok = [r["rate_Hz"] for r in rates if r["whole"] and r["missed_own"] == 0]
    return float(max(ok) if ok else 0.0), {"rates": rates, "baseline": s["baseline"],
                                           "host_stall_max_ms": s["host_stall_max_ms"],
                                           "searched": "ladder 100/250/500/1000 Hz to the first rate not whole, "
                                                       f"then {BISECT_STEPS} halvings"}


# -- the stream's cost to the cycle (no ROS: a socket client streaming as the bridge does) ---------------------------

STREAM_RATES_HZ = (100, 500)


def _thread_cpu_ns(pid: int) -> dict[int, int]:
    """Each thread's CPU time so far [ns] (``/proc/PID/task/TID/schedstat``)."""
    out = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{tid}/schedstat") as f:
                out[int(tid)] = int(f.read().split()[0])
        except (OSError, ValueError, IndexError):
            continue
    return out


def _socket_stream(rig: Any, rate: float, seconds: float, mark: Callable[[], None]) -> dict[str, Any]:
    """A stream of a smooth path at ``rate`` on one connection, the samples sent without waiting for their answers (as
    the bridge pipelines them; a reader thread takes the answers), then closed; the arm holds again. ``mark`` is
    called as the sending begins (the stream open) and as it ends (before the close)."""
    import json
    import socket

    q0 = np.array(rig.must("status")["q_rad"])
    sid = rig.must("stream_open", label="bench")["stream"]
    sent_at: list[float] = []
    lat: list[float] = []
    got: dict[str, Any] = {"ok": 0, "refused": 0, "first_refusal": None}
    sign = np.array([1.0, -1.0, 1.0, 1.0, -1.0, 1.0])[: q0.size]
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.connect(rig.socket)
        f = s.makefile("rb")

        def reader() -> None:
            while True:
                line = f.readline()
                if not line:
                    return
                r = json.loads(line)
                lat.append(time.monotonic() - sent_at[len(lat)])
                if r["ok"]:
                    got["ok"] += 1
                else:
                    got["refused"] += 1
                    got["first_refusal"] = got["first_refusal"] or r["error"]

        th = threading.Thread(target=reader, daemon=True)
        th.start()
        mark()
        t0 = due = time.monotonic()
        while (now := time.monotonic()) - t0 < seconds:
            q = q0 + 0.05 * math.sin(math.pi * (now - t0)) * sign
            sent_at.append(time.monotonic())
            s.sendall(json.dumps({"cmd": "stream", "stream": sid, "t_s": now, "q_rad": q.tolist()}).encode() + b"\n")
            due += 1.0 / rate
            pause = due - time.monotonic()
            if pause > 0:
                time.sleep(pause)
        wait_until = time.monotonic() + 10.0  # the answers still on their way (pipelined)
        while len(lat) < len(sent_at) and time.monotonic() < wait_until:
            time.sleep(0.001)
        mark()
        s.shutdown(socket.SHUT_RDWR)  # (the reader's readline ends)
        th.join(10.0)
    rig.call("stream_close", stream=sid)  # (refused if the stream ended before: its end says how)
    rig.wait_for(lambda: rig.must("status")["mode"] == "hold", 10.0, "hold after the stream's end")
    end = rig.must("status")["stream"] or {}
    return {"stream_end": end.get("end"), "outcome": end.get("outcome"), "sent": len(sent_at), "accepted": got["ok"],
            "refused": got["refused"],
            "first_refusal": got["first_refusal"], "sent_Hz": round(len(sent_at) / seconds, 1),
            "answer_p50_ms": round(1e3 * float(np.median(lat)), 3) if lat else None,
            "answer_p99_ms": round(1e3 * float(np.percentile(lat, 99)), 3) if lat else None}


@benchmark("ros2_stream_cycle_cpu_us", "us")
def ros2_stream_cycle_cpu_us(opts: dict) -> tuple[float, dict[str, Any]]:
    """The cycle thread's CPU time per streamed sample: a socket client streams into TRACK at 100 Hz, then 500 Hz
    (one window of --seconds each, samples pipelined as the bridge sends them), and the cycle thread's CPU per cycle
    (``/proc``'s schedstat of the daemon's main thread) grows by this much per sample a cycle (the two rates' slope:
    the TRACK mode's own cost cancels). 0 when no request runs on the cycle's thread. The detail has each window (the
    arm held with no stream, then each rate): the cycle thread's and the other threads' CPU per cycle, the samples,
    the answers' latency, and the missed cycles split into the host's and the daemon's own (probes, as
    ``loop_missed_ratio_own``). Simulator + daemon as deployed (SCHED_FIFO where permitted); no ROS."""
    from dragd.lab.rig import DEPLOYED_PRIORITY, Rig

    seconds, config = _opts(opts)
    probe = StallProbe(min(99, max(PROBE_PRIORITY, DEPLOYED_PRIORITY + 10)))
    windows: dict[str, dict[str, Any]] = {}
    logs: dict[str, tuple[int, dict[str, Any]]] = {}
    with Rig("bench-stream", config=config, as_deployed=True) as rig:
        rig.start_sim()
        rig.start_daemon()
        rig.must("start")
        rig.wait_for(lambda: rig.must("status")["mode"] == "hold", 10.0, "hold")
        assert rig.daemon is not None
        pid = rig.daemon.proc.pid
        probe.__enter__()
        try:
            for name, rate in (("held", 0), *((f"stream_{r}Hz", r) for r in STREAM_RATES_HZ)):
                marks: list[tuple[dict[str, Any], dict[int, int]]] = []

                def mark(into: list[tuple[dict[str, Any], dict[int, int]]] = marks) -> None:
                    into.append((rig.must("status"), _thread_cpu_ns(pid)))

                extra: dict[str, Any] = {}
                if rate:  # (the window: the sending alone, not the drives' switch to CSP nor the end into hold)
                    extra = _socket_stream(rig, rate, seconds, mark)
                else:
                    mark()
                    time.sleep(seconds)
                    mark()
                (s0, c0), (s1, c1) = marks
                cycles = s1["cycles"] - s0["cycles"]
                others = sum(ns - c0.get(tid, 0) for tid, ns in c1.items() if tid != pid)
                windows[name] = {"cycles": cycles,
                                 "cycle_thread_us_per_cycle": round((c1[pid] - c0[pid]) / 1e3 / cycles, 2),
                                 "other_threads_us_per_cycle": round(others / 1e3 / cycles, 2),
                                 "samples_per_cycle": round(extra.get("sent", 0) / cycles, 4),
                                 "control": s1.get("control"), **extra}
                log = rig.must("missed_ticks", since=s0["missed_episodes"])
                n_new = s1["missed_episodes"] - s0["missed_episodes"]
                log["episodes"] = log["episodes"][:max(0, n_new - log["lost"])]
                logs[name] = (s1["missed_cycles"] - s0["missed_cycles"], log)
            dt = 1.0 / float(rig.must("robot")["rate_Hz"])
            schedulers = rig.schedulers()
        finally:
            try:
                probe.__exit__(None, None, None)
            except Exception as e:  # noqa: BLE001 - the probes' end must not hide the session's own error
                probe.errors.append(str(e))
    for name, (missed, log) in logs.items():
        host, own = _missed_by_cause(missed, log, probe, dt) if probe.complete else (None, None)
        windows[name].update(missed_cycles=missed, missed_host=host, missed_own=own)
    lo, hi = (windows[f"stream_{r}Hz"] for r in STREAM_RATES_HZ)
    per = (hi["cycle_thread_us_per_cycle"] - lo["cycle_thread_us_per_cycle"]) / max(
        hi["samples_per_cycle"] - lo["samples_per_cycle"], 1e-9)
    return round(per, 1), {"windows": windows, "stalls_measured": probe.complete, "probe_errors": probe.errors,
                           "schedulers": schedulers}
