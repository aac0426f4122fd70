"""The daemon's fault sink: the controller's events after each cycle and command, recorded once.

The cycle never logs or allocates: what it decides (a fault, a protective stop, a mode change, a motion's end, a
drag's end) is queued as a controller event. ``FaultSink.record`` drains that queue after the cycle (and after each
command): the fault list (``status``'s ``faults``), journal lines with their priority, telemetry events, and the
handlers the daemon's parts registered per event kind (``on``). A part that reacts to a fault outside the cycle
(EMCY, a silent drive, a failed SDO switch) calls ``fault``.
"""

from __future__ import annotations

import asyncio
import os
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from dragd.hardware.cia402 import emcy_name

if TYPE_CHECKING:
    from dragd.control.controller import Controller, Event
    from dragd.daemon.recording import Recorder

MAX_FAULTS = 100  # the fault list keeps the newest
CONTACT_REACTION = {"stop": "hold", "retract": "retract", "compliant": "drag"}  # a contact's entry: what the arm did
LOG_ERR, LOG_WARNING, LOG_NOTICE, LOG_INFO = 3, 4, 5, 6  # syslog priorities (journalctl -p)

Log = Callable[..., None]  # log(text) or log(text, priority)
Handler = Callable[["Event"], object]


def journal_line(text: str, priority: int = LOG_INFO, journal: bool | None = None) -> str:
    """One log line; under systemd (stdout is the journal: $JOURNAL_STREAM) prefixed ``<priority>``, which journald
    takes as the line's priority, so ``journalctl -p warning`` shows dragd's faults."""
    if journal is None:
        journal = bool(os.environ.get("JOURNAL_STREAM"))
    return f"<{priority}>dragd: {text}" if journal else f"dragd: {text}"


def print_log(text: str, priority: int = LOG_INFO) -> None:
    print(journal_line(text, priority), flush=True)


class FaultSink:
    """The fault list, the journal and the routing of the controller's events to the parts that handle them."""

    def __init__(self, controller: Controller, recorder: Recorder, joint_names: list[str], node_ids: list[int],
                 log: Log) -> None:
        self.controller, self.recorder = controller, recorder
        self.joint_names, self.node_ids = joint_names, node_ids
        self.log = log
        self.faults: list[dict[str, Any]] = []
        self.fault_count = 0  # every fault entry since the start (the list is cleared by 'start', capped)
        self.protective_stops = 0
        self._contact_entry: dict[str, Any] | None = None  # the last contact's entry (its end and peaks follow)
        self._handlers: dict[str, list[Handler]] = {}
        self._before: list[Callable[[], None]] = []

    def on(self, kind: str, handler: Handler) -> None:
        """``handler(event)`` for each controller event of ``kind`` (after the sink's own entry and log line);
        kinds the sink does not record itself (drag_end, lease, ...) go to their handlers only."""
        self._handlers.setdefault(kind, []).append(handler)

    def before_record(self, fn: Callable[[], None]) -> None:
        """``fn()`` before each recording (a part that turns its own state into controller events: the hand)."""
        self._before.append(fn)

    # ------------------------------------------------------------------------------------------ faults

    def fault(self, joint: int | None, text: str, code: int = 0) -> None:
        """A safety reaction from outside the cycle (EMCY, a silent drive, a drive that failed a switch)."""
        self.controller.fault(joint, text, code)
        self.record()

    def on_emcy(self, joint: int, code: int, register: int) -> None:
        self.fault(joint, f"EMCY 0x{code:04X} ({emcy_name(code)}; error register 0x{register:02X}) "
                          f"from node {self.node_ids[joint]}", code)

    def entry(self, joint: int | None, t_s: float, text: str, code: int, **extra: Any) -> dict[str, Any]:
        """A fault list entry (status ``faults``; counted in ``fault_count``)."""
        self.fault_count += 1
        e = {"t_s": round(t_s, 4), "joint": self.joint_names[joint] if joint is not None else None,
             "node_id": self.node_ids[joint] if joint is not None else None, "code": code, "text": text, **extra}
        self.faults.append(e)
        if len(self.faults) > MAX_FAULTS:
            del self.faults[:-MAX_FAULTS]
        return e

    # ------------------------------------------------------------------------------------------ events

    def record(self) -> None:
        """What the cycle decided, recorded: the fault list, log lines (after the cycle), telemetry events."""
        for fn in self._before:
            fn()
        events = self.controller.events
        if not events:
            return
        self.controller.events = []
        rec = self.recorder
        for ev in events:
            f = ev.fields or {}
            if ev.kind == "mode":
                rec.event("mode", **f)
            elif ev.kind == "fault":
                self.entry(ev.joint, ev.t_s, ev.text, ev.code)
                self.log_later(f"fault at t={ev.t_s:.3f} s: {ev.text}", LOG_ERR)
                self._dispatch(ev)
                if f.get("new"):
                    rec.event("fault", text=ev.text, code=ev.code)
                continue
            elif ev.kind == "protective_stop":
                kind = f.get("kind")
                self.protective_stops += 1
                if kind == "contact":  # the joints, residual and estimated contact torque (docs/CONTACT.md)
                    extra = {k: v for k, v in f.items() if k not in ("kind", "reaction")}
                    self._contact_entry = self.entry(ev.joint, ev.t_s, ev.text, 0, kind=kind,
                                                     reaction=CONTACT_REACTION.get(str(f.get("reaction")), "hold"),
                                                     **extra)
                    rec.event("contact", text=ev.text, **f)
                else:
                    self.entry(ev.joint, ev.t_s, ev.text, 0, reaction="hold", kind=kind)
                self.log_later(f"protective stop at t={ev.t_s:.3f} s: {ev.text}", LOG_WARNING)
                rec.event("protective_stop", kind=kind, text=ev.text)
            elif ev.kind == "contact_end":
                entry = self._contact_entry
                if entry is not None and entry.get("t_end_s") is None:
                    entry.update(t_end_s=f.get("t_end_s"), peak_Nm=f.get("peak_Nm"), peak_A=f.get("peak_A"))
                rec.event("contact_end", t_end_s=f.get("t_end_s"), joints=f.get("names"), peak_Nm=f.get("peak_Nm"))
            elif ev.kind == "track_end":
                self._dispatch(ev)
                rec.event("track_end", label=f.get("label"), outcome=ev.text)
                continue
            self._dispatch(ev)

    def _dispatch(self, ev: Event) -> None:
        for handler in self._handlers.get(ev.kind, ()):
            handler(ev)

    # ------------------------------------------------------------------------------------------ the journal

    def log_later(self, text: str, priority: int = LOG_INFO) -> None:
        try:  # logged after this cycle, not inside it
            asyncio.get_running_loop().call_soon(self.log_at, text, priority)
        except RuntimeError:
            self.log_at(text, priority)

    def log_at(self, text: str, priority: int) -> None:
        """A log line with its journald priority (a custom ``log`` that takes only the text gets only the text)."""
        if priority == LOG_INFO:
            self.log(text)
            return
        try:
            self.log(text, priority)
        except TypeError:
            self.log(text)
