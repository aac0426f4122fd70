"""The cycle's compiled estimate and output steps (dragd/daemon/kernels.py) against their numpy reference.

Randomised sequences: encoder counts that wrap around int32, late and missing samples (joints not fresh), jumps the
plausibility check rejects (once, and persistent: the fault), velocity resets, commands beyond the int16 torque range
and NaN. Every array must match the reference exactly (the velocity filter's non-uniform gain to a few ulp: libm's exp
against numpy's).
"""

from __future__ import annotations

import math
import tracemalloc

import numpy as np
import pytest

from dragd.config import load_config
from dragd.control import plausible
from dragd.control.estimate import VelocityEstimator
from dragd.control.plausible import EncoderPlausibility
from dragd.daemon.cycle import Cycle
from dragd.daemon.kernels import kernels
from dragd.hardware.io import Feedback
from dragd.hardware.scaling import Scaling

from conftest import DEFAULT_CONFIG

pytestmark = [pytest.mark.unit, pytest.mark.skipif(kernels() is None, reason="numba is not installed")]

N = 6


@pytest.fixture(scope="module")
def scaling() -> Scaling:
    cfg = load_config(DEFAULT_CONFIG)
    sc = Scaling.from_config(cfg)
    # one joint reversed, offsets: the conversions' signs and offsets are exercised
    direction = np.array([1.0, -1.0, 1.0, 1.0, -1.0, 1.0])
    cpr = sc.counts_per_rev
    return Scaling(rad_per_count=direction * 2.0 * math.pi / cpr, counts_per_rad=cpr / (2.0 * math.pi) * direction,
                   offset_counts=np.array([0, 1200, -35000, 7, 2**30, -5], dtype=np.int64),
                   A_per_permille=sc.A_per_permille * direction, permille_per_A=sc.permille_per_A * direction,
                   counts_per_rev=cpr, direction=direction)


def _encoder(rng: np.random.Generator, steps: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Counts (int32 6064h values, wrapping), per-step fresh masks and intervals."""
    start = rng.integers(-2**31, 2**31 - 1, N)
    start[0] = 2**31 - 3000  # wraps within the run
    speed = rng.normal(0.0, 400.0, (steps, N)).cumsum(axis=0) * 0.05
    raw = start + np.cumsum(np.round(speed), axis=0).astype(np.int64)
    counts = ((raw + 2**31) % 2**32 - 2**31).astype(np.int64)
    fresh = rng.random((steps, N)) > 0.03
    fresh[rng.random(steps) < 0.3] = True  # long stretches where every joint is fresh (the uniform path)
    dt = np.full(steps, 1e-3)
    late = rng.random(steps) < 0.05
    dt[late] *= rng.uniform(1.2, 4.0, late.sum())
    return counts, fresh, dt


def test_velocity_kernel_matches_the_reference() -> None:
    rng = np.random.default_rng(7)
    counts, fresh, dt = _encoder(rng, 6000)
    cpr = np.full(N, 524288.0)
    direction = np.array([1.0, -1.0, 1.0, 1.0, 1.0, -1.0])
    ref, got = VelocityEstimator(cpr, 40.0, direction), VelocityEstimator(cpr, 40.0, direction)
    got.use_kernel(kernels()["velocity"])  # type: ignore[index]
    for k in range(counts.shape[0]):
        d = 0.0 if k in (0, 3000) else dt[k]  # dt 0: the reset path (Python in both)
        a = ref.update(counts[k], d, fresh[k]).copy()
        b = got.update(counts[k], d, fresh[k])
        np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-12, err_msg=f"step {k}")
        assert got._uniform == ref._uniform and np.array_equal(got._last, ref._last), f"step {k}"
        np.testing.assert_allclose(got._age, ref._age, rtol=0, atol=1e-15)
    assert np.abs(ref.velocity_rad_s).max() > 0.05  # the sequence moves


def test_inputs_and_outputs_kernels_match_scaling(scaling: Scaling) -> None:
    rng = np.random.default_rng(8)
    k = kernels()
    assert k is not None
    counts, _, _ = _encoder(rng, 3000)
    q_ref, q_got, i_ref, i_got = (np.zeros(N) for _ in range(4))
    tq_ref, tq_got, tc_ref, tc_got = (np.zeros(N, dtype=np.int64) for _ in range(4))
    tmp = np.zeros(N)
    for step in range(counts.shape[0]):
        permille = rng.normal(0.0, 300.0, N).round()
        scaling.position_rad(counts[step], q_ref, tmp)
        scaling.current_A(permille, i_ref)
        k["inputs"](counts[step], scaling.offset_counts, scaling.rad_per_count, q_got, permille, scaling.A_per_permille,
                    i_got)
        assert np.array_equal(q_got, q_ref) and np.array_equal(i_got, i_ref), f"step {step}"
        cmd = rng.normal(0.0, 3.0, N) * (100.0 if step % 10 == 0 else 1.0)  # beyond int16 per mille now and then
        cmd[rng.random(N) < 0.2] = 0.5 * np.round(rng.normal(0.0, 4.0, N))[0] / 1000 * 4.0  # ties at .5 per mille
        ref_q = q_ref + rng.normal(0.0, 0.01, N)
        scaling.torque_permille(cmd, tq_ref, tmp)
        scaling.target_counts(ref_q, tc_ref, tmp)
        k["outputs"](cmd, scaling.permille_per_A, tq_got, ref_q, scaling.counts_per_rad, scaling.offset_counts, tc_got)
        assert np.array_equal(tq_got, tq_ref) and np.array_equal(tc_got, tc_ref), f"step {step}"
    assert tq_ref.dtype == np.int64 and np.abs(tq_ref).max() <= 32768


def _plausibility_state(scaling: Scaling, rejects: list[str], kernel: object = None) -> EncoderPlausibility:
    """The cycle's encoder plausibility as the daemon builds it (6 rad/s, 1 kHz, hold after 3)."""
    return EncoderPlausibility(scaling.counts_per_rev, 1e-3, 6.0, 3, list(range(1, N + 1)),
                               lambda j, text: rejects.append(f"{j}: {text}"), kernel)


def test_plausibility_kernel_matches_the_reference(scaling: Scaling) -> None:
    rng = np.random.default_rng(9)
    k = kernels()
    assert k is not None
    counts, fresh, _ = _encoder(rng, 4000)
    jumps = rng.random(counts.shape) < 0.004
    counts = np.where(jumps, counts + rng.choice([-1, 1], counts.shape) * 200_000, counts)
    counts[2000:2010, 3] += 500_000  # persistent: rejected hold_after times, then a fault and the new baseline
    ref_faults: list[str] = []
    got_faults: list[str] = []
    ref, got = _plausibility_state(scaling, ref_faults), _plausibility_state(scaling, got_faults, k["plausible"])
    assert (ref.check.__func__, got.check.__func__) == (  # type: ignore[attr-defined]
        EncoderPlausibility._check, EncoderPlausibility._check_compiled)
    for c in (ref, got):
        c.prime(counts[0])
    for step in range(1, counts.shape[0]):
        fbs = []
        for _ in range(2):
            fb = Feedback(N)
            fb.counts[:] = counts[step]
            fb.rx[:] = fresh[step]
            fb.rx_count = int(fresh[step].sum())
            fbs.append(fb)
        for c, fb in ((ref, fbs[0]), (got, fbs[1])):
            fb.rx_count -= c.check(fb.counts, fb.rx, fb.stale)
        for a, b, what in ((fbs[0].counts, fbs[1].counts, "counts"), (fbs[0].rx, fbs[1].rx, "rx"),
                           (fbs[0].stale, fbs[1].stale, "stale"), (ref.prev_counts, got.prev_counts, "prev"),
                           (ref.since, got.since, "since"), (ref.run, got.run, "run")):
            assert np.array_equal(a, b), f"step {step}: {what}"
        assert fbs[0].rx_count == fbs[1].rx_count == int(fbs[0].rx.sum())
    assert got.rejects == ref.rejects > 10 and got_faults == ref_faults and len(ref_faults) >= 1


@pytest.mark.parametrize("compiled", [True, False])
def test_the_plausibility_check_keeps_no_memory_per_cycle(scaling: Scaling, compiled: bool) -> None:
    """The cycle's call on its usual path (plausible samples, some late): no memory taken per call."""
    k = kernels() if compiled else None
    if compiled and k is None:
        pytest.skip("numba is not importable here")
    rng = np.random.default_rng(4)
    # up to ~3 rad/s on 2^19 counts/rev (the bound is 6 rad/s), 10 % of the samples late
    counts = np.cumsum(rng.integers(-250, 250, (3000, N)), axis=0).astype(np.int64)
    fresh = rng.random((3000, N)) > 0.1
    faults: list[str] = []
    p = _plausibility_state(scaling, faults, None if k is None else k["plausible"])
    p.prime(counts[0])
    fb = Feedback(N)
    for step in range(1, 100):  # warm-up (first calls may cache)
        fb.counts[:] = counts[step]
        fb.rx[:] = fresh[step]
        p.check(fb.counts, fb.rx, fb.stale)
    rows = list(zip(counts[100:], fresh[100:], strict=True))
    c, rx, stale = fb.counts, fb.rx, fb.stale
    own = [tracemalloc.Filter(True, plausible.__file__)]  # (what other threads of this worker allocate: not ours)
    tracemalloc.start()
    before = sum(t.size for t in tracemalloc.take_snapshot().filter_traces(own).traces)
    for cr, fr in rows:
        c[:] = cr
        rx[:] = fr
        p.check(c, rx, stale)
    after = sum(t.size for t in tracemalloc.take_snapshot().filter_traces(own).traces)
    tracemalloc.stop()
    # nothing kept from one call to the next (one 6-element array held would be ~150 bytes)
    assert after - before <= 0, f"{after - before} bytes held by control/plausible.py after {len(rows)} calls"
    assert p.rejects == 0 and not faults


def test_one_signature_per_kernel() -> None:
    """The start-up compiles every kernel with the cycle's types: nothing compiles again in a cycle."""
    k = kernels()
    assert k is not None
    assert {name: len(f.signatures) for name, f in k.items()} == {name: 1 for name in k}


def test_the_cycle_runs_the_kernels_or_their_reference_as_chosen_at_construction() -> None:
    """``loop.compiled`` picks the kernels or the numpy reference once (no branch in ``step``); a held arm with a
    moving joint gives the same estimate and the same drive words either way."""
    from inproc import InProcess

    cfg = load_config(DEFAULT_CONFIG)
    got = {}
    for compiled in (True, False):
        ip = InProcess(cfg.model_copy(update={"loop": cfg.loop.model_copy(update={"compiled": compiled})}))
        cy = ip.cy
        assert (cy.encoders.check.__func__, cy.decode_inputs.__func__, cy.encode_outputs.__func__) == (
            (EncoderPlausibility._check_compiled, Cycle._inputs_compiled, Cycle._outputs_compiled) if compiled
            else (EncoderPlausibility._check, Cycle._inputs, Cycle._outputs))
        q0 = np.array([0.1, -0.4, 0.8, 0.0, 0.5, -0.2])
        ip.hold(q0)
        rows = []
        for k in range(300):
            q = q0.copy()
            q[2] += 0.05 * math.sin(k * 0.02)
            ip.feed(q, np.full(6, 0.3))
            ip.cycle()
            rows.append(np.r_[cy.est.q_rad, cy.est.current_A, cy.torque_permille, cy.target_counts])
        got[compiled] = np.array(rows)
    assert np.count_nonzero(got[True][:, 18:]) > 0  # (the drive words are not all zero: something was compared)
    np.testing.assert_array_equal(got[True][:, :12], got[False][:, :12])  # q and I: the same arithmetic, exactly
    # the command goes through the velocity filter (its kernel within a few ulp of numpy's exp): the words agree
    assert np.abs(got[True][:, 12:] - got[False][:, 12:]).max() <= 1
