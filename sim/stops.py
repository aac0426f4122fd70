"""The drive's own stops (quick stop, fault reaction, slow down on disable): a PI velocity loop that ramps the speed
reference to zero at a deceleration (6084h or 6085h) or, without one, holds the current limit against the motion;
at standstill for ``standstill_time_s`` (or after ``stop_timeout_s``) the stop ends and the caller engages the brake.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from dragd.hardware.cia402 import State


class StopGains(Protocol):
    """What a stop reads of the drive's parameters (sim/drive.py's DriveParams has them: this module does not
    import the drive that uses it)."""

    @property
    def quickstop_kd_A_s_per_rad(self) -> float: ...
    @property
    def quickstop_ki_A_per_rad(self) -> float: ...
    @property
    def standstill_velocity_rad_s(self) -> float: ...
    @property
    def standstill_time_s(self) -> float: ...
    @property
    def stop_timeout_s(self) -> float: ...


@dataclass
class Stop:
    """An active deceleration to rest."""

    decel_rad_s2: float | None  # None: current-limit stop
    then: State | None  # state after the stop; None: stay (quick stop active, codes 5-7)
    v_ref_rad_s: float
    integral_A: float
    started_s: float
    still_since_s: float | None = None


def stop_current(st: Stop, p: StopGains, v: float, limit_A: float, t: float, dt: float) -> tuple[float, bool, bool]:
    """One step of the stop loop: (current demand before clamping, finished, finished by the timeout)."""
    if st.decel_rad_s2 is None:
        st.v_ref_rad_s = 0.0
    elif st.v_ref_rad_s > 0.0:
        st.v_ref_rad_s = max(0.0, st.v_ref_rad_s - st.decel_rad_s2 * dt)
    elif st.v_ref_rad_s < 0.0:
        st.v_ref_rad_s = min(0.0, st.v_ref_rad_s + st.decel_rad_s2 * dt)
    error = st.v_ref_rad_s - v
    st.integral_A = max(-limit_A, min(limit_A, st.integral_A + p.quickstop_ki_A_per_rad * error * dt))
    if st.decel_rad_s2 is None and abs(v) > 4.0 * p.standstill_velocity_rad_s:
        demand_A = -limit_A if v > 0.0 else limit_A
    else:
        demand_A = p.quickstop_kd_A_s_per_rad * error + st.integral_A
    if st.v_ref_rad_s == 0.0 and abs(v) < p.standstill_velocity_rad_s:
        if st.still_since_s is None:
            st.still_since_s = t
        elif t - st.still_since_s >= p.standstill_time_s:
            return demand_A, True, False
    else:
        st.still_since_s = None
        if t - st.started_s > p.stop_timeout_s:
            return demand_A, True, True
    return demand_A, False, False
