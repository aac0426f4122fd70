"""Foxglove's well-known channels beside dragd's own: joint states, the arm's link transforms, logs, the URDF.

Written by the telemetry writer's thread (never the cycle), decimated to ``rate_Hz``:

- ``/joint_states``       ``dragd.JointState``: joint names (the URDF's), position, velocity, measured and
                          commanded current, one message per decimated cycle row
- ``/tf``                 ``foxglove.FrameTransforms``: every URDF link relative to its parent link, from
                          Pinocchio's forward kinematics at the measured pose (Foxglove's 3D panel places the
                          URDF's links on these frames)
- ``/log``                ``foxglove.Log``: the daemon's events (faults and protective stops as ERROR/WARNING)
- ``/robot_description``  ``std_msgs/String``: the URDF text, once per file (the 3D panel's URDF layer with
                          source "topic" reads it, so the file alone shows the arm)
- ``/hand_force``         ``foxglove.SceneUpdate``: in drag, an arrow at the grip point along the operator's force
                          estimated from the contact residual (``hand_force_N``, ``grip_m``; 1 cm per N, in the
                          URDF's root frame); an empty update otherwise (docs/CONTACT.md)

The schemas are Foxglove's JSON schemas (foxglove.FrameTransforms, foxglove.Log); dragd's own cycle channel
is unchanged. docs/foxglove_layout.json is a layout for these topics.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dragd.telemetry.layout import RowLayout, dumps

__all__ = [
    "FoxgloveSpec",
    "FoxgloveChannels",
    "ArmFrames",
    "JOINT_STATES_TOPIC",
    "TF_TOPIC",
    "LOG_TOPIC",
    "ROBOT_DESCRIPTION_TOPIC",
    "FRAME_TRANSFORMS_SCHEMA",
    "LOG_SCHEMA",
    "JOINT_STATE_SCHEMA",
    "STRING_SCHEMA",
    "log_level",
]

JOINT_STATES_TOPIC = "/joint_states"
TF_TOPIC = "/tf"
LOG_TOPIC = "/log"
ROBOT_DESCRIPTION_TOPIC = "/robot_description"
HAND_FORCE_TOPIC = "/hand_force"

_TIME = {
    "type": "object",
    "title": "time",
    "properties": {
        "sec": {"type": "integer", "minimum": 0},
        "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999},
    },
}
_XYZ = {k: {"type": "number"} for k in ("x", "y", "z")}

FRAME_TRANSFORMS_SCHEMA: dict[str, Any] = {
    "title": "foxglove.FrameTransforms",
    "description": "An array of FrameTransform messages",
    "type": "object",
    "properties": {
        "transforms": {
            "type": "array",
            "description": "Array of transforms",
            "items": {
                "title": "foxglove.FrameTransform",
                "description": "A transform between two reference frames in 3D space",
                "type": "object",
                "properties": {
                    "timestamp": {**_TIME, "description": "Timestamp of transform"},
                    "parent_frame_id": {"type": "string", "description": "Name of the parent frame"},
                    "child_frame_id": {"type": "string", "description": "Name of the child frame"},
                    "translation": {"title": "foxglove.Vector3", "type": "object", "properties": dict(_XYZ),
                                    "description": "Translation component of the transform"},
                    "rotation": {"title": "foxglove.Quaternion", "type": "object",
                                 "properties": {**_XYZ, "w": {"type": "number"}},
                                 "description": "Rotation component of the transform"},
                },
            },
        }
    },
}
"""Foxglove's JSON schema of foxglove.FrameTransforms."""

LOG_LEVELS = {"UNKNOWN": 0, "DEBUG": 1, "INFO": 2, "WARNING": 3, "ERROR": 4, "FATAL": 5}

LOG_SCHEMA: dict[str, Any] = {
    "title": "foxglove.Log",
    "description": "A log message",
    "type": "object",
    "properties": {
        "timestamp": {**_TIME, "description": "Timestamp of log message"},
        "level": {"title": "foxglove.LogLevel", "description": "Log level",
                  "oneOf": [{"title": k, "const": v} for k, v in LOG_LEVELS.items()]},
        "message": {"type": "string", "description": "Log message"},
        "name": {"type": "string", "description": "Process or node name"},
        "file": {"type": "string", "description": "Filename"},
        "line": {"type": "integer", "minimum": 0, "description": "Line number in the file"},
    },
}
"""Foxglove's JSON schema of foxglove.Log."""


def _array(desc: str, kind: str = "number") -> dict[str, Any]:
    return {"type": "array", "items": {"type": kind}, "description": desc}


JOINT_STATE_SCHEMA: dict[str, Any] = {
    "title": "dragd.JointState",
    "description": "the arm's joints at one (decimated) control cycle, in the order of `name`",
    "type": "object",
    "properties": {
        "timestamp": {**_TIME, "description": "log time of the cycle"},
        "name": _array("joint names (the URDF's)", "string"),
        "position_rad": _array("joint positions from the encoders [rad]"),
        "velocity_rad_s": _array("estimated joint velocities [rad/s]"),
        "current_A": _array("motor currents measured by the drives [A]"),
        "command_A": _array("commanded motor currents [A]"),
        "mode": {"type": "string", "description": "the daemon's mode"},
    },
    "required": ["timestamp", "name", "position_rad", "velocity_rad_s", "current_A", "command_A", "mode"],
}
"""The joint-state message (ROS sensor_msgs/JointState's content, units in the field names)."""

# --- the hand's force in drag (#29: docs/CONTACT.md) ---
_VEC3 = {"title": "foxglove.Vector3", "type": "object", "properties": dict(_XYZ)}
_QUAT = {"title": "foxglove.Quaternion", "type": "object", "properties": {**_XYZ, "w": {"type": "number"}}}
_COLOR = {"title": "foxglove.Color", "type": "object", "properties": {k: {"type": "number"} for k in "rgba"}}
SCENE_UPDATE_SCHEMA: dict[str, Any] = {
    "title": "foxglove.SceneUpdate",
    "description": "An update to the entities displayed in a 3D scene",
    "type": "object",
    "properties": {
        "deletions": {"type": "array", "items": {"title": "foxglove.SceneEntityDeletion", "type": "object",
                                                   "properties": {"timestamp": _TIME, "type": {"type": "integer"},
                                                                  "id": {"type": "string"}}}},
        "entities": {"type": "array", "items": {
            "title": "foxglove.SceneEntity", "type": "object",
            "properties": {
                "timestamp": _TIME, "frame_id": {"type": "string"}, "id": {"type": "string"},
                "lifetime": {"title": "duration", "type": "object",
                             "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}},
                "frame_locked": {"type": "boolean"},
                "arrows": {"type": "array", "items": {
                    "title": "foxglove.ArrowPrimitive", "type": "object",
                    "properties": {"pose": {"title": "foxglove.Pose", "type": "object",
                                            "properties": {"position": _VEC3, "orientation": _QUAT}},
                                   "shaft_length": {"type": "number"}, "shaft_diameter": {"type": "number"},
                                   "head_length": {"type": "number"}, "head_diameter": {"type": "number"},
                                   "color": _COLOR}}},
            }}},
    },
}
"""Foxglove's JSON schema of foxglove.SceneUpdate (the fields dragd writes: entities with arrows)."""
HAND_FORCE_M_PER_N = 0.01  # the arrow's length per newton
HAND_FORCE_MIN_N = 1.0  # below this no arrow is drawn


def hand_force_arrow(ts: int, frame_id: str, at_m: np.ndarray, force_N: np.ndarray) -> dict[str, Any]:
    """A SceneUpdate with the hand's force as an arrow at ``at_m`` (``frame_id`` axes); no arrow below
    ``HAND_FORCE_MIN_N``. The arrow primitive points along its pose's +x: the rotation taking x onto the force."""
    f = np.asarray(force_N, dtype=float)
    norm = float(np.linalg.norm(f))
    arrows: list[dict[str, Any]] = []
    if np.isfinite(norm) and norm >= HAND_FORCE_MIN_N:
        u = f / norm
        w, v = 1.0 + u[0], np.array([0.0, -u[2], u[1]])  # q = [1 + x·u, x × u], normalised (x = (1, 0, 0))
        if w < 1e-9:  # u = -x: half a turn about z
            w, v = 0.0, np.array([0.0, 0.0, 1.0])
        qn = math.sqrt(w * w + float(v @ v))
        length = norm * HAND_FORCE_M_PER_N
        arrows.append({"pose": {"position": dict(zip("xyz", map(float, at_m), strict=True)),
                                "orientation": {"x": v[0] / qn, "y": v[1] / qn, "z": v[2] / qn, "w": w / qn}},
                       "shaft_length": 0.8 * length, "shaft_diameter": 0.01, "head_length": 0.2 * length,
                       "head_diameter": 0.025, "color": {"r": 1.0, "g": 0.45, "b": 0.0, "a": 1.0}})
    return {"entities": [{"timestamp": _stamp(ts), "frame_id": frame_id, "id": "hand_force",
                          "lifetime": {"sec": 0, "nsec": 0}, "frame_locked": False, "arrows": arrows}]}
# --- end of the hand's force ---


STRING_SCHEMA: dict[str, Any] = {
    "title": "std_msgs/String",
    "type": "object",
    "properties": {"data": {"type": "string"}},
    "required": ["data"],
}


def log_level(name: str, fields: Mapping[str, Any]) -> int:
    """foxglove.Log level of a daemon event: faults ERROR, protective stops and teach faults WARNING."""
    if name == "fault" or (name == "mode" and fields.get("mode") == "fault"):
        return LOG_LEVELS["ERROR"]
    if name in ("protective_stop", "teach_fault"):
        return LOG_LEVELS["WARNING"]
    return LOG_LEVELS["INFO"]


def _stamp(ns: int) -> dict[str, int]:
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


class ArmFrames:
    """Forward kinematics of a URDF with Pinocchio: each link's transform from its parent link.

    ``joint_names`` gives the order of the positions passed to `transforms` (the telemetry's joint order);
    each must be one of the URDF's joints.
    """

    def __init__(self, urdf: str | os.PathLike[str], joint_names: Sequence[str]) -> None:
        import pinocchio as pin

        self._pin = pin
        self.model = pin.buildModelFromUrdf(os.fspath(urdf))
        self.data = self.model.createData()
        names = list(self.model.names)
        missing = [j for j in joint_names if j not in names]
        if missing:
            raise ValueError(f"{urdf}: no joint(s) {', '.join(missing)} in the URDF (joints: {', '.join(names[1:])})")
        self._idx_q = np.array([self.model.joints[names.index(j)].idx_q for j in joint_names], dtype=np.intp)
        self._q = pin.neutral(self.model)
        body = pin.FrameType.BODY
        frames = self.model.frames
        pairs: list[tuple[int, int]] = []  # (parent body frame, child body frame)
        for fid, f in enumerate(frames):
            if f.type != body:
                continue
            parent = f.parentFrame
            while parent != 0 and frames[parent].type != body and frames[parent].parentFrame != parent:
                parent = frames[parent].parentFrame
            if frames[parent].type == body and parent != fid:
                pairs.append((parent, fid))
        self.pairs = pairs
        self.root = next((frames[i].name for i, f in enumerate(frames) if f.type == body), "base_link")
        self.links = [frames[c].name for _p, c in pairs]
        self._names = [(frames[p].name, frames[c].name) for p, c in pairs]
        # the kinematic chain root -> last link (for a skeleton drawing): each body frame's origin in the root
        chain = [i for i, f in enumerate(frames) if f.type == body]
        self._chain = chain
        self.chain_names = [frames[i].name for i in chain]

    def origins(self, q_rad: np.ndarray) -> np.ndarray:
        """(n, 3) origins of the URDF's links (root first) in the root link's frame at ``q_rad``."""
        pin = self._pin
        q = self._q
        q[self._idx_q] = q_rad
        pin.framesForwardKinematics(self.model, self.data, q)
        omf = self.data.oMf
        root = omf[self._chain[0]]
        return np.array([root.actInv(omf[i]).translation for i in self._chain])

    def transforms(self, q_rad: np.ndarray, time_ns: int) -> dict[str, Any]:
        """foxglove.FrameTransforms of every link at ``q_rad`` (telemetry joint order)."""
        pin = self._pin
        q = self._q
        q[self._idx_q] = q_rad
        pin.framesForwardKinematics(self.model, self.data, q)
        omf = self.data.oMf
        stamp = _stamp(time_ns)
        out = []
        for (p, c), (pname, cname) in zip(self.pairs, self._names, strict=True):
            m = omf[p].actInv(omf[c])
            t = m.translation
            x, y, z, w = pin.Quaternion(m.rotation).coeffs()
            out.append({"timestamp": stamp, "parent_frame_id": pname, "child_frame_id": cname,
                        "translation": {"x": float(t[0]), "y": float(t[1]), "z": float(t[2])},
                        "rotation": {"x": float(x), "y": float(y), "z": float(z), "w": float(w)}})
        return {"transforms": out}


@dataclass
class FoxgloveSpec:
    """What the writer needs for the Foxglove channels: joint names, the URDF, the decimated rate."""

    joint_names: Sequence[str]
    urdf: str | os.PathLike[str] | None = None
    rate_Hz: float = 50.0
    transforms: bool = True
    encoding: str = "json"  # json (Foxglove's schemas) or ros2 (CDR, standard ROS 2 types: dragd/telemetry/ros2.py)
    kt_Nm_per_A: Sequence[float] | None = None  # the joint states' effort (ros2) = K_t x the measured current
    _frames: ArmFrames | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if not self.rate_Hz > 0:
            raise ValueError(f"telemetry foxglove rate_Hz must be > 0; got {self.rate_Hz}")
        if self.encoding not in ("json", "ros2"):
            raise ValueError(f"telemetry foxglove encoding: expected json or ros2, got {self.encoding!r}")
        if self.urdf is not None and self.transforms:
            self._frames = ArmFrames(self.urdf, self.joint_names)

    @property
    def frames(self) -> ArmFrames | None:
        return self._frames

    def urdf_text(self) -> str | None:
        return None if self.urdf is None else Path(self.urdf).read_text(encoding="utf-8")


class FoxgloveChannels:
    """Registers the well-known channels on an ``mcap.writer.Writer`` and writes decimated rows and events."""

    def __init__(self, mcap: Any, spec: FoxgloveSpec) -> None:
        self.spec = spec
        self._mcap = mcap
        self._period_ns = int(round(1e9 / spec.rate_Hz))
        self._next_ns: int | None = None
        self._names = list(spec.joint_names)

        def channel(topic: str, schema: dict[str, Any]) -> int:
            sid = mcap.register_schema(name=schema["title"], encoding="jsonschema", data=dumps(schema))
            return int(mcap.register_channel(topic=topic, message_encoding="json", schema_id=sid))

        self._joint_states = channel(JOINT_STATES_TOPIC, JOINT_STATE_SCHEMA)
        self._tf = channel(TF_TOPIC, FRAME_TRANSFORMS_SCHEMA) if spec.frames is not None else None
        self._log = channel(LOG_TOPIC, LOG_SCHEMA)
        self._seq = 0
        text = spec.urdf_text()
        self._description = channel(ROBOT_DESCRIPTION_TOPIC, STRING_SCHEMA) if text is not None else None
        self._urdf_text = text
        self._described = False
        self._hand = channel(HAND_FORCE_TOPIC, SCENE_UPDATE_SCHEMA)  # (#29: the hand's force in drag)
        self._root = spec.frames.root if spec.frames is not None else "base_link"

    def _add(self, channel_id: int, t_ns: int, message: dict[str, Any], seq: int = 0) -> int:
        data = dumps(message)
        self._mcap.add_message(channel_id=channel_id, log_time=t_ns, data=data, publish_time=t_ns, sequence=seq)
        return len(data)

    def pick(self, stamps: np.ndarray) -> np.ndarray:
        """Indices of the rows (log times ``stamps``, ns) at the decimated rate: the first row of each period."""
        if stamps.size == 0:
            return np.zeros(0, dtype=np.intp)
        bins = stamps // self._period_ns
        first = np.flatnonzero(np.diff(bins, prepend=bins[0] - 1) != 0)
        if self._next_ns is not None:
            first = first[stamps[first] >= self._next_ns]
        if first.size:
            self._next_ns = (int(bins[first[-1]]) + 1) * self._period_ns
        return first

    def add_rows(self, layout: RowLayout, rows: np.ndarray, stamps: Sequence[int]) -> int:
        """Joint states and transforms of the decimated rows; returns bytes added."""
        t = np.asarray(stamps, dtype=np.int64)
        if self._description is not None and not self._described and t.size:
            self._described = True
            self._add(self._description, int(t[0]), {"data": self._urdf_text})
        idx = self.pick(t)
        if idx.size == 0:
            return 0
        sl = layout.slices
        mode_col = layout.columns[layout.names.index("mode")] if "mode" in sl else None
        frames = self.spec.frames
        n = 0
        for i in idx.tolist():
            r = rows[i]
            ts = int(t[i])
            self._seq += 1
            mode = ""
            if mode_col is not None and mode_col.labels is not None:
                v = r[mode_col.offset]
                mode = mode_col.labels.get(int(v), str(int(v))) if np.isfinite(v) else ""
            q = r[sl["q_rad"]]
            n += self._add(self._joint_states, ts, {
                "timestamp": _stamp(ts), "name": self._names, "position_rad": q.tolist(),
                "velocity_rad_s": r[sl["dq_rad_s"]].tolist(), "current_A": r[sl["current_measured_A"]].tolist(),
                "command_A": r[sl["current_command_A"]].tolist(), "mode": mode}, self._seq)
            if frames is not None and self._tf is not None and np.isfinite(q).all():
                n += self._add(self._tf, ts, frames.transforms(q, ts), self._seq)
            if "hand_force_N" in sl:
                n += self._add(self._hand, ts, hand_force_arrow(ts, self._root, r[sl["grip_m"]], r[sl["hand_force_N"]]),
                               self._seq)
        return n

    def add_event(self, t_ns: int, name: str, fields: Mapping[str, Any]) -> int:
        text = name + (" " + dumps(dict(fields)).decode() if fields else "")
        return self._add(self._log, t_ns, {"timestamp": _stamp(t_ns), "level": log_level(name, fields),
                                           "message": text, "name": "dragd", "file": "", "line": 0})
