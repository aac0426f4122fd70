"""The daemon's side of hand guiding (docs/HAND.md): the drag lease's commands, what the hand's inputs and the end of
a drag leave in the fault list, the log and telemetry, and the buttons' actions.

The cycle decides (dragd/control/controller.py, hand.py, permission.py): drag ends the cycle its permission goes.
Here, after the cycle: an enabling switch's press becomes a drag request (with the checks ``mode drag`` makes), a
mark button marks a waypoint, a teach button starts or stops a teach session; every change of the inputs, the lease
or the permission is published as one ``hand`` message (the telemetry's ``/dragd/hand`` channel, the clients' event
log) with the whole state.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from dragd.clock import LockstepClock
from dragd.control import hand as H
from dragd.control import permission as P
from dragd.control.modes import MODE_NAMES, Mode
from dragd.teach.program import resolve_program

if TYPE_CHECKING:
    from dragd.config import Config
    from dragd.control.controller import Controller, Event
    from dragd.daemon.cycle import Cycle
    from dragd.daemon.faults import FaultSink
    from dragd.daemon.motion import Motions
    from dragd.daemon.recording import Recorder
    from dragd.daemon.teach import Teaching

# lockstep: how long (wall) the clock waits for a paced holder's next renewal before it counts the holder as gone
PACED_GUARD_S = 5.0

# why drag ended -> the fault list's kind (None: a normal end, an event only)
END_KINDS = {H.R_NOT_HELD: None, P.R_LEASE_CLOSED: None, H.R_SQUEEZED: "panic", H.R_STOP: "stop_input",
             H.R_STOP_LOST: "input_lost", H.R_STOP_FAULT: "input_fault", H.R_LOST: "input_lost",
             H.R_DISCREPANT: "input_fault", H.R_CHATTERING: "input_fault", H.R_STUCK: "input_fault",
             P.R_LEASE_LAPSED: "lease", P.R_NO_LEASE: "lease", H.R_UNARMED: "input_fault"}


class Guiding:
    """The lease commands, the hand's events and buttons, and their status."""

    def __init__(self, cfg: Config, controller: Controller, cycle: Cycle, motions: Motions, teaching: Teaching,
                 recorder: Recorder, faults: FaultSink, set_mode: Callable[..., object]) -> None:
        """``set_mode(name, by_enable=True)``: the operator's mode request (its checks), which the enabling switch's
        press makes; ``teaching``: the hand's teach buttons; ``faults``: the hand's faults and drag ends listed."""
        self.cfg, self.controller, self.cycle, self.motions, self.teaching = cfg, controller, cycle, motions, teaching
        self.recorder, self.faults, self.set_mode = recorder, faults, set_mode
        self.clock = cycle.clock
        self.last_refusal: dict[str, Any] | None = None  # a press of the enabling switch that did not start drag
        self.button_actions = 0
        self._tasks: set[asyncio.Task[Any]] = set()
        self._last_lapse: dict[str, Any] | None = None
        # a paced holder (``lease renew paced``) between the answer and its next renewal: (lease, wall time of the
        # answer); on the lockstep clock no period starts meanwhile (the gate), so its renewals fall at the same
        # simulated times on every run however slowly the client runs
        self._paced: tuple[int, float] | None = None
        self.paced_gate_timeouts = 0
        if isinstance(self.clock, LockstepClock):
            self.clock.gates.append(self._paced_gate)

    # ------------------------------------------------------------------------------------------ the lease

    def lease(self, action: str, lease: int | None, holder: str, period_s: float | None) -> dict[str, Any]:
        """The ``lease`` command: open (a new lease), renew, close (drag bound to it ends into HOLD), status."""
        c = self.controller
        ls, t = c.permission.lease, c.t
        if action == "status":
            return {"lease": ls.status(t), "drag": self.status()}
        if action == "open":
            lid = ls.open(t, holder, period_s)
            self.recorder.event("lease", action="open", lease=lid, holder=ls.holder, period_s=ls.period_s)
            self.publish()
            return {"lease": lid, "period_s": ls.period_s, "holder": ls.holder, "mode": MODE_NAMES[c.mode]}
        if lease is None:
            raise ValueError(f"lease {action}: missing field 'lease' (the number 'lease open' answered)")
        if action == "renew":
            self._paced = None
            ls.renew(t, lease)
            bound = c.drag_lease == lease
            return {"lease": lease, "remaining_s": round(ls.deadline_t - t, 4), "mode": MODE_NAMES[c.mode],
                    "require": c.permission.require,
                    "drag": bound and (c.mode == Mode.DRAG or (c.feedback_hold and c.resume_mode == Mode.DRAG))}
        if action == "close":
            ls.close(t, lease)
            if c.drag_lease == lease and c.mode == Mode.DRAG:
                c.end_drag(P.R_LEASE_CLOSED, self.cycle.est.q_rad)  # now, not at the next cycle: the answer says hold
                self.faults.record()
            self.recorder.event("lease", action="close", lease=lease, holder=ls.holder)
            self.publish()
            return {"lease": lease, "mode": MODE_NAMES[c.mode], "closed": True}
        raise ValueError(f"lease: action: expected open, renew, close or status, got {action!r}")

    async def renew_paced(self, lease: int | None) -> dict[str, Any]:
        """Renew now; answer a third of the period later on the daemon's clock (simulated time in lockstep), when the
        holder's next renewal is due. The holder reads no clock of its own: it renews on every answer."""
        ans = self.lease("renew", lease, "", None)
        c = self.controller
        ls = c.permission.lease
        await self.clock.sleep(ls.period_s / 3.0)
        if ls.active and ls.id == lease:
            self._paced = (int(lease or 0), time.monotonic())
        bound = c.drag_lease == lease
        ans.update(t_s=round(c.t, 6), remaining_s=round(ls.deadline_t - c.t, 4) if ls.active else 0.0,
                   state=ls.state, mode=MODE_NAMES[c.mode],
                   drag=bound and (c.mode == Mode.DRAG or (c.feedback_hold and c.resume_mode == Mode.DRAG)))
        return ans

    def _paced_gate(self) -> bool:
        """Lockstep: no period starts while a paced holder's renewal is due and has not come (at most
        ``PACED_GUARD_S`` of wall time: then the holder counts as gone and its lease lapses on the simulated clock)."""
        p = self._paced
        if p is None:
            return True
        ls = self.controller.permission.lease
        if not ls.active or ls.id != p[0]:
            self._paced = None
            return True
        if time.monotonic() - p[1] > PACED_GUARD_S:  # (a liveness guard in wall time, as the clock's own)
            self._paced = None
            self.paced_gate_timeouts += 1
            return True
        return False

    # ------------------------------------------------------------------------------------------ after the cycle

    def on_event(self, ev: Event) -> bool:
        """A controller event of ours (drag_end, lease): recorded; False for any other kind."""
        f = ev.fields or {}
        if ev.kind == "lease":
            self._last_lapse = {"t_s": round(ev.t_s, 4), **f}
            self.recorder.event("lease", **f)
            self.faults.log_later(f"t={ev.t_s:.3f} s: {ev.text}", 4)
            self.publish()
            return True
        if ev.kind != "drag_end":
            return False
        kind = END_KINDS.get(ev.text, "input_fault")
        text = f"drag ended: {ev.text}"
        if kind == "lease" and self._last_lapse is not None:
            text += f" (lease {self._last_lapse.get('lease')} of '{self._last_lapse.get('holder')}', no renewal for " \
                    f"{self._last_lapse.get('since_renewal_s')} s)"
        if kind is not None:
            self.faults.protective_stops += 1
            self.faults.entry(None, ev.t_s, text, 0, reaction="hold", kind=kind)
            self.faults.log_later(f"t={ev.t_s:.3f} s: {text}; the arm holds", 4)
        else:
            self.faults.log_later(f"t={ev.t_s:.3f} s: {text}; the arm holds")
        self.recorder.event("drag_end", reason=ev.text, kind=kind, lease=f.get("lease"))
        self.publish()
        return True

    def drain_hand(self) -> None:
        """The hand's events of the cycles since the last call: recorded, and acted on (presses)."""
        hand = self.controller.hand
        if hand is None or not hand.events:
            return
        events, hand.events = hand.events, []
        for e in events:
            inp = hand.inputs[e.input]
            fields = {"input": inp.label, "function": inp.function, "joint": inp.joint_name, "what": e.what}
            if e.detail:
                fields["detail"] = e.detail
            self.recorder.event("hand_input", **fields)
            if e.what == "fault":
                self.faults.entry(inp.joint, e.t_s, f"hand input {inp.label}: {e.detail}", 0,
                               reaction="not in drag until fixed and 'dragd start'" if inp.function != "stop"
                               else "held (counted as pressed) until fixed and 'dragd start'", kind="input_fault")
                self.faults.log_later(f"t={e.t_s:.3f} s: hand input {inp.label}: {e.detail}", 3)
            elif e.what == "lost":
                react = {"enable": "counted as released", "stop": "counted as pressed: the arm holds"}.get(
                    inp.function, "ignored while lost")
                self.faults.entry(inp.joint, e.t_s, f"hand input {inp.label} lost: no TPDO with {inp.where()} for "
                                                 f"{int(hand.lost_after[inp.joint])} cycles", 0, reaction=react,
                               kind="input_lost")
                self.faults.log_later(f"t={e.t_s:.3f} s: hand input {inp.label} ({inp.where()}) lost: {react}", 4)
            elif e.what == "pressed":
                self._pressed(inp, e.t_s)
        self.publish()

    def _pressed(self, inp: H.Input, t_s: float) -> None:
        if inp.function == "enable":
            self._spawn(self._enable_pressed(t_s))
        elif inp.function == "mark":
            self._spawn(self._mark(t_s))
        elif inp.function == "teach":
            self._spawn(self._teach(t_s))

    def _spawn(self, coro: Any) -> None:
        self.button_actions += 1
        task = asyncio.get_running_loop().create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def _refused(self, what: str, t_s: float, reason: str) -> None:
        self.last_refusal = {"t_s": round(t_s, 4), "button": what, "reason": reason}
        self.recorder.event("hand_refused", button=what, reason=reason)
        self.faults.log_later(f"t={t_s:.3f} s: {what}: {reason}", 4)
        self.publish()

    async def _enable_pressed(self, t_s: float) -> None:
        """The enabling switch pressed to the middle: a drag request, with the checks ``mode drag`` makes."""
        c = self.controller
        if c.mode == Mode.DRAG:
            return
        try:
            if c.mode in (Mode.IDLE, Mode.FAULT):
                raise ValueError(f"the drives are disabled ({MODE_NAMES[c.mode]}); run 'dragd start' first")
            if c.track.active or self.motions.planning:
                raise ValueError("a motion is running; stop it first")
            await self.motions.wait_cst("enabling switch")
            hand = c.hand
            if hand is None or hand.enable is None or not hand.enable.held:
                return  # released again meanwhile
            self.set_mode("drag", by_enable=True)
            self.publish()  # (the state with the mode it led to)
        except (ValueError, RuntimeError) as exc:
            self._refused("enabling switch", t_s, str(exc).removeprefix("mode drag: "))
        finally:
            self.faults.record()

    async def _mark(self, t_s: float) -> None:
        if self.teaching.recorder is None:
            self._refused("mark button", t_s, "not teaching: press the teach button (or 'dragd teach start') first")
            return
        try:
            self.teaching.mark()
        except ValueError as exc:
            self._refused("mark button", t_s, str(exc))

    async def _teach(self, t_s: float) -> None:
        try:
            if self.teaching.recorder is None:
                await self.teaching.start(self._next_name())
            else:
                await self.teaching.stop()
        except (ValueError, RuntimeError, OSError) as exc:
            self._refused("teach button", t_s, str(exc))
        finally:
            self.faults.record()

    def _next_name(self) -> str:
        """``hand_001``, ``hand_002``, ...: the first name no program in ``replay.program_dir`` has."""
        folder = self.cfg.program_dir
        k = 1
        while resolve_program(f"hand_{k:03d}", folder).with_suffix(".yaml").exists() or \
                resolve_program(f"hand_{k:03d}", folder).with_suffix(".mcap").exists():
            k += 1
        return f"hand_{k:03d}"

    # ------------------------------------------------------------------------------------------ state

    def publish(self) -> None:
        """The whole state as one ``hand`` message (the telemetry's /dragd/hand, the clients' event log)."""
        self.recorder.event("hand", **self.status())

    def status(self) -> dict[str, Any]:
        c = self.controller
        t = c.t
        st = c.permission.status(t)
        hand = c.hand
        st.update(mode=MODE_NAMES[c.mode], bound_lease=c.drag_lease or None, drag_ends=c.drag_ends,
                  last_drag_end=c.last_drag_end, last_refusal=self.last_refusal, exit_ramp_s=c.drag_exit_ramp_s,
                  hold_q_rad=c.q_hold.tolist() if c.mode == Mode.HOLD else None,
                  braking=c._brake_t0 >= 0.0,
                  stop_active=bool(hand.stop_active) if hand is not None else False,
                  inputs=hand.status() if hand is not None else [])
        return st
