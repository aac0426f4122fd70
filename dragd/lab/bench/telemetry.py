"""Telemetry size benchmarks: MB per hour of the telemetry MCAP, by option (docs/TELEMETRY.md).

A 1 kHz, 6-joint log of the simulated robot (the identification benchmark's cached held-out log: noisy Hall
currents, every joint moving) is written again through `TelemetryWriter` as the daemon writes it, once per
option; the figure is the finished file's size over the log's duration. Deterministic (no wall clock).
"""

from __future__ import annotations

import os
import tempfile
from functools import lru_cache
from pathlib import Path

import numpy as np

from dragd.lab.bench import benchmark


@lru_cache(maxsize=1)
def _rows() -> tuple[np.ndarray, np.ndarray]:
    from dragd.lab.bench.identify import _log, _plans
    from dragd.telemetry.layout import RowLayout
    from dragd.telemetry.reader import read_log
    from dragd.telemetry.schema import cycle_layout

    log = read_log(_log(_plans()[1], 1, None))
    lay = RowLayout(cycle_layout(6))
    n = log.n_rows
    rows = np.zeros((n, lay.width))
    for c in lay.columns:
        v = log.rows[c.name]
        if c.labels is not None:
            inv = {label: k for k, label in c.labels.items()}
            v = np.array([inv.get(str(x), 0) for x in np.asarray(v).reshape(-1)], dtype=float)
        rows[:, c.offset:c.offset + c.width] = np.asarray(v, dtype=float).reshape(n, c.width)
    t_ns = 1_700_000_000_000_000_000 + np.arange(n, dtype=np.int64) * 1_000_000  # 1 kHz log times
    return rows, t_ns


def _mb_per_h(decimation: int, foxglove: bool) -> float:
    from dragd.robots import resolve_urdf
    from dragd.telemetry.foxglove import FoxgloveSpec
    from dragd.telemetry.schema import cycle_layout
    from dragd.telemetry.writer import TelemetryWriter

    rows, t_ns = _rows()
    spec = FoxgloveSpec([f"joint{i}" for i in range(1, 7)], resolve_urdf("seed_cobot"), 30.0) if foxglove else None
    with tempfile.TemporaryDirectory(prefix="dragd-bench-size-") as d:
        path = Path(d) / "t.mcap"
        w = TelemetryWriter(path, cycle_layout(6), capacity=len(rows) + 1, foxglove=spec,
                            cycle_decimation=decimation)
        for r, t in zip(rows, t_ns.tolist(), strict=True):
            row = w.begin()
            assert row is not None
            row[:] = r
            w.commit(t)
        st = w.close(timeout_s=600)
        if st["dropped"] or st["errors"]:
            raise RuntimeError(f"telemetry size benchmark: {st}")
        size = os.path.getsize(path)
    hours = (t_ns[-1] - t_ns[0]) / 1e9 / 3600
    return size / 1e6 / hours


@benchmark("telemetry_MB_per_h", "MB/h")
def telemetry_MB_per_h(opts: dict) -> float:
    """Telemetry MCAP growth, 1 kHz: every cycle + Foxglove channels at 30 Hz (the default configuration)."""
    return _mb_per_h(1, True)


@benchmark("telemetry_MB_per_h_plain", "MB/h")
def telemetry_MB_per_h_plain(opts: dict) -> float:
    """Telemetry MCAP growth, 1 kHz: every cycle, no Foxglove channels (--no-foxglove)."""
    return _mb_per_h(1, False)


@benchmark("telemetry_MB_per_h_decimated10", "MB/h")
def telemetry_MB_per_h_decimated10(opts: dict) -> float:
    """Telemetry MCAP growth, 1 kHz: --telemetry-decimation 10, Foxglove channels at 30 Hz."""
    return _mb_per_h(10, True)


@benchmark("telemetry_MB_per_h_decimated100", "MB/h")
def telemetry_MB_per_h_decimated100(opts: dict) -> float:
    """Telemetry MCAP growth, 1 kHz: --telemetry-decimation 100, Foxglove channels at 30 Hz."""
    return _mb_per_h(100, True)
