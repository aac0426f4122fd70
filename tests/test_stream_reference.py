"""The streamed reference (dragd/control/stream.py) against a simulated cycle: lag, drift, jitter, running dry,
timeout and the end through Track, without processes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dragd.control.stream import StreamReference
from dragd.control.track import Track, TrackLimits

pytestmark = pytest.mark.unit

DT = 0.001
N = 6


def ref(q0=None, **kw) -> StreamReference:
    args = dict(delay_s=0.05, timeout_s=0.2, max_lead_s=1.0, catch_up=0.1)
    args.update(kw)
    return StreamReference(np.zeros(N) if q0 is None else q0, DT, **args)


def motion(t: float) -> np.ndarray:
    return 0.3 * np.sin(2 * np.pi * 0.5 * t) * np.ones(N)


def run(r: StreamReference, arrivals: list[tuple[float, float]], until: float) -> dict[str, np.ndarray]:
    """Cycles every DT up to ``until``: at each, the samples whose arrival time has come (sender time, arrival
    time) are appended, then the cycle samples the reference. Returns the reference and the playback per cycle."""
    out = np.zeros(N)
    taus, refs, ps, rates = [], [], [], []
    k = 0
    for i in range(int(round(until / DT))):
        tau = i * DT
        while k < len(arrivals) and arrivals[k][1] <= tau:
            ts = arrivals[k][0]
            r.append(ts, motion(ts), np.zeros(N))
            k += 1
        r.sample(tau, out)
        taus.append(tau)
        refs.append(out.copy())
        ps.append(r.p)
        rates.append(r.rate)
    return {"tau": np.array(taus), "ref": np.array(refs), "p": np.array(ps), "rate": np.array(rates)}


def test_a_steady_stream_is_played_back_delay_s_behind_on_the_senders_time_axis():
    r = ref(motion(0.0))
    period = 0.01
    arrivals = [(100.0 + k * period, 0.002 + k * period) for k in range(300)]  # sender clock starts at 100 s
    got = run(r, arrivals, 2.9)
    late = got["tau"] > 1.0
    # the playback lags the newest sample by the delay (its sawtooth between samples aside)
    newest_sender = np.array([100.0 + math.floor((t - 0.002) / period) * period for t in got["tau"][late]])
    lag = newest_sender + r.offset_s - got["p"][late]
    assert 0.035 < lag.min() and lag.max() < 0.065, (lag.min(), lag.max())
    assert np.abs(got["rate"][late] - 1.0).max() < 0.03
    assert r.dry_cycles == 0
    # the reference is the sent motion, delayed: compare with the motion at the playback's sender time
    sender_t = got["p"][late] - r.offset_s
    want = np.array([motion(t) for t in sender_t])
    assert np.abs(got["ref"][late] - want).max() < 0.3 * (2 * np.pi * 0.5) ** 2 * period ** 2  # linear interp.


@pytest.mark.parametrize("drift", [-0.03, 0.03])
def test_clock_drift_between_sender_and_daemon_is_absorbed(drift):
    r = ref(motion(0.0))
    period = 0.01
    # the sender's clock runs (1 + drift) against the daemon's: its 10 ms arrive every 10 ms / (1 + drift)
    arrivals = [(k * period, 0.002 + k * period / (1 + drift)) for k in range(900)]
    got = run(r, arrivals, 8.5)
    late = got["tau"] > 3.0
    assert abs(np.median(got["rate"][late]) - (1 + drift)) < 0.005
    assert r.dry_cycles == 0 and r.min_rem_s > 0.02, (r.dry_cycles, r.min_rem_s)


def test_jitter_within_the_delay_never_runs_the_buffer_dry():
    rng = np.random.default_rng(5)
    r = ref(motion(0.0))
    period = 0.01
    arrivals = sorted((k * period, 0.002 + k * period + float(rng.uniform(0, 0.02))) for k in range(300))
    got = run(r, arrivals, 2.9)
    assert r.dry_cycles == 0, r.min_rem_s
    assert np.abs(np.diff(got["rate"])).max() <= r.alpha * DT + 1e-12  # the rate changes smoothly


def test_running_dry_brakes_along_the_samples_and_stops_on_the_last():
    r = ref(motion(0.0))
    period = 0.01
    arrivals = [(k * period, 0.002 + k * period) for k in range(50)]  # the sender dies at 0.49 s, mid-swing
    got = run(r, arrivals, 1.5)
    last = motion(49 * period)
    assert r.ended and r.end_kind == "timeout" and r.outcome == "stream timeout: no sample for 0.2 s"
    assert np.abs(got["ref"][-1] - last).max() == 0.0  # exactly the last sample: nothing extrapolated
    assert np.isfinite(r.duration_s) and 0.49 + 0.2 < r.duration_s < 0.49 + 0.2 + 0.01
    # never beyond it: the playback never passes the newest sample
    assert (got["p"] <= 49 * period + r.offset_s + 1e-12).all()
    # the braking: the rate falls at about alpha per second (the discrete envelope: within 10 %; the last steps
    # below a tenth of the speed aside), so the path decelerates smoothly
    stop = (got["tau"] > 0.49) & (got["rate"] > 0.1)
    assert got["rate"][-1] == 0.0 and (np.diff(got["rate"][stop]) >= -1.1 * r.alpha * DT).all()


def test_the_clients_end_runs_out_the_samples_then_finishes():
    r = ref(motion(0.0))
    arrivals = [(k * 0.01, 0.002 + k * 0.01) for k in range(30)]
    out = np.zeros(N)
    k = 0
    tau = 0.0
    while k < len(arrivals):
        while k < len(arrivals) and arrivals[k][1] <= tau:
            r.append(arrivals[k][0], motion(arrivals[k][0]), np.zeros(N))
            k += 1
        r.sample(tau, out)
        tau += DT
    r.end("closed", "stream closed")
    while not np.isfinite(r.duration_s):
        r.sample(tau, out)
        tau += DT
        assert tau < 1.0
    assert r.outcome == "stream closed" and np.abs(out - motion(0.29)).max() == 0.0
    assert r.duration_s - 0.3 < 0.1  # the last ~50 ms of samples and the braking


def test_track_ends_a_stream_into_hold_with_its_reason():
    n = N
    one = np.ones(n)
    limits = TrackLimits(tracking_error_rad=one, residual_current_A=one * 100, residual_filter_alpha=0.1,
                         acceleration_rad_s2=one * 2, kp_Nm_per_rad=one, kd_Nm_s_per_rad=one, ki_Nm_per_rad_s=one,
                         integral_max_Nm=one, output_max_Nm=one, ramp_s=0.4, monitor_cycles=20,
                         position_lo_rad=-one * 3, position_hi_rad=one * 3)
    tr = Track(n, DT, limits, [f"j{i}" for i in range(n)])
    r = ref()
    q = np.zeros(n)
    tr.begin(r, 0.0, q, 1.0, 1)
    res = None
    t = 0.0
    for i in range(1, 1000):
        t = i * DT
        if i <= 20:
            r.append(i * 0.005, np.full(n, 0.001 * i), np.zeros(n))
        res = tr.step(t, tr.q_ref.copy(), np.zeros(n), np.zeros(n), 0)
        if res is not None:
            break
    assert res == "stream timeout: no sample for 0.2 s", res
    assert 0.2 < t < 0.35
    assert np.allclose(tr.q_ref, 0.02)  # where the last sample was


def test_the_cycle_takes_what_the_client_published_at_its_next_step_and_the_end_after_it():
    r = ref()
    out = np.zeros(N)
    r.sample(0.0, out)
    r.append(0.0, np.zeros(N), np.zeros(N))
    r.append(0.01, np.full(N, 0.001), np.zeros(N))
    r.request_end("closed", "stream closed")
    # the client's side: accepted, not yet the playback's (the cycle is the only writer of what it plays)
    assert (r.accepted, r.written, r.samples, r.count, r.ended, r.closing) == (2, 3, 0, 1, False, True)
    r.sample(0.001, out)
    assert (r.samples, r.count, r.last_arrival) == (2, 3, 0.001)
    assert r.ended and r.end_kind == "closed" and r.outcome == "stream closed"
    tau = 0.001
    while not np.isfinite(r.duration_s):  # the end ran out the samples written before it
        tau += DT
        r.sample(tau, out)
        assert tau < 1.0
    assert np.array_equal(out, np.full(N, 0.001))


def test_samples_written_from_another_thread_reach_the_playback_whole_and_in_order():
    import threading
    import time

    total = 3000
    r = ref(capacity=64)
    out = np.zeros(N)
    stop = threading.Event()

    def client() -> None:  # as the control socket's thread: appends as fast as the ring has room
        k = 0
        while k < total and not stop.is_set():
            if r.room() < 1:
                time.sleep(0)  # (the GIL to the playback, as a socket thread waiting for its client would)
                continue
            r.append(k * 0.001, np.full(N, k * 1e-6), np.full(N, float(k)))
            k += 1

    th = threading.Thread(target=client)
    th.start()
    seen = 0
    tau = 0.0
    guard = time.monotonic() + 120.0  # a hang guard only: the verdict never depends on the pace
    try:
        while r.samples < total:
            # The playback's time advances once the writer has published something new, or when the ring is full
            # (the writer then waits for the playback): a writer the host starves never lets the stream run dry,
            # which would end it (the timeout is counted in the playback's time).
            while r.written == r.count and r.room() >= 1 and th.is_alive():
                assert time.monotonic() < guard, "the writer thread published nothing for 120 s"
                time.sleep(0)
            r.sample(tau, out)
            # every slot the playback may read is whole: its position, its prediction and its time agree
            for i in range(max(r.k, 1), r.count):
                j = i - 1  # (slot 0 is the seed)
                s = r._s[i % r.cap] - r.offset_s
                assert np.all(r._q[i % r.cap] == j * 1e-6) and np.all(r._pred[i % r.cap] == float(j)), i
                assert abs(s - j * 0.001) < 1e-9, (i, s)
            assert r.samples >= seen
            seen = r.samples
            tau += DT
            assert tau < 60.0
    finally:
        stop.set()
        th.join()
    assert r.samples == r.accepted == total and not r.ended
