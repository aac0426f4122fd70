"""The simulator's compiled stiction kernel (sim/kernels.py) against the Python reference in sim/physics.py.

Randomised holding problems (SPD inverse inertias, stuck sets, holding torques above and below the static levels:
none, one and several break-aways, everything released) and whole runs of the arm — the bundled truth and one with
backlash rotors (extra DOFs) — with sinusoidal motor currents that make joints stick and break away again. Results
must match the reference exactly (the same operations in the same order).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim.axis import AxisIO
from sim.kernels import hold_kernel
from sim.physics import ArmPhysics, hold_stuck
from sim.truth import load_truth

from conftest import REPO

pytestmark = [pytest.mark.unit, pytest.mark.skipif(hold_kernel() is None, reason="numba is not installed")]


def _reference(minv: np.ndarray, a: np.ndarray, stuck: np.ndarray, lp: np.ndarray, ln: np.ndarray,
               fric: np.ndarray, dirs: np.ndarray) -> tuple[list[float], list[bool], list[float], list[float]]:
    """The physics' Python holding (sim.physics.hold_stuck) on list copies of the arrays."""
    out = a.tolist(), stuck.tolist(), fric.tolist(), dirs.tolist()
    hold_stuck(minv.tolist(), out[0], out[1], lp.tolist(), ln.tolist(), out[2], out[3])
    return out


def test_hold_kernel_matches_the_reference_on_random_problems() -> None:
    rng = np.random.default_rng(11)
    hold = hold_kernel()
    released = {0: 0, 1: 0, "several": 0, "all": 0}
    for trial in range(600):
        nf = int(rng.integers(1, 15))
        b = rng.normal(size=(nf, nf))
        minv = b @ b.T + nf * np.diag(rng.uniform(0.1, 3.0, nf))
        a = rng.normal(0.0, 5.0, nf)
        stuck = rng.random(nf) < rng.uniform(0.2, 1.0)
        scale = rng.choice([0.05, 0.5, 5.0])  # static levels from far below to far above the holding torques
        lp, ln = rng.uniform(0.0, 2.0, nf) * scale, rng.uniform(0.0, 2.0, nf) * scale
        fric, dirs = rng.normal(size=nf), rng.choice([-1.0, 0.0, 1.0], nf)
        want = _reference(minv, a, stuck, lp, ln, fric, dirs)
        got_a, got_st, got_fr, got_dr = a.copy(), stuck.copy(), fric.copy(), dirs.copy()
        hold(minv, got_a, got_st, lp, ln, got_fr, got_dr, np.zeros(nf, dtype=np.int64), np.zeros((nf, nf + 1)),
             np.zeros(nf))
        assert got_a.tolist() == want[0] and got_st.tolist() == want[1], trial
        assert got_fr.tolist() == want[2] and got_dr.tolist() == want[3], trial
        n_rel = int(stuck.sum() - got_st.sum())
        released[n_rel if n_rel < 2 else "several"] += 1
        released["all"] += int(stuck.any() and not got_st.any())
    assert min(released.values()) > 10, released  # every path was taken


@pytest.mark.parametrize("backlash", [False, True])
def test_the_arm_runs_the_same_with_the_kernel(backlash: bool) -> None:
    truth = load_truth(REPO / "sim/config/seed_cobot.yaml")
    if backlash:  # separate rotors on two joints: the inverse inertia gets its constant rotor block
        truth = truth.model_copy(update={"joints": [
            j.model_copy(update={"hidden": j.hidden.model_copy(update={"backlash_rad": 0.01})}) if i in (0, 3) else j
            for i, j in enumerate(truth.joints)]})
    model = truth.load_model()
    runs = {}
    for compiled in (False, True):
        axes = [AxisIO() for _ in truth.joints]
        phys = ArmPhysics(truth, model, axes, compiled=compiled)
        assert (phys._hold_kernel is not None) == compiled
        rng = np.random.default_rng(3)
        amp, w = rng.uniform(0.2, 1.5, phys.n), rng.uniform(1.0, 6.0, phys.n)
        rows, breakaways, partly = [], 0, 0
        for _ in range(16000):
            t = phys.t_s
            for j, ax in enumerate(axes):
                ax.power_stage_on, ax.brake_engaged = True, False
                ax.current_demand_A = amp[j] * math.sin(w[j] * t) + (0.3 if j % 2 else -0.2)
            before = sum(phys._stuck)
            partly += 0 < before < phys.nf
            phys.step()
            breakaways += max(0, before - sum(phys._stuck))
            rows.append(np.concatenate([phys._x, phys._v, phys._fric]))
        runs[compiled] = np.array(rows)
        # joints stick and break away again: the holding path (some DOFs stuck, not all) runs most steps
        assert breakaways > 10 and partly > 8000, (breakaways, partly)
    np.testing.assert_array_equal(runs[True], runs[False])
