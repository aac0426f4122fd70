"""The closed-loop plant behind a golden-trace *recording*: CiA 402 drives + the simulated arm, frame in / frame out.

Only the recording uses it (``tests/golden/record.py``): the trace stores the frames the plant sent, so replaying
a trace needs neither the plant nor real time. Deterministic: the sim's physics (seeded Hall noise), a small
CiA 402 state machine per drive, the drive's CST/CSP current computed as ``sim/drive.py`` does, and scripted
disturbances (the operator's hand torques, lost TPDOs, a drive fault, an EMCY, a drive that refuses to enable).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field

import numpy as np

from dragd.hardware.cia402 import (
    CW_FAULT_RESET,
    STATE_STATUSWORD_BITS,
    SW_REMOTE,
    SW_VOLTAGE_ENABLED,
    VOLTAGE_ENABLED_STATES,
    Command,
    State,
    decode_command,
)
from dragd.hardware.pdo import BusLayout
from sim.axis import AxisIO
from sim.physics import ArmPhysics
from sim.truth import load_truth

MODE_CSP, MODE_CST = 8, 10


@dataclass
class DriveEmu:
    """One drive: 402 state, latched command, mode; quick stop = disable at once (605Ah option 2 brakes)."""

    node_id: int
    rated_A: float
    rad_per_count: float
    kp: float
    kd: float
    limit_A: float
    state: State = State.SWITCH_ON_DISABLED
    prev_cw: int = 0
    mode: int = MODE_CST
    target_counts: int = 0
    offset_permille: int = 0
    refuse_enable: bool = False
    sw_dirty: bool = True  # compact layout: the event TPDO goes out when the statusword changes

    @property
    def statusword(self) -> int:
        sw = STATE_STATUSWORD_BITS[self.state] | SW_REMOTE
        if self.state in VOLTAGE_ENABLED_STATES:
            sw |= SW_VOLTAGE_ENABLED
        return sw

    def controlword(self, cw: int) -> None:
        prev, self.prev_cw = self.prev_cw, cw
        before = self.state
        if self.state is State.FAULT:
            if cw & CW_FAULT_RESET and not prev & CW_FAULT_RESET:
                self.state = State.SWITCH_ON_DISABLED
        else:
            cmd = decode_command(cw)
            s = self.state
            if cmd is Command.DISABLE_VOLTAGE:
                self.state = State.SWITCH_ON_DISABLED
            elif cmd is Command.QUICK_STOP:
                self.state = State.SWITCH_ON_DISABLED  # option 2: stop, then switch on disabled (at once here)
            elif cmd is Command.SHUTDOWN:
                self.state = State.READY_TO_SWITCH_ON
            elif cmd is Command.SWITCH_ON:
                if s in (State.READY_TO_SWITCH_ON, State.SWITCHED_ON, State.OPERATION_ENABLED):
                    self.state = State.SWITCHED_ON
            elif cmd is Command.ENABLE_OPERATION:
                if s in (State.READY_TO_SWITCH_ON, State.SWITCHED_ON) and not self.refuse_enable:
                    self.state = State.OPERATION_ENABLED
        if self.state is not before:
            self.sw_dirty = True

    def fault(self) -> None:
        self.state = State.FAULT
        self.sw_dirty = True

    def current_A(self, q: float, dq: float) -> float:
        if self.state is not State.OPERATION_ENABLED:
            return 0.0
        i = self.offset_permille * self.rated_A / 1000.0
        if self.mode == MODE_CSP:
            i += self.kp * (self.target_counts * self.rad_per_count - q) - self.kd * dq
        return max(-self.limit_A, min(self.limit_A, i))


@dataclass
class Plant:
    """The arm and its drives for one configuration's bus layouts."""

    layouts: dict[str, BusLayout]
    node_ids: list[int]
    offsets_counts: list[int]
    seed: int = 7
    hand_Nm: np.ndarray = field(default_factory=lambda: np.zeros(6))
    drop: set[int] = field(default_factory=set)  # joints whose TPDOs are lost
    emcy: list[tuple[int, int]] = field(default_factory=list)  # (node, code) to send this cycle

    def __post_init__(self) -> None:
        truth = load_truth().with_updates(noise_seed=self.seed)
        self.model = truth.load_model()
        self.n = n = self.model.nq
        self.axes = [AxisIO() for _ in range(n)]
        self.physics = ArmPhysics(truth, self.model, self.axes)
        self.sub = int(round(1e-3 / truth.dt_s))
        self.drives = []
        for j, jt in enumerate(truth.joints):
            hw = jt.drive
            self.drives.append(DriveEmu(self.node_ids[j], hw.rated_current_A, 2 * math.pi / hw.encoder_counts_per_rev,
                                        hw.csp_kp_A_per_rad, hw.csp_kd_A_s_per_rad,
                                        min(hw.max_torque_permille * hw.rated_current_A / 1000.0, hw.max_current_A)))
        self.cpr = [jt.drive.encoder_counts_per_rev for jt in truth.joints]
        self._rx = {}  # cob -> [(joint, offset, struct, fields)]
        self._tx = []  # (bus, cob, joint, struct, fields, cyclic)
        for bus, lay in self.layouts.items():
            for fr in lay.frames:
                for s in fr.slots:
                    entry = (s.joint, s.offset, struct.Struct(s.fmt), s.fields)
                    if fr.direction == "rpdo":
                        self._rx.setdefault(fr.cob_id, []).append(entry)
                    else:
                        self._tx.append((bus, fr.cob_id, *entry, fr.cyclic))

    def receive(self, cob: int, data: bytes) -> None:
        """A command frame from the daemon, applied at the next SYNC."""
        for joint, off, codec, fields in self._rx.get(cob, ()):
            d = self.drives[joint]
            for f, v in zip(fields, codec.unpack_from(data, off), strict=True):
                if f == "controlword":
                    d.controlword(v)
                elif f == "target_position":
                    d.target_counts = v
                else:
                    d.offset_permille = v

    def sync(self) -> list[tuple[str, int, bytes]]:
        """Sample at SYNC: the TPDOs (and EMCYs) every drive sends, as (bus, cob, data)."""
        q = self.physics.q_rad
        meas = self.physics.current_measured_A
        out = []
        for bus, cob, joint, _off, codec, fields, cyclic in self._tx:
            d = self.drives[joint]
            if joint in self.drop or (not cyclic and not d.sw_dirty):
                continue
            vals = []
            for f in fields:
                if f == "statusword":
                    vals.append(d.statusword)
                    d.sw_dirty = False
                elif f == "position":
                    vals.append(int(round(q[joint] / d.rad_per_count)) + self.offsets_counts[joint])
                else:
                    vals.append(max(-32768, min(32767, int(round(meas[joint] * 1000.0 / d.rated_A)))))
            out.append((bus, cob, codec.pack(*vals)))
        for node, code in self.emcy:
            bus = next(b for b, lay in self.layouts.items() if node in lay.node_ids)
            out.append((bus, 0x80 + node, struct.pack("<HB5x", code, 0x11)))
        self.emcy = []
        return out

    def step_1ms(self) -> None:
        phys = self.physics
        phys.tau_ext_Nm[:] = self.hand_Nm
        for _ in range(self.sub):
            q, dq = phys.q_rad.tolist(), phys.dq_rad_s.tolist()
            for j, (d, ax) in enumerate(zip(self.drives, self.axes, strict=True)):
                on = d.state is State.OPERATION_ENABLED
                ax.power_stage_on = on
                ax.brake_engaged = not on
                ax.current_demand_A = d.current_A(q[j], dq[j])
            phys.step()
