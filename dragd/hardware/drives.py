"""CiA 402 supervision of every drive from the cycle: the controlwords that walk each drive toward what the mode
needs, the enable timeout, and drives that leave operation enabled on their own.

Targets: ``ENABLED`` (hold, drag, track: operation enabled, a fault reset edge first where a drive is in fault),
``QUICK_STOP`` (a fault reaction: quick stop where enabled, else disable voltage), ``DISABLED`` (idle: shutdown to
ready to switch on). The walk is recomputed only when a statusword, the target or the reset phase changed, or an
enable is pending: the controlwords otherwise stay as they are (sent every cycle in the command RPDO). A drive that
leaves operation enabled on its own (quick stop, switched on, ready to switch on, ...) is a fault: it is never walked
back up without an operator's ``start``.
"""

from __future__ import annotations

from enum import IntEnum

import numpy as np

from dragd.hardware.cia402 import (
    CMD_DISABLE_VOLTAGE,
    CMD_QUICK_STOP,
    CMD_SHUTDOWN,
    CW_FAULT_RESET,
    State,
    decode_statusword,
    next_controlword,
)

STATE_NAMES = {s: s.name.lower() for s in State}


class Target(IntEnum):
    DISABLED = 0
    ENABLED = 1
    QUICK_STOP = 2


class DriveSupervisor:
    """The 402 walk of n drives; ``update`` once per cycle returns a fault to raise, or None."""

    def __init__(self, node_ids: list[int], enable_timeout_s: float) -> None:
        n = self.n = len(node_ids)
        self.node_ids = node_ids
        self.enable_timeout_s = enable_timeout_s
        self.states = [State.NOT_READY_TO_SWITCH_ON] * n
        self.enabled = np.zeros(n, dtype=bool)  # in operation enabled (what may be commanded)
        self.cw = np.zeros(n, dtype=np.int64)
        self.fault_reset_phase = 0
        self.enable_t0: float | None = None  # an enable under way since then
        self._target: Target | None = None
        self._statusword = np.full(n, -1, dtype=np.int64)
        self._changed = np.zeros(n, dtype=bool)

    def request_enable(self, t: float) -> None:
        """Enable every drive (fault reset first: two cycles, bit 7 low then high, for drives in fault)."""
        self.fault_reset_phase = 2
        self.enable_t0 = t

    @property
    def all_enabled(self) -> bool:
        return all(s == State.OPERATION_ENABLED for s in self.states)

    def update(self, statusword: np.ndarray, target: Target, t: float) -> tuple[int | None, str] | None:
        """Controlwords (``cw``) toward ``target``; a (joint, text) fault when a drive fails or drops out."""
        if target != Target.ENABLED:
            self.enable_t0 = None
        if (self.fault_reset_phase == 0 and self.enable_t0 is None and target == self._target
                and np.count_nonzero(np.not_equal(statusword, self._statusword, out=self._changed)) == 0):
            return None
        self._target = target
        self._statusword[:] = statusword
        want_enabled = target == Target.ENABLED
        for i in range(self.n):
            try:
                st = decode_statusword(int(statusword[i]))
            except ValueError:
                st = State.NOT_READY_TO_SWITCH_ON
            self.states[i] = st
            self.enabled[i] = st == State.OPERATION_ENABLED
            if target == Target.QUICK_STOP:
                self.cw[i] = CMD_QUICK_STOP if st == State.OPERATION_ENABLED else CMD_DISABLE_VOLTAGE
            elif want_enabled:
                if st in (State.FAULT, State.FAULT_REACTION_ACTIVE):
                    # rising edge of bit 7: one cycle low, then high
                    self.cw[i] = CW_FAULT_RESET if self.fault_reset_phase == 1 else CMD_DISABLE_VOLTAGE
                elif st != State.OPERATION_ENABLED and self.enable_t0 is None and self.fault_reset_phase == 0:
                    # it left operation enabled on its own (e.g. to switched on): never walked back up silently;
                    # the fault below takes the arm down and the operator's 'start' enables again
                    self.cw[i] = CMD_DISABLE_VOLTAGE
                else:
                    self.cw[i] = next_controlword(st, State.OPERATION_ENABLED)
            else:
                self.cw[i] = (CMD_SHUTDOWN if st not in (State.FAULT, State.FAULT_REACTION_ACTIVE)
                              else CMD_DISABLE_VOLTAGE)
        if self.fault_reset_phase > 0:
            self.fault_reset_phase -= 1
        if not want_enabled:
            return None
        if self.enable_t0 is not None:
            if self.all_enabled:
                self.enable_t0 = None
            elif t - self.enable_t0 > self.enable_timeout_s:
                bad = [f"node {self.node_ids[i]} in {STATE_NAMES[s]} (statusword 0x{int(statusword[i]):04X})"
                       for i, s in enumerate(self.states) if s != State.OPERATION_ENABLED]
                self.enable_t0 = None
                return None, (f"drives did not reach operation enabled within {self.enable_timeout_s:.1f} s: "
                              f"{', '.join(bad)}")
            return None
        for i, s in enumerate(self.states):
            if s in (State.FAULT, State.FAULT_REACTION_ACTIVE):
                return i, f"node {self.node_ids[i]} reports {STATE_NAMES[s]} (statusword 0x{int(statusword[i]):04X})"
            if s != State.OPERATION_ENABLED:
                return i, (f"node {self.node_ids[i]} left operation enabled: {STATE_NAMES[s]} "
                           f"(statusword 0x{int(statusword[i]):04X}); not re-enabled without 'dragd start'")
        return None
