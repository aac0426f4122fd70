"""The simulator's truth: what the simulated robot really is (never read by dragd/).

A YAML file (default ``sim/config/seed_cobot.yaml``) validated by a pydantic schema. Every error names the
file, the key path and the expectation, e.g.
``sim/config/seed_cobot.yaml: joints[2].gear_ratio: expected a positive number, got 'abc'``.
Any other robot: :func:`truth_for_robot` makes a truth from its URDF alone (joint names from the URDF, drives
sized to hold its gravity, modest friction and Hall noise); ``load_truth`` does so for a ``.urdf`` path or a bundled
robot without a truth file, so ``python -m sim run --config path/to/robot.urdf`` simulates it, and
``python -m sim.truth --robot path/to/robot.urdf`` prints that truth as YAML to tune.

Conventions (joint side unless a name says otherwise): rad, rad/s, N·m, A of motor current.
Negative-direction friction levels are negative numbers (as in dragd's config); viscous slopes are >= 0.
``static_*_Nm`` is the total breakaway level (|static| >= |Coulomb|); the Stribeck curve falls from it to Coulomb.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal

import numpy as np
from pydantic import Field, ValidationError, model_validator

from dragd.vocabulary import (
    ConfigError,
    Expect,
    Finite,
    NodeId,
    NonNegFloat,
    NonPosFloat,
    PosFloat,
    PosInt,
    Strict,
    format_validation_error,
    read_yaml,
)

if TYPE_CHECKING:
    from dragd.model import RobotModel
    from sim.drive import DriveParams
    from sim.drive_profile import DriveProfile, ProfileSpec

CONFIG_DIR = Path(__file__).resolve().parent / "config"
DEFAULT_TRUTH = CONFIG_DIR / "seed_cobot.yaml"

class TruthError(ConfigError):
    """A sim truth file that cannot be used; the message names file, key path and expectation."""


class DriveObject(Strict):
    """Where the drive's firmware keeps one process quantity (what the vendor's manual says), e.g. EPOS4's current
    actual value: ``{object: 30D1h:2, unit: mA}`` (sim/drive_profile.py lists the quantities and units)."""

    object: Annotated[str, Expect("an object address like 30D1h:2")]
    unit: str | None = None  # None: the quantity's CiA 402 unit


class DriveHardware(Strict):
    """The integrated drive's hardware and built-in loops (what its object dictionary and firmware hold).

    ``eds``, ``profile``, ``objects``, ``values``, ``can_fd``: which drive model it is (sim/drive_profile.py,
    docs/SIM_DRIVES.md) — by default the bundled canopen_eds/joint_drive.eds."""

    node_id: NodeId
    rated_current_A: PosFloat  # 6075h
    rated_torque_Nm: PosFloat  # 6076h, motor side; K_m = 6076h / 6075h
    max_torque_permille: Annotated[int, Field(ge=1, le=65535), Expect("an integer per mille 1..65535")] = 3000  # 6072h
    max_current_A: PosFloat  # 6073h (current-loop clamp)
    encoder_counts_per_rev: PosInt  # per joint revolution (absolute output encoder)
    csp_kp_A_per_rad: NonNegFloat = 40.0  # cyclic synchronous position loop, amperes of demand
    csp_kd_A_s_per_rad: NonNegFloat = 2.0  # ... and the CSV velocity-loop gain
    # integral of the position error (removes the friction and gravity offset); None: the drive model's — 0 for the
    # bundled joint drive, VENDOR_CSP_KI_PER_KP x kp for a drive from a vendor's EDS (docs/SIM_DRIVES.md)
    csp_ki_A_per_rad_s: NonNegFloat | None = None
    quickstop_decel_rad_s2: PosFloat = 10.0  # 6085h
    slowdown_decel_rad_s2: PosFloat = 4.0  # 6084h
    brake_release_delay_s: NonNegFloat = 0.05  # operation enabled -> brake released
    eds: str | None = None  # the drive's EDS (relative to this file); None: the bundled canopen_eds/joint_drive.eds
    profile: str | None = None  # an entry of sim/config/drives/; None: the entry matching the EDS's [DeviceInfo]
    objects: dict[str, DriveObject] = Field(default_factory=dict)  # quantity -> object (overrides the entry's)
    values: dict[str, int] = Field(default_factory=dict)  # "6502h" -> value the drive holds as delivered
    can_fd: bool | None = None  # PDOs beyond 8 bytes on a CAN FD bus; None: the entry's, else only the bundled EDS

    @model_validator(mode="after")
    def _currents(self) -> DriveHardware:
        if self.max_current_A > 65.535 * self.rated_current_A:
            raise ValueError(f"expected max_current_A <= 65.535 x rated_current_A (6073h is per mille), "
                             f"got {self.max_current_A}")
        return self


class FrictionTruth(Strict):
    """True joint friction, direction asymmetric: Stribeck curve plus viscous slope."""

    coulomb_pos_Nm: NonNegFloat = 0.0
    coulomb_neg_Nm: NonPosFloat = 0.0
    static_pos_Nm: NonNegFloat | None = None  # breakaway level; None: equal to Coulomb
    static_neg_Nm: NonPosFloat | None = None
    stribeck_velocity_rad_s: PosFloat = 0.02
    stribeck_exponent: Annotated[float, Field(gt=0, le=4), Expect("a number in (0, 4]")] = 2.0
    viscous_pos_Nm_s_per_rad: NonNegFloat = 0.0
    viscous_neg_Nm_s_per_rad: NonNegFloat = 0.0

    @model_validator(mode="after")
    def _static_above_coulomb(self) -> FrictionTruth:
        if self.static_pos_Nm is not None and self.static_pos_Nm < self.coulomb_pos_Nm:
            raise ValueError(f"expected static_pos_Nm >= coulomb_pos_Nm ({self.coulomb_pos_Nm}), "
                             f"got {self.static_pos_Nm}")
        if self.static_neg_Nm is not None and self.static_neg_Nm > self.coulomb_neg_Nm:
            raise ValueError(f"expected static_neg_Nm <= coulomb_neg_Nm ({self.coulomb_neg_Nm}), "
                             f"got {self.static_neg_Nm}")
        return self

    @property
    def static_pos(self) -> float:
        return self.coulomb_pos_Nm if self.static_pos_Nm is None else self.static_pos_Nm

    @property
    def static_neg(self) -> float:
        return self.coulomb_neg_Nm if self.static_neg_Nm is None else self.static_neg_Nm


class HardStops(Strict):
    """Mechanical end stops on the output: a spring-damper beyond each limit."""

    lower_rad: Finite
    upper_rad: Finite
    stiffness_Nm_per_rad: PosFloat = 20000.0
    damping_Nm_s_per_rad: NonNegFloat = 50.0

    @model_validator(mode="after")
    def _order(self) -> HardStops:
        if self.lower_rad >= self.upper_rad:
            raise ValueError(f"expected lower_rad < upper_rad, got {self.lower_rad} >= {self.upper_rad}")
        return self


class Ripple(Strict):
    """Position-periodic torque ripple: amplitude·sin(cycles·θ + phase), θ the joint or motor angle."""

    amplitude_Nm: NonNegFloat
    cycles_per_rev: PosFloat  # per revolution of the reference shaft
    reference: Literal["joint", "motor"] = "motor"
    phase_rad: Finite = 0.0


class Thermal(Strict):
    """First-order thermal model of the joint: C·dT/dt = P_friction + I²R − (T − T_ambient)/R_th.

    Friction levels and viscous slopes scale by 1 + friction_coefficient_per_K·(T − reference_C).
    """

    ambient_C: Finite = 25.0
    initial_C: Finite | None = None  # None: ambient
    reference_C: Finite = 25.0  # the friction truth holds at this temperature
    heat_capacity_J_per_K: PosFloat = 500.0
    thermal_resistance_K_per_W: PosFloat = 0.8
    winding_resistance_ohm: NonNegFloat = 0.4
    friction_coefficient_per_K: Annotated[float, Field(gt=-0.05, lt=0.05), Expect("a fraction per kelvin in "
                                                                                  "(-0.05, 0.05)")] = -0.005


class BackEmfHeadroom(Strict):
    """Current-loop voltage headroom: above ``knee_rad_s`` the back-EMF leaves the loop short of voltage and the
    winding current falls short of the reported (regulated) current by A_s_per_rad·(|q̇| − knee)·sign q̇."""

    A_s_per_rad: NonNegFloat
    knee_rad_s: NonNegFloat = 0.0


class FrictionDrift(Strict):
    """Friction warm-up over time, g = 1 − e^(−t/τ) (t: simulated time): the Coulomb/Stribeck levels × (1 + change·g),
    the viscous slope × (1 + viscous_change·g) (null: ``change`` for both)."""

    change: Annotated[float, Field(gt=-0.95, lt=5), Expect("a relative change in (-0.95, 5)")]
    time_constant_s: PosFloat
    viscous_change: Annotated[float, Field(gt=-0.95, lt=5), Expect("a relative change in (-0.95, 5)")] | None = None


class Payload(Strict):
    """A point mass on the flange (the last joint's frame) that the URDF does not have."""

    mass_kg: NonNegFloat
    com_m: tuple[Finite, Finite, Finite] = (0.0, 0.0, 0.0)


class Hidden(Strict):
    """Effects the compensation model does not have (all off by default), for model-gap work."""

    ripple: list[Ripple] = Field(default_factory=list)
    load_friction_per_Nm: NonNegFloat = 0.0  # Coulomb and static grow by this × |gravity torque|
    thermal: Thermal | None = None
    current_offset_A: Finite = 0.0  # Hall-sensor offset: the loop delivers demand − offset, reports demand
    backlash_rad: NonNegFloat = 0.0  # lost motion between rotor (friction, brake, motor) and output
    gear_stiffness_Nm_per_rad: PosFloat = 20000.0  # output-side contact stiffness when backlash > 0
    gear_damping_ratio: Annotated[float, Field(ge=0, le=2), Expect("a fraction of critical damping in [0, 2]")] = 0.5
    # share of the joint's friction on the output side of the play (output bearing, seals) when backlash > 0; the
    # rest acts on the rotor (motor bearings, gear input). 0 would leave the output floating inside the play.
    output_friction_fraction: Annotated[float, Field(ge=0, le=1), Expect("a fraction in [0, 1]")] = 0.3
    back_emf: BackEmfHeadroom | None = None
    friction_drift: FrictionDrift | None = None


class JointTruth(Strict):
    name: str
    drive: DriveHardware
    gear_ratio: PosFloat
    torque_constant_Nm_per_A: PosFloat  # true joint-side K_t
    rotor_inertia_kgm2: NonNegFloat  # motor side; reflected ×gear² as armature
    current_loop_time_constant_s: Annotated[float, Field(gt=0, le=0.01),
                                            Expect("a time constant in (0, 0.01] s")] = 3e-4
    current_noise_std_A: NonNegFloat = 0.02  # Hall sensor
    current_quantum_A: NonNegFloat = 0.0  # ADC step; 0: unquantised
    friction: FrictionTruth = FrictionTruth()
    hard_stops: HardStops
    brake_holding_torque_Nm: PosFloat
    initial_position_rad: Finite = 0.0
    bus_index: Annotated[int, Field(ge=0), Expect("a bus index >= 0")] = 0  # which of `--bus A,B,...` the drive is on
    hidden: Hidden = Hidden()

    @model_validator(mode="after")
    def _stops_contain_start(self) -> JointTruth:
        if not self.hard_stops.lower_rad <= self.initial_position_rad <= self.hard_stops.upper_rad:
            raise ValueError(f"expected initial_position_rad within hard_stops [{self.hard_stops.lower_rad}, "
                             f"{self.hard_stops.upper_rad}], got {self.initial_position_rad}")
        return self

    @property
    def armature_kgm2(self) -> float:
        """Rotor inertia reflected to the joint."""
        return self.rotor_inertia_kgm2 * self.gear_ratio**2


Bit = Annotated[int, Field(ge=0, le=31, strict=True), Expect("a bit of the drive's inputs 0..31")]


class HandContact(Strict):
    """A push button at the hand wired to a bit of one joint drive's digital inputs."""

    bit: Bit
    normally_closed: bool = False  # the bit reads 1 while the button is not pressed (a stop: a cut wire stops)


HandButton = Literal["mark", "stop", "teach"]


def _default_buttons() -> dict[HandButton, HandContact]:
    return {"mark": HandContact(bit=19), "stop": HandContact(bit=20, normally_closed=True),
            "teach": HandContact(bit=21)}


class HandTruth(Strict):
    """The guiding device on the simulated arm (sim/hand.py): a three-position enabling switch and buttons, wired to
    one drive's digital inputs (60FDh; CiA 402's manufacturer bits 16-31). The operator presses them
    (sim/operator.py ``press`` / ``let_go``); dragd's configuration says which bit is what (``hand.inputs``)."""

    joint: str | None = None  # the joint whose drive reads the contacts; None: the last joint (the wrist)
    enable_bits: list[Bit] = Field(default_factory=lambda: [16, 17], min_length=1, max_length=2)  # the middle position
    panic_bit: Bit | None = 18  # the squeezed position's contact (None: the device reports none)
    buttons: dict[HandButton, HandContact] = Field(default_factory=_default_buttons)
    bounce_ms: Annotated[float, Field(ge=0, le=20), Expect("milliseconds in [0, 20]")] = 0.0  # contact bounce

    @model_validator(mode="after")
    def _bits(self) -> HandTruth:
        bits = list(self.enable_bits) + ([self.panic_bit] if self.panic_bit is not None else []) + \
            [c.bit for c in self.buttons.values()]
        if len(set(bits)) != len(bits):
            raise ValueError(f"expected each contact on its own bit, got {bits}")
        return self


class BusTruth(Strict):
    channel: str = "udp_multicast:239.74.163.2"  # default for `python -m sim run` without --bus
    fd: bool = True


class Truth(Strict):
    robot: str = "seed_cobot"  # bundled robot name or URDF path (relative to the truth file)
    gravity_m_s2: tuple[Finite, Finite, Finite] = (0.0, 0.0, -9.81)
    bus: BusTruth = BusTruth()
    physics_rate_Hz: Annotated[int, Field(ge=4000, le=50000), Expect("an integer rate in [4000, 50000] Hz")] = 4000
    noise_seed: int = 0
    payload: Payload | None = None  # hidden: a flange load the URDF (and dragd's model) does not have
    # link name → {mass_kg, com_m, inertia_kgm2 (ixx, ixy, ixz, iyy, iyz, izz about the COM)}: replaces the URDF's
    inertials: dict[str, dict[str, Any]] | None = None
    joints: list[JointTruth] = Field(min_length=1)
    hand: HandTruth | None = HandTruth()  # the guiding device at the wrist (None: the arm has none)
    source: str = Field("<memory>", exclude=True)  # file it came from (not a YAML key)

    @model_validator(mode="after")
    def _cross(self) -> Truth:
        if self.physics_rate_Hz % 1000:
            raise ValueError(f"physics_rate_Hz: expected a multiple of 1000 Hz (whole steps per 1 ms tick), "
                             f"got {self.physics_rate_Hz}")
        names = [j.name for j in self.joints]
        if len(set(names)) != len(names):
            raise ValueError(f"joints: expected unique joint names, got {names}")
        ids = [j.drive.node_id for j in self.joints]
        if len(set(ids)) != len(ids):
            raise ValueError(f"joints: expected unique drive.node_id values, got {ids}")
        if self.hand is not None and self.hand.joint is not None and self.hand.joint not in names:
            raise ValueError(f"hand.joint: expected one of the joints {', '.join(names)}, got '{self.hand.joint}'")
        return self

    @property
    def dt_s(self) -> float:
        return 1.0 / self.physics_rate_Hz

    @property
    def base_dir(self) -> Path:
        return Path(self.source).resolve().parent if self.source != "<memory>" else Path.cwd()

    def check_model(self, joint_names: tuple[str, ...] | list[str]) -> None:
        """Raise TruthError unless the truth's joints are the model's, in order."""
        names = [j.name for j in self.joints]
        if names != list(joint_names):
            raise TruthError(f"{self.source}: joints: expected the robot's joints {', '.join(joint_names)} in order, "
                             f"got {', '.join(names)}")

    def load_model(self) -> RobotModel:
        """The robot model named by ``robot`` (with the truth's gravity), checked against the joints."""
        from dragd.model import RobotModel

        try:
            model = RobotModel.from_urdf(self.robot, base_dir=self.base_dir, gravity_m_s2=self.gravity_m_s2)
        except (FileNotFoundError, ValueError) as exc:
            raise TruthError(f"{self.source}: robot: expected a bundled robot name or URDF path, "
                             f"got {self.robot!r} ({exc})") from None
        if self.inertials:
            try:
                model.apply_inertials(self.inertials, f"{self.source}")
            except (KeyError, TypeError, ValueError) as exc:
                raise TruthError(f"{self.source}: inertials: {exc}") from None
        self.check_model(model.joint_names)
        return model

    def with_updates(self, **changes: Any) -> Truth:
        """A revalidated copy with nested changes merged in; ``joints`` may be a dict keyed by index or name.

        Example: ``truth.with_updates(joints={"joint2": {"friction": {"coulomb_pos_Nm": 0.0}}})``.
        """
        data = self.model_dump(mode="python")
        _merge(data, changes)
        return validate_truth(data, self.source)


def _merge(data: dict[str, Any], changes: dict[str, Any]) -> None:
    for key, value in changes.items():
        if key == "joints" and isinstance(value, dict):
            names = [j["name"] for j in data["joints"]]
            for jkey, jchange in value.items():
                idx = names.index(jkey) if isinstance(jkey, str) else int(jkey)
                _merge(data["joints"][idx], jchange)
        elif isinstance(value, dict) and isinstance(data.get(key), dict):
            _merge(data[key], value)
        else:
            data[key] = value


def validate_truth(data: Any, source: str = "<memory>") -> Truth:
    """Validate a truth mapping; errors name ``source``, the key path and the expectation."""
    if not isinstance(data, dict):
        raise TruthError(f"{source}: expected a mapping of keys (robot, joints, ...), got {type(data).__name__}")
    try:
        truth = Truth.model_validate({**data, "source": source})
    except ValidationError as exc:
        raise TruthError(format_validation_error(source, Truth, exc)) from None
    return _absolute_eds(truth)


def _absolute_eds(truth: Truth) -> Truth:
    """The joints' ``drive.eds`` paths made absolute (relative to the truth file's folder)."""
    joints = []
    for j in truth.joints:
        eds = j.drive.eds
        if eds is not None and not Path(eds).expanduser().is_absolute():
            eds = str((truth.base_dir / Path(eds).expanduser()).resolve())
        elif eds is not None:
            eds = str(Path(eds).expanduser())
        joints.append(j if eds == j.drive.eds
                      else j.model_copy(update={"drive": j.drive.model_copy(update={"eds": eds})}))
    return truth.model_copy(update={"joints": joints}) if joints != list(truth.joints) else truth


def drive_profiles(truth: Truth) -> list[DriveProfile]:
    """Every joint's drive built from its EDS and profile (sim/drive_profile.py); a TruthError lists every problem of
    every joint at once."""
    from sim.drive_profile import ProfileError

    profiles, problems = [], []
    for i, j in enumerate(truth.joints):
        params = drive_params(j, truth.bus.fd, where=f"{truth.source}: joints[{i}] ({j.name}).drive")
        try:
            profiles.append(params.build_profile())
        except ProfileError as exc:
            problems += [line for line in str(exc).splitlines() if line not in problems]  # (a catalog's once)
    if problems:
        raise TruthError("\n".join(problems))
    return profiles


def spread_over_buses(truth: Truth, bus: str | None) -> Truth:
    """With several buses (``--bus A,B,C``) and a truth whose joints all sit on bus 0: joint i of n on bus i*k//n of
    the k buses (as ``dragd config init`` splits joints over buses); otherwise the truth unchanged."""
    k = len([b for b in (bus or truth.bus.channel).split(",") if b])
    if k <= 1 or any(j.bus_index for j in truth.joints):
        return truth
    n = len(truth.joints)
    return truth.with_updates(joints={i: {"bus_index": i * k // n} for i in range(n)})


def with_eds(truth: Truth, eds: str | Path) -> Truth:
    """The truth with every joint's drive built from ``eds`` (``python -m sim run --eds FILE``): its catalog entry
    (sim/config/drives/, matched by the EDS's [DeviceInfo]) replaces the joints' own objects, values and profile, and
    the drive model's CSP integral the truth's (a vendor's position loop integrates: csp_ki_A_per_rad_s None)."""
    path = str(Path(eds).expanduser().resolve())
    return truth.with_updates(joints={i: {"drive": {"eds": path, "profile": None, "objects": {}, "values": {},
                                                    "can_fd": None, "csp_ki_A_per_rad_s": None}}
                                      for i in range(len(truth.joints))})


def load_truth(path: str | Path | None = None) -> Truth:
    """Load the truth file (default: the bundled seed cobot's); a ``.urdf`` file or a bundled robot name: its
    curated truth under sim/config/ if there is one, else :func:`truth_for_robot`."""
    from dragd.robots import BUNDLED

    if path is not None and (str(path) in BUNDLED or str(path).endswith(".urdf")):
        curated = CONFIG_DIR / f"{path}.yaml"
        return load_truth(curated) if str(path) in BUNDLED and curated.is_file() else truth_for_robot(path)
    path = Path(path) if path is not None else DEFAULT_TRUTH
    try:
        data = read_yaml(path)
    except ConfigError as exc:
        raise TruthError(str(exc)) from None
    if isinstance(data, dict) and "source" in data:
        raise TruthError(f"{path}: source: unknown key")
    return validate_truth(data, str(path))


def drive_spec(joint: JointTruth, where: str = "") -> ProfileSpec:
    """The joint's drive model as sim/drive_profile.py reads it (errors name ``where``, the truth file and key)."""
    from sim.drive_profile import ProfileSpec

    hw = joint.drive
    return ProfileSpec(eds=hw.eds, profile=hw.profile,
                       objects={k: {"object": o.object, **({"unit": o.unit} if o.unit else {})}
                                for k, o in hw.objects.items()},
                       values=dict(hw.values), can_fd=hw.can_fd, where=where or f"joints.{joint.name}.drive",
                       assumed_csp_ki=None if hw.csp_ki_A_per_rad_s is not None or not csp_ki_A_per_rad_s(joint)
                       else csp_ki_A_per_rad_s(joint))


def csp_ki_A_per_rad_s(joint: JointTruth) -> float:
    """The CSP loop's integral gain: the truth's, else the drive model's — 0 (P+D, as the bundled drive) unless the
    drive's EDS offers no torque offset a master could feed forward (no writable, RPDO-mappable 60B2h): such a drive
    holds the arm with its own, integrating position loop (VENDOR_CSP_KI_PER_KP x kp)."""
    from sim.drive_profile import VENDOR_CSP_KI_PER_KP, takes_torque_offset

    hw = joint.drive
    if hw.csp_ki_A_per_rad_s is not None:
        return hw.csp_ki_A_per_rad_s
    if hw.eds is None or takes_torque_offset(hw.eds, hw.node_id):
        return 0.0
    return VENDOR_CSP_KI_PER_KP * hw.csp_kp_A_per_rad


def drive_params(joint: JointTruth, fd: bool, base_dir: str | None = None, where: str = "") -> DriveParams:
    """The simulated drive's parameters for one joint (what its object dictionary and firmware hold); ``base_dir``:
    where a relative ``eds`` path starts (the truth file's folder)."""
    from sim.drive import DriveParams

    hw = joint.drive
    return DriveParams(
        profile=drive_spec(joint, where),
        base_dir=base_dir,
        node_id=hw.node_id,
        rated_current_A=hw.rated_current_A,
        rated_torque_Nm=hw.rated_torque_Nm,
        max_current_A=hw.max_current_A,
        encoder_counts_per_rev=hw.encoder_counts_per_rev,
        max_torque_permille=hw.max_torque_permille,
        csp_kp_A_per_rad=hw.csp_kp_A_per_rad,
        csp_kd_A_s_per_rad=hw.csp_kd_A_s_per_rad,
        csp_ki_A_per_rad_s=csp_ki_A_per_rad_s(joint),
        quickstop_decel_rad_s2=hw.quickstop_decel_rad_s2,
        slowdown_decel_rad_s2=hw.slowdown_decel_rad_s2,
        brake_release_delay_s=hw.brake_release_delay_s,
        fd=fd,
    )


# ------------------------------------------------------------------------------------------ dragd params <-> truth


def truth_from_params(params: Any, base: Truth | None = None) -> Truth:
    """The truth that a dragd params file describes (``dragd identify fit``/``dragd gap --out``), on top of ``base``
    (default: the bundled truth) for everything a params file does not hold (drives, noise, stops, inertias).

    K_t, friction (amperes × K_t → N·m) and the model-gap effects (docs/GAP.md) become the truth's; effects the
    params do not name are switched off, so the simulated robot is exactly the extended model.
    """
    base = base or load_truth()
    changes: dict[str, Any] = {"joints": {}, "payload": None if params.payload is None else params.payload.model_dump()}
    if params.inertials:  # the identified arm (dragd identify fit --method full)
        changes["inertials"] = {k: v.model_dump(mode="python") for k, v in params.inertials.items()}
    for jt in base.joints:
        jp = params.joints.get(jt.name)
        if jp is None:
            continue
        kt = jp.torque_constant_Nm_per_A or jt.torque_constant_Nm_per_A
        f, tf = jp.friction, jt.friction
        fr: dict[str, Any] = {}
        for key, tkey in (("coulomb_pos_A", "coulomb_pos_Nm"), ("coulomb_neg_A", "coulomb_neg_Nm"),
                          ("static_pos_A", "static_pos_Nm"), ("static_neg_A", "static_neg_Nm")):
            v = getattr(f, key)
            fr[tkey] = v * kt if v is not None else getattr(tf, tkey)
        for d in ("pos", "neg"):
            v = getattr(f, f"viscous_{d}_A_s_per_rad")
            v = f.viscous_A_s_per_rad if v is None else v
            fr[f"viscous_{d}_Nm_s_per_rad"] = v * kt if v is not None else getattr(tf, f"viscous_{d}_Nm_s_per_rad")
        if f.stribeck_velocity_rad_s is not None:
            fr["stribeck_velocity_rad_s"] = f.stribeck_velocity_rad_s
        if f.stribeck_exponent is not None:
            fr["stribeck_exponent"] = min(f.stribeck_exponent, 4.0)
        if fr["static_pos_Nm"] is not None and fr["static_pos_Nm"] < fr["coulomb_pos_Nm"]:
            fr["static_pos_Nm"] = fr["coulomb_pos_Nm"]
        if fr["static_neg_Nm"] is not None and fr["static_neg_Nm"] > fr["coulomb_neg_Nm"]:
            fr["static_neg_Nm"] = fr["coulomb_neg_Nm"]
        e = jp.effects
        # the params' current residual s·sin(c·q) + k·cos(c·q) is the current the motion needs; the sim's ripple is a
        # torque that drives the joint: amplitude·sin(c·q + φ) = −K_t·(s·sin + k·cos)
        ripple = [{"amplitude_Nm": kt * float(np.hypot(h.sin_A, h.cos_A)), "cycles_per_rev": h.cycles_per_rev,
                   "reference": "joint", "phase_rad": float(np.arctan2(-h.cos_A, -h.sin_A))}
                  for h in e.position_periodic]
        hidden = {"ripple": ripple, "load_friction_per_Nm": e.load_friction_per_Nm,
                  "current_offset_A": e.current_offset_A,
                  "backlash_rad": e.backlash_rad or 0.0, "thermal": None,
                  "output_friction_fraction": (e.backlash_output_friction_fraction
                                               if e.backlash_output_friction_fraction is not None
                                               else jt.hidden.output_friction_fraction),
                  "back_emf": None if e.back_emf is None else e.back_emf.model_dump(),
                  "friction_drift": None if e.temperature_drift is None else
                  {"change": e.temperature_drift.friction_change,
                   "time_constant_s": e.temperature_drift.time_constant_s,
                   "viscous_change": e.temperature_drift.viscous_change}}
        jc: dict[str, Any] = {"torque_constant_Nm_per_A": kt, "friction": fr, "hidden": hidden}
        rotor = e.armature_kgm2 if e.armature_kgm2 is not None else e.backlash_inertia_kgm2
        if rotor is not None:
            jc["rotor_inertia_kgm2"] = rotor / jt.gear_ratio ** 2
        changes["joints"][jt.name] = jc
    return base.with_updates(**changes)


def params_from_truth(truth: Truth) -> dict[str, Any]:
    """A dragd params mapping (``dragd.config.ParamsFile``) holding the truth's K_t, friction (A), rotor inertia and
    the hidden effects a params file can express — the model that "knows everything" about this robot."""
    joints: dict[str, Any] = {}
    for j in truth.joints:
        kt = j.torque_constant_Nm_per_A
        f, h = j.friction, j.hidden
        eff: dict[str, Any] = {"armature_kgm2": j.armature_kgm2,
                               "load_friction_per_Nm": h.load_friction_per_Nm, "current_offset_A": h.current_offset_A}
        eff["position_periodic"] = [
            {"cycles_per_rev": r.cycles_per_rev, "sin_A": -r.amplitude_Nm * float(np.cos(r.phase_rad)) / kt,
             "cos_A": -r.amplitude_Nm * float(np.sin(r.phase_rad)) / kt}
            for r in h.ripple if r.reference == "joint"]
        if h.back_emf is not None:
            eff["back_emf"] = h.back_emf.model_dump()
        if h.friction_drift is not None:
            eff["temperature_drift"] = {"friction_change": h.friction_drift.change,
                                        "time_constant_s": h.friction_drift.time_constant_s,
                                        "viscous_change": h.friction_drift.viscous_change}
        if h.backlash_rad:
            eff["backlash_rad"] = h.backlash_rad
            eff["backlash_output_friction_fraction"] = h.output_friction_fraction
        joints[j.name] = {
            "torque_constant_Nm_per_A": kt,
            "friction": {"coulomb_pos_A": f.coulomb_pos_Nm / kt, "coulomb_neg_A": f.coulomb_neg_Nm / kt,
                         "static_pos_A": f.static_pos / kt, "static_neg_A": f.static_neg / kt,
                         "stribeck_velocity_rad_s": f.stribeck_velocity_rad_s, "stribeck_exponent": f.stribeck_exponent,
                         "viscous_pos_A_s_per_rad": f.viscous_pos_Nm_s_per_rad / kt,
                         "viscous_neg_A_s_per_rad": f.viscous_neg_Nm_s_per_rad / kt},
            "effects": eff}
    out: dict[str, Any] = {"version": 1, "method": "truth", "robot": truth.robot, "joints": joints}
    if truth.payload is not None:
        out["payload"] = truth.payload.model_dump()
    return out


# ------------------------------------------------------------------------------------------ any robot


def truth_for_robot(robot: str | Path, base_dir: Path | None = None, *,
                    gravity_m_s2: tuple[float, float, float] = (0.0, 0.0, -9.81), noise_seed: int = 1,
                    initial_q_rad: list[float] | None = None) -> Truth:
    """A truth for any URDF: joint names and ranges from it, drives sized as ``dragd config init`` sizes them
    (dragd/robots/sizing.py: they hold the robot's gravity) with the true K_t 0.5-3 % below that belief, friction
    about 5 % of each joint's peak torque (Coulomb; static 1.3×, viscous 6 %/(rad/s), 2-8 % direction asymmetry),
    20 mA Hall noise, a 12-bit current ADC, hard stops 0.05 rad beyond the URDF's limits. Deterministic per
    ``noise_seed``; starts at ``initial_q_rad`` (default: the URDF's zero, moved inside the ranges)."""
    from dragd.model import RobotModel
    from dragd.robots import urdf_reference
    from dragd.robots.sizing import ENCODER_COUNTS_PER_REV, GEAR_RATIO, size_joints

    try:
        ref = urdf_reference(robot, base_dir)
        model = RobotModel.from_urdf(ref, base_dir, gravity_m_s2)
    except (FileNotFoundError, ValueError) as exc:
        raise TruthError(f"robot {robot}: {exc}") from None
    sizes = size_joints(model)
    rng = np.random.default_rng(noise_seed)
    q0 = initial_q_rad if initial_q_rad is not None else [min(max(0.0, s.lower_rad + 0.2), s.upper_rad - 0.2)
                                                           for s in sizes]
    if len(q0) != len(sizes):
        raise TruthError(f"initial_q_rad: expected {len(sizes)} values ({', '.join(model.joint_names)}), got {len(q0)}")
    joints = []
    for i, sz in enumerate(sizes):
        peak, limit, large = sz.peak_torque_Nm, sz.current_limit_A, sz.large
        fc, asym = 0.05 * peak, float(rng.uniform(0.92, 0.98))
        joints.append({
            "name": sz.name,
            "drive": {"node_id": i + 1, "rated_current_A": sz.rated_current_A,
                      "rated_torque_Nm": sz.rated_motor_torque_Nm, "max_torque_permille": 3000,
                      "max_current_A": limit, "encoder_counts_per_rev": ENCODER_COUNTS_PER_REV,
                      # the seed cobot's CSP stiffness and damping relative to the drive's peak torque
                      "csp_kp_A_per_rad": limit * 10.0 / 3.0, "csp_kd_A_s_per_rad": limit / (6.0 if large else 12.0)},
            "gear_ratio": GEAR_RATIO,
            "torque_constant_Nm_per_A": sz.kt_Nm_per_A * float(rng.uniform(0.97, 0.995)),  # a real gear loses a little
            "rotor_inertia_kgm2": 1.7e-4 * sz.rated_motor_torque_Nm,  # the seed's motors: 1.7e-4 kg·m² per N·m rated
            "current_loop_time_constant_s": 3.0e-4 if large else 2.5e-4,
            "current_noise_std_A": 0.020,
            "current_quantum_A": 2.0 * limit * 5.0 / 3.0 / 4096,  # 12-bit ADC over ±5/3 of the current limit
            "friction": {"coulomb_pos_Nm": fc, "coulomb_neg_Nm": -fc * asym, "static_pos_Nm": 1.3 * fc,
                         "static_neg_Nm": -1.3 * fc * asym, "stribeck_velocity_rad_s": 0.02 if large else 0.03,
                         "stribeck_exponent": 1.5, "viscous_pos_Nm_s_per_rad": 0.06 * peak,
                         "viscous_neg_Nm_s_per_rad": 0.06 * peak * asym},
            "hard_stops": {"lower_rad": sz.lower_rad - 0.05, "upper_rad": sz.upper_rad + 0.05,
                           "stiffness_Nm_per_rad": 20000.0 if large else 10000.0,
                           "damping_Nm_s_per_rad": 100.0 if large else 30.0},
            "brake_holding_torque_Nm": 1.4 * peak,
            "initial_position_rad": float(q0[i]),
        })
    data = {"robot": ref, "gravity_m_s2": list(gravity_m_s2), "noise_seed": noise_seed, "joints": joints}
    return validate_truth(data, f"<truth for {ref}>")


def truth_yaml(truth: Truth) -> str:
    """A truth as a YAML file's text (``load_truth`` reads it back)."""
    import yaml

    head = (f"# The simulated {Path(truth.robot).stem}'s truth, generated from its URDF by sim/truth.py "
            "truth_for_robot;\n# dragd never reads this file. Joint side: rad, rad/s, N·m, A of motor current.\n")
    return head + yaml.safe_dump(truth.model_dump(mode="json"), sort_keys=False, default_flow_style=None, width=110)


def main(argv: list[str] | None = None) -> int:
    """``python -m sim.truth --robot PATH [--seed N]``: print a generated truth as YAML (to tune, then --config)."""
    import argparse
    import sys

    parser = argparse.ArgumentParser(prog="python -m sim.truth", description=main.__doc__)
    parser.add_argument("--robot", required=True, help="bundled robot name or URDF path")
    parser.add_argument("--seed", type=int, default=1, help="noise seed (also varies K_t and friction asymmetry)")
    args = parser.parse_args(argv)
    try:
        truth = truth_for_robot(args.robot, Path.cwd(), noise_seed=args.seed)
    except TruthError as exc:
        print(f"sim: {exc}", file=sys.stderr)
        return 2
    sys.stdout.write(truth_yaml(truth))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
