"""dragd's configuration: a typed schema of the YAML files in ``config/`` and of identified-params files.

Every error names the file, the key path and what was expected, e.g.
``config/default.yaml: joints[2].gear_ratio: expected a positive number, got 'abc'``.
Unknown keys are errors. ``joints[].name`` are the robot's URDF joint names, in the URDF's order (``load_config``
checks them against the robot). An identified-parameters file (written by ``dragd identify fit``), keyed by the
same names, overrides per-joint torque constants and friction of the configuration it is loaded with.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
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
    format_validation_error,
    read_yaml,
)
from dragd.vocabulary import Strict as _Strict  # (the models below keep their base's short name)

SYSTEM_CONFIG = Path("/etc/dragd/dragd.yaml")


class RobotConfig(_Strict):
    urdf: str = Field(default="seed_cobot", description="bundled robot name or URDF path (relative to the config file)")
    gravity_m_s2: tuple[Finite, Finite, Finite] = (0.0, 0.0, -9.81)


class BusConfig(_Strict):
    name: str = "arm"
    interface: str = "socketcan"  # socketcan, udp_multicast, virtual, or any python-can interface (pcan, kvaser, ...)
    channel: str = "can0"
    bitrate: PosInt = 1_000_000
    fd: bool = False
    data_bitrate: PosInt | None = None
    load_limit_pct: Annotated[float, Field(gt=0, le=100), Expect("a percentage in (0, 100]")] = 70.0
    # PDO layout (dragd/hardware/pdo.py): shared (a command frame shared by up to 8 joints on CAN FD), compact
    # (classic CAN, drag only, a shared torque frame), per_node (one SYNC RPDO per drive, no dummy entries), auto
    # (shared on CAN FD where every drive maps dummy entries, else per_node)
    layout: Literal["shared", "compact", "per_node", "auto"] = "shared"
    # per_node: the SYNC RPDO carries 607Ah target positions (CSP: identify run, replay, track); false: drag only
    position_targets: bool = True

    @model_validator(mode="after")
    def _fd_rate(self) -> BusConfig:
        import can

        if self.interface not in ("socketcan", "udp_multicast", "virtual") and \
                self.interface not in can.interfaces.VALID_INTERFACES:
            raise ValueError(f"interface: expected socketcan, udp_multicast, virtual or a python-can interface "
                             f"({', '.join(sorted(can.interfaces.VALID_INTERFACES))}), got '{self.interface}'")
        if self.fd and self.data_bitrate is None:
            raise ValueError("data_bitrate: expected the CAN FD data-phase bitrate when fd is true")
        return self


ObjectAddress = Annotated[str, Field(pattern=r"^\s*(0x)?[0-9A-Fa-f]{4}h?(\s*:\s*(0x)?[0-9A-Fa-f]{1,2}h?)?\s*$"),
                          Expect("an object address like 6078h or 30D1h:2 (index in hex, sub-index in decimal or "
                                 "hex with h)")]
CurrentUnit = Literal["permille_rated_current", "permille_rated_torque", "A", "dA", "cA", "mA", "uA"]


class CurrentObject(_Strict):
    """The object carrying the measured motor current in the drive's TPDO (docs/DRIVES.md "Current feedback")."""

    object: ObjectAddress = "6078h"
    # null: the CiA 402 unit of 6078h (per mille of the rated current) or 6077h (per mille of the rated torque);
    # a vendor object needs its unit
    unit: CurrentUnit | None = None


class RatedCurrentObject(_Strict):
    """Where the drive keeps the motor's rated current (6075h per CiA 402); object null: the drive has none, the
    joint's ``rated_current_A`` is used unverified."""

    object: ObjectAddress | None = "6075h"
    unit: Literal["A", "mA"] = "mA"


class RatedTorqueObject(_Strict):
    """Where the drive keeps the motor's rated torque (6076h per CiA 402; the unit of 6071h, 60B2h, 6077h); object
    null: the drive has none."""

    object: ObjectAddress | None = "6076h"
    unit: Literal["Nm", "mNm", "uNm"] = "mNm"
    write: bool = False  # a drive that reads 0 (not set) gets the configuration's rated torque written at boot
    # the drive's rated torque / rated current against the joint's K_m: apart by more than this is reported
    tolerance: Annotated[float, Field(gt=0, le=1), Expect("a fraction in (0, 1]")] = 0.05


class WatchdogObject(_Strict):
    """A vendor object that stops the drive when its command frames stop (where 1400h+k sub 5 is missing):
    ``safety.rpdo_timeout_ms`` is written to it in its unit."""

    object: ObjectAddress
    unit: Literal["ms", "us", "100us", "s"] = "ms"


class DriveConfig(_Strict):
    """A drive profile: the drive's EDS and what the EDS cannot say (docs/DRIVES.md). Joints name it by its key in
    ``drives``; a joint without ``drive`` has dragd's own joint drive (canopen_eds/joint_drive.eds)."""

    eds: str | None = None  # EDS file, relative to this configuration file; null: dragd's joint_drive.eds
    current: CurrentObject = CurrentObject()
    torque_command: Literal["60B2h", "6071h"] | None = None  # null: 60B2h where PDO-mappable, else 6071h
    # how the drive follows motions (identify run, replay, track): csp = its own position loop, dragd's feed-forward
    # in 60B2h; cst = dragd's position loop (replay.cst_*) + the feed-forward in the torque command, no mode switch.
    # null: csp where the command is 60B2h and the drive can do CSP, else cst (CiA 402 CSP ignores 6071h)
    motion_mode: Literal["csp", "cst"] | None = None
    rated_current: RatedCurrentObject = RatedCurrentObject()
    rated_torque: RatedTorqueObject = RatedTorqueObject()
    rpdo_watchdog: WatchdogObject | None = None
    # the drive's digital inputs (CiA 402 60FDh: bits 0-3 limit/home/interlock, 16-31 the manufacturer's), or a
    # vendor object that holds them (e.g. Wittenstein simco 3A13h:5): read where `inputs` name this drive's joint
    digital_inputs: ObjectAddress = "60FDh"


class FrictionConfig(_Strict):
    """Joint friction as motor current [A] (joint-side torque / K_t); negative-direction levels are negative."""

    coulomb_pos_A: NonNegFloat = 0.0
    coulomb_neg_A: NonPosFloat = 0.0
    static_pos_A: NonNegFloat | None = None  # None: equal to Coulomb (no Stribeck hump)
    static_neg_A: NonPosFloat | None = None
    stribeck_velocity_rad_s: PosFloat = 0.02
    stribeck_exponent: Annotated[float, Field(gt=0, le=4), Expect("a number in (0, 4] (seed 001: 1 or 2)")] = 2.0
    viscous_pos_A_s_per_rad: NonNegFloat = 0.0
    viscous_neg_A_s_per_rad: NonNegFloat = 0.0


class StartupConfig(_Strict):
    """Seed 001's start-up term f_s·sin(2πft) for a joint at rest, faded out as it starts moving."""

    amplitude_pos_A: NonNegFloat | None = None  # None: the joint's static friction level × law.startup_scale
    amplitude_neg_A: NonNegFloat | None = None
    frequency_Hz: Annotated[float, Field(gt=0, le=250), Expect("a frequency in (0, 250] Hz")] = 16.0
    rest_threshold_rad_s: PosFloat = 0.01  # Φ: |q̇| below it counts as rest
    fade_width_rad_s: PosFloat = 0.02  # the term fades to zero over [Φ, Φ + width]
    # break-out latch: crept this far from where it settled -> the sine is held at its peak that way (0: off;
    # None: 1.25 counts of the joint's encoder — one count of jitter never fires it, the second count of creep does)
    breakout_slip_rad: NonNegFloat | None = None
    breakout_hold_s: PosFloat = 0.1  # ... for at most this long (past Φ friction compensation takes over)
    settle_s: Annotated[float, Field(ge=0.005, le=10.0),
                        Expect("seconds in [0.005, 10] (at least the 5 ms blend)")] = 0.1
    # ... the latch re-arms after the joint has been still this long


class BackEmfConfig(_Strict):
    """Motor electrical constants for seed 000 eq. 26's back-EMF headroom term."""

    constant_V_s_per_rad: NonNegFloat = 0.0
    resistance_ohm: PosFloat = 1.0


class PeriodicTerm(_Strict):
    """One harmonic of a position-periodic current (cogging, gear ripple): sin_A·sin(c·q) + cos_A·cos(c·q)."""

    cycles_per_rev: PosFloat  # per joint revolution
    sin_A: Finite = 0.0
    cos_A: Finite = 0.0


class TemperatureDrift(_Strict):
    """Friction warm-up, t since start, g = 1 − e^(−t/τ): the Coulomb/Stribeck current × (1 + friction_change·g),
    the viscous current × (1 + viscous_change·g) — the lubricant's viscosity falls faster with temperature than the
    contact friction does; ``viscous_change`` null: the same change for both."""

    friction_change: Annotated[float, Field(gt=-0.95, lt=5), Expect("a relative change in (-0.95, 5)")]
    time_constant_s: PosFloat
    viscous_change: Annotated[float, Field(gt=-0.95, lt=5), Expect("a relative change in (-0.95, 5)")] | None = None


class BackEmfEffect(_Strict):
    """Current-loop voltage headroom: the delivered current falls short of the reported one above a knee speed,
    by A_s_per_rad·(|q̇| − knee)·sign q̇ (the law adds it; knee 0 = seed 000 eq. 26's linear term)."""

    A_s_per_rad: NonNegFloat
    knee_rad_s: NonNegFloat = 0.0


class JointEffects(_Strict):
    """Model-gap effects of one joint (``dragd gap``, docs/GAP.md); every default is "not in the model"."""

    position_periodic: list[PeriodicTerm] = Field(default_factory=list)
    load_friction_per_Nm: NonNegFloat = 0.0  # Coulomb/static levels grow by this × |gravity torque| (N·m per N·m)
    current_offset_A: Finite = 0.0  # reported − delivered current, constant (Hall offset)
    temperature_drift: TemperatureDrift | None = None
    back_emf: BackEmfEffect | None = None
    armature_kgm2: NonNegFloat | None = None  # inertia: rotor inertia at the joint (with the URDF's dynamics)
    backlash_rad: NonNegFloat | None = None  # play between rotor and output (simulation/prediction only)
    backlash_inertia_kgm2: NonNegFloat | None = None  # ... the rotor inertia on the motor side of it (joint side)
    # ... share of the joint's friction on the output side of the play (output bearing, seals)
    backlash_output_friction_fraction: Annotated[float, Field(ge=0, le=1), Expect("a fraction in [0, 1]")] | None = None
    # ... the drive's position loop on the output encoder [A/rad, A·s/rad] that moves the rotor through the play
    backlash_loop_A_per_rad: tuple[NonNegFloat, NonNegFloat] | None = None
    backlash_cutoff_Hz: PosFloat | None = None  # ... bandwidth of the loop-input estimate bridging the play's crossings


class Payload(_Strict):
    """A point mass on the flange (the last joint's frame) that the URDF does not have."""

    mass_kg: NonNegFloat
    com_m: tuple[Finite, Finite, Finite] = (0.0, 0.0, 0.0)


class LinkInertial(_Strict):
    """A link's identified inertial (``dragd identify fit --method full``): replaces the URDF's for that link."""

    mass_kg: PosFloat
    com_m: tuple[Finite, Finite, Finite]  # centre of mass in the link (joint) frame
    inertia_kgm2: tuple[Finite, Finite, Finite, Finite, Finite, Finite]  # ixx, ixy, ixz, iyy, iyz, izz about the COM

    @model_validator(mode="after")
    def _consistent(self) -> LinkInertial:
        import numpy as np

        xx, xy, xz, yy, yz, zz = self.inertia_kgm2
        e = np.linalg.eigvalsh(np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]]))
        tol = 1e-9 * max(1.0, float(np.abs(e).max()))
        if e.min() < -tol or any(e.sum() - 2 * v < -tol for v in e):
            moments = ", ".join(f"{v:.4g}" for v in e)
            raise ValueError("inertia_kgm2: expected a physically consistent inertia (principal moments ≥ 0 satisfying "
                             f"the triangle inequality a + b ≥ c), got principal moments {moments}")
        return self


class JointConfig(_Strict):
    name: str
    node_id: NodeId
    bus: str = "arm"
    drive: str | None = None  # a key of ``drives``; null: dragd's own joint drive (canopen_eds/joint_drive.eds)
    gear_ratio: PosFloat
    torque_constant_Nm_per_A: PosFloat | None = None  # joint side K_t
    motor_torque_constant_Nm_per_A: PosFloat | None = None  # K_m; then K_t = K_m · gear · efficiency
    gear_efficiency: Annotated[float, Field(gt=0, le=1), Expect("a number in (0, 1]")] = 1.0
    current_limit_A: PosFloat
    rated_current_A: PosFloat  # 6075h (or the drive profile's rated_current object)
    # 6076h, motor side; default K_m · rated current (then torque per mille = current per mille of rated_current_A)
    rated_torque_Nm: PosFloat | None = None
    encoder_counts_per_rev: PosInt  # per joint revolution
    encoder_offset_counts: int = 0  # counts at the URDF's zero
    direction: Literal[1, -1] = 1  # +1: drive's positive = URDF's positive
    position_limits_rad: tuple[Finite, Finite] | None = None  # soft limits; default: the URDF's
    velocity_limit_rad_s: PosFloat = 1.0  # drag speed cap
    drag_damping_Nm_s_per_rad: NonNegFloat = 1.0  # virtual damping in drag: the released arm comes to rest
    friction: FrictionConfig = FrictionConfig()
    startup: StartupConfig = StartupConfig()
    back_emf: BackEmfConfig = BackEmfConfig()
    effects: JointEffects = JointEffects()  # model-gap effects (docs/GAP.md)

    @model_validator(mode="after")
    def _kt(self) -> JointConfig:
        if (self.torque_constant_Nm_per_A is None) == (self.motor_torque_constant_Nm_per_A is None):
            raise ValueError("torque_constant_Nm_per_A: expected exactly one of torque_constant_Nm_per_A (joint side) "
                             "or motor_torque_constant_Nm_per_A (motor side, with gear_ratio)")
        if self.position_limits_rad is not None and self.position_limits_rad[0] >= self.position_limits_rad[1]:
            raise ValueError("position_limits_rad: expected [lower, upper] with lower < upper, "
                             f"got {list(self.position_limits_rad)}")
        slip, count = self.startup.breakout_slip_rad, self.rad_per_count
        if slip is not None and 0.0 < slip < count:
            raise ValueError(f"startup.breakout_slip_rad: expected 0 (off) or at least one encoder count "
                             f"({count:.3g} rad), got {slip}")
        return self

    @property
    def rad_per_count(self) -> float:
        """One encoder count (6064h) in joint radians."""
        return 2.0 * math.pi / self.encoder_counts_per_rev

    @property
    def breakout_slip_rad(self) -> float:
        """The break-out latch's slip distance [rad] (default 1.25 encoder counts; 0: off)."""
        slip = self.startup.breakout_slip_rad
        return 1.25 * self.rad_per_count if slip is None else slip

    @property
    def kt_Nm_per_A(self) -> float:
        """Joint-side torque constant: joint torque per ampere of motor current."""
        if self.torque_constant_Nm_per_A is not None:
            return self.torque_constant_Nm_per_A
        return self.motor_torque_constant_Nm_per_A * self.gear_ratio * self.gear_efficiency  # type: ignore[operator]

    @property
    def km_Nm_per_A(self) -> float:
        """Motor-side torque constant (6076h/6075h)."""
        return self.kt_Nm_per_A / (self.gear_ratio * self.gear_efficiency)

    @property
    def rated_torque_motor_Nm(self) -> float:
        return self.rated_torque_Nm if self.rated_torque_Nm is not None else self.km_Nm_per_A * self.rated_current_A


class LawConfig(_Strict):
    """Switches and shared shaping of the compensation law's terms."""

    gravity: bool = True
    friction: bool = True
    stribeck: bool = True
    startup: bool = True
    back_emf: bool = False
    damping: bool = True
    friction_smoothing_rad_s: PosFloat = 0.005  # tanh width of the zero crossing
    friction_deadband_rad_s: NonNegFloat = 0.0  # seed 000's v_lim: no friction compensation inside ±v_lim
    friction_scale: Annotated[float, Field(ge=0, le=1.2), Expect("a factor in [0, 1.2]")] = 0.95  # < 1: no run-away
    startup_scale: NonNegFloat = 0.9  # default start-up amplitude = scale × believed static friction level
    startup_waveform: Literal["sine", "square"] = "sine"  # square: the peers' dither, for comparison
    startup_handover: Literal["fade", "abrupt"] = "fade"  # abrupt: seed 001 eq. 28's switch at Φ, for comparison
    startup_breakout: bool = True  # the break-out latch (false: seed 001's velocity hand-over only)
    # the latch fires only where the sine's margin below static friction exceeds this fraction of |G|/K_t
    gravity_uncertainty: Annotated[float, Field(ge=0, le=1), Expect("a fraction in [0, 1]")] = 0.02
    velocity_filter_Hz: Annotated[float, Field(gt=0, le=500), Expect("a cutoff in (0, 500] Hz")] = 40.0


class LoopConfig(_Strict):
    rate_Hz: Annotated[float, Field(gt=0, le=4000), Expect("a rate in (0, 4000] Hz")] = 1000.0
    tpdo_deadline_us: PosInt = 600  # collect TPDOs until SYNC + this
    stale_cycles_hold: PosInt = 10  # an axis missing this many TPDOs in a row -> hold (feedback hold)
    stale_cycles_disable: PosInt = 50  # ... and this many -> disable all (fault)
    fresh_cycles_resume: PosInt = 100  # no axis stale > 1 cycle for this long after a feedback hold -> requested mode
    realtime_priority: Annotated[int, Field(ge=1, le=99), Expect("a SCHED_FIFO priority 1..99")] | None = None
    # with realtime_priority: mlockall(MCL_CURRENT | MCL_FUTURE) so page faults never stall the cycle (where
    # permitted: LimitMEMLOCK=infinity in the unit; 'dragd status' memory_locked says whether it applied)
    lock_memory: bool = True
    # with realtime_priority: every CPU's wake-up latency held to this many µs while the daemon runs (the kernel's
    # PM QoS, /dev/cpu_dma_latency); 0: idle CPUs poll instead of sleeping deeply, so the cycle's wake-ups start at
    # once with warm caches. Off (null) by default: idle CPUs then spin, and in a virtual machine a host may preempt
    # the busy vCPUs (docs/DECISIONS.md). 'dragd status' cpu_latency says whether it applied;
    # under systemd: systemd/dragd-cpu-latency.conf and systemd/70-dragd-cpu-latency.rules (docs/SYSTEMD.md)
    cpu_latency_us: Annotated[int, Field(ge=0, le=2_000_000_000)] | None = None
    cpus: list[Annotated[int, Field(ge=0)]] | None = None
    # the cycle's arithmetic by compiled kernels (numba: the drag law and its latch, dragd/control/fused.py; the
    # estimate and output steps, dragd/daemon/kernels.py); false: the numpy reference functions (the same results
    # to the last bits of exp/tanh/sin)
    compiled: bool = True


class GuardConfig(_Strict):
    """The gravity model will be wrong (docs/PAYLOAD.md): the check before drag and the runaway guard in it."""

    runaway: bool = True  # the runaway guard in drag
    observer_Hz: Annotated[float, Field(gt=0, le=200), Expect("a bandwidth in (0, 200] Hz")] = 10.0
    # the residual and speeds the decisions use are low-passed at this (velocity noise, late samples)
    decide_Hz: Annotated[float, Field(gt=0, le=100), Expect("a bandwidth in (0, 100] Hz")] = 8.0
    speed_rad_s: PosFloat = 0.03  # slower joints are not running away
    residual_A: PosFloat = 0.3  # smaller missing torques (as current) are friction's business
    confirm_s: Annotated[float, Field(ge=0, le=0.5), Expect("a time in [0, 0.5] s")] = 0.03
    keep_speed: Annotated[float, Field(gt=0, le=1), Expect("a fraction in (0, 1]")] = 0.85
    unexplained_max: Annotated[float, Field(gt=0, le=1), Expect("a fraction in (0, 1]")] = 0.1
    # a runaway's residual drives the arm: r·q̇ at least this share of Σ|r_j·q̇_j| (else a braking hand's)
    drive_share: Annotated[float, Field(ge=-1, le=1), Expect("a share in [-1, 1]")] = 0.5
    hold_ramp_s: Annotated[float, Field(ge=0, le=1), Expect("a time in [0, 1] s")] = 0.02  # drag → hold on a trip
    # check before drag: |hold current − G/K_t| may exceed the joint's static friction by this much (+ a fraction)
    check: bool = True
    check_tolerance_A: NonNegFloat = 0.3
    check_tolerance_fraction: Annotated[float, Field(ge=0, le=1), Expect("a fraction in [0, 1]")] = 0.1
    check_settle_s: PosFloat = 0.3  # the hold current is averaged over this long at rest


class SafetyConfig(_Strict):
    soft_limit_margin_rad: PosFloat = 0.1  # walls start this far inside the position limits
    wall_stiffness_Nm_per_rad: PosFloat = 200.0
    wall_damping_Nm_s_per_rad: NonNegFloat = 10.0
    speed_cap_damping_Nm_s_per_rad: NonNegFloat = 20.0
    hold_kp_Nm_per_rad: PosFloat = 300.0
    hold_kd_Nm_s_per_rad: NonNegFloat = 15.0
    mode_ramp_s: PosFloat = 0.2  # blend time between modes' command laws
    rpdo_timeout_ms: PosInt = 50  # drive-side watchdog on the cyclic command RPDO (1400h+k sub 5)
    abort_connection_option: Literal[1, 2, 3] = 3  # 6007h: 1 fault, 2 disable voltage, 3 quick stop
    quick_stop_option: Literal[0, 1, 2, 5, 6] = 2  # 605Ah
    guard: GuardConfig = GuardConfig()  # the runaway guard in drag and the gravity check before it (docs/PAYLOAD.md)
    # a position sample further from the last accepted one than this speed allows is an encoder fault (rejected)
    encoder_plausible_speed_rad_s: PosFloat = 6.0
    # a commanded motion (track, identify run, replay) accelerating harder than this on any joint is refused
    track_acceleration_limit_rad_s2: PosFloat = 20.0


class MasterConfig(_Strict):
    """The CANopen master's own parameters."""

    node_id: NodeId = 127  # the master's heartbeat COB-ID is 0x700 + node_id
    heartbeat_ms: PosInt = 100  # master heartbeat producer period
    heartbeat_consumer_ms: PosInt = 300  # drives' 1016h: master heartbeat loss after this long
    drive_heartbeat_ms: PosInt = 100  # drives' 1017h
    boot_timeout_s: PosFloat = 5.0
    enable_timeout_s: PosFloat = 1.0  # CiA 402 walk to operation enabled
    sdo_timeout_s: PosFloat = 0.3


class TelemetryConfig(_Strict):
    path: str | None = None
    capacity_rows: PosInt = 8192
    max_file_MiB: PosInt = 512  # rotate the MCAP file beyond this size
    keep_rotated: PosInt = 20
    rerun: bool = False
    # size: write every N-th cycle row to /dragd/cycle (1 = every cycle; record windows always keep every cycle)
    cycle_decimation: PosInt = 1
    # Foxglove's well-known channels beside /dragd/cycle (joint states, link transforms, logs, the URDF)
    foxglove: bool = True
    foxglove_rate_Hz: Annotated[float, Field(gt=0, le=1000), Expect("a rate in (0, 1000] Hz")] = 30.0
    # their encoding: json (Foxglove's schemas) or ros2 (CDR, standard ROS 2 types: sensor_msgs/JointState, tf2_msgs,
    # rcl_interfaces/Log on /rosout; docs/ROS2.md)
    foxglove_encoding: Literal["json", "ros2"] = "json"
    # how often the daemon hands the ring's rows to its writer process: each hand-over takes the GIL from the cycle
    # for a moment (at 50 Hz the demo's period p99 was 1090-1160 us, at 4 Hz 1040-1060 us)
    forward_interval_s: Annotated[float, Field(gt=0, le=2.0), Expect("an interval in (0, 2] s")] = 0.25


class ControlConfig(_Strict):
    socket: str = "/run/dragd/dragd.sock"
    # folders the socket's requests may read/write files in (record, track, teach/replay program paths); relative:
    # to this file. Default: replay.program_dir, the telemetry folder, /var/lib/dragd, the temporary folder
    allowed_dirs: list[str] | None = None
    # where clients (operators in group dragd) leave trajectory files for the daemon, e.g. 'dragd identify run': the
    # systemd unit's PrivateTmp gives the daemon its own /tmp (systemd/dragd.tmpfiles.conf creates it 2770)
    spool_dir: str = "/var/lib/dragd/spool"


PerJoint = PosFloat | list[PosFloat]  # one value for every joint, or a list with one per joint


class ReplayConfig(_Strict):
    """Teach and replay (dragd/teach, docs/TEACH.md): recording, replay limits, the monitors during replay."""

    program_dir: str = "/var/lib/dragd/programs"  # taught programs (NAME.yaml + NAME.mcap); relative: to this file
    record_rate_Hz: Annotated[float, Field(gt=0, le=1000), Expect("a rate in (0, 1000] Hz")] = 50.0
    max_record_s: PosFloat = 1800.0  # recorder capacity (preallocated)
    frame: str = "tool0"  # the frame of circular moves and TCP speed limits
    velocity_limits_rad_s: PerJoint | None = None  # default: joints[].velocity_limit_rad_s (and the URDF's)
    acceleration_limits_rad_s2: PerJoint = 2.0
    jerk_limits_rad_s3: PerJoint = 20.0
    cartesian_speed_m_s: PosFloat = 0.5  # TCP speed limit of every replayed move
    cartesian_acceleration_m_s2: PosFloat = 2.0
    move_to_start_speed: Annotated[float, Field(gt=0, le=1), Expect("a fraction in (0, 1]")] = 0.25
    settle_s: NonNegFloat = 0.4  # dwell at every stop (point-to-point waypoints, end of a cycle)
    keyframe_tolerance_rad: PosFloat = 0.0087  # keyframes of a continuous recording keep the path within this
    inertia_feedforward: bool = True  # M(q)q̈ + C(q,q̇)q̇ of the planned motion in the CSP torque offset
    # the daemon's position loop around the drives' CSP loops during a replay (in the torque offset): stiffness
    # and damping against what the feed-forward misses (friction and torque-constant beliefs); 0 = the drive's only
    # (the defaults suit a light wrist joint; config/default.yaml tunes them per joint for the seed cobot)
    position_kp_Nm_per_rad: NonNegFloat | list[NonNegFloat] = 300.0
    position_kd_Nm_s_per_rad: NonNegFloat | list[NonNegFloat] = 3.0
    position_ki_Nm_per_rad_s: NonNegFloat | list[NonNegFloat] = 600.0  # only while the joint's reference moves
    position_integral_limit_A: NonNegFloat | list[NonNegFloat] = 0.3
    position_output_limit_A: NonNegFloat | list[NonNegFloat] = 0.6  # the loop's authority (P + D + I)
    # the daemon's position loop of the joints whose drives follow motions in CST (drives.X.motion_mode: cst): their
    # only position loop, with the model's feed-forward; the integral learns what the model misses (friction) while
    # the reference moves and the error is within half the tracking bound, and fades at rest
    cst_kp_Nm_per_rad: NonNegFloat | list[NonNegFloat] = 300.0
    cst_kd_Nm_s_per_rad: NonNegFloat | list[NonNegFloat] = 15.0
    cst_ki_Nm_per_rad_s: NonNegFloat | list[NonNegFloat] = 1500.0
    cst_integral_limit_A: NonNegFloat | list[NonNegFloat] = 1.0
    ramp_s: PosFloat = 0.4  # pause / resume / stop / speed-override changes (longer when the path is fast)
    tracking_error_limit_rad: PerJoint = 0.035  # |q - q_ref| beyond this stops the motion (hold)
    residual_current_limit_A: PerJoint = 2.0  # |measured - predicted current| beyond this stops the motion
    residual_filter_Hz: Annotated[float, Field(gt=0, le=500), Expect("a cutoff in (0, 500] Hz")] = 10.0
    monitor_cycles: PosInt = 20  # a monitor must see its bound exceeded this many cycles in a row


# --- contact detection (docs/CONTACT.md); the bands themselves are calibrated into the params file ------------------


class ContactModeConfig(_Strict):
    """Contact detection in one mode: how sensitive (the calibrated bands / sensitivity) and what the arm does."""

    sensitivity: Annotated[float, Field(gt=0, le=4), Expect("a factor in (0, 4] (1: the calibrated bands; 2: half "
                                                             "as wide)")] = 1.0
    # stop: protective stop, the arm held where it is (drives enabled); retract: back off along the residual by
    # retract_rad at most, then hold; compliant: drag under the hand where drag is permitted now (else stop)
    reaction: Literal["stop", "retract", "compliant"] = "stop"


class GripConfig(_Strict):
    """Where the operator's hand holds the arm: the point whose wrench the drag residual estimates (docs/CONTACT.md)."""

    frame: str = "tool0"  # a frame of the URDF (a link or joint name); the last joint's where there is no tool0
    offset_m: tuple[Finite, Finite, Finite] = (0.0, 0.0, 0.0)  # the grip point in that frame
    # a resting joint's equation in the hand's force, relative to a moving one's: its residual is uncertain by its
    # static friction (~1.4-3 N·m on the seed cobot), a moving joint's by the identified model's error (~0.1 N·m)
    rest_weight: Annotated[float, Field(gt=0, le=1), Expect("a weight in (0, 1]")] = 0.03


class ContactConfig(_Strict):
    """The model-based contact detector (dragd/control/contact.py) in the modes where the arm moves by itself or is
    held; its per-joint bands come from ``dragd contact calibrate`` (the params file's ``contact``)."""

    enabled: bool = True
    hold: ContactModeConfig = ContactModeConfig()
    track: ContactModeConfig = ContactModeConfig()  # replay, `dragd track`, streams
    identify: ContactModeConfig = ContactModeConfig()  # `dragd identify run`
    # retract: the largest joint displacement [rad] and the speed of the hold pose's move
    retract_rad: Annotated[float, Field(gt=0, le=0.2), Expect("radians in (0, 0.2]")] = 0.03
    retract_speed_rad_s: Annotated[float, Field(gt=0, le=1.0), Expect("rad/s in (0, 1]")] = 0.15
    # the protective stop of a motion (every reaction begins with it): from the arm's state at the detection to rest,
    # every joint together, deceleration and jerk bounded per joint (docs/CONTACT.md "Reactions")
    stop_deceleration_rad_s2: PerJoint = 10.0
    stop_jerk_rad_s3: PerJoint = 1000.0
    grip: GripConfig = GripConfig()  # the hand's wrench in drag (status, telemetry, the live view)
    wrench_Hz: Annotated[float, Field(gt=0, le=100), Expect("a cutoff in (0, 100] Hz")] = 5.0  # its low-pass


# --- end of contact detection --------------------------------------------------------------------------------------


class StreamConfig(_Strict):
    """Position streams into TRACK (the control socket's ``stream`` commands, the ROS 2 bridge): docs/ROS2.md."""

    # the playback lags the newest sample by this: the jitter a stream may have before the arm slows down
    delay_s: Annotated[float, Field(ge=0.005, le=1.0), Expect("seconds in [0.005, 1]")] = 0.05
    # no sample for this long (the cycle's time): the stream ends into HOLD at the last sample. The arm has stopped
    # there already (running dry within delay_s); a stream whose samples pause for less resumes
    timeout_s: Annotated[float, Field(gt=0, le=2.0), Expect("seconds in (0, 2]")] = 0.5
    # a sample further ahead of the playback than this is refused (a sender's clock that jumped)
    max_lead_s: Annotated[float, Field(gt=0, le=4.0), Expect("seconds in (0, 4]")] = 1.0
    # the playback rate stays within 1 ± this while it keeps delay_s (clock drift between sender and daemon)
    catch_up: Annotated[float, Field(ge=0, le=0.5), Expect("a fraction in [0, 0.5]")] = 0.1


# --- drag permission and the hand's inputs (#30; docs/HAND.md) ------------------------------------------------------

InputBit = Annotated[int, Field(ge=0, le=63, strict=True), Expect("a bit number 0..63 of the drive's inputs object")]


class HandInput(_Strict):
    """One input at the hand, wired to a digital input of a joint's drive (60FDh, or ``drives.X.digital_inputs``)."""

    function: Literal["enable", "mark", "stop", "teach"]
    joint: str  # the joint whose drive reads the contact (a name of ``joints``)
    bit: InputBit
    # enable only: the second channel of a two-channel enabling switch (both must agree; ISO 13849 category 3)
    second_bit: InputBit | None = None
    # enable only: the contact of the squeezed (panic, position 3) position, where the device reports it
    panic_bit: InputBit | None = None
    active: Literal["high", "low"] = "high"  # low: a normally-closed contact (a stop wire that breaks stops)
    name: str | None = None  # a label for status and events (default: the function)

    @model_validator(mode="after")
    def _bits(self) -> HandInput:
        if self.function != "enable" and (self.second_bit is not None or self.panic_bit is not None):
            raise ValueError(f"second_bit, panic_bit: expected only on an 'enable' input, got them on "
                             f"'{self.function}'")
        bits = [b for b in (self.bit, self.second_bit, self.panic_bit) if b is not None]
        if len(set(bits)) != len(bits):
            raise ValueError(f"bit, second_bit, panic_bit: expected different bits, got {bits}")
        return self

    @property
    def label(self) -> str:
        return self.name or self.function

    @property
    def bits(self) -> list[int]:
        """Every bit the input reads (channels, then the panic contact)."""
        return [b for b in (self.bit, self.second_bit, self.panic_bit) if b is not None]


class HandConfig(_Strict):
    """The guiding device's inputs and how they are judged (docs/HAND.md)."""

    inputs: list[HandInput] = Field(default_factory=list)
    # a press counts once the contact has been steady this long (a release, a stop and a panic act at once)
    debounce_ms: Annotated[float, Field(ge=0, le=100), Expect("milliseconds in [0, 100]")] = 5.0
    # the two channels of an enabling switch may disagree this long (contact travel) before it is a fault
    discrepancy_ms: Annotated[float, Field(gt=0, le=1000), Expect("milliseconds in (0, 1000]")] = 50.0
    # more edges than chatter_edges within chatter_window_ms: a chattering contact (faulted until `start`)
    chatter_edges: Annotated[int, Field(ge=2, le=1000), Expect("a number of edges >= 2")] = 8
    chatter_window_ms: Annotated[float, Field(gt=0, le=10000), Expect("milliseconds in (0, 10000]")] = 200.0
    # where the inputs ride in an event TPDO of their own: its keep-alive (event timer) and inhibit time
    event_timer_ms: Annotated[int, Field(ge=1, le=100), Expect("milliseconds in [1, 100]")] = 10
    event_inhibit_ms: Annotated[int, Field(ge=1, le=20), Expect("milliseconds in [1, 20]")] = 2
    # the inputs count as lost (not enabled, stop pressed) once their TPDO is this late: null: the cyclic feedback's
    # loop.stale_cycles_hold periods, or 2.5 event timers for an event TPDO
    lost_after_ms: Annotated[float, Field(gt=0, le=1000), Expect("milliseconds in (0, 1000]")] | None = None


class DragConfig(_Strict):
    """What DRAG requires (docs/HAND.md): the enabling switch held, a client's lease, both, or (lab only) nothing."""

    # none: only with `dragd run --lab-unguarded-drag` (a lab's flag; status reports it)
    require: Literal["enable_input", "lease", "both", "none"] = "lease"
    # a software client's lease: renewed at least this often, else drag ends into HOLD (a client may ask for less)
    lease_s: Annotated[float, Field(ge=0.05, le=10.0), Expect("seconds in [0.05, 10]")] = 0.5
    # the blend from the drag law to the hold when drag ends (release, stop, a lapsed lease): short, so the arm is
    # held within a fraction of a degree, and not zero, so the current does not jump
    exit_ramp_s: Annotated[float, Field(ge=0.002, le=0.2), Expect("seconds in [0.002, 0.2]")] = 0.02
    # the brake when drag ends: the hold's damping this strong, its pose following the arm, until the arm rests
    # (every joint below 0.01 rad/s) or exit_brake_s passed; then the hold's own stiffness where the arm came to rest.
    # A moving arm stops in about |q̇|·J/exit_damping (J: the joint's inertia) instead of springing back through its
    # pose; a hand that keeps pushing meets the hold's stiffness (docs/HAND.md)
    # (per joint; null: five times replay.position_kd_Nm_s_per_rad, the arm's own tuning to its joints' inertia)
    exit_damping_Nm_s_per_rad: NonNegFloat | list[NonNegFloat] | None = None
    exit_brake_s: Annotated[float, Field(ge=0, le=1.0), Expect("seconds in [0, 1]")] = 0.15

# --- end of drag permission and the hand's inputs -------------------------------------------------------------------


class Config(_Strict):
    robot: RobotConfig = RobotConfig()
    params: str | None = None  # identified-parameters file, relative to the config file
    buses: list[BusConfig] = Field(default_factory=lambda: [BusConfig()])
    drives: dict[str, DriveConfig] = Field(default_factory=dict)  # drive profiles by name (docs/DRIVES.md)
    joints: list[JointConfig]
    law: LawConfig = LawConfig()
    loop: LoopConfig = LoopConfig()
    safety: SafetyConfig = SafetyConfig()
    master: MasterConfig = MasterConfig()
    telemetry: TelemetryConfig = TelemetryConfig()
    control: ControlConfig = ControlConfig()
    replay: ReplayConfig = ReplayConfig()
    stream: StreamConfig = StreamConfig()
    payload: Payload | None = None  # flange payload not in the URDF (docs/GAP.md)
    inertials: dict[str, LinkInertial] | None = None  # identified link inertials over the URDF's (docs/MODEL.md)
    contact: ContactConfig = ContactConfig()  # contact detection (docs/CONTACT.md)
    drag: DragConfig = DragConfig()  # what drag requires: enabling switch, lease (docs/HAND.md)
    hand: HandConfig = HandConfig()  # the guiding device's inputs at the hand (docs/HAND.md)
    source: str = Field("<memory>", exclude=True)  # file it came from (not a YAML key)
    # from the params file (not YAML keys of the configuration): the contact detector's calibrated bands and the
    # identified rotor inertias [kg·m²] by joint (notes.armature_kgm2)
    contact_calibration: Any = Field(None, exclude=True)
    armature_kgm2: dict[str, float] | None = Field(None, exclude=True)

    @model_validator(mode="after")
    def _cross(self) -> Config:
        names = [j.name for j in self.joints]
        twice = sorted({n for n in names if names.count(n) > 1})
        if twice:
            raise ValueError(f"joints: expected each of the URDF's joint names once, got {', '.join(twice)} twice")
        bus_names = [b.name for b in self.buses]
        if len(set(bus_names)) != len(bus_names):
            raise ValueError(f"buses: expected unique bus names, got {bus_names}")
        for i, j in enumerate(self.joints):
            if j.bus not in bus_names:
                raise ValueError(f"joints[{i}].bus: expected one of the buses {bus_names}, got '{j.bus}'")
            if j.drive is not None and j.drive not in self.drives:
                raise ValueError(f"joints[{i}].drive: expected one of the drives {sorted(self.drives)} (the keys of "
                                 f"'drives'), got '{j.drive}'")
        seen: dict[tuple[str, int], str] = {}
        for j in self.joints:
            key = (j.bus, j.node_id)
            if key in seen:
                raise ValueError(f"joints: {j.name} and {seen[key]} share node id {j.node_id} on bus '{j.bus}'")
            seen[key] = j.name
        self._cross_timing()
        self._cross_hand(names)
        if self.stream.max_lead_s <= self.stream.delay_s:
            raise ValueError(f"stream.max_lead_s: expected more than stream.delay_s ({self.stream.delay_s:g} s), got "
                             f"{self.stream.max_lead_s:g}")
        r = self.replay
        for name in ("velocity_limits_rad_s", "acceleration_limits_rad_s2", "jerk_limits_rad_s3",
                    "tracking_error_limit_rad", "residual_current_limit_A", "position_kp_Nm_per_rad",
                    "position_kd_Nm_s_per_rad", "position_ki_Nm_per_rad_s", "position_integral_limit_A",
                    "position_output_limit_A", "cst_kp_Nm_per_rad", "cst_kd_Nm_s_per_rad", "cst_ki_Nm_per_rad_s",
                    "cst_integral_limit_A"):
            v = getattr(r, name)
            if isinstance(v, list) and len(v) != len(self.joints):
                raise ValueError(f"replay.{name}: expected one value or {len(self.joints)} (one per joint), "
                                 f"got {len(v)}")
        return self

    def _cross_timing(self) -> None:
        """Timing and node-id combinations that would leave an arm unwatched or fault it for nothing."""
        m, s, lp = self.master, self.safety, self.loop
        period_ms = 1000.0 / lp.rate_Hz
        if m.heartbeat_consumer_ms < 2 * m.heartbeat_ms:
            raise ValueError(f"master.heartbeat_consumer_ms: expected >= 2 x master.heartbeat_ms "
                             f"({2 * m.heartbeat_ms} ms: one lost heartbeat must not stop the drives), "
                             f"got {m.heartbeat_consumer_ms}")
        if m.heartbeat_consumer_ms > 5000:
            raise ValueError(f"master.heartbeat_consumer_ms: expected <= 5000 ms (a dead master must stop the drives "
                             f"within seconds), got {m.heartbeat_consumer_ms}")
        lo_ms = max(5.0, 3.0 * period_ms)
        if not lo_ms <= s.rpdo_timeout_ms <= 1000:
            raise ValueError(f"safety.rpdo_timeout_ms: expected {lo_ms:g}..1000 ms (at least 3 cycles of "
                             f"{period_ms:g} ms, at most 1 s of an unwatched arm), got {s.rpdo_timeout_ms}")
        if lp.tpdo_deadline_us >= period_ms * 1000.0:
            raise ValueError(f"loop.tpdo_deadline_us: expected below the cycle period {period_ms * 1000.0:g} us "
                             f"(loop.rate_Hz {lp.rate_Hz:g}), got {lp.tpdo_deadline_us}")
        tc = self.telemetry
        if tc.capacity_rows < 2 * lp.rate_Hz * tc.forward_interval_s:
            least = math.ceil(2 * lp.rate_Hz * tc.forward_interval_s)
            raise ValueError(f"telemetry.capacity_rows: expected at least {least} "
                             f"(two hand-overs of telemetry.forward_interval_s {tc.forward_interval_s:g} s at "
                             f"loop.rate_Hz {lp.rate_Hz:g}: a smaller ring drops rows), got {tc.capacity_rows}")
        if m.drive_heartbeat_ms > 1000:
            raise ValueError(f"master.drive_heartbeat_ms: expected <= 1000 ms (the daemon consumes the drives' "
                             f"heartbeats: a silent drive must be noticed within seconds), got {m.drive_heartbeat_ms}")
        for i, j in enumerate(self.joints):
            if j.velocity_limit_rad_s >= s.encoder_plausible_speed_rad_s:
                raise ValueError(f"safety.encoder_plausible_speed_rad_s: expected above every joint's "
                                 f"velocity_limit_rad_s, got {s.encoder_plausible_speed_rad_s} <= joints[{i}] "
                                 f"({j.name}) {j.velocity_limit_rad_s}")
            if j.node_id == m.node_id:
                raise ValueError(f"master.node_id: expected a node id no drive uses, got {m.node_id} "
                                 f"= joints[{i}] ({j.name}).node_id")

    def _cross_hand(self, names: list[str]) -> None:
        """The hand's inputs against the joints and what drag requires (the drives' objects: dragd/hardware/plan.py)."""
        seen: dict[tuple[str, int], str] = {}
        for i, inp in enumerate(self.hand.inputs):
            if inp.joint not in names:
                raise ValueError(f"hand.inputs[{i}].joint: expected one of the joints {', '.join(names)}, got "
                                 f"'{inp.joint}'")
            for b in inp.bits:
                key = (inp.joint, b)
                if key in seen:
                    raise ValueError(f"hand.inputs[{i}] ({inp.label}): {inp.joint} bit {b} is already "
                                     f"{seen[key]}'s; expected each bit wired to one input")
                seen[key] = f"hand.inputs[{i}] ({inp.label})"
        enables = [i for i, inp in enumerate(self.hand.inputs) if inp.function == "enable"]
        if len(enables) > 1:
            raise ValueError(f"hand.inputs: expected at most one 'enable' input (one enabling switch; two contacts "
                             f"are its second_bit), got {len(enables)} (inputs {enables})")
        kd = self.drag.exit_damping_Nm_s_per_rad
        if isinstance(kd, list) and len(kd) != len(names):
            raise ValueError(f"drag.exit_damping_Nm_s_per_rad: expected one value or {len(names)} (one per joint: "
                             f"{', '.join(names)}), got {len(kd)}")
        req = self.drag.require
        if req in ("enable_input", "both") and not enables:
            raise ValueError(f"drag.require: '{req}' needs an enabling switch: expected a hand.inputs entry with "
                             "function: enable")
        if req in ("lease", "none") and enables:
            raise ValueError(f"drag.require: expected 'enable_input' or 'both' with an enabling switch wired "
                             f"(hand.inputs[{enables[0]}]), got '{req}' (an enabling switch that does not end drag "
                             "would be a false promise)")

    def per_joint(self, value: float | list[float]) -> list[float]:
        """A ``PerJoint`` setting as one value per joint."""
        return list(value) if isinstance(value, list) else [float(value)] * len(self.joints)

    @property
    def program_dir(self) -> Path:
        p = Path(self.replay.program_dir).expanduser()
        return p if p.is_absolute() else self.base_dir / p

    @property
    def joint_names(self) -> list[str]:
        return [j.name for j in self.joints]

    @property
    def base_dir(self) -> Path:
        return Path(self.source).resolve().parent if self.source != "<memory>" else Path.cwd()

    def bus(self, name: str) -> BusConfig:
        return next(b for b in self.buses if b.name == name)

    def drive_of(self, joint: int) -> DriveConfig:
        """The drive profile of ``joints[joint]`` (dragd's own joint drive where it names none)."""
        name = self.joints[joint].drive
        return self.drives[name] if name is not None else DriveConfig()

    def eds_of(self, joint: int) -> Path:
        """The EDS file of ``joints[joint]``'s drive (relative paths: to this configuration file)."""
        eds = self.drive_of(joint).eds
        if eds is None:
            from dragd.resources import eds_path

            return eds_path()
        p = Path(eds).expanduser()
        return p if p.is_absolute() else self.base_dir / p


# ----------------------------------------------------------------------------------------------- params


class FrictionParams(_Strict):
    """Identified friction of one joint (amperes); a None value was not identifiable and keeps the config's."""

    coulomb_pos_A: NonNegFloat | None = None
    coulomb_neg_A: NonPosFloat | None = None
    viscous_A_s_per_rad: NonNegFloat | None = None  # one viscous slope for both directions
    viscous_pos_A_s_per_rad: NonNegFloat | None = None
    viscous_neg_A_s_per_rad: NonNegFloat | None = None
    static_pos_A: NonNegFloat | None = None
    static_neg_A: NonPosFloat | None = None
    stribeck_velocity_rad_s: PosFloat | None = None
    stribeck_exponent: PosFloat | None = None


class StartupParams(_Strict):
    frequency_Hz: Annotated[float, Field(gt=0, le=250)] | None = None
    amplitude_pos_A: NonNegFloat | None = None
    amplitude_neg_A: NonNegFloat | None = None


class JointParams(_Strict):
    torque_constant_Nm_per_A: PosFloat | None = None
    friction: FrictionParams = FrictionParams()
    startup: StartupParams = StartupParams()
    std: dict[str, Any] = Field(default_factory=dict)  # standard deviations, reasons for nulls
    effects: JointEffects = JointEffects()  # model-gap effects added by `dragd gap` (docs/GAP.md)


class ContactJointBands(_Strict):
    """One joint's contact-detection bands [A] (``dragd contact calibrate``; docs/CONTACT.md)."""

    base_A: NonNegFloat
    slow_A: NonNegFloat
    speed_A_s_per_rad: NonNegFloat
    accel_A_s2_per_rad: NonNegFloat
    slow_speed_rad_s: PosFloat
    settling_A: PosFloat
    held_A: PosFloat
    held_moving_A: NonNegFloat = 0.0


class ContactParams(_Strict):
    """The contact detector's calibration: the observer gain its bands hold for, the bands per joint, how."""

    observer_gain_per_s: PosFloat
    margin: PosFloat  # every calibration sample's deviation ≤ band / margin
    joints: dict[str, ContactJointBands]
    calibration: dict[str, Any] = Field(default_factory=dict)  # logs, left-out windows, per-joint maxima


class ParamsFile(_Strict):
    version: Literal[1] = 1
    method: str | None = None
    robot: str | None = None
    joints: dict[str, JointParams] = Field(default_factory=dict)
    payload: Payload | None = None  # added by `dragd gap` (payload_mass)
    inertials: dict[str, LinkInertial] | None = None  # URDF link name → identified inertial (docs/MODEL.md)
    contact: ContactParams | None = None  # contact-detection bands (`dragd contact calibrate`, docs/CONTACT.md)
    notes: dict[str, Any] = Field(default_factory=dict)


# ----------------------------------------------------------------------------------------------- the robot


def robot_joint_names(cfg: Config) -> tuple[tuple[str, ...], Path]:
    """The joint names of the configuration's robot (URDF order) and its URDF file; ConfigError if unloadable."""
    from dragd.model import RobotModel

    try:
        model = RobotModel.from_urdf(cfg.robot.urdf, cfg.base_dir)
    except (FileNotFoundError, ValueError) as exc:
        raise ConfigError(f"{cfg.source}: robot.urdf: {exc}") from None
    return model.joint_names, model.urdf_path or Path(cfg.robot.urdf)


def check_joint_names(cfg: Config, robot: tuple[tuple[str, ...] | list[str], Path | str]) -> None:
    """Raise ConfigError unless ``joints[].name`` are the robot's joint names in the URDF's order.

    ``robot``: (the URDF's joint names, the URDF file), as :func:`robot_joint_names` returns them.
    """
    names, urdf = list(robot[0]), robot[1]
    got = cfg.joint_names
    if got == names:
        return
    unknown = [n for n in got if n not in names]
    missing = [n for n in names if n not in got]
    what = "; ".join(x for x in (f"unknown {', '.join(unknown)}" if unknown else "",
                                 f"missing {', '.join(missing)}" if missing else "",
                                 "out of order" if not unknown and not missing else "") if x)
    raise ConfigError(f"{cfg.source}: joints[].name: expected the robot's joints {', '.join(names)} in this order "
                      f"(from {urdf}), got {', '.join(got)} ({what})")


# ----------------------------------------------------------------------------------------------- loading


def default_config_path() -> Path:
    """``$DRAGD_CONFIG``, else /etc/dragd/dragd.yaml if present, else the repository's config/default.yaml."""
    env = os.environ.get("DRAGD_CONFIG")
    if env:
        return Path(env)
    if SYSTEM_CONFIG.is_file():
        return SYSTEM_CONFIG
    from dragd.resources import config_path

    return config_path("default.yaml")


def load_params(path: str | Path) -> ParamsFile:
    path = Path(path)
    data = read_yaml(path)
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping with 'joints', got {type(data).__name__}")
    try:
        return ParamsFile.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(format_validation_error(str(path), ParamsFile, exc)) from None


def save_params(params: ParamsFile, path: str | Path) -> None:
    """Write a params file (YAML), the format ``load_config`` overlays and the simulator reads."""
    from dragd.atomic import write_atomic

    data = params.model_dump(mode="json", exclude_none=False)
    write_atomic(path, yaml.safe_dump(data, sort_keys=False))  # temp + fsync + rename: never half a params file


def apply_params(cfg: Config, params: ParamsFile, source: str = "params") -> Config:
    """Return a new Config with identified values overriding the configured ones (None keeps the config's)."""
    by_name = {j.name: j for j in cfg.joints}
    unknown = sorted(set(params.joints) - set(by_name))
    if unknown:
        raise ConfigError(f"{source}: joints: expected joint names among {', '.join(by_name)}, "
                          f"got {', '.join(unknown)}")
    joints = []
    for j in cfg.joints:
        p = params.joints.get(j.name)
        if p is None:
            joints.append(j)
            continue
        update: dict[str, Any] = {}
        if p.torque_constant_Nm_per_A is not None:
            update["torque_constant_Nm_per_A"] = p.torque_constant_Nm_per_A
            update["motor_torque_constant_Nm_per_A"] = None
        fr = {k: v for k, v in p.friction.model_dump().items() if v is not None}
        if "viscous_A_s_per_rad" in fr:
            v = fr.pop("viscous_A_s_per_rad")
            fr.setdefault("viscous_pos_A_s_per_rad", v)
            fr.setdefault("viscous_neg_A_s_per_rad", v)
        if fr:
            update["friction"] = j.friction.model_copy(update=fr)
        st = {k: v for k, v in p.startup.model_dump().items() if v is not None}
        if st:
            update["startup"] = j.startup.model_copy(update=st)
        if p.effects != JointEffects():
            update["effects"] = p.effects
        joints.append(j.model_copy(update=update))
    # revalidate the result so the overlay can't produce an invalid joint
    data = cfg.model_dump(mode="python")
    data["joints"] = [jj.model_dump(mode="python") for jj in joints]
    if params.payload is not None:
        data["payload"] = params.payload.model_dump(mode="python")
    if params.inertials:
        data["inertials"] = {k: v.model_dump(mode="python") for k, v in params.inertials.items()}
    try:
        out = Config.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(format_validation_error(source, Config, exc)) from None
    arm = (params.notes or {}).get("armature_kgm2")
    armature = ({k: float(v) for k, v in arm.items() if k in by_name and v is not None} if isinstance(arm, dict)
                else cfg.armature_kgm2)
    return out.model_copy(update={"source": cfg.source, "armature_kgm2": armature or None,
                                  "contact_calibration": params.contact if params.contact is not None
                                  else cfg.contact_calibration})


def load_config(path: str | Path | None = None, params: str | Path | None = None, robot: bool = True) -> Config:
    """Load and validate a configuration file; overlay its ``params`` file, or ``params`` when given.

    ``robot``: check ``joints[].name`` against the robot's URDF (:func:`check_joint_names`).
    """
    path = Path(path) if path is not None else default_config_path()
    data = read_yaml(path)
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping of sections (robot, buses, joints, ...), "
                          f"got {type(data).__name__}")
    if "source" in data:
        raise ConfigError(f"{path}: source: unknown key")
    try:
        cfg = Config.model_validate({**data, "source": str(path)})
    except ValidationError as exc:
        raise ConfigError(format_validation_error(str(path), Config, exc)) from None
    if robot:
        check_joint_names(cfg, robot_joint_names(cfg))
    params_path = Path(params) if params is not None else (cfg.base_dir / cfg.params if cfg.params else None)
    if params_path is not None:
        cfg = apply_params(cfg, load_params(params_path), str(params_path))
    return cfg
