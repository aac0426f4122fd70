"""The telemetry's well-known channels in ROS 2's encoding (CDR, ``ros2msg`` schemas) instead of JSON:
``telemetry.foxglove_encoding: ros2``, and ``dragd log ros2`` (a pure ROS 2 bag from any dragd telemetry file).

- ``/joint_states``       ``sensor_msgs/msg/JointState``: names (the URDF's), position, velocity, effort = K_t·I
                          (the measured current through the model's torque constants), one per decimated row
- ``/tf``                 ``tf2_msgs/msg/TFMessage``: every URDF link relative to its parent (Pinocchio FK)
- ``/robot_description``  ``std_msgs/msg/String``: the URDF, once
- ``/rosout``             ``rcl_interfaces/msg/Log``: the daemon's events (faults ERROR, protective stops WARN)

Encoded with mcap-ros2-support's serializer from the definitions below (no ROS installation); tests decode them
with ROS's own type support (rclpy) and the ROS 2 MCAP reader. A file that mixes these with dragd's JSON channels
reads in Foxglove's ROS 2 panels; ``ros2 bag play`` refuses files whose topics differ in serialization format
(rosbag2 #1245), so ``dragd log ros2`` writes a file with only these channels and the ``ros2`` profile.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from dragd.telemetry.foxglove import (
    JOINT_STATES_TOPIC,
    ROBOT_DESCRIPTION_TOPIC,
    TF_TOPIC,
    FoxgloveChannels,
    FoxgloveSpec,
)
from dragd.telemetry.layout import RowLayout

ROSOUT_TOPIC = "/rosout"
_SEP = "=" * 80 + "\n"
_TIME = "MSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n"
_HEADER = "MSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n"

# the message definitions as ROS 2's ros2msg schema encoding concatenates them (comments dropped)
DEFINITIONS: dict[str, str] = {
    "sensor_msgs/msg/JointState": ("std_msgs/Header header\nstring[] name\nfloat64[] position\nfloat64[] velocity\n"
                                   "float64[] effort\n" + _SEP + _HEADER + _SEP + _TIME),
    "tf2_msgs/msg/TFMessage": ("geometry_msgs/TransformStamped[] transforms\n" + _SEP +
                               "MSG: geometry_msgs/TransformStamped\nstd_msgs/Header header\nstring child_frame_id\n"
                               "geometry_msgs/Transform transform\n" + _SEP +
                               "MSG: geometry_msgs/Transform\ngeometry_msgs/Vector3 translation\n"
                               "geometry_msgs/Quaternion rotation\n" + _SEP +
                               "MSG: geometry_msgs/Vector3\nfloat64 x\nfloat64 y\nfloat64 z\n" + _SEP +
                               "MSG: geometry_msgs/Quaternion\nfloat64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n"
                               + _SEP + _HEADER + _SEP + _TIME),
    "std_msgs/msg/String": "string data\n",
    "rcl_interfaces/msg/Log": ("uint8 DEBUG=10\nuint8 INFO=20\nuint8 WARN=30\nuint8 ERROR=40\nuint8 FATAL=50\n"
                               "builtin_interfaces/Time stamp\nuint8 level\nstring name\nstring msg\nstring file\n"
                               "string function\nuint32 line\n" + _SEP + _TIME),
}
LOG_LEVELS = {"INFO": 20, "WARN": 30, "ERROR": 40}


def log_level(name: str, fields: Mapping[str, Any]) -> int:
    """rcl_interfaces/Log level of a daemon event (as the Foxglove log's: faults ERROR, stops WARN)."""
    if name == "fault" or (name == "mode" and fields.get("mode") == "fault"):
        return LOG_LEVELS["ERROR"]
    if name in ("protective_stop", "teach_fault"):
        return LOG_LEVELS["WARN"]
    return LOG_LEVELS["INFO"]


def _time(ns: int) -> dict[str, int]:
    return {"sec": int(ns // 1_000_000_000), "nanosec": int(ns % 1_000_000_000)}


def encoders() -> dict[str, Any]:
    """CDR encoders of ``DEFINITIONS`` (message dicts in, bytes out)."""
    from mcap_ros2._dynamic import serialize_dynamic  # (mcap-ros2-support's serializer; its Writer uses it too)

    return {name: serialize_dynamic(name, text)[name] for name, text in DEFINITIONS.items()}


class Ros2Channels(FoxgloveChannels):
    """`FoxgloveChannels` in ROS 2's encoding: the same topics, rates and decimation, standard ROS 2 types."""

    def __init__(self, mcap: Any, spec: FoxgloveSpec) -> None:
        self.spec = spec
        self._mcap = mcap
        self._period_ns = int(round(1e9 / spec.rate_Hz))
        self._next_ns: int | None = None
        self._names = list(spec.joint_names)
        self._kt = np.asarray(spec.kt_Nm_per_A if spec.kt_Nm_per_A is not None else np.ones(len(self._names)))
        self._enc = encoders()

        def channel(topic: str, datatype: str) -> int:
            sid = mcap.register_schema(name=datatype, encoding="ros2msg", data=DEFINITIONS[datatype].encode())
            return int(mcap.register_channel(topic=topic, message_encoding="cdr", schema_id=sid))

        self._types: dict[int, str] = {}
        self._joint_states = channel(JOINT_STATES_TOPIC, "sensor_msgs/msg/JointState")
        self._types[self._joint_states] = "sensor_msgs/msg/JointState"
        self._tf = channel(TF_TOPIC, "tf2_msgs/msg/TFMessage") if spec.frames is not None else None
        if self._tf is not None:
            self._types[self._tf] = "tf2_msgs/msg/TFMessage"
        self._log = channel(ROSOUT_TOPIC, "rcl_interfaces/msg/Log")
        self._types[self._log] = "rcl_interfaces/msg/Log"
        self._seq = 0
        text = spec.urdf_text()
        self._description = channel(ROBOT_DESCRIPTION_TOPIC, "std_msgs/msg/String") if text is not None else None
        if self._description is not None:
            self._types[self._description] = "std_msgs/msg/String"
        self._urdf_text = text
        self._described = False

    def _add(self, channel_id: int, t_ns: int, message: dict[str, Any], seq: int = 0) -> int:
        data = self._enc[self._types[channel_id]](message)
        self._mcap.add_message(channel_id=channel_id, log_time=t_ns, data=data, publish_time=t_ns, sequence=seq)
        return len(data)

    def add_rows(self, layout: RowLayout, rows: np.ndarray, stamps: Sequence[int]) -> int:
        sl = layout.slices
        return self.add_joint_rows(np.asarray(stamps, dtype=np.int64), rows[:, sl["q_rad"]], rows[:, sl["dq_rad_s"]],
                                   rows[:, sl["current_measured_A"]])

    def add_joint_rows(self, t: np.ndarray, q_rad: np.ndarray, dq_rad_s: np.ndarray, current_A: np.ndarray) -> int:
        """Joint states and transforms of the rows at the decimated rate (log times ``t`` ns); bytes added."""
        if self._description is not None and not self._described and t.size:
            self._described = True
            self._add(self._description, int(t[0]), {"data": self._urdf_text})
        idx = self.pick(t)
        frames = self.spec.frames
        n = 0
        for i in idx.tolist():
            ts = int(t[i])
            self._seq += 1
            q = q_rad[i]
            n += self._add(self._joint_states, ts, {
                "header": {"stamp": _time(ts), "frame_id": ""}, "name": self._names, "position": q.tolist(),
                "velocity": dq_rad_s[i].tolist(), "effort": (current_A[i] * self._kt).tolist()}, self._seq)
            if frames is not None and self._tf is not None and np.isfinite(q).all():
                fox = frames.transforms(q, ts)["transforms"]
                n += self._add(self._tf, ts, {"transforms": [
                    {"header": {"stamp": _time(ts), "frame_id": f["parent_frame_id"]},
                     "child_frame_id": f["child_frame_id"],
                     "transform": {"translation": f["translation"], "rotation": f["rotation"]}} for f in fox]},
                    self._seq)
        return n

    def add_event(self, t_ns: int, name: str, fields: Mapping[str, Any]) -> int:
        text = name + (" " + json.dumps(dict(fields), default=str) if fields else "")
        return self._add(self._log, t_ns, {"stamp": _time(t_ns), "level": log_level(name, fields), "name": "dragd",
                                           "msg": text, "file": "", "function": "", "line": 0})


def export(src: str | os.PathLike[str], dst: str | os.PathLike[str], spec: FoxgloveSpec) -> dict[str, Any]:
    """A pure ROS 2 bag (MCAP, profile ``ros2``, CDR only: what ``ros2 bag play`` accepts) from a dragd telemetry
    file: its cycle rows as ``/joint_states`` and ``/tf`` at ``spec.rate_Hz``, its events on ``/rosout``, the URDF on
    ``/robot_description``. Returns counts."""
    from mcap.writer import CompressionType, Writer

    from dragd.telemetry.reader import read_log, read_log_times

    log = read_log(src, ["q_rad", "dq_rad_s", "current_measured_A"])
    t = read_log_times(src)
    q = log.rows["q_rad"]
    if len(t) != len(q):
        raise ValueError(f"{src}: {len(q)} cycle rows but {len(t)} log times")
    if q.ndim != 2 or q.shape[1] != len(spec.joint_names):
        raise ValueError(f"{src}: rows of {q.shape[1] if q.ndim == 2 else 1} joints, but the configuration names "
                         f"{len(spec.joint_names)} ({', '.join(spec.joint_names)}): give the arm's --config")
    events = sorted(log.events, key=lambda e: e.time_ns)
    with open(dst, "wb") as fh:
        w = Writer(fh, compression=CompressionType.ZSTD)
        w.start(profile="ros2", library="dragd")
        ch = Ros2Channels(w, spec)
        k = 0
        for i in range(0, len(t), 4096):  # in blocks, events in time order between them
            end = min(i + 4096, len(t))
            while k < len(events) and events[k].time_ns <= t[end - 1]:
                ch.add_event(events[k].time_ns, events[k].name, events[k].fields)
                k += 1
            ch.add_joint_rows(t[i:end], q[i:end], log.rows["dq_rad_s"][i:end], log.rows["current_measured_A"][i:end])
        for e in events[k:]:
            ch.add_event(e.time_ns, e.name, e.fields)
        w.finish()
    return {"rows": int(len(t)), "joint_states": ch._seq, "events": len(events), "path": os.fspath(dst)}
