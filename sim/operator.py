"""A scripted virtual operator: external joint torques or a flange wrench on the simulated arm, over time.

A scenario is a list of segments run one after the other (sim time):

* ``push``: a constant load (one joint's torque, a torque vector and/or a flange force/moment) for ``duration_s``;
* ``ramp``: a joint torque (N·m/s) or a flange force along a direction (N/s) rising from ``start`` until the arm
  moves beyond ``threshold_rad`` from where the ramp began (the weight-and-pulley start-up test), then ``hold``
  the load or ``release`` it; records a ``breakaway`` event with the load and time (or ``ramp_limit`` /
  ``ramp_timeout``);
* ``hold``: keep the present load for ``duration_s``;
* ``release``: take the load away (optionally over ``ramp_down_s``), then no load for ``duration_s``;
* ``move``: a hand moving one joint at ``velocity_rad_s`` (PI loop on its torque); a ``move`` event records the
  mean torque it took over the segment's second half (drag effort);
* ``hand``: a spring–damper "hand" pulling the joints (``q_rad``) or the flange (``position_m``, optional
  ``rpy_rad``) to a target, absolute or relative to the pose at the segment's start;
* ``strike``: a hand or an object striking a chosen link: a force of a given profile (``half_sine`` over
  ``duration_s``, or ``trapezoid``: ``rise_s``, ``hold_s``, ``fall_s``) up to ``peak_N`` along ``direction`` (world)
  at ``point_m`` in the link's frame; records ``strike`` (start) and ``strike_end`` events with the peak force;
* ``obstacle``: a rigid object the arm may run into: a plane (``point_m``, outward ``normal``, world) that a point of
  a link (``link``, ``link_point_m``) cannot pass without a spring–damper force (``stiffness_N_m``, ``damping_N_s_m``,
  pushing only) for ``duration_s``; records ``obstacle_contact`` (first touch) and ``obstacle_end`` (peak force,
  deepest penetration).
* ``press`` / ``let_go``: a button of the guiding device at the wrist (sim/hand.py: ``enable`` to the ``middle`` or
  ``squeeze`` position, ``mark``, ``stop``, ``teach``), pressed or let go at the segment's start (``hold_s``: let go
  by itself that long later, while the next segments run); the load stays as the previous segment left it (a
  ``hand`` segment's spring ends with it), ``duration_s`` (default 0) before the next segment. Events ``press`` and
  ``let_go`` record the instants.

After the last segment the operator lets go (no load).
The operator's Cartesian force (a flange hand, push or ramp; a strike; an obstacle) is its truth: :meth:`Operator.trace`
returns it every millisecond (time, the force [N] in world axes, where it acts), NaN while the load is joint torques.
Flange wrenches act at the scenario's ``frame`` (default ``tool0``, else the last joint) with world-aligned axes
and become joint torques through the frame Jacobian: τ = Jᵀ·[f; m].
From YAML (``sim/scenarios/*.yaml``, schema-validated) or Python (:func:`load_scenario`, :func:`validate_scenario`).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal

import numpy as np
import pinocchio as pin
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from dragd.vocabulary import ConfigError, Expect, format_validation_error, read_yaml

if TYPE_CHECKING:
    from dragd.model import RobotModel

SCENARIO_DIR = Path(__file__).resolve().parent / "scenarios"
TRACE_DT_S = 1e-3  # the force trace's sampling
TRACE_ROWS = 1 << 18  # ... kept (the last ~4 min)

PosFloat = Annotated[float, Field(gt=0, allow_inf_nan=False), Expect("a positive number")]
NonNegFloat = Annotated[float, Field(ge=0, allow_inf_nan=False), Expect("a number >= 0")]
Finite = Annotated[float, Field(allow_inf_nan=False), Expect("a finite number")]
Vec3 = tuple[Finite, Finite, Finite]


class ScenarioError(ConfigError):
    """A scenario that cannot be used; the message names file, key path and expectation."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_default=True, frozen=True)


class Push(_Strict):
    kind: Literal["push"]
    joint: str | None = None  # with torque_Nm
    torque_Nm: Finite | None = None
    torques_Nm: list[Finite] | None = None  # one per joint
    force_N: Vec3 | None = None  # at the flange frame, world axes
    moment_Nm: Vec3 | None = None
    duration_s: NonNegFloat

    @model_validator(mode="after")
    def _load(self) -> Push:
        if (self.joint is None) != (self.torque_Nm is None):
            raise ValueError("expected joint and torque_Nm together")
        if self.joint is None and self.torques_Nm is None and self.force_N is None and self.moment_Nm is None:
            raise ValueError("expected a load: joint + torque_Nm, torques_Nm, force_N and/or moment_Nm")
        return self


class Ramp(_Strict):
    kind: Literal["ramp"]
    joint: str | None = None  # a joint torque ramp [N·m] ...
    force_direction: Vec3 | None = None  # ... or a flange force ramp along this direction [N]
    start: Finite = 0.0  # N·m or N
    rate_per_s: PosFloat  # N·m/s or N/s (magnitude; the sign of the load follows ``sign``)
    sign: Literal[1, -1] = 1
    limit: PosFloat | None = None  # stop rising at this magnitude: end (``ramp_limit``), or hold it until timeout_s
    threshold_rad: PosFloat = 0.002  # displacement (max over the watched joints) that counts as moving
    timeout_s: PosFloat | None = None
    then: Literal["hold", "release"] = "release"

    @model_validator(mode="after")
    def _target(self) -> Ramp:
        if (self.joint is None) == (self.force_direction is None):
            raise ValueError("expected exactly one of joint (torque ramp) or force_direction (flange force ramp)")
        if self.force_direction is not None and np.linalg.norm(self.force_direction) == 0:
            raise ValueError("expected a non-zero force_direction")
        return self


class Hold(_Strict):
    kind: Literal["hold"]
    duration_s: NonNegFloat


class Release(_Strict):
    kind: Literal["release"]
    ramp_down_s: NonNegFloat = 0.0
    duration_s: NonNegFloat = 0.0


class Hand(_Strict):
    kind: Literal["hand"]
    q_rad: list[Finite] | None = None  # joint-space target ...
    position_m: Vec3 | None = None  # ... or flange position target (world)
    rpy_rad: Vec3 | None = None  # optional flange orientation target (world roll-pitch-yaw)
    relative: bool = False  # targets are offsets from the pose at the segment's start
    stiffness: PosFloat = 300.0  # N·m/rad (joint) or N/m (flange)
    damping: NonNegFloat = 30.0  # N·m·s/rad or N·s/m
    rot_stiffness_Nm_per_rad: PosFloat = 10.0
    rot_damping_Nm_s_per_rad: NonNegFloat = 0.5
    max_load: PosFloat = 100.0  # saturation: N·m per joint, or N of flange force
    duration_s: NonNegFloat

    @model_validator(mode="after")
    def _target(self) -> Hand:
        if (self.q_rad is None) == (self.position_m is None):
            raise ValueError("expected exactly one of q_rad (joint target) or position_m (flange target)")
        if self.rpy_rad is not None and self.position_m is None:
            raise ValueError("expected rpy_rad only with position_m")
        return self


class Move(_Strict):
    """A hand that moves one joint at a set speed: a PI velocity loop on the joint's torque (the measuring
    hand of drag-effort tests). Records a ``move`` event with the mean torque and speed over the second half."""

    kind: Literal["move"]
    joint: str
    velocity_rad_s: Finite
    kp_Nm_s_per_rad: PosFloat = 200.0
    ki_Nm_per_rad: NonNegFloat = 2000.0
    max_load: PosFloat = 60.0  # N·m saturation
    duration_s: PosFloat


class Strike(_Strict):
    """A hand or an object striking ``link``: a force profile on a point of it (docs/CONTACT.md, the contact demo)."""

    kind: Literal["strike"]
    link: str  # a frame of the robot (its URDF link name)
    point_m: Vec3 = (0.0, 0.0, 0.0)  # where it strikes, in the link's frame
    direction: Vec3  # of the force on the arm (world axes; normalised)
    peak_N: PosFloat
    profile: Literal["half_sine", "trapezoid"] = "half_sine"
    duration_s: PosFloat = 0.1  # half_sine: the whole pulse
    rise_s: PosFloat = 0.01  # trapezoid
    hold_s: NonNegFloat = 0.05
    fall_s: PosFloat = 0.01

    @model_validator(mode="after")
    def _direction(self) -> Strike:
        if np.linalg.norm(self.direction) == 0:
            raise ValueError("expected a non-zero direction")
        return self

    @property
    def length_s(self) -> float:
        return self.duration_s if self.profile == "half_sine" else self.rise_s + self.hold_s + self.fall_s

    def force(self, elapsed: float) -> float:
        """The force's magnitude [N] ``elapsed`` seconds into the strike."""
        if self.profile == "half_sine":
            return self.peak_N * math.sin(math.pi * elapsed / self.duration_s) if elapsed < self.duration_s else 0.0
        if elapsed < self.rise_s:
            return self.peak_N * elapsed / self.rise_s
        if elapsed < self.rise_s + self.hold_s:
            return self.peak_N
        x = elapsed - self.rise_s - self.hold_s
        return self.peak_N * (1.0 - x / self.fall_s) if x < self.fall_s else 0.0


class Obstacle(_Strict):
    """A plane the arm may run into: a point of ``link`` penetrating it meets a spring–damper force (pushing only)."""

    kind: Literal["obstacle"]
    link: str
    link_point_m: Vec3 = (0.0, 0.0, 0.0)  # the point of the link that touches, in the link's frame
    point_m: Vec3  # a point of the plane (world)
    normal: Vec3  # the plane's outward normal (world): the side the arm is on
    stiffness_N_m: PosFloat = 20000.0
    damping_N_s_m: NonNegFloat = 100.0
    duration_s: PosFloat

    @model_validator(mode="after")
    def _normal(self) -> Obstacle:
        if np.linalg.norm(self.normal) == 0:
            raise ValueError("expected a non-zero normal")
        return self


# --- the guiding device's buttons (#30; sim/hand.py) ---


class Press(_Strict):
    """Press a button of the guiding device at the wrist (the enabling switch to the middle or squeezed)."""

    kind: Literal["press"]
    button: Literal["enable", "mark", "stop", "teach"]
    position: Literal["middle", "squeeze"] = "middle"  # enable only
    hold_s: PosFloat | None = None  # let go by itself this long later (a momentary press: mark, teach)
    duration_s: NonNegFloat = 0.0

    @model_validator(mode="after")
    def _enable_only(self) -> Press:
        if self.position != "middle" and self.button != "enable":
            raise ValueError(f"expected position only with button enable, got it with {self.button!r}")
        return self


class LetGo(_Strict):
    """Let go of a button (the enabling switch back to released)."""

    kind: Literal["let_go"]
    button: Literal["enable", "mark", "stop", "teach"]
    duration_s: NonNegFloat = 0.0

# --- end of the guiding device's buttons ---


Segment = Annotated[Push | Ramp | Hold | Release | Hand | Move | Strike | Obstacle | Press | LetGo,
                    Field(discriminator="kind")]
SEGMENT_KINDS: dict[str, type[_Strict]] = {"push": Push, "ramp": Ramp, "hold": Hold, "release": Release, "hand": Hand,
                                           "move": Move, "strike": Strike, "obstacle": Obstacle, "press": Press,
                                           "let_go": LetGo}


class Scenario(_Strict):
    name: str = "scenario"
    frame: str | None = None  # flange frame for wrenches; default tool0 or the last joint
    segments: list[Segment] = Field(min_length=1)
    source: str = Field("<memory>", exclude=True)


def validate_scenario(data: Any, source: str = "<memory>") -> Scenario:
    """Validate a scenario mapping; errors name ``source``, the key path and the expectation."""
    if isinstance(data, Scenario):
        return data
    if not isinstance(data, dict):
        raise ScenarioError(f"{source}: expected a mapping with 'segments', got {type(data).__name__}")
    if "source" in data:
        raise ScenarioError(f"{source}: source: unknown key")
    # segments one by one against their own kind, so errors name the segment's keys and expectations
    errors: list[str] = []
    segments = data.get("segments")
    if isinstance(segments, list):
        for i, seg in enumerate(segments):
            where = f"segments[{i}]"
            kind = seg.get("kind") if isinstance(seg, dict) else None
            cls = SEGMENT_KINDS.get(kind) if isinstance(kind, str) else None
            if not isinstance(seg, dict):
                errors.append(f"{source}: {where}: expected a mapping with 'kind', got {seg!r}")
            elif cls is None:
                errors.append(f"{source}: {where}.kind: expected one of {', '.join(SEGMENT_KINDS)}, got {kind!r}")
            else:
                try:
                    cls.model_validate(seg)
                except ValidationError as exc:
                    prefix = f"{source}: {where}.{kind}"
                    for line in format_validation_error(prefix, cls, exc).splitlines():
                        rest = line[len(prefix) + 2:]
                        errors.append(f"{prefix}: {rest}" if rest.startswith("expected") else f"{prefix}.{rest}")
    if errors:
        raise ScenarioError("\n".join(errors))
    try:
        return Scenario.model_validate({**data, "source": source})
    except ValidationError as exc:
        raise ScenarioError(format_validation_error(source, Scenario, exc)) from None


def load_scenario(path: str | Path) -> Scenario:
    """Load a scenario file; a bare name is looked up in ``sim/scenarios``."""
    p = Path(path)
    if not p.is_file() and not p.suffix and (SCENARIO_DIR / f"{p}.yaml").is_file():
        p = SCENARIO_DIR / f"{p}.yaml"
    try:
        data = read_yaml(p)
    except ConfigError as exc:
        raise ScenarioError(str(exc)) from None
    return validate_scenario(data, str(p))


class Operator:
    """Runs a scenario: :meth:`apply` writes the operator's joint torques for the present sim time."""

    def __init__(self, scenario: Scenario | dict[str, Any] | str | Path, model: RobotModel | pin.Model,
                 start_t_s: float | None = None, hand: Any = None) -> None:
        """``hand``: the guiding device (sim/hand.py ``HandDevice``) that ``press`` / ``let_go`` segments use."""
        if isinstance(scenario, (str, Path)):
            scenario = load_scenario(scenario)
        self.scenario = validate_scenario(scenario)
        src = self.scenario.source
        self.model: pin.Model = getattr(model, "model", model)
        self.data = self.model.createData()
        self.n = self.model.nv
        names = list(self.model.names[1:])
        self._index = {name: i for i, name in enumerate(names)}
        if self.scenario.frame is not None:
            if not self.model.existFrame(self.scenario.frame):
                raise ScenarioError(f"{src}: frame: expected a frame of the robot, got {self.scenario.frame!r}")
            self.frame_id = self.model.getFrameId(self.scenario.frame)
        elif self.model.existFrame("tool0"):
            self.frame_id = self.model.getFrameId("tool0")
        else:
            self.frame_id = self.model.getFrameId(names[-1])
        for i, seg in enumerate(self.scenario.segments):
            where = f"{src}: segments[{i}].{seg.kind}"
            joint = getattr(seg, "joint", None)
            if joint is not None and joint not in self._index:
                raise ScenarioError(f"{where}.joint: expected one of {', '.join(names)}, got {joint!r}")
            link = getattr(seg, "link", None)
            if link is not None and not self.model.existFrame(link):
                raise ScenarioError(f"{where}.link: expected a link (frame) of the robot, got {link!r}")
            for key in ("torques_Nm", "q_rad"):
                vec = getattr(seg, key, None)
                if vec is not None and len(vec) != self.n:
                    raise ScenarioError(f"{where}.{key}: expected {self.n} values ({', '.join(names)}), got {len(vec)}")

        self.hand = hand
        self._let_go_at: list[tuple[float, str]] = []  # momentary presses: (when, button)
        pressed = sorted({seg.button for seg in self.scenario.segments if isinstance(seg, (Press, LetGo))})
        if pressed and hand is None:
            raise ScenarioError(f"{src}: segments press/let_go {', '.join(pressed)}: the simulated arm has no guiding "
                                "device (the truth's hand is null)")
        missing = [b for b in pressed if hand is not None and b not in hand.controls]
        if missing:
            raise ScenarioError(f"{src}: segments press/let_go: button(s) {', '.join(missing)}: expected one of "
                                f"{', '.join(hand.controls)} (the truth's hand)")
        self.events: list[dict[str, Any]] = []
        self.done = False
        self._start_t = start_t_s
        self._seg = -1
        self._seg_t0 = 0.0
        self._tau = np.zeros(self.n)  # constant part of the load (joint torques)
        self._wrench = np.zeros(6)  # constant part of the load (flange force, moment)
        self._has_wrench = False
        # per-segment state
        self._q0 = np.zeros(self.n)
        self._ramp_value = 0.0
        self._onset: tuple[float, float] | None = None
        self._release_from: tuple[np.ndarray, np.ndarray] | None = None
        self._target_q = np.zeros(self.n)
        self._target_M: pin.SE3 | None = None
        self._target_xyz: list[float] = [0.0, 0.0, 0.0]  # (its translation as floats: the per-step spring)
        self._direction = np.zeros(3)
        self._scratch = np.zeros(self.n)
        self._move_integral = 0.0
        self._move_sum: list[float] = [0.0, 0.0, 0]
        self._dt_hint = 2.5e-4  # the physics step; set by apply() from successive calls
        self._last_t: float | None = None
        # the truth of the Cartesian load: its force [N] (world) and where it acts, every TRACE_DT_S (NaN: none known)
        self.force_N = np.zeros(3)
        self.force_at_m = np.zeros(3)
        self._force_known = False
        self._trace = np.full((TRACE_ROWS, 7), np.nan)
        self._trace_n = 0
        self._trace_next = -math.inf
        self._peak = 0.0
        self._depth = 0.0
        self._touched = False
        self._link_id = 0

    # ------------------------------------------------------------------------------------------- API

    @property
    def segment_index(self) -> int:
        return self._seg

    def trace(self, since_t_s: float = -math.inf) -> dict[str, list[Any]]:
        """The Cartesian load's truth every ``TRACE_DT_S`` from ``since_t_s`` on: t [s], force [N] (world), where
        it acts [m] (world); NaN rows while the load is joint torques (a joint-space hand) or none is applied."""
        n = self._trace_n
        first = max(0, n - TRACE_ROWS)
        rows = np.array([self._trace[k % TRACE_ROWS] for k in range(first, n)]) if n else np.zeros((0, 7))
        if rows.size:
            rows = rows[rows[:, 0] >= since_t_s]
        return {"t_s": rows[:, 0].tolist(), "force_N": rows[:, 1:4].tolist(), "at_m": rows[:, 4:7].tolist()}

    def breakaways(self) -> list[dict[str, Any]]:
        return [e for e in self.events if e["kind"] == "breakaway"]

    def apply(self, t_s: float, q_rad: np.ndarray, dq_rad_s: np.ndarray, out_Nm: np.ndarray) -> None:
        """Write the operator's joint torques at sim time ``t_s`` (arm state q, dq) into ``out_Nm``."""
        if self._last_t is not None and t_s > self._last_t:
            self._dt_hint = t_s - self._last_t
        self._last_t = t_s
        if self._start_t is None:
            self._start_t = t_s
        if self._seg < 0:
            if t_s < self._start_t:
                out_Nm[:] = 0.0
                return
            self._event(t_s, "start", name=self.scenario.name)
            self._enter(0, t_s, q_rad)
        if self._let_go_at:
            self._let_go_due(t_s)
        while not self.done and self._segment_over(t_s, q_rad, dq_rad_s):
            self._enter(self._seg + 1, t_s, q_rad)
        self._force_known = False
        if self.done:
            out_Nm[:] = 0.0
            self._record(t_s)
            return
        self._load(t_s, q_rad, dq_rad_s, out_Nm)
        self._record(t_s)

    def _record(self, t_s: float) -> None:
        if t_s + 1e-9 < self._trace_next:
            return
        self._trace_next = t_s + TRACE_DT_S - 1e-9 if self._trace_next == -math.inf else self._trace_next + TRACE_DT_S
        if self._trace_next < t_s:  # (a gap: restart the grid)
            self._trace_next = t_s + TRACE_DT_S - 1e-9
        row = self._trace[self._trace_n % TRACE_ROWS]
        row[0] = t_s
        if self._force_known:
            row[1:4] = self.force_N
            row[4:7] = self.force_at_m
        else:
            row[1:7] = np.nan
        self._trace_n += 1

    # ------------------------------------------------------------------------------------------- segments

    def _event(self, t_s: float, kind: str, **info: Any) -> None:
        self.events.append({"t": round(t_s, 6), "kind": kind, "segment": self._seg, **info})

    def _enter(self, index: int, t_s: float, q: np.ndarray) -> None:
        segs = self.scenario.segments
        if index >= len(segs):
            self._seg = len(segs)
            self.done = True
            self._event(t_s, "done")
            return
        self._seg, self._seg_t0 = index, t_s
        seg = segs[index]
        self._event(t_s, "segment", segment_kind=seg.kind)
        np.copyto(self._q0, q)
        if isinstance(seg, Push):
            self._tau[:] = 0.0
            if seg.torques_Nm is not None:
                self._tau[:] = seg.torques_Nm
            if seg.joint is not None:
                self._tau[self._index[seg.joint]] += seg.torque_Nm
            self._wrench[:3] = seg.force_N if seg.force_N is not None else (0.0, 0.0, 0.0)
            self._wrench[3:] = seg.moment_Nm if seg.moment_Nm is not None else (0.0, 0.0, 0.0)
            self._has_wrench = seg.force_N is not None or seg.moment_Nm is not None
        elif isinstance(seg, Ramp):
            self._tau[:] = 0.0
            self._wrench[:] = 0.0
            self._has_wrench = seg.force_direction is not None
            self._ramp_value = seg.start
            self._onset = None
            if seg.force_direction is not None:
                d = np.asarray(seg.force_direction, dtype=float)
                self._direction[:] = d / np.linalg.norm(d)
        elif isinstance(seg, Release):
            self._release_from = (self._tau.copy(), self._wrench.copy())
        elif isinstance(seg, Move):
            self._tau[:] = 0.0
            self._wrench[:] = 0.0
            self._has_wrench = False
            self._move_integral = 0.0
            self._move_sum = [0.0, 0.0, 0]
        elif isinstance(seg, (Strike, Obstacle)):
            self._tau[:] = 0.0
            self._wrench[:] = 0.0
            self._has_wrench = False
            self._peak = 0.0
            self._depth = 0.0
            self._touched = False
            self._link_id = self.model.getFrameId(seg.link)
            if isinstance(seg, Strike):
                d = np.asarray(seg.direction, dtype=float)
                self._direction[:] = d / np.linalg.norm(d)
                self._event(t_s, "strike", link=seg.link, peak_N=seg.peak_N, profile=seg.profile,
                            length_s=seg.length_s, direction=self._direction.tolist())
            else:
                nrm = np.asarray(seg.normal, dtype=float)
                self._direction[:] = nrm / np.linalg.norm(nrm)
        elif isinstance(seg, (Press, LetGo)):
            self._button(seg, t_s)
        elif isinstance(seg, Hand):
            self._tau[:] = 0.0
            self._wrench[:] = 0.0
            self._has_wrench = False
            if seg.q_rad is not None:
                self._target_q[:] = np.asarray(seg.q_rad) + (q if seg.relative else 0.0)
            else:
                pin.framesForwardKinematics(self.model, self.data, q)
                now = self.data.oMf[self.frame_id]
                pos = np.asarray(seg.position_m, dtype=float)
                if seg.rpy_rad is None:
                    rot = now.rotation.copy()
                else:
                    rot = pin.rpy.rpyToMatrix(*seg.rpy_rad)
                    if seg.relative:
                        rot = rot @ now.rotation
                self._target_M = pin.SE3(rot, pos + (now.translation if seg.relative else 0.0))
                self._target_xyz = self._target_M.translation.tolist()

    def _button(self, seg: Press | LetGo, t_s: float) -> None:
        """A press or let-go of the guiding device; the load stays as it was (a hand segment's spring ends)."""
        if isinstance(seg, Press):
            self.hand.press(t_s, seg.button, seg.position)
            self._event(t_s, "press", button=seg.button, position=seg.position)
            if seg.hold_s is not None:
                self._let_go_at.append((t_s + seg.hold_s, seg.button))
        else:
            self.hand.let_go(t_s, seg.button)
            self._event(t_s, "let_go", button=seg.button)
        prev = self.scenario.segments[self._seg - 1] if self._seg > 0 else None
        if isinstance(prev, Hand):
            self._tau[:] = 0.0

    def _let_go_due(self, t_s: float) -> None:
        due = [b for when, b in self._let_go_at if when <= t_s]
        if due:
            self._let_go_at = [(when, b) for when, b in self._let_go_at if when > t_s]
            for b in due:
                self.hand.let_go(t_s, b)
                self._event(t_s, "let_go", button=b)

    def _segment_over(self, t_s: float, q: np.ndarray, dq: np.ndarray) -> bool:
        seg = self.scenario.segments[self._seg]
        elapsed = t_s - self._seg_t0
        if isinstance(seg, Ramp):
            return self._ramp_over(seg, t_s, elapsed, q, dq)
        if isinstance(seg, Release):
            if elapsed >= seg.ramp_down_s + seg.duration_s:
                self._tau[:] = 0.0
                self._wrench[:] = 0.0
                self._has_wrench = False
                return True
            return False
        if isinstance(seg, Strike):
            if elapsed >= seg.length_s:
                self._event(t_s, "strike_end", link=seg.link, peak_N=round(self._peak, 3))
                return True
            return False
        if isinstance(seg, Obstacle):
            if elapsed >= seg.duration_s:
                self._event(t_s, "obstacle_end", link=seg.link, peak_N=round(self._peak, 3),
                            depth_m=round(self._depth, 6), touched=self._touched)
                return True
            return False
        if isinstance(seg, Move) and elapsed >= seg.duration_s:
            tau_sum, v_sum, count = self._move_sum
            self._event(t_s, "move", joint=seg.joint, velocity_rad_s=seg.velocity_rad_s,
                        torque_Nm_mean=tau_sum / max(1, count), velocity_mean_rad_s=v_sum / max(1, count),
                        samples=count)
            self._tau[:] = 0.0
            return True
        return elapsed >= seg.duration_s

    def _ramp_over(self, seg: Ramp, t_s: float, elapsed: float, q: np.ndarray, dq: np.ndarray) -> bool:
        watch = [self._index[seg.joint]] if seg.joint is not None else slice(None)
        value = seg.start + seg.rate_per_s * elapsed
        capped = seg.limit is not None and value >= seg.limit
        if capped:
            value = seg.limit  # type: ignore[assignment]
        if self._onset is None and np.any(dq[watch] != 0.0):
            self._onset = (t_s, seg.sign * self._ramp_value)
        moved = float(np.max(np.abs(q[watch] - self._q0[watch])))
        end = None
        if moved > seg.threshold_rad:
            end = "breakaway"
        elif seg.timeout_s is not None and elapsed >= seg.timeout_s:
            end = "ramp_timeout"
        elif capped and seg.timeout_s is None:
            end = "ramp_limit"
        if end is None:
            self._ramp_value = value
            return False
        load = seg.sign * self._ramp_value  # the load applied up to now (this step's rise not yet applied)
        info: dict[str, Any] = {"displacement_rad": moved, "elapsed_s": round(elapsed, 6)}
        if seg.joint is not None:
            info.update(joint=seg.joint, torque_Nm=load)
        else:
            info.update(force_N=load, direction=self._direction.tolist())
        if self._onset is not None:
            info.update(onset_t=round(self._onset[0], 6), onset_load=self._onset[1])
        self._event(t_s, end, **info)
        if seg.then == "hold":
            self._set_ramp_load(seg, load)
        else:
            self._tau[:] = 0.0
            self._wrench[:] = 0.0
            self._has_wrench = False
        return True

    def _set_ramp_load(self, seg: Ramp, load: float) -> None:
        self._tau[:] = 0.0
        self._wrench[:] = 0.0
        if seg.joint is not None:
            self._tau[self._index[seg.joint]] = load
            self._has_wrench = False
        else:
            self._wrench[:3] = load * self._direction
            self._has_wrench = True

    def _load(self, t_s: float, q: np.ndarray, dq: np.ndarray, out: np.ndarray) -> None:
        seg = self.scenario.segments[self._seg]
        if isinstance(seg, Ramp):
            self._set_ramp_load(seg, seg.sign * self._ramp_value)
        elif isinstance(seg, Release) and self._release_from is not None:
            frac = 0.0 if seg.ramp_down_s == 0 else max(0.0, 1.0 - (t_s - self._seg_t0) / seg.ramp_down_s)
            self._tau[:] = self._release_from[0] * frac
            self._wrench[:] = self._release_from[1] * frac
            self._has_wrench = frac > 0 and bool(self._wrench.any())
        elif isinstance(seg, Hand):
            self._hand(seg, q, dq, out)
            return
        elif isinstance(seg, Strike):
            self._strike(seg, t_s - self._seg_t0, q, out)
            return
        elif isinstance(seg, Obstacle):
            self._obstacle(seg, t_s, q, dq, out)
            return
        elif isinstance(seg, Move):
            j = self._index[seg.joint]
            err = seg.velocity_rad_s - dq[j]
            self._move_integral += err * self._dt_hint
            tau = seg.kp_Nm_s_per_rad * err + seg.ki_Nm_per_rad * self._move_integral
            tau = max(-seg.max_load, min(seg.max_load, tau))
            if abs(tau) >= seg.max_load:  # anti-windup
                self._move_integral -= err * self._dt_hint
            self._tau[:] = 0.0
            self._tau[j] = tau
            if t_s - self._seg_t0 >= seg.duration_s / 2:
                self._move_sum[0] += tau
                self._move_sum[1] += dq[j]
                self._move_sum[2] += 1
        out[:] = self._tau
        if self._has_wrench:
            out += self._wrench_torque(q, self._wrench)
            self._flange_force(self._wrench[:3])

    def _flange_force(self, f: np.ndarray) -> None:
        """The truth: a force ``f`` (world) at the scenario's frame (its placement from the last Jacobian)."""
        self.force_N[:] = f
        self.force_at_m[:] = self.data.oMf[self.frame_id].translation
        self._force_known = True

    def _point_jacobian(self, q: np.ndarray, frame_id: int, point: tuple[float, float, float]) -> tuple[np.ndarray,
                                                                                                         np.ndarray]:
        """(linear Jacobian 3×n, world position) of a point given in a frame (world axes)."""
        J = pin.computeFrameJacobian(self.model, self.data, q, frame_id, pin.LOCAL_WORLD_ALIGNED)
        M = self.data.oMf[frame_id]
        r = M.rotation @ np.asarray(point, dtype=float)
        # v_p = v_o + ω × r  ⇒  J_p = J_v − [r]× J_ω
        Jp = J[:3] - np.cross(r, J[3:].T).T
        return Jp, M.translation + r

    def _strike(self, seg: Strike, elapsed: float, q: np.ndarray, out: np.ndarray) -> None:
        f = seg.force(elapsed)
        self._peak = max(self._peak, f)
        Jp, at = self._point_jacobian(q, self._link_id, seg.point_m)
        force = f * self._direction
        out[:] = Jp.T @ force
        self.force_N[:] = force
        self.force_at_m[:] = at
        self._force_known = True

    def _obstacle(self, seg: Obstacle, t_s: float, q: np.ndarray, dq: np.ndarray, out: np.ndarray) -> None:
        Jp, at = self._point_jacobian(q, self._link_id, seg.link_point_m)
        nrm = self._direction
        depth = float(np.dot(np.asarray(seg.point_m, dtype=float) - at, nrm))  # > 0: inside the obstacle
        f = 0.0
        if depth > 0.0:
            v = float(nrm @ (Jp @ dq))  # the point's speed along the normal (< 0: moving in)
            f = max(0.0, seg.stiffness_N_m * depth - seg.damping_N_s_m * v)
            if not self._touched:
                self._touched = True
                self._event(t_s, "obstacle_contact", link=seg.link, at_m=[round(x, 5) for x in at.tolist()])
            self._depth = max(self._depth, depth)
        self._peak = max(self._peak, f)
        force = f * nrm
        out[:] = Jp.T @ force
        self.force_N[:] = force
        self.force_at_m[:] = at
        self._force_known = True

    def _wrench_torque(self, q: np.ndarray, wrench: np.ndarray) -> np.ndarray:
        J = pin.computeFrameJacobian(self.model, self.data, q, self.frame_id, pin.LOCAL_WORLD_ALIGNED)
        return J.T @ wrench

    def _hand(self, seg: Hand, q: np.ndarray, dq: np.ndarray, out: np.ndarray) -> None:
        if seg.q_rad is not None:
            np.subtract(self._target_q, q, out=out)
            out *= seg.stiffness
            out -= seg.damping * dq
            np.clip(out, -seg.max_load, seg.max_load, out=out)
            return
        J = pin.computeFrameJacobian(self.model, self.data, q, self.frame_id, pin.LOCAL_WORLD_ALIGNED)
        now = self.data.oMf[self.frame_id]
        at = now.translation
        twist = J @ dq
        wrench = np.zeros(6)
        assert self._target_M is not None
        # the spring on floats, element by element as numpy would (3-vectors: numpy's call overhead was the cost)
        k, c = seg.stiffness, seg.damping
        tx, ty, tz = self._target_xyz
        nx, ny, nz = at.tolist()
        wx, wy, wz = twist[:3].tolist()
        fx, fy, fz = k * (tx - nx) - c * wx, k * (ty - ny) - c * wy, k * (tz - nz) - c * wz
        norm = math.sqrt(fx * fx + fy * fy + fz * fz)  # (np.linalg.norm costs ~4 µs a call: a tenth of the step)
        if norm > seg.max_load:
            scale = seg.max_load / norm
            fx, fy, fz = fx * scale, fy * scale, fz * scale
        f = (fx, fy, fz)
        wrench[:3] = f
        if seg.rpy_rad is not None:
            err = pin.log3(self._target_M.rotation @ now.rotation.T)  # world-frame rotation error
            wrench[3:] = seg.rot_stiffness_Nm_per_rad * err - seg.rot_damping_Nm_s_per_rad * twist[3:]
        out[:] = J.T @ wrench
        self.force_N[:] = f
        self.force_at_m[:] = at  # (the placement the Jacobian left, as _flange_force reads it)
        self._force_known = True
