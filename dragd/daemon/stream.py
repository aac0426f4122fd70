"""Position streams into TRACK: ``stream_open``, ``stream`` (one sample), ``stream_close`` (docs/PROTOCOL.md).

A client (the ROS 2 bridge's command topic, any socket client) opens a stream from HOLD: the drives switch to CSP
through the same entry as a ``track`` (`Motions.track`: the same checks, the same monitors, the same end into HOLD)
and the cycle plays the samples back (dragd/control/stream.py). Every sample is checked before it joins, as a
``track`` file is: finite, within the position limits and the drives' 32-bit encoding, the first one at the arm's
pose, no faster than ``safety.encoder_plausible_speed_rad_s`` nor accelerating harder than
``safety.track_acceleration_limit_rad_s2`` between samples, and a rigid-body effort within every joint's
``current_limit_A`` (accelerations over spans of at least 10 ms, so that stamp jitter at high rates is no step).
A refused sample ends the stream (the arm stops along the samples it has, then holds).

Threads: ``stream`` and ``stream_close`` are answered on the control socket's own thread (dragd/server.py's
`ThreadedControlServer`), never on the cycle's: a client's samples, however many, cost the cycle nothing but taking
what was published (`StreamReference.take`, at the start of its playback step). The checks read the cycle's state
(the mode, the playback's place, the limits) and write only the stream's client side (its ring beyond the playback,
its end request); ``stream_open`` (the drives' switch to CSP) runs on the cycle's loop as every other command.

A client that dies, hangs or is cut off stops sending: after ``stream.timeout_s`` without a sample (the cycle's time)
the stream ends the same way. No request keeps a stream alive but a valid sample: the deadline is the daemon's.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np

from dragd.control.modes import MODE_NAMES, Mode
from dragd.control.stream import StreamReference
from dragd.daemon.motion import START_TOLERANCE_RAD

OFF_CYCLE_COMMANDS = frozenset({"stream", "stream_close"})  # answered on the control socket's thread
ACCEL_SPAN_S = 0.01  # a sample's acceleration is checked over velocities across at least this long
ACCEL_SEARCH = 256  # ... looking at most this many samples back for them

if TYPE_CHECKING:
    from dragd.config import Config
    from dragd.control.controller import Controller
    from dragd.daemon.cycle import Cycle
    from dragd.daemon.motion import Motions
    from dragd.daemon.recording import Recorder
    from dragd.hardware.scaling import Scaling
    from dragd.model import RobotModel


class Streams:
    """The daemon's position stream (one at a time): opening, checking and appending samples, its status."""

    def __init__(self, cfg: Config, controller: Controller, cycle: Cycle, motions: Motions, model: RobotModel,
                 scaling: Scaling, recorder: Recorder) -> None:
        """``motions``: a stream is a motion (its checks, the CSP switch, TRACK, the end into HOLD)."""
        self.cfg, self.controller, self.cycle, self.motions = cfg, controller, cycle, motions
        self.model, self.scaling, self.recorder = model, scaling, recorder
        self.ref: StreamReference | None = None
        self.id = 0  # the running (or last) stream's number; a sample names it
        self.opened = 0
        self.refused = 0  # samples refused (each ended its stream)
        self.opening = False  # the drives are switching to CSP for a stream
        self._pin: Any = None
        self._model: Any = None  # the Pinocchio model the data below belongs to (a payload change replaces it)
        self._data: Any = None

    # ------------------------------------------------------------------------------------------ state

    def running(self) -> bool:
        """The stream is the motion in TRACK (it may be running out its last samples after its end)."""
        c = self.controller
        return self.ref is not None and c.track.trajectory is self.ref and c.mode == Mode.TRACK

    def _live(self, stream: int, what: str) -> StreamReference:
        ref = self.ref
        if ref is None or stream != self.id:
            raise ValueError(f"{what}: no stream {stream} (the last one opened is {self.id or 'none'}); "
                             "'stream_open' first")
        if ref.closing or not self.running():
            raise ValueError(f"{what}: stream {stream} ended ({self._outcome(ref)}); open a new one from hold")
        return ref

    def _outcome(self, ref: StreamReference) -> str:
        if ref.end_kind is not None:
            return ref.outcome
        req = ref._end_request
        if req is not None:
            return req[1]
        c = self.controller
        if c.mode == Mode.FAULT:
            return "fault"
        return "stopped (replay_stop, stop or a monitor: see faults)"

    # ------------------------------------------------------------------------------------------ commands

    async def open(self, label: str = "stream") -> dict[str, Any]:
        """Switch the drives to CSP and play a stream from the present pose (HOLD only)."""
        c = self.controller
        if c.mode != Mode.HOLD:
            raise ValueError(f"stream_open: expected the arm held (hold), it is {MODE_NAMES[c.mode]}"
                             + (": a stream never takes the arm from the operator's hand; 'dragd mode hold' first"
                                if c.mode == Mode.DRAG else ""))
        if c.track.active or self.motions.planning or self.running() or self.opening:
            raise ValueError("stream_open: a motion is running (or being planned, or a stream opening); stop it first")
        compact = self.motions.untargeted_buses()  # (drives that follow motions in CST need no position targets)
        if compact:
            raise ValueError(f"stream_open: bus(es) {', '.join(compact)} use the 'compact' PDO layout, which carries "
                             "no position targets; streams (CSP) need the 'shared' layout")
        sc = self.cfg.stream
        ref = StreamReference(self.cycle.est.q_rad.copy(), self.cycle.dt, sc.delay_s, sc.timeout_s, sc.max_lead_s,
                              sc.catch_up, label=str(label))
        self.opening = True
        try:
            await self.motions.track(ref)  # the track's checks, the CSP switch, TRACK
        finally:
            self.opening = False
        self.id += 1
        self.opened += 1
        self.ref = ref
        self.recorder.event("stream_open", stream=self.id, label=str(label), delay_s=sc.delay_s, timeout_s=sc.timeout_s)
        return {"stream": self.id, "mode": MODE_NAMES[c.mode], "delay_s": sc.delay_s, "timeout_s": sc.timeout_s,
                "max_lead_s": sc.max_lead_s}

    def sample(self, stream: int, t_s: float, q_rad: list[float]) -> dict[str, Any]:
        """One sample (sender time ``t_s``, positions in the configuration's joint order), checked, appended."""
        ref = self._live(stream, "stream")
        try:
            q, pred = self._check(ref, float(t_s), q_rad)
        except ValueError as exc:
            self.refused += 1
            ref.request_end("refused", f"stream refused: {exc}")
            raise ValueError(f"stream {stream}: {exc}; the stream ends (the arm stops along its samples, "
                             "then holds)") from None
        ref.append(float(t_s), q, pred)
        return {"samples": ref.accepted, "lead_s": round(ref.lead_s, 4)}

    def close(self, stream: int) -> dict[str, Any]:
        """The client's end of the stream: the playback runs out the samples it has, then the arm holds."""
        ref = self._live(stream, "stream_close")
        ref.request_end("closed", "stream closed")
        return {"stream": stream, "samples": ref.accepted}

    # ------------------------------------------------------------------------------------------ the checks

    def _check(self, ref: StreamReference, t_s: float, q_rad: list[float]) -> tuple[np.ndarray, np.ndarray]:
        """A sample as the ``track`` checks a file; ValueError naming the joint, the value and the limit."""
        c = self.controller
        names = self.cfg.joint_names
        q = np.asarray(q_rad, dtype=float)
        if q.shape != (c.n,) or not np.all(np.isfinite(q)):
            raise ValueError(f"q_rad: expected {c.n} finite joint positions ({', '.join(names)}), got "
                             f"{list(q_rad)[:8]}")
        if not math.isfinite(t_s):
            raise ValueError(f"t_s: expected a finite time, got {t_s}")
        if t_s <= ref.t_last:
            raise ValueError(f"t_s {t_s:.6f} is not after the previous sample's {ref.t_last:.6f}")
        s = ref.stream_time(t_s)
        p = ref.p
        if s - p > ref.max_lead_s:
            latest = p + ref.max_lead_s - ref.offset_s  # the latest stamp the playback's place allows, sender time
            raise ValueError(f"t_s {t_s:.6f}: expected at most {latest:.6f} (stream.max_lead_s {ref.max_lead_s:g} s "
                             f"after the playback, which is at sender time {p - ref.offset_s:.6f}): the sample lies "
                             f"{s - p:.3f} s ahead of it — a gap in the samples (lost or late ones: the playback "
                             "stopped at the last it had), a sender's clock that jumped, or samples sent faster than "
                             "their stamps advance")
        if ref.room() < 1:
            raise ValueError(f"{ref.cap} samples ahead of the playback: the buffer is full")
        lo, hi = c.safety.lim_lo_rad, c.safety.lim_hi_rad
        out = (q < lo) | (q > hi)
        if out.any():
            j = int(np.argmax(out))
            raise ValueError(f"{names[j]} at {q[j]:+.4f} rad leaves its position limits [{lo[j]:+.3f}, {hi[j]:+.3f}]")
        sc = self.scaling
        counts = (q * sc.counts_per_rev / (2 * np.pi)) * sc.direction + sc.offset_counts
        if np.abs(counts).max() >= 2 ** 31:
            j = int(np.argmax(np.abs(counts)))
            raise ValueError(f"{names[j]}'s target is beyond the drives' 32-bit position encoding")
        prev = ref.newest(0)
        assert prev is not None
        s0, q0 = prev
        if ref.accepted == 0:
            err = np.abs(q - q0)
            if err.max() > START_TOLERANCE_RAD:
                j = int(np.argmax(err))
                raise ValueError(f"the first sample is {np.degrees(err[j]):.2f}° from the arm's pose on {names[j]} "
                                 f"(max {np.degrees(START_TOLERANCE_RAD):.1f}°); a stream starts where the arm is")
        h = s - s0
        v = (q - q0) / h
        vmax = self.cfg.safety.encoder_plausible_speed_rad_s
        j = int(np.argmax(np.abs(v)))
        if abs(v[j]) > vmax:
            raise ValueError(f"{names[j]} would move at {abs(v[j]):.2f} rad/s between samples at t_s {t_s:.6f} "
                             f"(a step in the target?), beyond safety.encoder_plausible_speed_rad_s {vmax:g}")
        a = self._acceleration(ref, s, q)
        amax = self.cfg.safety.track_acceleration_limit_rad_s2
        j = int(np.argmax(np.abs(a)))
        if abs(a[j]) > amax:
            raise ValueError(f"{names[j]} would accelerate at {abs(a[j]):.1f} rad/s² at t_s {t_s:.6f}, beyond "
                             f"safety.track_acceleration_limit_rad_s2 {amax:g}")
        full, grav = self._effort(q, v, a)
        need = np.abs(full) / c.kt
        over = need - c.params.current_limit_A
        j = int(np.argmax(over))
        if over[j] > 0:
            raise ValueError(f"{names[j]} would need {need[j]:.2f} A (rigid-body effort {full[j]:+.1f} N·m), beyond "
                             f"its current_limit_A {c.params.current_limit_A[j]:.2f} A: slow the motion down")
        return q, full - grav

    @staticmethod
    def _acceleration(ref: StreamReference, s: float, q: np.ndarray) -> np.ndarray:
        """The acceleration the sample asks for, from velocities over spans of at least ``ACCEL_SPAN_S`` back to the
        samples before it: at 500 Hz - 1 kHz a stamp taken 50 µs off its position would make the difference of
        successive samples' velocities a noise of tens of rad/s² (a step still shows: in the speed check, per
        segment, and here over the span)."""
        def back_to(t: float, start: int) -> tuple[int, float, np.ndarray] | None:
            """The newest sample from ``start`` back stamped at or before ``t``, else the oldest one kept."""
            found = None
            for k in range(start, start + ACCEL_SEARCH):
                got = ref.newest(k)
                if got is None:
                    break
                found = (k, got[0], got[1])
                if got[0] <= t:
                    break
            return found

        one = back_to(s - ACCEL_SPAN_S, 0)
        assert one is not None  # (the seed at least)
        k1, s1, q1 = one
        two = back_to(s1 - ACCEL_SPAN_S, k1 + 1)
        if two is None:  # only the seed before: the first sample
            return np.zeros_like(q)
        _k2, s2, q2 = two
        return 2.0 * ((q - q1) / (s - s1) - (q1 - q2) / (s1 - s2)) / (s - s2)

    def _effort(self, q: np.ndarray, v: np.ndarray, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The rigid-body effort M q̈ + C q̇ + G and G alone [N·m] (the daemon's model, its own scratch data)."""
        if self._pin is None:
            import pinocchio

            self._pin = pinocchio
        model = self.model.model
        if model is not self._model:
            self._model, self._data = model, model.createData()
        pin = self._pin
        full = np.array(pin.rnea(model, self._data, q, v, a))
        grav = np.array(pin.computeGeneralizedGravity(model, self._data, q))
        return full, grav

    # ------------------------------------------------------------------------------------------ status

    def status(self) -> dict[str, Any] | None:
        """The running (or last) stream: its state, outcome, samples, lead and playback rate."""
        ref = self.ref
        if ref is None:
            return None
        running = self.running()
        state = ("running" if not ref.closing else "ending") if running else "ended"
        req = ref._end_request
        kind = ref.end_kind if ref.end_kind is not None else req[0] if req is not None else None
        return {"stream": self.id, "state": state, "label": ref.label,
                "end": kind if kind is not None else (None if running else "stopped"),
                "outcome": None if state == "running" else self._outcome(ref),
                "samples": ref.accepted, "lead_s": round(ref.lead_s, 4), "rate": round(ref.rate, 4),
                "min_buffer_s": None if ref.min_rem_s == math.inf else round(ref.min_rem_s, 4),
                "dry_cycles": ref.dry_cycles, "refused": self.refused, "opened": self.opened}
