import json
import math
import tracemalloc

import numpy as np
import pytest

from dragd.stats import Histogram, RateCounter

pytestmark = pytest.mark.unit


def test_counts_mean_max_and_out_of_range():
    h = Histogram(0.0, 10.0, 1.0)
    for x in [0.0, 0.5, 1.0, 9.99, -1.0, 10.0, 25.0, float("nan")]:
        h.add(x)
    assert h.count == 7  # NaN excluded
    assert h.nan == 1
    assert h.below == 1
    assert h.above == 2
    assert h.max == 25.0
    assert h.min == -1.0
    assert h.mean == pytest.approx((0 + 0.5 + 1 + 9.99 - 1 + 10 + 25) / 7)
    assert dict(h.bins()) == {0.0: 2, 1.0: 1, 9.0: 1}


def test_percentile_is_upper_bin_edge_within_resolution():
    rng = np.random.default_rng(1)
    xs = rng.uniform(800.0, 1200.0, 20_000)
    h = Histogram(0.0, 2000.0, 5.0)
    for x in xs:
        h.add(float(x))
    for p in (50, 90, 99, 99.9):
        exact = float(np.percentile(xs, p, method="inverted_cdf"))
        got = h.percentile(p)
        assert exact <= got <= exact + h.resolution, (p, exact, got)
    assert h.percentile(100) == pytest.approx(xs.max())


def test_percentile_below_and_above_range():
    h = Histogram(10.0, 20.0, 1.0)
    for x in (1.0, 2.0, 3.0, 15.0, 50.0):
        h.add(x)
    assert h.percentile(20) == 10.0  # in 'below': reports lo as upper bound
    assert h.percentile(100) == 50.0  # in 'above': exact max
    assert h.percentile(70) == 16.0


def test_empty_and_invalid():
    h = Histogram(0, 1, 0.1)
    assert math.isnan(h.mean)
    assert math.isnan(h.percentile(50))
    d = h.to_dict()
    assert d["count"] == 0 and d["p50"] is None and d["max"] is None
    with pytest.raises(ValueError, match="lo < hi"):
        Histogram(1, 1, 0.1)
    with pytest.raises(ValueError, match="bin_width"):
        Histogram(0, 1, 0)
    with pytest.raises(ValueError, match="bins"):
        Histogram(0, 1e9, 1e-3)
    with pytest.raises(ValueError, match="percentile"):
        h.percentile(0)


def test_to_dict_is_json_and_reset():
    h = Histogram(0, 2000, 10)
    for x in (990.0, 1000.0, 1010.0, 5000.0):
        h.add(x)
    d = json.loads(json.dumps(h.to_dict()))
    assert d["count"] == 4 and d["above"] == 1 and d["max"] == 5000.0
    assert d["resolution"] == 10
    assert d["p50"] == 1010.0  # nearest rank 2 is 1000, in bin [1000, 1010): upper edge
    h.reset()
    assert h.count == 0 and h.bins() == []


def test_add_does_not_allocate():
    h = Histogram(0.0, 2000.0, 1.0)
    h.add(1.0)
    values = [float(i % 1500) + 0.25 for i in range(20_000)]
    tracemalloc.start()
    before = tracemalloc.get_traced_memory()[0]
    for x in values:
        h.add(x)
    after = tracemalloc.get_traced_memory()[0]
    tracemalloc.stop()
    assert after - before < 4096  # a few counter ints at most, nothing per sample
    assert h.count == 20_001


def test_rate_counter():
    r = RateCounter(window_s=1.0, buckets=10)
    t0 = 1_000_000_000_000
    for k in range(2000):  # 1 kHz for 2 s
        r.add(1, t0 + k * 1_000_000)
    assert r.total == 2000
    assert r.rate_Hz(t0 + 2_000_000_000) == pytest.approx(1000, rel=0.12)
    # after 5 s of silence the window is empty
    assert r.rate_Hz(t0 + 7_000_000_000) == 0.0
    with pytest.raises(ValueError):
        RateCounter(window_s=0)


def test_percentile_matches_nearest_rank_on_random_samples():
    """The bin search gives what a nearest-rank percentile of the raw samples gives, mapped to its bin's upper edge
    (capped at the max; below range: lo; above range: the max), for bins in the thousands as the status reads."""
    import random

    rng = random.Random(3)
    for _ in range(200):
        lo, hi, w = 0.0, rng.choice([100.0, 5000.0]), rng.choice([1.0, 2.0, 5.0, 10.0])
        h = Histogram(lo, hi, w)
        xs = [rng.uniform(-50.0, hi + 200.0) for _ in range(rng.randint(1, 400))]
        for x in xs:
            h.add(x)
        ordered = sorted(xs)
        for p in (0.5, 1, 50, 90, 99, 100):
            v = ordered[max(1, math.ceil(p / 100 * len(xs))) - 1]
            want = (min(lo, max(xs)) if v < lo else max(xs) if v >= hi
                    else min(lo + (int((v - lo) / w) + 1) * w, max(xs)))
            assert h.percentile(p) == pytest.approx(want, abs=1e-9), (p, lo, hi, w)
