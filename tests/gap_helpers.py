"""Proof data for the model-gap tests: the sim's truth with one effect hidden (or none, or two), the model that lacks
exactly that effect, and offline logs of the ``gap`` plan (2 poses × 3 speeds, ~54 s, 20 mA Hall noise, ADC and
per-mille quantisation, encoder counts; sim/drive.py's CSP loop without target interpolation)."""

from __future__ import annotations

import functools
from concurrent.futures import ProcessPoolExecutor
from typing import Any

import numpy as np

START = np.array([0.0, -0.6, 1.2, -0.6, 1.5708, 0.0])

# the effect (the case's name unless "effect" says), where it is hidden (truth changes), the joints it must be named on
RIPPLE = {"amplitude_Nm": 0.4, "cycles_per_rev": 24.0, "reference": "joint", "phase_rad": 0.7}
CASES: dict[str, dict[str, Any]] = {
    "clean": {"joints": {}, "expect": []},
    "viscous_friction": {"joints": {}, "expect": ["joint1", "joint2", "joint3", "joint4", "joint5", "joint6"]},
    "stribeck": {"joints": {f"joint{k}": {"friction": {"stribeck_velocity_rad_s": 0.1, "stribeck_exponent": 1.0}}
                            for k in (2, 3)}, "expect": ["joint2", "joint3"]},
    "inertia": {"joints": {}, "expect": ["joint1", "joint2", "joint3", "joint4", "joint5", "joint6"]},
    "position_periodic": {"joints": {"joint3": {"hidden": {"ripple": [RIPPLE]}}}, "expect": ["joint3"]},
    "load_dependent_friction": {"joints": {"joint2": {"hidden": {"load_friction_per_Nm": 0.04}}}, "expect": ["joint2"]},
    "temperature_drift": {"joints": {"joint2": {"hidden": {"thermal": {"heat_capacity_J_per_K": 20.0,
                                                                      "thermal_resistance_K_per_W": 3.0}}}},
                          "expect": ["joint2"]},
    "backlash": {"joints": {"joint1": {"hidden": {"backlash_rad": 0.02}}}, "expect": ["joint1"]},
    # a realistic play (17 arcmin), and one on the shoulder, whose gravity load never reverses in this plan: the teeth
    # stay on one flank, the play is never crossed and changes nothing in the current
    "backlash_small": {"joints": {"joint1": {"hidden": {"backlash_rad": 0.005}}}, "effect": "backlash",
                       "expect": ["joint1"]},
    "backlash_loaded": {"joints": {"joint2": {"hidden": {"backlash_rad": 0.02}}}, "effect": "backlash", "expect": []},
    "back_emf": {"joints": {"joint2": {"hidden": {"back_emf": {"A_s_per_rad": 0.4, "knee_rad_s": 0.2}}}},
                 "expect": ["joint2"]},
    "payload_mass": {"joints": {}, "payload": {"mass_kg": 1.5, "com_m": [0.0, 0.0, 0.05]},
                     "expect": ["joint2", "joint3", "joint4"]},
    "current_offset": {"joints": {"joint4": {"hidden": {"current_offset_A": 0.08}}}, "expect": ["joint4"]},
    # belief errors (the sim is clean; the model is off): a wrist's K_t 30 % high, the shoulder's Coulomb levels
    # 0.25 A low
    "torque_constant": {"joints": {}, "expect": ["joint4"]},
    "coulomb_friction": {"joints": {}, "expect": ["joint2"]},
    "two": {"joints": {"joint3": {"hidden": {"ripple": [RIPPLE]}}, "joint4": {"hidden": {"current_offset_A": 0.08}}},
            "expect": {"position_periodic": ["joint3"], "current_offset": ["joint4"]}},
}


def truth_for(case: str) -> Any:
    from sim.truth import load_truth

    c = CASES[case]
    t = load_truth()
    ch: dict[str, Any] = {}
    if c["joints"]:
        ch["joints"] = c["joints"]
    if c.get("payload"):
        ch["payload"] = c["payload"]
    return t.with_updates(**ch) if ch else t


def model_for(case: str) -> dict[str, Any]:
    """The params of the truth *without* the hidden effect (the model that "knows everything else")."""
    from sim.truth import load_truth, params_from_truth

    base = truth_for("stribeck") if case == "stribeck" else load_truth()
    p = params_from_truth(base)
    for nm, j in p["joints"].items():
        if case == "viscous_friction":
            j["friction"]["viscous_pos_A_s_per_rad"] = j["friction"]["viscous_neg_A_s_per_rad"] = 0.0
        if case == "stribeck" and nm in ("joint2", "joint3"):
            j["friction"]["static_pos_A"] = j["friction"]["coulomb_pos_A"]
            j["friction"]["static_neg_A"] = j["friction"]["coulomb_neg_A"]
        if case == "inertia":
            j["effects"]["armature_kgm2"] = None
        if case == "torque_constant" and nm == "joint4":
            j["torque_constant_Nm_per_A"] *= 1.3
        if case == "coulomb_friction" and nm == "joint2":  # both levels 0.25 A low, the hump above them kept
            for k, dk in (("coulomb_pos_A", -0.25), ("static_pos_A", -0.25), ("coulomb_neg_A", 0.25),
                          ("static_neg_A", 0.25)):
                j["friction"][k] += dk
    return p


@functools.cache
def plan(poses: int = 2) -> Any:
    from dragd.config import load_config
    from dragd.identify import excitation as E
    from dragd.model import RobotModel

    model = RobotModel.from_urdf("seed_cobot")
    lim = E.Limits.from_model(model, load_config())
    b = E.PlanBuilder(START, lim)
    E.add_gap(b, poses=poses, rng=np.random.default_rng(3))
    return b.build(f"gap-{poses}")


def _generate(args: tuple[str, int, int]) -> tuple[str, dict[str, np.ndarray]]:
    from sim.offline import generate

    from identify_helpers import cached_npz  # (kept across runs of the same sources: see identify_helpers)

    case, seed, poses = args

    def make() -> dict[str, np.ndarray]:
        p = plan(poses)
        return generate(p.t_s, p.q_rad, truth_for(case), seed=seed)

    return case, cached_npz(f"gap-{case}-{seed}-{poses}", make)


def generate_all(cases: list[str], seed: int = 7, poses: int = 2, workers: int = 2) -> dict[str, dict[str, np.ndarray]]:
    """Offline logs of the gap plan for each case (two processes: the machine has two cores), generated once for
    the same sources (tests/identify_helpers.py: cached_npz)."""
    with ProcessPoolExecutor(workers) as ex:
        return dict(ex.map(_generate, [(c, seed, poses) for c in cases]))


def as_log(data: dict[str, np.ndarray], name: str) -> Any:
    from dragd.identify.data import Log

    return Log(name, data["t_s"].copy(), data["q_rad"].copy(), data["current_measured_A"].copy(),
               data["dq_rad_s"].copy())
