"""Encoder plausibility: a position sample further from the last accepted one than physics allows is rejected.

The bound is ``plausible_speed_rad_s`` × the time since each joint's last accepted sample (+2 counts of quantisation):
periods a stalled host slept through count, so real motion across a stall is never taken for a jump. A rejected
sample is treated as a missing TPDO (the joint's previous counts stand, it counts as stale); rejected ``hold_after``
times in a row it is a real offset, not a glitch: a fault, and the new position becomes the baseline.

Part of the cycle's estimate step (dragd/daemon/cycle.py calls ``check`` before the velocity filter): nothing here
allocates on the usual path; the check runs as a compiled kernel (dragd/daemon/kernels.py) or as the numpy reference
it is tested against, chosen once at construction; the rare path (a rejection) stays in Python.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np


class EncoderPlausibility:
    """Per-joint jump rejection of encoder counts; ``check`` is the cycle's call."""

    def __init__(self, counts_per_rev: np.ndarray, dt_s: float, plausible_speed_rad_s: float, hold_after: int,
                 node_ids: list[int], fault: Callable[[int, str], None], kernel: Any = None) -> None:
        """``fault(joint index, text)`` is called on a persistent jump; ``kernel``: the compiled check (None: numpy)."""
        cpr = np.asarray(counts_per_rev, dtype=float)
        n = cpr.shape[0]
        self.counts_per_rev = cpr
        self.step_counts = plausible_speed_rad_s * dt_s * cpr / (2.0 * math.pi) + 2.0  # per period
        self.hold_after, self.node_ids, self._fault = hold_after, node_ids, fault
        self.rejects = 0  # samples rejected since start-up
        self.prev_counts = np.zeros(n, dtype=np.int64)  # the last accepted sample
        self.since = np.ones(n)  # periods since the last accepted sample (+1), missed ticks included
        self.run = np.zeros(n, dtype=np.int64)  # rejections in a row
        self.mask = np.zeros(n, dtype=bool)
        self._d = np.zeros(n)
        self._lim = np.zeros(n)
        self._kernel = kernel
        self.check: Callable[[np.ndarray, np.ndarray, np.ndarray], int] = (
            self._check if kernel is None else self._check_compiled)

    def prime(self, counts: np.ndarray) -> None:
        """The first full set of positions is the baseline."""
        self.prev_counts[:] = counts
        self.since.fill(1.0)

    def skip(self, periods: int) -> None:
        """``periods`` ticks were missed: the bound grows with them."""
        np.add(self.since, periods, out=self.since)

    def _check(self, counts: np.ndarray, rx: np.ndarray, stale: np.ndarray) -> int:
        """Reject the implausible samples among the fresh ones (``rx``) in place: their ``counts`` become the last
        accepted ones, ``rx`` False, ``stale`` the periods since; returns how many were dropped (the numpy
        reference)."""
        d, lim, mask = self._d, self._lim, self.mask
        np.subtract(counts, self.prev_counts, out=d, casting="unsafe")
        np.abs(d, out=d)
        np.multiply(self.step_counts, self.since, out=lim)
        np.greater(d, lim, out=mask)
        mask &= rx
        dropped = self._reject(counts, rx, stale) if np.count_nonzero(mask) else 0
        self._remember(counts, rx)
        return dropped

    def _check_compiled(self, counts: np.ndarray, rx: np.ndarray, stale: np.ndarray) -> int:
        """``_check`` by the kernel (which also does the bookkeeping when nothing was rejected)."""
        if self._kernel(counts, rx, self.prev_counts, self.since, self.run, self.step_counts, self.mask):
            dropped: int = self._reject(counts, rx, stale)  # the rare path
            self._remember(counts, rx)
            return dropped
        return 0

    def _remember(self, counts: np.ndarray, rx: np.ndarray) -> None:
        """The accepted samples are the next cycle's reference; the others age."""
        since = self.since
        np.copyto(self.prev_counts, counts, where=rx)
        since += 1.0
        np.copyto(since, 1.0, where=rx)
        np.copyto(self.run, 0, where=rx)

    def _reject(self, counts: np.ndarray, rx: np.ndarray, stale: np.ndarray) -> int:
        """The rare path: each sample in ``mask`` is dropped (the joint counts as stale); persistent, a fault."""
        dropped = 0
        for j in np.flatnonzero(self.mask):
            raw = int(counts[j])
            jump_rad = (raw - int(self.prev_counts[j])) * 2.0 * np.pi / float(self.counts_per_rev[j])
            self.rejects += 1
            self.run[j] += 1
            if self.run[j] >= self.hold_after:
                # persistent: a real offset, not a glitch: fault (brakes), and the new position is the baseline
                self._fault(int(j), f"encoder jump on node {self.node_ids[j]}: position moved {jump_rad:+.4f} rad in "
                                    f"{int(self.since[j])} cycle(s), beyond physics; samples rejected, arm stopped")
                self.run[j] = 0
                continue  # accepted as the new baseline by _remember
            counts[j] = self.prev_counts[j]
            rx[j] = False
            dropped += 1
            stale[j] = int(self.since[j])
        return dropped
