"""The daemon's modes: what the arm does and which law computes its command."""

from __future__ import annotations

from enum import IntEnum


class Mode(IntEnum):
    IDLE = 0  # drives disabled, brakes on
    HOLD = 1  # gravity + joint PD around the pose
    DRAG = 2  # gravity + friction + start-up: zero force
    TRACK = 3  # CSP: follow a joint trajectory (identification runs, replay)
    FAULT = 4  # a safety reaction disabled the drives; `start` clears it


MODE_NAMES: dict[Mode, str] = {m: m.name.lower() for m in Mode}
ENABLED_MODES = frozenset({Mode.HOLD, Mode.DRAG, Mode.TRACK})  # the drives are (to be) in operation enabled
