"""Bad logs through the real CLI: every error names the file, the column and the line (issue #13 item 7), and the
headerless UR RTDE layout of the public UR10e dataset (synthetic file here; the dataset itself when present)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from dragd.identify.data import LogError, load_log

from conftest import run_cli

pytestmark = pytest.mark.unit

N = 6


def _log(seconds: float = 10.0, rate: float = 200.0, n: int = N) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A joint-2 sine with a Coulomb-like current: plain radians, finite, strictly increasing time."""
    t = np.arange(0.0, seconds, 1.0 / rate)
    q = np.zeros((t.size, n))
    q[:, 1] = 0.4 * np.sin(2 * np.pi * 0.2 * t)
    i = np.random.default_rng(1).normal(0.0, 0.02, (t.size, n))
    i[:, 1] += 0.6 * np.sign(np.cos(2 * np.pi * 0.2 * t))
    return t, q, i


def _write(path: Path, t: np.ndarray, q: np.ndarray, i: np.ndarray, header: bool = True) -> Path:
    n = q.shape[1]
    cols = ["t"] + [f"q{k + 1}" for k in range(n)] + [f"i{k + 1}" for k in range(n)]
    np.savetxt(path, np.column_stack([t, q, i]), delimiter=",", fmt="%.6f", header=",".join(cols) if header else "",
               comments="")
    if not header:
        path.write_text(path.read_text().lstrip("\n"))
    return path


def _fails(*args: str) -> str:
    proc = run_cli(*args, check=False)
    assert proc.returncode != 0, proc.stdout
    return proc.stderr


def _fit(log: Path, tmp: Path, *extra: str) -> str:
    return _fails("identify", "fit", "--robot", "seed_cobot", "--log", str(log), "--out", str(tmp / "p.yaml"), *extra)


def test_nan_is_an_error_naming_file_column_and_rows_in_fit_and_gap(tmp_path):
    t, q, i = _log()
    i[[40, 41, 900], 2] = np.nan
    p = _write(tmp_path / "nan_i3.csv", t, q, i)
    for err in (_fit(p, tmp_path), _fails("gap", "--measured", str(p))):
        assert f"{p}: i3: NaN or infinite values at lines 42, 43, 902" in err and "--drop-bad-rows" in err, err


def test_drop_bad_rows_skips_nan_rows_naming_the_column(tmp_path):
    t, q, i = _log()
    i[[40, 41], 2] = np.inf
    p = _write(tmp_path / "inf_i3.csv", t, q, i)
    proc = run_cli("identify", "fit", "--robot", "seed_cobot", "--log", str(p), "--method", "lowspeed", "--out",
                   str(tmp_path / "p.yaml"), "--drop-bad-rows", "--json", check=False)
    out = proc.stdout + proc.stderr
    assert "2 rows with NaN or infinite values dropped (i3: 2 rows (lines 42, 43))" in out, out


def test_time_not_increasing_names_column_t_and_the_line(tmp_path):
    t, q, i = _log()
    t[300] = t[298]
    p = _write(tmp_path / "time.csv", t, q, i)
    err = _fit(p, tmp_path)
    assert f"{p}: t: expected strictly increasing time, got t = 1.490000 s after 1.495000 s at line 302" in err, err


def test_joint_count_names_file_columns_found_and_robot_joints(tmp_path):
    t, q, i = _log(n=5)
    p = _write(tmp_path / "five.csv", t, q, i)
    err = _fit(p, tmp_path)
    assert f"{p}: joints: the log has 5 joints (q1..q5)" in err and \
        "(joint1, joint2, joint3, joint4, joint5, joint6); columns found: t, q1..q5, i1..i5" in err, err


def test_headerless_column_count_that_fits_no_layout_names_columns_and_joints(tmp_path):
    t, q, i = _log()
    p = _write(tmp_path / "fourteen.csv", t, np.column_stack([q, q[:, :1]]), i, header=False)
    err = _fit(p, tmp_path)
    assert f"{p}: headerless CSV with 14 columns does not fit the robot's 6 joints: expected 31" in err, err


def test_angles_in_degrees_are_named(tmp_path):
    t, q, i = _log()
    q[:, 1] = 85.0 * (1.0 - np.cos(2 * np.pi * 0.1 * t))  # 0..170 degrees
    p = _write(tmp_path / "deg.csv", t, q, i)
    err = _fit(p, tmp_path)
    assert f"{p}: looks like degrees: column q2 spans 0..170; expected radians" in err, err


def test_velocity_column_in_degrees_is_named(tmp_path):
    t, q, i = _log()
    cols = ["t"] + [f"q{k}" for k in range(1, 7)] + [f"i{k}" for k in range(1, 7)] + [f"dq{k}" for k in range(1, 7)]
    dq = np.degrees(np.gradient(q, t, axis=0))
    p = tmp_path / "dqdeg.csv"
    np.savetxt(p, np.column_stack([t, q, i, dq]), delimiter=",", header=",".join(cols), comments="")
    with pytest.raises(LogError, match=r"dqdeg\.csv: looks like degrees: column dq2 is 57\.\d× the rate of q2"):
        load_log(p)


def _ur_rows(t: np.ndarray, q: np.ndarray, i: np.ndarray) -> np.ndarray:
    dq = np.gradient(q, t, axis=0)
    k = np.array([10.0, 10.7, 8.5, 9.0, 9.5, 10.1])
    return np.column_stack([t, q, dq, i, i * 1.01, i * k])


def test_headerless_31_columns_read_as_the_ur_rtde_layout_without_extension(tmp_path):
    t, q, i = _log()
    p = tmp_path / "ur-synthetic"  # no extension: sniffed
    np.savetxt(p, _ur_rows(t, q, i), delimiter=",", fmt="%.4f")
    log = load_log(p, joints=[f"joint{k}" for k in range(1, 7)])
    assert any("headerless 31 columns: read as UR RTDE layout t,q,qd,i,i_target,tau_target" in w
               for w in log.warnings)
    assert log.n == 6 and log.dq is not None and log.i_target is not None and log.tau_target is not None
    assert np.allclose(log.i, np.round(i, 4)) and np.allclose(log.tau_target[:, 1], np.round(i[:, 1] * 10.7, 4))
    named = load_log(tmp_path / "ur-synthetic")  # also when named without the extension it does not have
    assert named.t.shape == log.t.shape


def test_garbage_block_and_truncated_last_row(tmp_path):
    t, q, i = _log()
    rows = [",".join(f"{v:.4f}" for v in r) for r in _ur_rows(t + 3047.0, q, i)]
    garbage = ["-0.1231," + ",".join(["253.0000"] * 30), "0.0000," + ",".join(["0.0000"] * 30),
               "2.6e154," + ",".join(["1e200"] * 30)]
    lines = rows[:1] + garbage + rows[1:]
    lines[-1] = ",".join(lines[-1].split(",")[:20])  # the writer stopped mid-row
    p = tmp_path / "load.csv"
    p.write_text("\n".join(lines))
    err = _fit(p, tmp_path)
    assert f"{p}: t: expected strictly increasing time, got t = -0.123100 s after 3047.000000 s at line 2; " \
           "3 rows out of sequence at lines 2–4" in err and "--drop-bad-rows" in err, err
    log = load_log(p, drop_bad_rows=True)
    assert log.t.shape[0] == t.shape[0] - 1 and np.all(np.diff(log.t) > 0)
    assert f"line {len(lines)}: last row truncated (20 of 31 fields" in " ".join(log.warnings)
    assert "3 rows with time out of sequence dropped (lines 2–4)" in " ".join(log.warnings)
    lines.insert(100, "1.0,2.0")  # a short row mid-file is an error (only the last row may be cut)
    p.write_text("\n".join(lines))
    with pytest.raises(LogError, match=r"load\.csv: line 101: 2 fields, expected 31; fix the log or pass "
                                       r"--drop-bad-rows"):
        load_log(p)
    assert "malformed rows skipped at lines 101" in " ".join(load_log(p, drop_bad_rows=True).warnings)


# ----------------------------------------------------------------------------- the public UR10e dataset


def _dataset() -> Path | None:
    root = Path(os.environ.get("DRAGD_UR10E_DATA", "/work/scratch/ur10e/repo"))
    d = root / "dataset_ur10e" if (root / "dataset_ur10e").is_dir() else root
    return d if (d / "identification_data").is_dir() else None


DATA = _dataset()
needs_data = pytest.mark.skipif(DATA is None, reason="UR10e dataset absent (set DRAGD_UR10E_DATA to the directory "
                                                     "holding dataset_ur10e: github:shamilmamedov/dynamic_calibration)")


@needs_data
def test_ur10e_load_file_named_without_extension_garbage_block_and_truncated_row(tmp_path):
    name = DATA / "identification_data" / "ur-20_02_19_15harm50secLoad"
    err = _fit(name, tmp_path)
    assert "ur-20_02_19_15harm50secLoad.csv: t: expected strictly increasing time" in err and \
        "at line 2; 9 rows out of sequence at lines 2–10" in err and "--drop-bad-rows" in err, err
    log = load_log(name, drop_bad_rows=True)
    w = " ".join(log.warnings)
    assert "headerless 31 columns: read as UR RTDE layout" in w and "lines 2–10" in w
    assert "line 6107: last row truncated" in w
    assert log.n == 6 and log.tau_target is not None and np.all(np.diff(log.t) > 0)
    assert np.abs(log.q).max() < 2 * np.pi


@needs_data
def test_ur10e_training_logs_load_as_the_rtde_layout():
    for name in ("identification_data/ur-20_02_12-50sec_12harm.csv", "validation_data/ur-20_01_17-p1.csv"):
        log = load_log(DATA / name, joints=[f"j{k}" for k in range(6)])
        assert log.n == 6 and log.i_target is not None and log.tau_target is not None
        assert not any("dropped" in w or "skipped" in w for w in log.warnings)
        # the controller's own gain: target torque / target current ≈ 8..15 N·m/A on a loaded joint (joint 2)
        m = np.abs(log.i_target[:, 1]) > 0.1
        assert 8.0 < np.median(log.tau_target[m, 1] / log.i_target[m, 1]) < 15.0
