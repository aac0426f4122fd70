"""``contact_cycle_us``: what the contact detector adds to one cycle of the daemon (docs/CONTACT.md).

The cycle's contact part exactly as dragd/daemon/cycle.py calls it — Pinocchio's p = M̄(q)·q̇ and C(q, q̇), the
detector's compiled update (HOLD and TRACK: residual, states, bands, events) or, in DRAG, the residual and the
hand's force at the grip point (its Jacobian, the 3×3 solve, the low-pass) — timed per call over varied poses,
speeds and currents, with the configuration's model and bands shaped like a calibration's. Without the detector the
cycle makes none of these calls (in DRAG with the runaway guard it computes p anyway). Reported: the median over
the modes' medians, each mode's median and 99th percentile in ``detail``.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from dragd.lab.bench import benchmark


def _watch(cfg_path: str | None, compiled: bool) -> tuple[Any, Any, Any]:
    from dragd.config import ContactJointBands, ContactParams, load_config
    from dragd.control.contact_watch import ContactWatch
    from dragd.control.params import LawParams
    from dragd.model import RobotModel

    cfg = load_config(cfg_path)
    if cfg.contact_calibration is None:  # bands shaped like a calibration's (their values do not change the cost)
        band = ContactJointBands(base_A=0.4, slow_A=0.3, speed_A_s_per_rad=0.5, accel_A_s2_per_rad=0.1,
                                 slow_speed_rad_s=0.1, settling_A=0.8, held_A=0.3, held_moving_A=0.2)
        cfg = cfg.model_copy(update={"contact_calibration": ContactParams(
            observer_gain_per_s=25.0, margin=1.5, joints={nm: band for nm in cfg.joint_names})})
    model = RobotModel.from_config(cfg)
    model.add_grip(cfg.contact.grip.frame, cfg.contact.grip.offset_m, cfg.source)
    w = ContactWatch.from_config(cfg, LawParams.from_config(cfg), 1.0 / cfg.loop.rate_Hz, compiled)
    return cfg, model, w


@benchmark("contact_cycle_us", "us")
def contact_cycle_us(opts: dict) -> tuple[float, dict]:
    """Median wall time the contact detector adds to one cycle (hold, track, drag), compiled kernels."""
    cfg, model, w = _watch(opts.get("config"), compiled=True)
    n = model.nq
    rng = np.random.default_rng(2)
    m = 1000
    lo, hi = model.position_limits_rad
    qs = rng.uniform(np.maximum(lo, -2.5), np.minimum(hi, 2.5), (m, n))
    dqs = rng.normal(0.0, 0.2, (m, n))
    iis = rng.normal(0.0, 1.0, (m, n))
    p, g = np.zeros(n), np.zeros(n)
    dq_ref = np.full(n, 0.1)
    iterations = int(opts.get("iterations", 20000))
    detail: dict[str, float] = {}
    medians = []
    for mode in ("hold", "track", "drag"):
        w.select(mode)
        samples = np.empty(iterations)
        for k in range(iterations):
            q, dq, i = qs[k % m], dqs[k % m] * (mode != "hold"), iis[k % m]
            t = k * 1e-3
            model.gravity(q, g)  # (the cycle's, with or without the detector: not timed)
            t0 = time.perf_counter_ns()
            model.momentum(q, dq, p)
            C = model.coriolis(q, dq)
            w.step(t, dq, p, i, g, C, True, dq_ref if mode == "track" else None)
            if mode == "drag":
                w.grip_force(model.grip_jacobian(q))
                model.grip_position(w.grip_m)
            samples[k] = time.perf_counter_ns() - t0
            if w.det.active and k % 50 == 0:  # (random currents raise events: start afresh now and then)
                w.select("")
                w.select(mode)
        s = samples[iterations // 10:] / 1e3  # (the first calls warm the caches)
        detail[f"{mode}_p50_us"] = round(float(np.median(s)), 2)
        detail[f"{mode}_p99_us"] = round(float(np.percentile(s, 99)), 2)
        medians.append(float(np.median(s)))
    detail["compiled"] = float(w._grip is not None)
    return float(np.median(medians)), detail
