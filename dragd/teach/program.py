"""Taught programs: a versioned, human-readable YAML file (+ the raw MCAP recording next to it).

    format: dragd.teach.program        # identifies the file
    version: 1                         # schema version; newer files are refused with a clear message
    name: demo
    created: '2025-01-01T12:00:00Z'
    robot: seed_cobot                  # the configuration's robot (URDF name or path)
    frame: tool0                       # the frame circular moves are planned for
    joints: [joint1, ..., joint6]
    config: /etc/dragd/dragd.yaml      # configuration the daemon ran with
    recording: {mcap: demo.mcap, rate_Hz: 50.0, duration_s: 12.3, samples: 616, dropped: 0}
    waypoints:                         # marked during the drag (absolute encoders), in order
      - {name: p1, t_s: 2.134, q_rad: [0.1, -0.6, 1.2, -0.6, 1.5708, 0.0]}
    keyframes: null                    # `dragd teach keyframes`: the path reduced to keyframes
    path:                              # the continuous recording, one row per sample: [t_s, q1 .. qN]
      - [0.0, 0.1, -0.6, 1.2, -0.6, 1.5708, 0.0]

Times are seconds from ``teach start``; positions are joint-side radians.
"""

from __future__ import annotations

import math
import re
from datetime import UTC, datetime
from pathlib import Path
from typing import Annotated, Any, Final, Literal

import numpy as np
import yaml
from pydantic import Field, ValidationError, model_validator

from dragd.vocabulary import (
    ConfigError,
    Expect,
    Finite,
    NonNegFloat,
    StrictEditable,
    format_validation_error,
    read_yaml,
)

FORMAT: Final = "dragd.teach.program"
VERSION: Final = 1
NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")

class ProgramError(ConfigError):
    """A program file that cannot be used; the message names the file, the key and what was expected."""


class Waypoint(StrictEditable):
    name: str
    t_s: NonNegFloat
    q_rad: list[Finite]


# a keyframe's kind, owned by the program format (dragd/teach/keyframes.py, which finds them, imports it from here: the
# daemon reads programs and must not import the planner's scipy beside the cycle)
KeyframeKind = Literal["start", "end", "pause", "mark", "shape"]  # (the order of importance: keyframes._RANK)


class Keyframe(StrictEditable):
    t_s: NonNegFloat
    q_rad: list[Finite]
    kind: KeyframeKind = "shape"


class Recording(StrictEditable):
    mcap: str | None = None  # relative to the program file
    rate_Hz: Annotated[float, Field(gt=0), Expect("a positive rate")] = 50.0
    duration_s: NonNegFloat = 0.0
    samples: Annotated[int, Field(ge=0)] = 0
    dropped: Annotated[int, Field(ge=0)] = 0  # samples beyond the recorder's capacity


class Program(StrictEditable):
    format: Literal["dragd.teach.program"] = FORMAT
    version: Literal[1] = VERSION
    name: str
    created: str = ""
    robot: str = "seed_cobot"
    frame: str = "tool0"
    joints: list[str]
    config: str | None = None
    recording: Recording = Recording()
    waypoints: list[Waypoint] = Field(default_factory=list)
    keyframes: list[Keyframe] | None = None
    path: list[list[Finite]] = Field(default_factory=list)
    notes: dict[str, Any] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _shapes(self) -> Program:
        n = len(self.joints)
        if n == 0:
            raise ValueError("joints: expected the robot's joint names, got an empty list")
        for i, w in enumerate(self.waypoints):
            if len(w.q_rad) != n:
                raise ValueError(f"waypoints[{i}].q_rad: expected {n} values ({', '.join(self.joints)}), "
                                 f"got {len(w.q_rad)}")
        for i, k in enumerate(self.keyframes or []):
            if len(k.q_rad) != n:
                raise ValueError(f"keyframes[{i}].q_rad: expected {n} values, got {len(k.q_rad)}")
        last = -math.inf
        for i, row in enumerate(self.path):
            if len(row) != n + 1:
                raise ValueError(f"path[{i}]: expected {n + 1} values [t_s, {', '.join(self.joints)}], got {len(row)}")
            if row[0] <= last:
                raise ValueError(f"path[{i}]: expected times increasing, got {row[0]} after {last}")
            last = row[0]
        names = [w.name for w in self.waypoints]
        dup = sorted({x for x in names if names.count(x) > 1})
        if dup:
            raise ValueError(f"waypoints: expected unique names, got {', '.join(dup)} more than once")
        return self

    # ---------------------------------------------------------------------------------------- views

    @property
    def n(self) -> int:
        return len(self.joints)

    def waypoint_array(self) -> np.ndarray:
        return np.array([w.q_rad for w in self.waypoints], dtype=float).reshape(-1, self.n)

    def path_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """(t_s, q_rad) of the continuous recording."""
        a = np.array(self.path, dtype=float).reshape(-1, self.n + 1)
        return a[:, 0].copy(), a[:, 1:].copy()

    def summary(self) -> dict[str, Any]:
        return {"name": self.name, "version": self.version, "created": self.created, "waypoints": len(self.waypoints),
                "waypoint_names": [w.name for w in self.waypoints], "samples": len(self.path),
                "duration_s": self.recording.duration_s,
                "keyframes": None if self.keyframes is None else len(self.keyframes),
                "mcap": self.recording.mcap}


def check_name(name: str) -> str:
    if not NAME_RE.match(name):
        raise ProgramError(f"program name '{name}': expected 1-64 characters of letters, digits, '_', '-', '.', "
                           "starting with a letter or digit")
    return name


def now_iso() -> str:
    return datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


# -------------------------------------------------------------------------------------------- file I/O


class _Dumper(yaml.SafeDumper):
    pass


class _Flow(list):
    """A list written on one line (joint vectors, path rows)."""


_Dumper.add_representer(_Flow, lambda d, v: d.represent_sequence("tag:yaml.org,2002:seq", v, flow_style=True))


def _round(v: float, digits: int) -> float:
    r = round(float(v), digits)
    return 0.0 if r == 0 else r


def to_yaml(program: Program) -> str:
    data = program.model_dump(mode="json")
    data["joints"] = _Flow(data["joints"])
    for w in data["waypoints"]:
        w["t_s"] = _round(w["t_s"], 4)
        w["q_rad"] = _Flow(_round(x, 7) for x in w["q_rad"])
    if data["keyframes"] is not None:
        for k in data["keyframes"]:
            k["t_s"] = _round(k["t_s"], 4)
            k["q_rad"] = _Flow(_round(x, 7) for x in k["q_rad"])
    data["path"] = [_Flow([_round(r[0], 4)] + [_round(x, 7) for x in r[1:]]) for r in data["path"]]
    head = (f"# dragd taught program '{program.name}' (format {FORMAT} v{VERSION}); "
            "joint positions in rad, times in s\n"
            "# from 'teach start'. Replay: dragd replay PROGRAM [--interp linear|circular|spline]\n")
    return head + yaml.dump(data, Dumper=_Dumper, sort_keys=False, width=200)


def save_program(program: Program, path: str | Path) -> Path:
    from dragd.atomic import write_atomic

    return write_atomic(path, to_yaml(program))  # temp + fsync + rename: a reader never sees half a program


def load_program(path: str | Path) -> Program:
    path = Path(path)
    if not path.is_file():
        raise ProgramError(f"{path}: program file not found")
    try:
        data = read_yaml(path)
    except ConfigError as exc:
        raise ProgramError(str(exc)) from None
    return program_from_data(data, str(path))


def program_from_data(data: Any, source: str = "<memory>") -> Program:
    if not isinstance(data, dict):
        raise ProgramError(f"{source}: expected a mapping (a dragd taught program), got {type(data).__name__}")
    fmt = data.get("format")
    if fmt != FORMAT:
        raise ProgramError(f"{source}: format: expected '{FORMAT}', got {fmt!r}")
    version = data.get("version")
    if isinstance(version, int) and version > VERSION:
        raise ProgramError(f"{source}: version: the program is version {version}; this dragd reads up to "
                           f"version {VERSION} (update dragd)")
    try:
        return Program.model_validate(data)
    except ValidationError as exc:
        raise ProgramError(format_validation_error(source, Program, exc)) from None


def resolve_program(name_or_path: str, program_dir: str | Path) -> Path:
    """A bare name → ``program_dir/NAME.yaml``; anything with a '/' or a .yaml/.yml suffix is a path."""
    text = str(name_or_path)
    if "/" in text or text.endswith((".yaml", ".yml")):
        return Path(text).expanduser()
    check_name(text)
    return Path(program_dir) / f"{text}.yaml"


def interrupted_sessions(program_dir: str | Path) -> list[Path]:
    """Teach recordings in ``program_dir`` without their program file (sessions that never reached ``stop``)."""
    d = Path(program_dir)
    if not d.is_dir():
        return []
    return sorted(p for p in d.glob("*.mcap") if not p.with_suffix(".yaml").exists()
                  and not p.with_suffix(".yml").exists())


def list_programs(program_dir: str | Path) -> list[dict[str, Any]]:
    """Every readable program in ``program_dir`` (unreadable files are listed with their error)."""
    out: list[dict[str, Any]] = []
    d = Path(program_dir)
    if not d.is_dir():
        return out
    for p in sorted(d.glob("*.yaml")):
        try:
            prog = load_program(p)
        except ProgramError as exc:
            out.append({"path": str(p), "error": str(exc)})
            continue
        out.append({"path": str(p), **prog.summary()})
    for m in interrupted_sessions(d):  # teach sessions that never reached 'stop': their recording is the autosave
        out.append({"path": str(m), "interrupted": True,
                    "error": f"interrupted teach session: 'dragd teach recover {m}' writes its program"})
    return out
