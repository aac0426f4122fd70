"""The telemetry contract: topics, schema and metadata names, `Field`, and the daemon's cycle row.

Every writer of a dragd MCAP (the daemon, its record windows, ``python -m sim log``) lays its rows out with
`cycle_layout`; every reader (dragd/telemetry/reader.py) relies on these names.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

from dragd.control.modes import MODE_NAMES

__all__ = [
    "CYCLE_TOPIC",
    "EVENTS_TOPIC",
    "CYCLE_SCHEMA",
    "EVENT_SCHEMA",
    "RUN_METADATA",
    "WRITER_METADATA",
    "Field",
    "Labels",
    "MODE_LABELS",
    "cycle_layout",
    "event_json_schema",
]

CYCLE_TOPIC = "/dragd/cycle"
"""One JSON message per control cycle (a row of `cycle_layout`)."""
EVENTS_TOPIC = "/dragd/events"
"""Rare events (mode changes, faults, record start/stop): ``{"name": ..., **fields}``."""
HAND_TOPIC = "/dragd/hand"
"""The hand guiding state at every change (docs/HAND.md): what drag requires, the lease, the hand's inputs; the
events named ``hand`` go here instead of ``EVENTS_TOPIC``."""
HAND_EVENT = "hand"
HAND_SCHEMA = "dragd.Hand"
CYCLE_SCHEMA = "dragd.Cycle"
EVENT_SCHEMA = "dragd.Event"
RUN_METADATA = "dragd.run"
"""Metadata record written at the start of a file (label, config, ...)."""
WRITER_METADATA = "dragd.telemetry.writer"
"""Metadata record written when a file is finished: the writer's row/event counters."""

Labels = Mapping[int, str] | Sequence[str] | type[enum.Enum]


@dataclass(frozen=True)
class Field:
    """A layout entry: ``width`` values of ``kind``; ``labels`` make it an enum (label strings)."""

    width: int = 1
    kind: Literal["float", "int", "bool"] = "float"
    labels: Labels | None = None
    description: str | None = None
    digits: int | None = None
    """Significant digits written for floats (default: the writer's ``float_digits``)."""


MODE_LABELS: dict[int, str] = {int(m): name for m, name in MODE_NAMES.items()}
"""The ``mode`` field's labels: 0 idle, 1 hold, 2 drag, 3 track, 4 fault."""

# name -> (per joint, kind, description); the order is the row's order
_CYCLE_FIELDS: tuple[tuple[str, bool, str, str], ...] = (
    ("t_s", False, "float", "controller time since the daemon started [s]"),
    ("mode", False, "enum", "the daemon's mode"),
    ("q_rad", True, "float", "joint positions from the encoders [rad]"),
    ("dq_rad_s", True, "float", "estimated joint velocities [rad/s]"),
    ("current_measured_A", True, "float", "motor currents measured by the drives [A]"),
    ("current_command_A", True, "float", "commanded motor currents (torque offset in track/hold) [A]"),
    ("gravity_A", True, "float", "gravity current of the model at the measured pose [A]"),
    ("friction_A", True, "float", "friction compensation (drag, else 0) [A]"),
    ("startup_A", True, "float", "start-up (breakaway) assist (drag, else 0) [A]"),
    ("damping_A", True, "float", "damping term (drag, else 0) [A]"),
    ("statusword", True, "int", "CiA 402 statusword (6041h) of each drive"),
    ("rx", True, "bool", "the joint's feedback arrived this cycle"),
    ("period_us", False, "float", "time since the previous cycle [us]"),
    ("compute_us", False, "float", "time from feedback received to command computed [us]"),
    ("q_ref_rad", True, "float", "position reference: the path (track), the hold pose (hold), else commanded [rad]"),
    ("track_t_s", False, "float", "trajectory time (track, else -1) [s]"),
    ("residual_A", True, "float", "filtered measured minus predicted current (track, else 0) [A]"),
    ("back_emf_A", True, "float", "back-EMF compensation (drag, else 0) [A]"),
    ("effects_A", True, "float", "identified extra effects (drag, else 0) [A]"),
)


def cycle_layout(n_joints: int) -> dict[str, int | Field]:
    """The ``/dragd/cycle`` row of an arm with ``n_joints`` joints: field name -> width or `Field`, in order."""
    if n_joints < 1:
        raise ValueError(f"cycle_layout: n_joints must be >= 1; got {n_joints}")
    out: dict[str, int | Field] = {}
    for name, per_joint, kind, description in _CYCLE_FIELDS:
        width = n_joints if per_joint else 1
        if kind == "enum":
            out[name] = Field(width, kind="int", labels=MODE_LABELS, description=description)
        else:
            out[name] = Field(width, kind=kind, description=description)  # type: ignore[arg-type]
    return out


def hand_json_schema() -> dict[str, Any]:
    """JSON Schema of a ``/dragd/hand`` message (dragd/daemon/hand.py ``Guiding.status``)."""
    lease = {"type": "object", "properties": {
        "state": {"type": "string", "enum": ["none", "active", "lapsed", "closed"]},
        "id": {"type": ["integer", "null"]},
        "holder": {"type": "string"}, "period_s": {"type": "number"}, "remaining_s": {"type": "number"},
        "since_renewal_s": {"type": "number"}, "renewals": {"type": "integer"}, "lapses": {"type": "integer"}}}
    an_input = {"type": "object", "properties": {
        "function": {"type": "string", "enum": ["enable", "mark", "stop", "teach"]}, "name": {"type": "string"},
        "joint": {"type": "string"}, "object": {"type": "string"},
        "bits": {"type": "array", "items": {"type": "integer"}},
        "position": {"type": "string", "enum": ["released", "enabled", "squeezed"]}, "held": {"type": "boolean"},
        "pressed": {"type": "boolean"}, "lost": {"type": "boolean"}, "fault": {"type": ["string", "null"]},
        "raw": {"type": ["integer", "null"]}, "edges": {"type": "integer"}}}
    return {
        "title": HAND_SCHEMA,
        "type": "object",
        "description": "hand guiding: what drag requires, the drag lease, the guiding device's inputs (each change)",
        "properties": {"name": {"type": "string"}, "require": {"type": "string"},
                       "lab_unguarded": {"type": "boolean"},
                       "refusal": {"type": ["string", "null"]}, "mode": {"type": "string"}, "lease": lease,
                       "bound_lease": {"type": ["integer", "null"]}, "drag_ends": {"type": "integer"},
                       "stop_active": {"type": "boolean"}, "inputs": {"type": "array", "items": an_input}},
        "required": ["name"],
        "additionalProperties": True,
    }


def event_json_schema() -> dict[str, Any]:
    """JSON Schema of an ``/dragd/events`` message."""
    return {
        "title": EVENT_SCHEMA,
        "type": "object",
        "description": "rare daemon event; further fields depend on the event name",
        "properties": {"name": {"type": "string"}},
        "required": ["name"],
        "additionalProperties": True,
    }
