"""The guiding device's inputs at the hand, judged every cycle from the drives' digital inputs (docs/HAND.md).

Each configured input (``hand.inputs``) reads bits of one joint's drive inputs word (60FDh, or the drive profile's
vendor object) and the age of the TPDO that carries it. What the cycle decides from them:

``enable``  a three-position enabling switch. Held in the middle (every channel active, no panic contact): the
            operator may drag. Released (position 1) or squeezed (position 3, the panic contact where the device
            reports it) ends drag at once — no debounce in that direction. A press counts after ``debounce_ms``
            steady, and only from a switch seen fully released since dragd started, since its signal was lost and
            since a squeeze (a contact held through a reboot, a lost TPDO or a panic never starts drag). Two channels
            that disagree longer than ``discrepancy_ms``, the middle and the panic contact active at once, and a
            contact that chatters are faults: latched until the operator's ``start`` finds the contact sane again.
``stop``    a protective stop: active at once (the arm holds, motions end, nothing starts), released after the
            debounce; a lost or chattering stop contact counts as pressed.
``mark``, ``teach``  buttons: a debounced press is an event the daemon acts on (a waypoint; teach start/stop).

An input whose TPDO is older than its limit is *lost*: the enable counts as released (and must be released and
pressed again once its signal returns), a stop as pressed, buttons do nothing. Pure: Python numbers and numpy arrays
in, events out (appended only on a change); no I/O, no allocation on a cycle where nothing changes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from dragd.config import Config

# an enabling switch's position
RELEASED, ENABLED, SQUEEZED = 0, 1, 2
POSITION_NAMES = ("released", "enabled", "squeezed")
# an input's latched fault
NO_FAULT, DISCREPANT, CHATTERING, STUCK = 0, 1, 2, 3
FAULT_NAMES = ("", "channels disagree", "chattering contact", "stuck contact")

# the enabling switch's refusals (constants: the cycle asks for them without allocating)
R_NOT_HELD = "the enabling switch is not held (hand.inputs: enable)"
R_SQUEEZED = "the enabling switch is squeezed (panic): release it fully, then press it to the middle"
R_UNARMED = ("the enabling switch was already held (when dragd started, before its signal was lost or through a "
             "squeeze): release it fully, then press it to the middle")
R_LOST = "the enabling switch's signal is lost (the TPDO carrying its inputs is late)"
R_DISCREPANT = ("the enabling switch's two channels disagree (a stuck or broken contact): fix it, release it, "
                "then 'dragd start'")
R_CHATTERING = "the enabling switch's contact chatters: fix it, then 'dragd start'"
R_STUCK = "the enabling switch reads held and squeezed at once (a stuck contact): fix it, then 'dragd start'"
R_STOP = "the stop button is pressed"
R_STOP_LOST = "the stop button's signal is lost (the TPDO carrying its inputs is late): counted as pressed"
R_STOP_FAULT = "the stop button's contact chatters: counted as pressed until fixed and 'dragd start'"
_ENABLE_FAULT = {DISCREPANT: R_DISCREPANT, CHATTERING: R_CHATTERING, STUCK: R_STUCK}


@dataclass(frozen=True)
class HandEvent:
    """A change the daemon records (and acts on: ``pressed`` of mark/teach, ``pressed`` of enable = a drag request)."""

    t_s: float
    input: int  # index into HandInputs.inputs
    what: str  # pressed | released | squeezed | lost | found | fault | cleared
    detail: str = ""


class Input:
    """One input's wiring (masks into its joint's inputs word) and state."""

    def __init__(self, index: int, function: str, label: str, joint: int, joint_name: str, bits: list[int],
                 panic_bit: int | None, active_low: bool, obj: str, chatter_edges: int) -> None:
        self.index, self.function, self.label = index, function, label
        self.joint, self.joint_name, self.obj = joint, joint_name, obj
        self.bits = bits  # the channels (enable: 1 or 2)
        self.panic_bit = panic_bit
        self.masks = [1 << b for b in bits]
        self.panic_mask = 0 if panic_bit is None else 1 << panic_bit
        self.active_low = active_low
        self.raw = -1  # the last reading (bit pattern of the channels, panic as bit 2); -1 none yet
        self.raw_since = 0.0  # when the reading last changed
        self.level = False  # mark/teach/stop: the judged (debounced) state: pressed
        self.position = RELEASED  # enable
        self.armed = False  # enable: seen fully released (since the start, a loss, a squeeze)
        self.held = False  # enable: in the middle after an armed press (what permits drag)
        self.lost = True  # (not seen yet: counts as lost, silently, until its TPDO first arrives)
        self.seen = False
        self.fault = NO_FAULT
        self.fault_t = 0.0
        self.discrepant_since = -1.0
        self.stuck_since = -1.0
        self.edges = np.full(chatter_edges + 1, -1e9)  # the times of the latest edges (a ring)
        self.edge_k = 0
        self.edge_count = 0

    def where(self) -> str:
        """``joint6 60FDh bit 16`` (every bit the input reads)."""
        bits = ", ".join(str(b) for b in self.bits + ([self.panic_bit] if self.panic_bit is not None else []))
        return f"{self.joint_name} {self.obj} bit{'s' if ',' in bits else ''} {bits}"

    def status(self) -> dict[str, object]:
        out: dict[str, object] = {"function": self.function, "name": self.label, "joint": self.joint_name,
                                  "object": self.obj, "bits": self.bits, "active": "low" if self.active_low else "high",
                                  "lost": self.lost, "fault": FAULT_NAMES[self.fault] or None,
                                  "raw": None if self.raw < 0 else self.raw, "edges": self.edge_count}
        if self.function == "enable":
            out.update(position=POSITION_NAMES[self.position], held=self.held, armed=self.armed,
                       panic_bit=self.panic_bit)
        else:
            out["pressed"] = self.level
        return out


class HandInputs:
    """Every configured input, judged each cycle (``update``); ``events`` collects what changed."""

    def __init__(self, inputs: list[Input], debounce_s: float, discrepancy_s: float, chatter_edges: int,
                 chatter_window_s: float, lost_after_cycles: np.ndarray) -> None:
        self.inputs = inputs
        self.debounce_s = debounce_s
        self.discrepancy_s = discrepancy_s
        self.chatter_edges = chatter_edges
        self.chatter_window_s = chatter_window_s
        self.lost_after = lost_after_cycles  # per joint: the inputs' TPDO this many cycles old is lost
        self.enable: Input | None = next((i for i in inputs if i.function == "enable"), None)
        self.stops = [i for i in inputs if i.function == "stop"]
        self.events: list[HandEvent] = []
        self.stop_active = False  # any stop pressed, lost or faulted (the cycle holds)
        self.changed = False  # something changed this cycle (the daemon publishes the state)

    @classmethod
    def from_config(cls, cfg: Config, objects: list[str] | None = None,
                    lost_after_cycles: np.ndarray | None = None) -> HandInputs | None:
        """The configuration's inputs (None without any); ``objects``: per joint the inputs object's name (the drive
        profile's, default 60FDh); ``lost_after_cycles``: per joint, how old its inputs' TPDO may get."""
        h = cfg.hand
        if not h.inputs:
            return None
        names = cfg.joint_names
        n = len(names)
        rate = cfg.loop.rate_Hz
        if lost_after_cycles is None:
            lost = h.lost_after_ms * rate / 1000.0 if h.lost_after_ms is not None else cfg.loop.stale_cycles_hold
            lost_after_cycles = np.full(n, max(1, int(round(lost))), dtype=np.int64)
        made = []
        for k, inp in enumerate(h.inputs):
            j = names.index(inp.joint)
            made.append(Input(k, inp.function, inp.label, j, inp.joint,
                              [inp.bit] + ([inp.second_bit] if inp.second_bit is not None else []), inp.panic_bit,
                              inp.active == "low", objects[j] if objects else "60FDh", h.chatter_edges))
        return cls(made, h.debounce_ms * 1e-3, h.discrepancy_ms * 1e-3, h.chatter_edges, h.chatter_window_ms * 1e-3,
                   lost_after_cycles)

    # ------------------------------------------------------------------------------------------ the cycle

    def update(self, t: float, words: np.ndarray, age: np.ndarray) -> None:
        """Judge every input from its joint's inputs word and the age (cycles) of the TPDO that carried it."""
        self.changed = False
        stop = False
        for inp in self.inputs:
            j = inp.joint
            if int(age[j]) > int(self.lost_after[j]):
                self._lose(t, inp)
            else:
                if inp.lost:
                    inp.lost = False
                    if inp.seen:
                        self._event(t, inp, "found")
                    inp.seen = True
                word = int(words[j])
                raw = 0
                for k, m in enumerate(inp.masks):
                    if (word & m) != 0:
                        raw |= 1 << k
                if inp.panic_mask and (word & inp.panic_mask) != 0:
                    raw |= 4
                if inp.active_low:
                    raw ^= (1 << len(inp.masks)) - 1  # (a panic contact is read as wired: active high)
                if raw != inp.raw:
                    if inp.raw >= 0:
                        self._edge(t, inp)
                    inp.raw, inp.raw_since = raw, t
                if inp.function == "enable":
                    self._enable(t, inp, raw)
                elif inp.function == "stop":
                    self._stop(t, inp, raw)
                else:
                    self._button(t, inp, raw)
            if inp.function == "stop" and (inp.level or inp.lost or inp.fault != NO_FAULT):
                stop = True
        self.stop_active = stop

    def _event(self, t: float, inp: Input, what: str, detail: str = "") -> None:
        self.events.append(HandEvent(t, inp.index, what, detail))
        self.changed = True

    def _lose(self, t: float, inp: Input) -> None:
        if inp.lost:
            return  # (also before its TPDO first arrived: nothing was lost then)
        inp.lost = True
        inp.raw = -1
        inp.discrepant_since = inp.stuck_since = -1.0
        if inp.function == "enable":
            inp.position, inp.held, inp.armed = RELEASED, False, False
        elif inp.function != "stop":
            inp.level = False
        self._event(t, inp, "lost")

    def _edge(self, t: float, inp: Input) -> None:
        """Count an edge; more than ``chatter_edges`` within the window: a chattering contact (latched)."""
        inp.edge_count += 1
        e = inp.edges
        e[inp.edge_k] = t
        inp.edge_k = (inp.edge_k + 1) % e.shape[0]
        oldest = e[inp.edge_k]  # the (chatter_edges + 1)-th latest edge
        if inp.fault == NO_FAULT and t - oldest <= self.chatter_window_s:
            self._fault(t, inp, CHATTERING, f"{self.chatter_edges + 1} edges within "
                                            f"{self.chatter_window_s * 1e3:g} ms")

    def _fault(self, t: float, inp: Input, code: int, detail: str) -> None:
        inp.fault, inp.fault_t = code, t
        if inp.function == "enable":
            inp.held, inp.armed = False, False
            if inp.position == ENABLED:
                inp.position = RELEASED
        self._event(t, inp, "fault", f"{FAULT_NAMES[code]} ({inp.where()}): {detail}")

    def _enable(self, t: float, inp: Input, raw: int) -> None:
        nch = len(inp.masks)
        full = (1 << nch) - 1
        chans = raw & full
        panic = bool(raw & 4)
        # two channels that disagree: not enabled at once; a fault once it lasts (a stuck or broken contact)
        if nch == 2 and chans not in (0, full):
            if inp.discrepant_since < 0.0:
                inp.discrepant_since = t
            elif inp.fault == NO_FAULT and t - inp.discrepant_since > self.discrepancy_s:
                bits = ", ".join(f"bit {b} = {'active' if chans >> k & 1 else 'inactive'}"
                                 for k, b in enumerate(inp.bits))
                self._fault(t, inp, DISCREPANT, f"{bits} for {(t - inp.discrepant_since) * 1e3:.0f} ms")
        else:
            inp.discrepant_since = -1.0
        if chans and panic:  # the middle and the squeezed position at once
            if inp.stuck_since < 0.0:
                inp.stuck_since = t
            elif inp.fault == NO_FAULT and t - inp.stuck_since > self.debounce_s:
                self._fault(t, inp, STUCK, "the middle position's contact and the panic contact active together")
        else:
            inp.stuck_since = -1.0
        if panic:
            position = SQUEEZED  # at once
        elif chans == full:  # the middle: once steady (a press is debounced)
            position = ENABLED if inp.position == ENABLED or t - inp.raw_since >= self.debounce_s else inp.position
        else:
            position = RELEASED  # any channel inactive: at once
        if position == RELEASED and chans == 0 and not panic and not inp.armed and inp.fault == NO_FAULT:
            inp.armed = True  # seen fully released: the next press counts
        if position == inp.position:
            return
        was = inp.position
        inp.position = position
        if position == ENABLED:
            if inp.armed and inp.fault == NO_FAULT:
                inp.held = True
                self._event(t, inp, "pressed")
            else:
                self._event(t, inp, "held_unarmed")
            return
        if was == ENABLED:
            inp.held = False
        if position == SQUEEZED:
            inp.armed = False
            self._event(t, inp, "squeezed")
        elif was == ENABLED or was == SQUEEZED:
            self._event(t, inp, "released")

    def _stop(self, t: float, inp: Input, raw: int) -> None:
        if raw:
            if not inp.level:
                inp.level = True
                self._event(t, inp, "pressed")
        elif inp.level and t - inp.raw_since >= self.debounce_s:
            inp.level = False
            self._event(t, inp, "released")

    def _button(self, t: float, inp: Input, raw: int) -> None:
        level = bool(raw)
        if level == inp.level or t - inp.raw_since < self.debounce_s:
            return
        inp.level = level
        if inp.fault == NO_FAULT:
            self._event(t, inp, "pressed" if level else "released")

    # ------------------------------------------------------------------------------------------ decisions

    def enable_refusal(self) -> str | None:
        """None while the enabling switch permits drag, else why not (a constant)."""
        e = self.enable
        if e is None:
            return R_NOT_HELD
        if e.fault != NO_FAULT:
            return _ENABLE_FAULT[e.fault]
        if e.lost:
            return R_LOST
        if e.held:
            return None
        if e.position == SQUEEZED:
            return R_SQUEEZED
        if e.position == ENABLED:
            return R_UNARMED
        return R_NOT_HELD

    def stop_refusal(self) -> str | None:
        """None unless a stop input holds the arm (pressed, lost, faulted)."""
        if not self.stop_active:
            return None
        for s in self.stops:
            if s.fault != NO_FAULT:
                return R_STOP_FAULT
            if s.lost:
                return R_STOP_LOST
        return R_STOP

    def acknowledge(self, t: float) -> list[str]:
        """The operator's ``start``: clear the latched faults whose cause is gone; what stays faulted, and why."""
        kept = []
        for inp in self.inputs:
            if inp.fault == NO_FAULT:
                continue
            n_recent = int(np.count_nonzero(inp.edges >= t - self.chatter_window_s))
            ok = not inp.lost and inp.raw >= 0
            if inp.fault == DISCREPANT:
                ok = ok and inp.discrepant_since < 0.0
            elif inp.fault == STUCK:
                ok = ok and inp.stuck_since < 0.0
            elif inp.fault == CHATTERING:
                ok = ok and n_recent == 0
            if ok:
                inp.fault = NO_FAULT
                if inp.function == "enable":
                    inp.armed = inp.raw == 0  # released now: the next press counts
                self._event(t, inp, "cleared")
            else:
                kept.append(f"{inp.label} ({inp.where()}): {FAULT_NAMES[inp.fault]}")
        return kept

    def status(self) -> list[dict[str, object]]:
        return [i.status() for i in self.inputs]
