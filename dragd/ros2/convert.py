"""What the bridge translates between ROS 2 messages and the daemon's requests, without ROS types: joint order,
trajectories, service names, diagnostics. Pure functions (tests/test_ros2_convert.py needs no rclpy)."""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from typing import Any

OK, WARN, ERROR, STALE = 0, 1, 2, 3  # diagnostic_msgs/DiagnosticStatus levels


def order(names: Sequence[str], values: Sequence[float], joints: Sequence[str], what: str) -> list[float]:
    """``values`` named by ``names`` in the daemon's joint order ``joints``; ValueError naming what is missing,
    unknown, doubled, of the wrong count or not finite."""
    names = list(names)
    if len(values) != len(names):
        raise ValueError(f"{what}: {len(names)} names but {len(values)} positions")
    unknown = [n for n in names if n not in joints]
    twice = sorted({n for n in names if names.count(n) > 1})
    missing = [j for j in joints if j not in names]
    if unknown or twice or missing:
        parts = ([f"unknown joint(s) {', '.join(unknown)}"] if unknown else []) + \
                ([f"joint(s) named twice {', '.join(twice)}"] if twice else []) + \
                ([f"missing joint(s) {', '.join(missing)}"] if missing else [])
        raise ValueError(f"{what}: {'; '.join(parts)} (expected each of {', '.join(joints)} once)")
    out = [float(values[names.index(j)]) for j in joints]
    bad = [j for j, v in zip(joints, out, strict=True) if not math.isfinite(v)]
    if bad:
        raise ValueError(f"{what}: positions of {', '.join(bad)} are not finite")
    return out


def trajectory_samples(names: Sequence[str], points: Sequence[tuple[float, Sequence[float]]], joints: Sequence[str],
                       q_now: Sequence[float] | None) -> tuple[list[float], list[list[float]]]:
    """A ``trajectory_msgs/JointTrajectory`` (joint names; points as (time_from_start [s], positions)) as the samples
    of the daemon's ``track`` (``t_s`` from 0, ``q_rad`` in the daemon's joint order).

    As ``joint_trajectory_controller`` does, a first point later than 0 is reached from where the arm is (``q_now``
    prepended at 0). Every joint must be named (no partial trajectories); times must increase strictly. The daemon
    then checks the motion as it checks any ``track`` (limits, start pose, speed, acceleration, current)."""
    if not points:
        raise ValueError("trajectory: no points")
    qs = [order(names, p, joints, f"trajectory point {k}") for k, (_t, p) in enumerate(points)]
    ts = [float(t) for t, _p in points]
    bad = [k for k, t in enumerate(ts) if not math.isfinite(t) or t < 0]
    if bad:
        raise ValueError(f"trajectory: point {bad[0]}: time_from_start must be finite and >= 0, got {ts[bad[0]]}")
    back = [k for k in range(1, len(ts)) if ts[k] <= ts[k - 1]]
    if back:
        k = back[0]
        raise ValueError(f"trajectory: time_from_start must increase strictly: point {k} at {ts[k]:g} s after "
                         f"point {k - 1} at {ts[k - 1]:g} s")
    if ts[0] > 0.0:
        if q_now is None:
            raise ValueError("trajectory: the arm's pose is not known yet (no state from the daemon)")
        ts, qs = [0.0, *ts], [[float(x) for x in q_now], *qs]
    if len(ts) < 2:
        raise ValueError("trajectory: a single point at time_from_start 0 is no motion; give the time to reach it")
    return ts, qs


def service_name(program: str) -> str:
    """A program name as a ROS 2 name token (letters, digits, underscores; not starting with a digit)."""
    token = re.sub(r"[^A-Za-z0-9_]", "_", program).strip("_") or "program"
    token = re.sub(r"_+", "_", token)
    return f"p_{token}" if token[0].isdigit() else token


def _kv(values: dict[str, Any]) -> list[tuple[str, str]]:
    return [(k, "" if v is None else (f"{v:.6g}" if isinstance(v, float) else str(v))) for k, v in values.items()]


def diagnostics(status: dict[str, Any], bridge: dict[str, Any]) -> list[tuple[int, str, str, list[tuple[str, str]]]]:
    """``diagnostic_msgs/DiagnosticStatus`` entries (level, name, message, key/values) from the daemon's ``status``
    and the bridge's own counters: the loop's figures, faults, the buses, the drives, the bridge."""
    out: list[tuple[int, str, str, list[tuple[str, str]]]] = []
    missed = status.get("missed_cycles", 0)
    loop = {k: status.get(k) for k in ("cycles", "period_p50_us", "period_p99_us", "period_max_us", "compute_p50_us",
                                       "compute_p99_us", "missed_cycles", "missed_episodes", "late_tpdo_cycles",
                                       "tpdo_latency_p99_us", "scheduler", "feedback_holds")}
    out.append((OK, "dragd: loop", f"{status.get('cycles', 0)} cycles, {missed} missed, period p99 "
                                    f"{status.get('period_p99_us') or 0:.0f} us", _kv(loop)))
    faults = status.get("faults") or []
    mode = status.get("mode")
    level = ERROR if mode == "fault" else WARN if faults else OK
    message = faults[-1]["text"] if faults else "no faults"
    fv: dict[str, Any] = {"mode": mode, "fault_count": status.get("fault_count", 0)}
    for k, f in enumerate(faults[-5:]):
        fv[f"fault {k + 1}"] = f"t={f.get('t_s')} s {f.get('joint') or ''}: {f.get('text')}"
    guard = status.get("guard") or {}
    fv["guard_trips"] = guard.get("trips")
    out.append((level, "dragd: faults", message, _kv(fv)))
    comms = status.get("comms") or {}
    for name, load in (status.get("bus_load_pct") or {}).items():
        bv = {"worst_case_load_pct": load, "tx_errors": status.get("tx_errors"),
              "error_frames": status.get("error_frames"), "rejected_frames": status.get("rejected_frames"),
              "duplicate_tpdos": status.get("duplicate_tpdos"), "late_tpdo_cycles": status.get("late_tpdo_cycles"),
              "outages": comms.get("outages"), "drive_reboots": comms.get("reboots")}
        level = ERROR if comms.get("outage") else WARN if status.get("tx_errors") or status.get("error_frames") else OK
        out.append((level, f"dragd: bus {name}", f"worst-case load {load:.1f} % of the bit rate (the PDO layout's "
                    "budget)" + ("; OUTAGE: no heartbeat from any drive" if comms.get("outage") else ""), _kv(bv)))
    drives = status.get("drives") or []
    bad = [d for d in drives if "FAULT" in str(d.get("state", "")).upper()]
    out.append((ERROR if bad else OK, "dragd: drives",
                f"{len(bad)} drive(s) in fault" if bad else f"{len(drives)} drives",
                _kv({d["joint"]: f"{d['state']} (node {d['node_id']}, stale {d['stale_cycles']})" for d in drives})))
    blevel = ERROR if not bridge.get("daemon") else WARN if bridge.get("stream_latched") else OK
    out.append((blevel, "dragd: ros2 bridge", bridge.get("message", ""), _kv(bridge)))
    return out
