"""The guiding device on the simulated arm: a three-position enabling switch and push buttons at the wrist, wired to
one drive's digital inputs (60FDh; the truth's ``hand``), pressed by the scripted operator (sim/operator.py).

Each period the runner asks ``word(t)`` for the drive's inputs word: the enabling switch's position (released: no
contact; the middle: every channel closed; squeezed: the channels open and the panic contact closed, where the device
has one), the buttons (a normally-closed one reads 1 until pressed), contact bounce after each change
(``bounce_ms``), and the device faults the fault matrix injects (``inject``):

- ``stuck_enable``  channel (0 or 1), seconds: that channel of the enabling switch stays closed (a welded contact)
- ``chattering``    button (enable, mark, stop, teach), period_ms, seconds: the contact opens and closes by itself
- ``inputs_cut``    seconds: every contact reads open (a cut cable to the hand: the stop's normally-closed wire too)

Times are the physics' (sim time on both clocks).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from sim.axis import AxisIO
    from sim.truth import HandTruth

RELEASED, MIDDLE, SQUEEZED = 0, 1, 2
POSITIONS = {"released": RELEASED, "middle": MIDDLE, "squeeze": SQUEEZED}
BUTTONS = ("enable", "mark", "stop", "teach")
KINDS = ("stuck_enable", "chattering", "inputs_cut")


class HandError(ValueError):
    """A press of a button the device lacks, or a device fault it cannot take (the message says which)."""


class HandDevice:
    """The device's state: the switch's position, the buttons held, bounce and faults; ``apply`` writes the word."""

    def __init__(self, truth: HandTruth, joint_names: list[str], axes: list[AxisIO]) -> None:
        self.truth = truth
        self.joint_name = truth.joint or joint_names[-1]
        self.joint = joint_names.index(self.joint_name)
        self.axis = axes[self.joint]
        self.enable_masks = [1 << b for b in truth.enable_bits]
        self.panic_mask = 0 if truth.panic_bit is None else 1 << truth.panic_bit
        self.buttons = {name: (1 << c.bit, c.normally_closed) for name, c in truth.buttons.items()}
        self.position = RELEASED
        self.pressed: dict[str, bool] = {name: False for name in self.buttons}
        self.changed_t: dict[str, float] = {}  # when each control last changed (bounce)
        self.stuck: dict[int, float] = {}  # enable channel -> until
        self.chatter: dict[str, tuple[float, float, float]] = {}  # control -> (from, period_s, until)
        self.cut_until = -1.0
        self.events: list[dict[str, Any]] = []
        self.t = 0.0

    @property
    def controls(self) -> list[str]:
        return ["enable", *self.buttons]

    # ------------------------------------------------------------------------------------------ the operator

    def press(self, t: float, button: str, position: str = "middle") -> None:
        """The operator presses ``button`` (the enabling switch to ``position``: middle or squeeze)."""
        if button == "enable":
            if position not in ("middle", "squeeze"):
                raise HandError(f"press enable: position: expected middle or squeeze, got {position!r}")
            self._set(t, "enable", POSITIONS[position])
        elif button in self.buttons:
            self._set(t, button, True)
        else:
            raise HandError(f"press: button: expected one of {', '.join(self.controls)} (the truth's hand), got "
                            f"{button!r}")

    def let_go(self, t: float, button: str) -> None:
        if button == "enable":
            self._set(t, "enable", RELEASED)
        elif button in self.buttons:
            self._set(t, button, False)
        else:
            raise HandError(f"let_go: button: expected one of {', '.join(self.controls)}, got {button!r}")

    def _set(self, t: float, control: str, value: Any) -> None:
        old = self.position if control == "enable" else self.pressed[control]
        if old == value:
            return
        if control == "enable":
            self.position = value
        else:
            self.pressed[control] = value
        self.changed_t[control] = t
        self.events.append({"t": round(t, 6), "control": control,
                            "state": value if isinstance(value, bool) else ("released", "middle", "squeeze")[value]})

    # ------------------------------------------------------------------------------------------ faults

    def inject(self, t: float, kind: str, args: dict[str, Any]) -> dict[str, Any]:
        def number(name: str, default: float, lo: float, hi: float) -> float:
            v = args.get(name, default)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not lo <= v <= hi:
                raise HandError(f"inject {kind}: {name}: expected a number in [{lo:g}, {hi:g}], got {v!r}")
            return float(v)

        seconds = number("seconds", 1.0, 0.001, 600.0)
        done: dict[str, Any] = {"kind": kind, "t_mono": t, "seconds": seconds, "joint": self.joint_name}
        if kind == "stuck_enable":
            ch = int(number("channel", len(self.enable_masks) - 1, 0, len(self.enable_masks) - 1))
            self.stuck[ch] = t + seconds
            done["channel"] = ch
        elif kind == "chattering":
            button = args.get("button", "enable")
            if button not in self.controls:
                raise HandError(f"inject chattering: button: expected one of {', '.join(self.controls)}, "
                                f"got {button!r}")
            self.chatter[button] = (t, number("period_ms", 4.0, 0.5, 1000.0) * 1e-3, t + seconds)
            done["button"] = button
        elif kind == "inputs_cut":
            self.cut_until = t + seconds
        else:
            raise HandError(f"inject: kind: expected one of {', '.join(KINDS)}, got {kind!r}")
        return done

    # ------------------------------------------------------------------------------------------ the word

    def _closed(self, t: float, control: str, closed: bool) -> bool:
        """A contact's reading at ``t``: bounce after a change, chatter."""
        chat = self.chatter.get(control)
        if chat is not None:
            t0, period, until = chat
            if t < until:
                if int((t - t0) / (period / 2.0)) % 2 == 1:
                    return not closed
            else:
                del self.chatter[control]
        bounce = self.truth.bounce_ms * 1e-3
        since = t - self.changed_t.get(control, -1.0)
        if bounce > 0.0 and 0.0 <= since < bounce and int(since / 0.0005) % 2 == 1:
            return not closed  # (a bouncing contact: opens and closes every 0.5 ms until it settles)
        return closed

    def word(self, t: float) -> int:
        """The drive's inputs word at ``t``."""
        if t < self.cut_until:
            return 0
        w = 0
        middle = self.position == MIDDLE
        for k, m in enumerate(self.enable_masks):
            closed = self._closed(t, "enable", middle)
            until = self.stuck.get(k)
            if until is not None:
                if t < until:
                    closed = True
                else:
                    del self.stuck[k]
            if closed:
                w |= m
        if self.panic_mask and self.position == SQUEEZED:
            w |= self.panic_mask
        for name, (mask, nc) in self.buttons.items():
            closed = self._closed(t, name, self.pressed[name])
            if closed != nc:  # a normally-closed contact opens when pressed
                w |= mask
        return w

    def apply(self, t: float) -> None:
        """The period's end: the drive reads the word (its next SYNC's TPDO, its event TPDOs)."""
        self.t = t
        self.axis.digital_inputs = self.word(t)

    def state(self) -> dict[str, Any]:
        return {"joint": self.joint_name, "enable": ("released", "middle", "squeeze")[self.position],
                "pressed": dict(self.pressed), "word": self.axis.digital_inputs,
                "faults": {"stuck_enable": sorted(self.stuck), "chattering": sorted(self.chatter),
                           "inputs_cut": self.t < self.cut_until}}
