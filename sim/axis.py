"""The exchange between one simulated joint drive and the arm physics (joint side, SI units and amperes)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class AxisIO:
    """One joint's signals, written once per physics step by the side named in each comment."""

    position_rad: float = 0.0  # physics -> drive: true joint position
    velocity_rad_s: float = 0.0  # physics -> drive: true joint velocity
    current_measured_A: float = 0.0  # physics -> drive: Hall-sensor motor current (noise, quantisation)
    current_demand_A: float = 0.0  # drive -> physics: current-loop setpoint, motor current
    power_stage_on: bool = False  # drive -> physics: False = no motor torque
    brake_engaged: bool = True  # drive -> physics: holding brake clamps the joint
    digital_inputs: int = 0  # hand device -> drive: the contacts wired to the drive's inputs (60FDh bits; sim/hand.py)
