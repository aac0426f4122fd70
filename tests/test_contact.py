"""Contact detection offline (docs/CONTACT.md): the detector on logs of an arm whose torques are known.

The logs come from Pinocchio's inverse dynamics of the bundled seed cobot with a friction "truth" a few per cent off
the params the detector is given, 20 mA of current noise, 100 Hz, and external torques of known size and time: a
struck moving arm and a pushed held arm. ``dragd contact calibrate`` sets the bands on free motion, ``dragd contact
detect`` must find every contact — on the right joint, with its torque — and nothing else. The real robot's logs are
tests/test_ur10e_contact.py's.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from conftest import run_cli

pytestmark = pytest.mark.unit

KT = np.array([9.09, 9.09, 9.09, 4.545, 4.545, 4.545])
COULOMB_A = np.array([0.6, 0.7, 0.5, 0.25, 0.2, 0.2])
VISCOUS_A_S = np.array([0.5, 0.6, 0.4, 0.1, 0.1, 0.1])
Q0 = np.array([0.0, -0.6, 1.2, -0.6, 1.5708, 0.0])


def _params(path: Path) -> Path:
    from dragd.config import FrictionParams, JointParams, ParamsFile, save_params
    from dragd.model import RobotModel

    names = RobotModel.from_urdf("seed_cobot").joint_names
    joints = {nm: JointParams(torque_constant_Nm_per_A=float(KT[j]), friction=FrictionParams(
        coulomb_pos_A=float(COULOMB_A[j]), coulomb_neg_A=-float(COULOMB_A[j]),
        viscous_A_s_per_rad=float(VISCOUS_A_S[j]))) for j, nm in enumerate(names)}
    save_params(ParamsFile(method="full", robot="seed_cobot", joints=joints), path)
    return path


def _log(path: Path, seed: int, freq: float, contacts: list[tuple[float, float, int, float]] = (),
         rest_from: float | None = None, seconds: float = 24.0) -> Path:
    """CSV t,q,dq,i of a smooth multi-sine motion (at rest for the first second and from ``rest_from``) with
    external torques (start s, duration s, joint, N·m; half-sine pulses); the truth's friction 4 % above the params'."""
    from dragd.model import RobotModel

    rng = np.random.default_rng(seed)
    rm = RobotModel.from_urdf("seed_cobot")
    m, d = rm.model, rm.data
    t = np.arange(0.0, seconds, 0.01)
    amp = rng.uniform(0.2, 0.5, 6)
    ph = rng.uniform(0, 2 * np.pi, 6)
    w = 2 * np.pi * freq * rng.uniform(0.7, 1.3, 6)
    s = np.clip((t - 1.0) / 1.5, 0.0, 1.0)  # a smooth start from rest ...
    if rest_from is not None:
        s = s * np.clip((rest_from - t) / 1.5, 0.0, 1.0)  # ... and a smooth stop
    env = s * s * (3 - 2 * s)
    x = np.sin(np.outer(t, w) + ph) - np.sin(ph)
    q = Q0 + env[:, None] * amp * x
    dq = np.gradient(q, t, axis=0)
    ddq = np.gradient(dq, t, axis=0)
    tau_ext = np.zeros_like(q)
    for t0, dur, j, nm in contacts:
        k = (t >= t0) & (t < t0 + dur)
        tau_ext[k, j] += nm * np.sin(np.pi * (t[k] - t0) / dur)
    i = np.empty_like(q)
    for k in range(t.shape[0]):
        tau = pin.rnea(m, d, q[k], dq[k], ddq[k])
        fr = 1.04 * KT * (COULOMB_A * np.tanh(dq[k] / 0.005) + VISCOUS_A_S * dq[k])
        i[k] = (tau + fr - tau_ext[k]) / KT
    i += rng.normal(0.0, 0.02, i.shape)
    cols = ["t"] + [f"q{j}" for j in range(1, 7)] + [f"dq{j}" for j in range(1, 7)] + [f"i{j}" for j in range(1, 7)]
    np.savetxt(path, np.column_stack([t, q, dq, i]), delimiter=",", header=",".join(cols), comments="", fmt="%.7g")
    return path


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    tmp = tmp_path_factory.mktemp("contact")
    return {
        "params": _params(tmp / "params.yaml"),
        "free_a": _log(tmp / "free_a.csv", 1, 0.15, rest_from=20.0),
        "free_b": _log(tmp / "free_b.csv", 2, 0.25, rest_from=21.0),
        "free_c": _log(tmp / "free_c.csv", 3, 0.2, rest_from=20.0),  # never calibrated on
        # struck while moving (joints 2, 3, 1), pushed while held (joint 2, then joint 4)
        "contact": _log(tmp / "contact.csv", 4, 0.2, rest_from=15.0, seconds=26.0, contacts=[
            (5.0, 0.25, 1, 40.0), (8.5, 0.3, 2, -25.0), (11.0, 0.4, 0, 30.0), (19.0, 1.0, 1, -30.0),
            (22.5, 1.0, 3, 8.0)]),
        "out": tmp,
    }


@pytest.fixture(scope="module")
def calibrated(files: dict[str, Path]) -> tuple[Path, dict]:
    p2 = files["out"] / "contact.yaml"
    proc = run_cli("contact", "calibrate", "--robot", "seed_cobot", "--params", str(files["params"]), "--log",
                   str(files["free_a"]), "--log", str(files["free_b"]), "--out", str(p2), "--json", timeout=300)
    return p2, json.loads(proc.stdout)


def test_calibrate_sets_every_band_from_the_logs_and_reports_its_margin(calibrated: tuple[Path, dict]) -> None:
    from dragd.config import load_params

    p2, rep = calibrated
    params = load_params(p2)
    assert params.contact is not None and params.contact.observer_gain_per_s == 25.0
    assert params.contact.margin == 1.5 and len(params.contact.joints) == 6
    assert params.joints["joint2"].torque_constant_Nm_per_A == pytest.approx(KT[1])  # the input params kept
    for nm, j in rep["report"]["joints"].items():
        # every calibration sample at ≤ 1/margin of its band; the band binds somewhere (the least band)
        assert 0.6 <= j["moving_max_ratio"] <= 1 / 1.5 + 1e-3, (nm, j)  # (reported to 3 decimals)
        assert j["moving_samples"] > 1000 and j["held_samples"] > 50
        b = rep["joints"][nm]
        assert b["settling_A"] >= 1.5 * COULOMB_A[int(nm[-1]) - 1] - 1e-6  # at least the static band
        assert b["held_A"] > 0 and b["base_A"] >= 0


def test_detect_finds_every_contact_on_its_joint_and_nothing_else(files: dict[str, Path],
                                                                  calibrated: tuple[Path, dict]) -> None:
    p2, _ = calibrated
    d = json.loads(run_cli("contact", "detect", "--robot", "seed_cobot", "--params", str(p2), "--log",
                           str(files["contact"]), "--json", timeout=300).stdout)
    assert set(d) >= {"events", "thresholds_A", "bands", "max_ratio"}
    assert len(d["thresholds_A"]) == 6 and all(x > 0 for x in d["thresholds_A"])
    events = d["events"]
    assert [set(e) >= {"t_start_s", "t_end_s", "joints", "peak_Nm"} for e in events] == [True] * len(events)
    truth = [(5.0, 0.25, "joint2", 40.0), (8.5, 0.3, "joint3", 25.0), (11.0, 0.4, "joint1", 30.0),
             (19.0, 1.0, "joint2", 30.0), (22.5, 1.0, "joint4", 8.0)]
    assert len(events) == len(truth), events
    for e, (t0, dur, joint, nm) in zip(events, truth, strict=True):
        assert t0 <= e["t_start_s"] <= t0 + dur, (e, t0)  # found during the contact
        assert joint in e["joints"], (e, joint)
        peak = e["peak_Nm"][e["joints"].index(joint)]
        # the residual is the contact torque low-passed at 25/s: a short pulse is seen a little lower
        assert 0.5 * nm <= peak <= 1.2 * nm, (e, nm)
    held = events[3]
    assert held["states"][held["joints"].index("joint2")] == "held"  # judged against its latched baseline


def test_free_motion_never_calibrated_on_raises_nothing(files: dict[str, Path], calibrated: tuple[Path, dict]) -> None:
    p2, _ = calibrated
    d = json.loads(run_cli("contact", "detect", "--robot", "seed_cobot", "--params", str(p2), "--log",
                           str(files["free_c"]), "--json", timeout=300).stdout)
    assert d["events"] == []
    assert max(v for v in d["max_ratio"].values()) < 1.0


def test_the_compiled_detector_and_its_numpy_reference_see_the_same_events(files: dict[str, Path],
                                                                          calibrated: tuple[Path, dict]) -> None:
    from dragd.cli.contact import detect
    from dragd.config import load_params
    from dragd.contact.model import ContactModel
    from dragd.control.contact import contact_kernel
    from dragd.identify.data import load_log

    if contact_kernel() is None:
        pytest.skip("numba is not installed")
    p2, _ = calibrated
    params = load_params(p2)
    model = ContactModel.from_files("seed_cobot", params, str(p2))
    log = load_log(files["contact"], joints=list(model.names))
    a, ja = detect(model, params, str(p2), log, compiled=True)
    b, jb = detect(model, params, str(p2), log, compiled=False)
    assert ja["events"] == jb["events"] and len(ja["events"]) == 5
    np.testing.assert_allclose(a.d_A, b.d_A, rtol=1e-12, atol=1e-12)


def test_sensitivity_scales_the_bands(files: dict[str, Path], calibrated: tuple[Path, dict]) -> None:
    """--sensitivity 0.5: every band twice as wide; on free motion the deviation's share of it about halves (not
    exactly: a held joint's stillness and baseline tests scale with its band too)."""
    p2, _ = calibrated
    base = ["contact", "detect", "--robot", "seed_cobot", "--params", str(p2), "--log", str(files["free_c"]), "--json"]
    lo = json.loads(run_cli(*base, "--sensitivity", "0.5", timeout=300).stdout)
    hi = json.loads(run_cli(*base, timeout=300).stdout)
    np.testing.assert_allclose(lo["thresholds_A"], 2 * np.array(hi["thresholds_A"]), rtol=3e-3)  # (4 decimals)
    assert lo["events"] == hi["events"] == []
    for nm, r in hi["max_ratio"].items():
        assert lo["max_ratio"][nm] <= 0.6 * r + 0.01, (nm, lo["max_ratio"][nm], r)


def test_bad_input_is_named(files: dict[str, Path], tmp_path: Path) -> None:
    base = ["contact", "detect", "--robot", "seed_cobot", "--log", str(files["contact"])]
    r = run_cli(*base, "--params", str(files["params"]), check=False)  # no bands yet
    assert r.returncode == 2 and "no contact bands" in r.stderr and "contact calibrate" in r.stderr
    r = run_cli(*base, "--params", str(files["params"]), "--torque-constants", "1,2", check=False)
    assert r.returncode == 2 and "--torque-constants: expected 6" in r.stderr
    r = run_cli(*base, "--params", str(files["params"]), "--columns", "q,x,i", check=False)
    assert r.returncode == 2 and "--columns" in r.stderr and "'x'" not in r.stderr.split("got")[0]
    r = run_cli(*base, "--params", str(files["params"]), "--sensitivity", "0", check=False)
    assert r.returncode == 2 and "--sensitivity" in r.stderr
    out = tmp_path / "p.yaml"
    r = run_cli("contact", "calibrate", "--robot", "seed_cobot", "--params", str(files["params"]), "--log",
                str(files["free_a"]), "--out", str(out), "--margin", "0.9", check=False)
    assert r.returncode == 2 and "--margin" in r.stderr and not out.exists()
    null_kt = tmp_path / "nokt.yaml"
    null_kt.write_text(files["params"].read_text().replace("torque_constant_Nm_per_A: 9.09",
                                                           "torque_constant_Nm_per_A: null", 1))
    r = run_cli("contact", "calibrate", "--robot", "seed_cobot", "--params", str(null_kt), "--log",
                str(files["free_a"]), "--out", str(out), check=False)
    assert r.returncode == 2 and "joint1" in r.stderr and "--torque-constants" in r.stderr
    for r in (run_cli(*base, "--params", str(files["params"]), check=False),):
        assert len(r.stderr.strip().splitlines()) == 1, r.stderr


def test_labels_of_a_periodic_run_and_of_a_held_pose() -> None:
    """The labels find bumps added to a periodic signal against its own other cycles, and pushes on a held current."""
    from dragd.contact.labels import held_labels, periodic_labels

    rng = np.random.default_rng(5)
    t = np.arange(0.0, 40.0, 0.01)
    q = np.column_stack([0.5 * np.sin(2 * np.pi * t / 4.0 + k) for k in range(3)])
    dq = np.gradient(q, t, axis=0)
    i = 2.0 * q + 0.5 * np.sign(dq) + rng.normal(0.0, 0.03, q.shape)
    bumps = [(9.3, 1, 1.5), (22.1, 0, -1.2), (31.7, 2, 0.8)]
    for t0, j, a in bumps:
        k = (t >= t0) & (t < t0 + 0.15)
        i[k, j] += a
    lab = periodic_labels(t, q, dq, i)
    assert len(lab.contacts) == 3
    for c, (t0, j, a) in zip(lab.contacts, bumps, strict=True):
        assert abs(c.t_onset_s - t0) <= 0.03 and c.joint == j and c.peak_A == pytest.approx(abs(a), rel=0.25)
    held = np.tile([0.1, 5.0, 2.0], (t.shape[0], 1)) + rng.normal(0.0, 0.02, (t.shape[0], 3))
    k = (t >= 10.0) & (t < 11.0)
    held[k, 1] += 3.0 * np.sin(np.pi * (t[k] - 10.0))
    held[(t >= 11.0) & (t < 13.0), 1] -= 0.8 * np.exp(-(t[(t >= 11.0) & (t < 13.0)] - 11.0))  # the spring-back
    lab = held_labels(t, held, ((9.5, 12.0),))
    (c,) = lab.contacts
    assert 10.0 <= c.t_start_s <= 10.15 and 10.7 <= c.t_end_s <= 11.0 and c.joint == 1
    with pytest.raises(ValueError, match="outside the log"):
        held_labels(t, held, ((50.0, 51.0),))


def test_score_counts_hits_misses_and_false_alarms() -> None:
    from dragd.contact.labels import Contact
    from dragd.contact.score import score

    cs = [Contact(1.0, 1.5, 2.0, [2.0], 0, True, 1.05), Contact(5.0, 5.4, 0.8, [0.8], 0, True, 5.0),
          Contact(8.0, 9.0, 3.0, [3.0], 0, False, 8.0)]
    ev = [(1.1, 2.5, ["a"]), (3.0, 3.2, ["a"]), (8.9, 9.5, ["a"]), (9.3, 9.4, ["a"])]
    s = score(cs, ev)
    assert [r["found"] for r in s["contacts"]] == [True, False, True]
    assert s["contacts"][0]["delay_ms"] == pytest.approx(50.0)
    assert [f["t_start_s"] for f in s["false_alarms"]] == [3.0, 9.3]  # 9.3: after the contact's end + 0.2 s
    assert s["required"] == 2 and s["required_found"] == 2 and s["median_impact_delay_ms"] == pytest.approx(50.0)
