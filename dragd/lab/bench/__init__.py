"""Benchmarks: ``dragd bench [NAME ...] --json`` → ``{"NAME": {"value": x, "unit": "..."}}``.

Performance goals live here, not in timed tests. Each benchmark is a function returning (value, unit);
figures and the commands that made them are recorded in docs/PERFORMANCE.md.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Benchmark:
    name: str
    unit: str
    doc: str
    run: Callable[[dict], Any]  # a float, (value, detail mapping) reported under "detail", or a report (dict)


REGISTRY: dict[str, Benchmark] = {}


class BenchError(RuntimeError):
    """A benchmark cannot measure what it promises here (the message says why and what to do)."""


def benchmark(name: str, unit: str) -> Callable[[Callable[[dict], Any]], Callable[[dict], Any]]:
    def wrap(fn: Callable[[dict], Any]) -> Callable[[dict], Any]:
        REGISTRY[name] = Benchmark(name, unit, (fn.__doc__ or "").strip().splitlines()[0], fn)
        return fn

    return wrap


@benchmark("compensation_us", "us")
def compensation_us(opts: dict) -> float:
    """Median wall time of one full 6-joint evaluation of the law including G(q) (Pinocchio) and the latch: the
    numpy reference functions (``loop.compiled: false``)."""
    return _law_timing(opts, compiled=False)


@benchmark("compensation_compiled_us", "us")
def compensation_compiled_us(opts: dict) -> float:
    """The same with the compiled kernels the daemon runs (dragd/control/fused.py)."""
    return _law_timing(opts, compiled=True)


def _law_timing(opts: dict, compiled: bool) -> float:
    from dragd.config import load_config
    from dragd.control.fused import DragLaw
    from dragd.control.params import LawParams
    from dragd.model import RobotModel

    cfg = load_config(opts.get("config"))
    model = RobotModel.from_urdf(cfg.robot.urdf, cfg.base_dir, cfg.robot.gravity_m_s2)
    p = LawParams.from_config(cfg)
    n = model.nq
    rng = np.random.default_rng(1)
    qs = rng.uniform(-np.pi, np.pi, (1000, n))
    dqs = rng.normal(0.0, 0.2, (1000, n))
    law, g, extra = DragLaw(p, compiled), np.zeros(n), np.zeros(n)
    if compiled and not law.compiled:
        raise RuntimeError("compensation_compiled_us: numba is not available here")
    law.state.reset(0.0)
    samples = np.empty(int(opts.get("iterations", 20000)))
    for k in range(samples.shape[0]):
        q, dq = qs[k % 1000], dqs[k % 1000]
        t0 = time.perf_counter_ns()
        model.gravity(q, g)
        law.breakout(q, dq, k * 1e-3, p, None)
        law.compensate(g, dq, k * 1e-3, p, extra, q)
        samples[k] = time.perf_counter_ns() - t0
    return float(np.median(samples) / 1e3)


def _load_plugins() -> None:
    """Import modules that register further benchmarks (kept lazy: some pull in heavy dependencies)."""
    import importlib

    for mod in ("dragd.lab.bench.loop", "dragd.lab.bench.identify", "dragd.lab.bench.gap",
                "dragd.lab.bench.gap_confusion", "dragd.lab.bench.ident_real", "dragd.lab.bench.contact_real",
                "dragd.lab.bench.contact_cycle",
                "dragd.lab.bench.faults", "dragd.lab.bench.telemetry", "dragd.lab.bench.yardstick",
                "dragd.lab.bench.ros2", "dragd.lab.bench.drives"):
        try:
            importlib.import_module(mod)
        except ModuleNotFoundError as exc:
            if exc.name != mod:
                raise


def names() -> list[str]:
    _load_plugins()
    return sorted(REGISTRY)


def run(selected: list[str], opts: dict) -> dict[str, dict[str, Any]]:
    _load_plugins()
    unknown = [n for n in selected if n not in REGISTRY]
    if unknown:
        raise KeyError(f"unknown benchmark(s) {', '.join(unknown)}; expected some of: {', '.join(sorted(REGISTRY))}")
    result: dict[str, dict[str, Any]] = {}
    opts = {**opts, "selected": list(selected)}  # a benchmark needing external data may skip when not named
    for name in selected or sorted(REGISTRY):
        b = REGISTRY[name]
        v = b.run(opts)
        if isinstance(v, dict):  # a report (e.g. the fault matrix): reported as it is
            result[name] = v
            continue
        value, detail = v if isinstance(v, tuple) else (v, None)  # a benchmark may add its evidence
        result[name] = {"value": round(float(value), 6), "unit": b.unit}
        if detail is not None:
            result[name]["detail"] = detail
    return result
