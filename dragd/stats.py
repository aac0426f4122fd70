"""Fixed-bin histogram and event-rate counter for cycle statistics.

Both classes preallocate everything at construction; their hot-path methods
(`Histogram.add`, `RateCounter.add`) do O(1) work and create no containers,
so the 1 kHz cycle may call them directly.
"""

from __future__ import annotations

import array
import math
import time
from typing import Any

import numpy as np

__all__ = ["Histogram", "RateCounter"]

_MAX_BINS = 1_000_000


class Histogram:
    """Fixed-width-bin histogram over ``[lo, hi)`` with exact count/mean/min/max.

    Samples below ``lo`` / at or above ``hi`` are counted in ``below`` / ``above``;
    NaN samples are counted in ``nan`` and excluded from everything else.
    Percentiles come from the bins: `percentile` returns the *upper edge* of the
    bin holding the nearest-rank sample (capped at the observed max), so it
    over-estimates by less than ``bin_width`` -- the stated resolution.
    """

    __slots__ = (
        "lo", "hi", "bin_width", "n_bins", "_inv_width", "_store", "_counts",
        "count", "below", "above", "nan", "_sum", "min", "max",
    )

    def __init__(self, lo: float, hi: float, bin_width: float) -> None:
        if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
            raise ValueError(f"Histogram needs finite lo < hi; got lo={lo!r}, hi={hi!r}")
        if not (math.isfinite(bin_width) and bin_width > 0):
            raise ValueError(f"Histogram bin_width must be a positive number; got {bin_width!r}")
        n_bins = math.ceil((hi - lo) / bin_width - 1e-9)
        if n_bins > _MAX_BINS:
            raise ValueError(
                f"Histogram [{lo}, {hi}) with bin_width={bin_width} needs {n_bins} bins; "
                f"expected at most {_MAX_BINS} (use a wider bin)"
            )
        self.lo = float(lo)
        self.hi = float(hi)
        self.bin_width = float(bin_width)
        self.n_bins = n_bins
        self._inv_width = 1.0 / self.bin_width
        # a C array the cycle's add() increments as fast as a list's items, viewed by numpy for the percentiles'
        # cumsum + searchsorted (status requests)
        self._store = array.array("q", bytes(8 * n_bins))
        self._counts = np.frombuffer(self._store, dtype=np.int64)
        self.count = 0
        self.below = 0
        self.above = 0
        self.nan = 0
        self._sum = 0.0
        self.min = math.inf
        self.max = -math.inf

    def add(self, x: float) -> None:
        """Record one sample. O(1), allocation-free (no containers created)."""
        if x != x:  # NaN
            self.nan += 1
            return
        self.count += 1
        self._sum += x
        if x > self.max:
            self.max = x
        if x < self.min:
            self.min = x
        if x < self.lo:
            self.below += 1
        elif x >= self.hi:
            self.above += 1
        else:
            i = int((x - self.lo) * self._inv_width)
            if i >= self.n_bins:  # rounding at the top edge
                i = self.n_bins - 1
            self._store[i] += 1

    def reset(self) -> None:
        """Forget all samples (keeps the bins)."""
        self._counts.fill(0)
        self.count = self.below = self.above = self.nan = 0
        self._sum = 0.0
        self.min = math.inf
        self.max = -math.inf

    @property
    def mean(self) -> float:
        """Exact mean of the finite samples (NaN when empty)."""
        return self._sum / self.count if self.count else math.nan

    @property
    def resolution(self) -> float:
        """Worst-case over-estimate of `percentile` for in-range samples."""
        return self.bin_width

    def percentile(self, p: float) -> float:
        """Nearest-rank ``p``-th percentile (0 < p <= 100) from the bins.

        Returns an upper bound: the upper edge of the bin containing the sample
        (never above the observed max). A sample below range reports ``lo``;
        above range reports the observed max. NaN when empty.
        """
        if not 0.0 < p <= 100.0:
            raise ValueError(f"percentile p must be in (0, 100]; got {p!r}")
        if self.count == 0:
            return math.nan
        rank = max(1, math.ceil(p / 100.0 * self.count))
        if rank <= self.below:
            return min(self.lo, self.max)
        # running counts and a bisection in numpy: a status request reads six percentiles of bins in the thousands,
        # served on the cycle's event loop (a Python loop over the bins cost ~0.2 ms there)
        i = int(np.searchsorted(np.cumsum(self._counts), rank - self.below))  # first bin reaching the rank
        if i < self.n_bins:
            return min(self.lo + (i + 1) * self.bin_width, self.max)
        return self.max

    def bins(self) -> list[tuple[float, int]]:
        """Non-empty bins as ``(lower_edge, count)`` pairs."""
        return [(self.lo + i * self.bin_width, int(self._counts[i])) for i in np.flatnonzero(self._counts).tolist()]

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (NaN/inf reported as None)."""

        def num(v: float) -> float | None:
            return v if math.isfinite(v) else None

        return {
            "lo": self.lo,
            "hi": self.hi,
            "bin_width": self.bin_width,
            "resolution": self.resolution,
            "count": self.count,
            "below": self.below,
            "above": self.above,
            "nan": self.nan,
            "mean": num(self.mean),
            "min": num(self.min),
            "max": num(self.max),
            "p50": num(self.percentile(50)) if self.count else None,
            "p90": num(self.percentile(90)) if self.count else None,
            "p99": num(self.percentile(99)) if self.count else None,
            "p99_9": num(self.percentile(99.9)) if self.count else None,
            "bins": [[edge, c] for edge, c in self.bins()],
        }


class RateCounter:
    """Events per second over a sliding window of ``buckets`` time buckets.

    ``add`` is O(1) amortised and creates no containers; pass ``now_ns`` from
    the cycle's clock to avoid an extra clock read.
    """

    __slots__ = ("window_s", "_bucket_ns", "_counts", "_n", "_current", "_start_ns", "total")

    def __init__(self, window_s: float = 1.0, buckets: int = 10) -> None:
        if not (window_s > 0 and math.isfinite(window_s)):
            raise ValueError(f"RateCounter window_s must be a positive number; got {window_s!r}")
        if buckets < 2:
            raise ValueError(f"RateCounter needs at least 2 buckets; got {buckets!r}")
        self.window_s = float(window_s)
        self._n = int(buckets)
        self._bucket_ns = max(1, int(round(window_s * 1e9 / buckets)))
        self._counts = [0] * self._n
        self._current = -1
        self._start_ns = -1
        self.total = 0

    def _advance(self, now_ns: int) -> None:
        b = now_ns // self._bucket_ns
        if self._current < 0:
            self._current = b
            self._start_ns = now_ns
            return
        gap = b - self._current
        if gap <= 0:
            return
        if gap >= self._n:
            for i in range(self._n):
                self._counts[i] = 0
        else:
            for k in range(1, gap + 1):
                self._counts[(self._current + k) % self._n] = 0
        self._current = b

    def add(self, n: int = 1, now_ns: int | None = None) -> None:
        """Count ``n`` events at ``now_ns`` (CLOCK_MONOTONIC ns; read if omitted)."""
        if now_ns is None:
            now_ns = time.monotonic_ns()
        self._advance(now_ns)
        self._counts[self._current % self._n] += n
        self.total += n

    def rate_Hz(self, now_ns: int | None = None) -> float:
        """Events per second over the last window (shorter while warming up)."""
        if now_ns is None:
            now_ns = time.monotonic_ns()
        if self._current < 0:
            return 0.0
        self._advance(now_ns)
        span_ns = (self._n - 1) * self._bucket_ns + (now_ns - self._current * self._bucket_ns)
        span_ns = min(span_ns, now_ns - self._start_ns)
        if span_ns <= 0:
            return 0.0
        return sum(self._counts) * 1e9 / span_ns
