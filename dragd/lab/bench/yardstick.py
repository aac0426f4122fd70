"""A fixed yardstick: how fast this machine runs Python of the cycle's kind, to read CPU figures across machines.

CPU time per cycle (``daemon_cpu_us_per_cycle``, ...) depends on the machine as much as on dragd. ``yardstick_us``
times one fixed workload in the benchmark's own process, in the same run as the figures it sits beside: the mix of
a cycle (attribute and dict access, float arithmetic, small numpy operations on 6-vectors, struct packing of PDO
payloads), nothing of dragd's. A figure divided by it (``..._yardsticks``) compares across machines; the workload
must never change (a changed yardstick is a new benchmark with a new name).
"""

from __future__ import annotations

import struct
import time

import numpy as np

from dragd.lab.bench import benchmark

REPEATS = 2000
_CODEC = struct.Struct("<HiH")


def _workload(state: dict[str, np.ndarray], out: np.ndarray, buf: bytearray) -> float:
    """One pass of the fixed mix (~100 µs on the machines seen so far)."""
    q, dq, g = state["q"], state["dq"], state["g"]
    acc = 0.0
    for k in range(6):  # per joint, as a cycle's Python glue does
        v = float(q[k]) * 0.5 + float(dq[k]) * 0.25
        acc += v * v if v > 0.0 else -v
        _CODEC.pack_into(buf, 8 * k, 0x0F, int(v * 1000.0) & 0x7FFFFFFF, k)
    for _ in range(20):  # small array arithmetic, the numpy side
        np.multiply(q, 1.0001, out=out)
        np.add(out, dq, out=out)
        np.subtract(out, g, out=out)
        acc += float(np.dot(out, q))
    s = 0
    for i in range(400):  # interpreter work: branches, ints, a dict
        s += i if i & 1 else -i
        state["n"][0] = s
    for k in range(0, 48, 8):
        acc += _CODEC.unpack_from(buf, k)[1] * 1e-9
    return acc + s * 1e-12


def measure_us(repeats: int = REPEATS) -> float:
    """Median wall time of one pass [µs] (in this process: run it with nothing else of the benchmark going on)."""
    rng = np.random.default_rng(7)
    state = {"q": rng.uniform(-1.0, 1.0, 6), "dq": rng.normal(0.0, 0.1, 6), "g": rng.normal(0.0, 1.0, 6),
             "n": np.zeros(1)}
    out, buf = np.zeros(6), bytearray(64)
    for _ in range(200):
        _workload(state, out, buf)
    samples = np.empty(repeats)
    for i in range(repeats):
        t0 = time.perf_counter_ns()
        _workload(state, out, buf)
        samples[i] = time.perf_counter_ns() - t0
    return float(np.median(samples) / 1e3)


_MEASURED: list[float] = []


def yardstick_us_once() -> float:
    """The yardstick of this benchmark run (measured on first use)."""
    if not _MEASURED:
        _MEASURED.append(measure_us())
    return _MEASURED[0]


@benchmark("yardstick_us", "us")
def yardstick_us(opts: dict) -> float:
    """A fixed Python + numpy workload's median time in this run: divide CPU figures by it to compare machines."""
    return yardstick_us_once()
