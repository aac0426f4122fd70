"""A position stream played back in TRACK: what a client streams (ROS 2's ros2_control, the ``stream`` command)
becomes the path the drives' CSP loops follow.

Samples ``(t, q)`` arrive off the cycle, on the control socket's own thread (the daemon checks each one first:
dragd/daemon/stream.py), and are written into a preallocated ring beyond what the playback may read: one writer (the
client's side: ``append``, ``request_end``) and one reader (the cycle: ``sample``), no lock. The writer fills a slot,
then publishes it by advancing ``written``; at the start of each ``sample`` the cycle takes what was published (and an
end the client asked for) into its own state — the cycle is the only writer of the playback and of what it commands,
and the writer never touches a slot the playback still reads (``room``). The cycle samples the ring through the same
interface as a `Trajectory` (``sample``/``row``), so `Track` runs it with its clock, its monitors and its end into
HOLD. The playback:

- lags the newest sample by ``delay_s`` (the jitter the stream may have), on the sender's time axis (sample spacing
  from the sender's stamps, not from arrival times); the rate varies within ``1 ± catch_up`` to hold that lag
  against clock drift and the start;
- interpolates linearly between samples: the reference never leaves the hull of checked samples (no overshoot
  beyond a limit), its speed is a checked segment's;
- when the stream runs dry (late, lost or ended) it decelerates along the samples it has at ``1 / delay_s`` of its
  rate per second (the path's speed falls to zero within the last samples: nothing is extrapolated);
- ends the motion (``duration_s`` becomes the present time, `Track` holds at the reference) once the playback
  stopped at the last sample after ``end`` or after ``timeout_s`` without a sample, counted in the cycle's time.

Every time here is the trajectory clock ``tau`` that `Track` passes in: the stream reads no clock of its own.
"""

from __future__ import annotations

import math

import numpy as np

from dragd.control.trajectory import Trajectory

CAPACITY = 4096  # samples kept ahead of the playback (a 1 kHz stream 4 s ahead)


class StreamReference(Trajectory):
    """The ring of streamed samples and its playback; ``sample`` is allocation-free (called by `Track.step`).

    A `Trajectory` to `Track`: no velocity table (the cycle differentiates the reference), no feed-forward (the
    prediction ``pred_table`` is the residual monitor's only), ``duration_s`` infinite until the playback ended."""

    def __init__(self, q0: np.ndarray, dt_s: float, delay_s: float, timeout_s: float, max_lead_s: float,
                 catch_up: float, label: str = "stream", capacity: int = CAPACITY) -> None:
        if not (delay_s > 0 and timeout_s > 0 and max_lead_s > delay_s and 0 <= catch_up < 1):
            raise ValueError(f"stream: expected delay_s > 0, timeout_s > 0, max_lead_s > delay_s and catch_up in "
                             f"[0, 1), got {delay_s}, {timeout_s}, {max_lead_s}, {catch_up}")
        q0 = np.asarray(q0, dtype=float)
        n = q0.shape[0]
        self.label = label
        self.dt_s = dt_s
        self.delay_s, self.timeout_s, self.max_lead_s, self.catch_up = delay_s, timeout_s, max_lead_s, catch_up
        self.alpha = 1.0 / delay_s  # the playback rate's largest change per second (running dry: braking)
        self.kp = 2.0  # rate correction per second of lead error (within ± catch_up)
        self.cap = int(capacity)
        self.table = q0[None, :].copy()  # the seed as a one-row table (Motions.validate, the joint count)
        self._init_tables(None, None, 0, [], {})
        self.duration_s = math.inf  # the time the playback stopped after the end (Track then holds)
        self._s = np.zeros(self.cap)  # sample times on the stream's own axis (s)
        self._q = np.zeros((self.cap, n))
        self._pred = np.zeros((self.cap, n))  # M q̈ + C q̇ at each sample (the residual monitor's)
        self.pred_table = self._pred
        self._q[0] = q0  # the seed: where the arm was when the stream opened
        # the client's side (written off the cycle, read by the cycle only through ``written`` and ``_end_request``)
        self.written = 1  # slots written and published (absolute index of the next; the seed is the first)
        self.accepted = 0  # the client's samples accepted
        self.offset_s = 0.0  # stream axis = sender time + offset (set by the first sample)
        self.t_last = -math.inf  # the newest sample's sender time
        self._end_request: tuple[str, str] | None = None  # (kind, outcome) the client's side asked for
        # the cycle's side
        self.count = 1  # slots the playback reads (absolute index of the next): the published ones it took
        self.samples = 0  # the client's samples the playback took
        self.start_q = q0.copy()
        self.p = 0.0  # playback position on the stream axis
        self.rate = 0.0  # d p / d tau
        self.now = 0.0  # tau of the last cycle
        self.last_arrival = 0.0  # tau when the newest sample arrived (the opening counts as one)
        self.lead_s = 0.0  # newest sample − playback, as of the last cycle
        self.min_rem_s = math.inf  # the least buffer the playback had while streaming (0: it ran dry)
        self.dry_cycles = 0  # cycles the playback was slowed by a buffer running dry
        self.k = 0  # absolute index of the segment the playback is in
        self.f = 0.0
        self.ended = False
        self.end_kind: str | None = None  # closed | timeout | refused
        self.outcome = "done"  # what Track reports when the playback ends (the track_end event's text)
        self._timeout_text = f"stream timeout: no sample for {timeout_s:g} s"

    # -- the client's side (between cycles)

    def stream_time(self, t_s: float) -> float:
        """Where a sample stamped ``t_s`` (sender time) lies on the stream axis."""
        return (self.p + self.delay_s) if self.accepted == 0 else t_s + self.offset_s

    def newest(self, back: int = 0) -> tuple[float, np.ndarray] | None:
        """The ``back``-th newest sample written (0: the newest, the seed included) as (stream time, q), or None."""
        i = self.written - 1 - back
        if i < 0 or self.written - i > self.cap:
            return None
        return float(self._s[i % self.cap]), self._q[i % self.cap]

    def room(self) -> int:
        """Samples that can still be appended (the playback's segment ``k`` read as of its last cycle: it only grows,
        so an older value errs on the safe side)."""
        return self.cap - (self.written - self.k)

    @property
    def closing(self) -> bool:
        """The stream takes no more samples: it ended, or the client's side asked it to."""
        return self.ended or self._end_request is not None

    def append(self, t_s: float, q: np.ndarray, pred_Nm: np.ndarray) -> None:
        """A checked sample (its time after the newest, room in the ring: the caller checked), published to the cycle
        once written whole."""
        s = self.stream_time(t_s)
        if self.accepted == 0:
            self.offset_s = s - t_s
        i = self.written % self.cap
        self._s[i] = s
        self._q[i] = q
        self._pred[i] = pred_Nm
        self.accepted += 1
        self.t_last = t_s
        self.written += 1  # (last: the cycle reads the slot only after this)

    def request_end(self, kind: str, outcome: str) -> None:
        """The client's side: no more samples (closed, refused); the cycle ends the stream at its next step, after
        the samples written before."""
        if self._end_request is None:
            self._end_request = (kind, outcome)

    def end(self, kind: str, outcome: str) -> None:
        """The cycle's side: no more samples, the playback runs out the samples it has, then the motion ends with
        ``outcome``."""
        if not self.ended:
            self.ended, self.end_kind, self.outcome = True, kind, outcome

    # -- the cycle's side (Track.step)

    def take(self) -> None:
        """What the client's side published since the last cycle: its samples (they arrived now), then its end."""
        written = self.written
        if written != self.count:
            self.samples += written - self.count
            self.count = written
            self.last_arrival = self.now
        req = self._end_request
        if req is not None and not self.ended:
            self.end(*req)

    def sample(self, tau: float, out: np.ndarray) -> np.ndarray:
        """The reference at trajectory time ``tau``: take what the client's side published, advance the playback,
        interpolate the samples."""
        dtau = tau - self.now if tau > self.now else 0.0
        self.now = tau
        self.take()
        if not self.ended and tau - self.last_arrival > self.timeout_s:
            self.end("timeout", self._timeout_text)
        cap = self.cap
        s_last = self._s[(self.count - 1) % cap]
        rem = s_last - self.p
        if self.samples > 0:
            if self.ended:
                target = 1.0
            else:
                err = (rem + tau - self.last_arrival - self.delay_s) * self.kp
                target = 1.0 + (self.catch_up if err > self.catch_up else -self.catch_up if err < -self.catch_up
                                else err)
                if rem < self.min_rem_s:
                    self.min_rem_s = rem
            # the rate moves toward its target at most alpha per second, and never above what can still stop
            # within the samples there are (the braking envelope)
            step = self.alpha * dtau
            r = self.rate + step if target > self.rate + step else self.rate - step if target < self.rate - step \
                else target
            brake = math.sqrt(2.0 * self.alpha * rem) if rem > 0.0 else 0.0
            if r > brake:
                r = brake
                if not self.ended:
                    self.dry_cycles += 1
            self.rate = r if r > 0.0 else 0.0
            self.p += self.rate * dtau
            if self.p > s_last:
                self.p = s_last
        self.lead_s = s_last - self.p
        if self.ended and self.lead_s <= 1e-9 and self.duration_s == math.inf:
            self.duration_s = tau
        k = self.k
        while k + 1 < self.count and self._s[(k + 1) % cap] <= self.p:
            k += 1
        self.k = k
        if k + 1 < self.count:
            s0 = self._s[k % cap]
            self.f = (self.p - s0) / (self._s[(k + 1) % cap] - s0)
        else:
            self.f = 0.0
        return self.row(self._q, out)

    def row(self, table: np.ndarray, out: np.ndarray) -> np.ndarray:
        """A ring (positions, the prediction) at the playback's place of the last ``sample``."""
        cap, k, f = self.cap, self.k, self.f
        out[:] = table[k % cap]
        if f > 0.0:
            np.subtract(table[(k + 1) % cap], table[k % cap], out=self._d)
            self._d *= f
            out += self._d
        return out
