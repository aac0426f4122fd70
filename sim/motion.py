"""The drive's power stage and its control laws: what current it demands in each regime.

OFF (power stage off, brake engaged), COMMAND (operation enabled: the mode's law — CST, CSP, CSV, profile torque) and
STOPPING (sim/stops.py). Torque and current objects are converted with the factors of sim/scaling.py; the demand is
clamped by the lower of the torque and current limits. Motion timing (brake release, ramps, stops) runs on the physics
time handed to ``step``.
"""

from __future__ import annotations

from collections.abc import Callable
from enum import IntEnum
from typing import TYPE_CHECKING, Any, Protocol

from dragd.hardware.cia402 import Mode, State
from sim.axis import AxisIO
from sim.stops import Stop, StopGains, stop_current

if TYPE_CHECKING:
    from sim.scaling import Scaling


class MotionParams(StopGains, Protocol):
    """What the laws read of the drive's parameters (sim/drive.py's DriveParams; the drive imports this module,
    never the other way round)."""

    @property
    def encoder_counts_per_rev(self) -> int: ...
    @property
    def csp_kp_A_per_rad(self) -> float: ...
    @property
    def csp_kd_A_s_per_rad(self) -> float: ...
    @property
    def csp_ki_A_per_rad_s(self) -> float: ...


class StopCounter(Protocol):
    """Where a stop that timed out is counted (sim/drive.py's DriveCounters)."""

    stop_timeouts: int

_INT32_MIN, _INT32_MAX = -(1 << 31), (1 << 31) - 1


class Regime(IntEnum):
    OFF = 0  # power stage off, brake engaged
    COMMAND = 1  # operation enabled: the mode's control law
    STOPPING = 2  # the drive's own velocity loop brings the joint to rest


class Motion:
    """Regime, brake and the state of the mode laws of one drive (slots: see ``Slots`` in sim/drive.py)."""

    def __init__(self, params: MotionParams, io: AxisIO, cells: list[Any], slots: Any, scaling: Scaling,
                 counters: StopCounter, stopped: Callable[[State | None], None]) -> None:
        self.params = params
        self.io = io
        self.cells = cells
        self.s = slots
        self.scaling = scaling
        self.counters = counters
        self._stopped = stopped  # the stop ended at rest (or timed out): the state machine's next state
        self.counts_per_rad = params.encoder_counts_per_rev / (2.0 * 3.141592653589793)
        self.t = 0.0  # physics time of the last step
        self.reset()

    def reset(self) -> None:
        """Power-on: off, brake engaged, no mode."""
        self.regime = Regime.OFF
        self.stop: Stop | None = None
        self.brake_released = False
        self.enabled_at_s = 0.0
        self.mode = 0
        self.pt_ref = 0.0  # profile torque reference, in target torque units
        self.csp_last_target = 0
        self.csp_last_change_s = 0.0
        self.csp_interval_s = 0.0
        self.csp_v_ff_rad_s = 0.0
        self.csp_integral_A = 0.0
        self.internal_limit = False
        self.target_reached = False

    # --- regime changes ----------------------------------------------------------------------------------
    def power_off(self) -> None:
        self.regime = Regime.OFF
        self.brake_released = False
        self.internal_limit = False
        self.cells[self.s.torque_demand] = 0

    def enable(self) -> None:
        """Operation enabled: the mode's law from now on (the brake opens after its delay)."""
        self.stop = None
        self.regime = Regime.COMMAND
        self.enabled_at_s = self.t
        self.pt_ref = 0.0
        self.csp_last_target = self.cells[self.s.target_position]
        self.csp_last_change_s = self.t
        self.csp_v_ff_rad_s = 0.0
        self.csp_integral_A = 0.0
        self.target_reached = False

    def set_mode(self, mode: int) -> None:
        self.mode = mode
        cells = self.cells
        self.pt_ref = cells[self.s.torque_demand] * self.scaling.demand_per_target if self.regime is Regime.COMMAND \
            else 0.0
        self.csp_last_target = cells[self.s.target_position]
        self.csp_v_ff_rad_s = 0.0
        self.csp_integral_A = 0.0
        self.target_reached = False

    def start_stop(self, decel_rad_s2: float | None, then: State | None) -> None:
        """Begin a deceleration to rest with the drive's velocity loop (bumpless from the last demand)."""
        self.stop = Stop(decel_rad_s2=decel_rad_s2, then=then, v_ref_rad_s=self.io.velocity_rad_s,
                         integral_A=self.io.current_demand_A, started_s=self.t)
        self.regime = Regime.STOPPING
        self.target_reached = False

    # --- one physics step --------------------------------------------------------------------------------
    def limit_A(self) -> float:
        cells, s, k = self.cells, self.s, self.scaling
        torque_A = cells[s.max_torque] * k.max_torque
        current_A = cells[s.max_current] * k.max_current
        return torque_A if torque_A < current_A else current_A

    def command_current(self, t: float, dt: float) -> float:
        cells, s, k = self.cells, self.s, self.scaling
        mode = self.mode
        offset_A = cells[s.torque_offset] * k.torque_offset
        if mode == Mode.CYCLIC_SYNC_TORQUE:
            demand_A = cells[s.target_torque] * k.target_torque + offset_A
        elif mode == Mode.CYCLIC_SYNC_POSITION:
            demand_A = self._csp_current(t, dt, cells) + offset_A
        elif mode == Mode.CYCLIC_SYNC_VELOCITY:
            v_ref = (cells[s.target_velocity] + cells[s.velocity_offset]) / self.counts_per_rad
            demand_A = self.params.csp_kd_A_s_per_rad * (v_ref - self.io.velocity_rad_s) + offset_A
        elif mode == Mode.PROFILE_TORQUE:
            demand_A = self._pt_step(cells, dt) * k.target_torque + offset_A
        else:
            demand_A = 0.0
        return self.clamp(demand_A)

    def clamp(self, demand_A: float) -> float:
        limit_A = self.limit_A()
        if demand_A > limit_A:
            demand_A, self.internal_limit = limit_A, True
        elif demand_A < -limit_A:
            demand_A, self.internal_limit = -limit_A, True
        else:
            self.internal_limit = False
        lo, hi = self.s.torque_demand_range
        v = round(demand_A / self.scaling.torque_demand)
        self.cells[self.s.torque_demand] = lo if v < lo else hi if v > hi else v
        return demand_A

    def _csp_current(self, t: float, dt: float, cells: list[Any]) -> float:
        s = self.s
        target = cells[s.target_position]
        if target != self.csp_last_target:
            interval = t - self.csp_last_change_s
            if 0.0 < interval < 0.1:
                self.csp_v_ff_rad_s = (target - self.csp_last_target) / self.counts_per_rad / interval
                self.csp_interval_s = interval
            else:
                self.csp_v_ff_rad_s = 0.0
            self.csp_last_target = target
            self.csp_last_change_s = t
        elif t - self.csp_last_change_s > 3.0 * self.csp_interval_s:
            self.csp_v_ff_rad_s = 0.0
        error = target - cells[s.position]
        cells[s.following_error] = _INT32_MIN if error < _INT32_MIN else _INT32_MAX if error > _INT32_MAX else error
        p = self.params
        error_rad = target / self.counts_per_rad - self.io.position_rad
        if p.csp_ki_A_per_rad_s:
            limit_A = self.limit_A()
            integral_A = self.csp_integral_A + p.csp_ki_A_per_rad_s * error_rad * dt
            self.csp_integral_A = max(-limit_A, min(limit_A, integral_A))
        return (p.csp_kp_A_per_rad * error_rad + p.csp_kd_A_s_per_rad * (self.csp_v_ff_rad_s - self.io.velocity_rad_s)
                + self.csp_integral_A)

    def _pt_step(self, cells: list[Any], dt: float) -> float:
        target = float(cells[self.s.target_torque])
        step = cells[self.s.torque_slope] * dt
        ref = self.pt_ref
        if step <= 0.0:  # (no 6087h: the reference steps; 6087h = 0 holds it, as before)
            if self.s.torque_slope_internal:
                ref = target
        elif ref < target:
            ref = min(target, ref + step)
        elif ref > target:
            ref = max(target, ref - step)
        self.pt_ref = ref
        self.target_reached = ref == target
        return ref

    def stop_current(self, t: float, dt: float) -> float:
        st = self.stop
        assert st is not None
        demand_A, finished, timed_out = stop_current(st, self.params, self.io.velocity_rad_s, self.limit_A(), t, dt)
        demand_A = self.clamp(demand_A)
        if finished:
            if timed_out:
                self.counters.stop_timeouts += 1
            self.stop = None
            self.power_off()
            self._stopped(st.then)
        return demand_A
