"""Identification input: MCAP/CSV loading and every kind of bad input named clearly."""

from __future__ import annotations

import numpy as np
import pytest

from dragd.identify.data import LogError, load_log, prepare
from dragd.identify.methods import identify

from identify_helpers import robot, sync_log

pytestmark = pytest.mark.unit


def _csv(path, t, q, i, dq=None, header=None):
    n = q.shape[1]
    cols = ["t"] + [f"q{k + 1}" for k in range(n)] + [f"i{k + 1}" for k in range(n)]
    arr = [t[:, None], q, i]
    if dq is not None:
        cols += [f"dq{k + 1}" for k in range(n)]
        arr.append(dq)
    np.savetxt(path, np.hstack(arr), delimiter=",", header=header or ",".join(cols), comments="")
    return path


def _synthetic(n_joints=6, seconds=20.0, rate=500.0, moving=(1,)):
    t = np.arange(0.0, seconds, 1.0 / rate)
    q = np.zeros((t.size, n_joints))
    i = np.random.default_rng(0).normal(0.0, 0.02, (t.size, n_joints))
    for j in moving:
        q[:, j] = 0.3 * np.sin(2 * np.pi * 0.1 * t)
        i[:, j] += 0.5 * np.sign(np.cos(2 * np.pi * 0.1 * t))
    return t, q, i


@pytest.mark.slow
def test_mcap_and_csv_of_the_same_run_load_alike():
    m = load_log(sync_log("mcap"))
    c = load_log(sync_log("csv"))
    assert m.n == c.n == 6 and m.t.shape == c.t.shape
    assert c.dq is not None and m.dq is None  # the CSV carries the drive's velocity
    assert np.allclose(m.q, c.q, atol=1e-8)
    assert abs(m.rate_Hz - 1000.0) < 1e-6 and m.modes == {"track": m.t.shape[0]}


def test_missing_columns_are_named(tmp_path):
    t, q, i = _synthetic()
    p = _csv(tmp_path / "a.csv", t, q, i)
    text = p.read_text().splitlines()
    header = text[0].split(",")
    keep = [k for k, c in enumerate(header) if c not in ("i3", "i4")]
    rows = [",".join(np.array(r.split(","))[keep]) for r in text]
    p.write_text("\n".join(rows) + "\n")
    with pytest.raises(LogError, match=r"a\.csv: columns: missing i3, i4"):
        load_log(p)


def test_unknown_column_and_bad_number_are_named(tmp_path):
    t, q, i = _synthetic()
    p = _csv(tmp_path / "b.csv", t, q, i)
    lines = p.read_text().splitlines()
    p.write_text("\n".join([lines[0].replace("q2", "angle2")] + lines[1:]) + "\n")
    with pytest.raises(LogError, match="unknown angle2"):
        load_log(p)
    p = _csv(tmp_path / "c.csv", t, q, i)
    lines = p.read_text().splitlines()
    lines[7] = lines[7].replace(lines[7].split(",")[3], "abc", 1)
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(LogError, match=r"line 8: 'abc' is not a number"):
        load_log(p)


def test_nan_rows_are_an_error_naming_the_column_unless_dropped(tmp_path):
    t, q, i = _synthetic()
    i[[10, 11, 500], 2] = np.nan
    q[700, 0] = np.inf
    p = _csv(tmp_path / "n.csv", t, q, i)
    with pytest.raises(LogError, match=r"n\.csv: q1: NaN or infinite values at line 702 \(q1: 1 row \(line 702\); "
                                       r"i3: 3 rows \(lines 12, 13, 502\)\).*--drop-bad-rows"):
        load_log(p)
    log = load_log(p, drop_bad_rows=True)
    assert log.t.shape[0] == t.shape[0] - 4
    assert any("4 rows with NaN or infinite values dropped (q1: 1 row (line 702); i3: 3 rows (lines 12, 13, 502))"
               in w for w in log.warnings)


def test_non_monotonic_time_is_an_error_naming_the_row(tmp_path):
    t, q, i = _synthetic()
    t[100] = t[98]
    p = _csv(tmp_path / "m.csv", t, q, i)
    with pytest.raises(LogError, match=r"m\.csv: t: expected strictly increasing time, got t = 0\.196000 s after "
                                       r"0\.198000 s at line 102 — .*--drop-bad-rows"):
        load_log(p)
    log = load_log(p, drop_bad_rows=True)  # only the row out of sequence goes
    assert log.t.shape[0] == t.shape[0] - 1 and 102 not in log.lines
    assert any("1 row with time out of sequence dropped (line 102)" in w for w in log.warnings)


def test_joint_count_mismatch_names_both(tmp_path):
    t, q, i = _synthetic(n_joints=5)
    log = load_log(_csv(tmp_path / "five.csv", t, q, i))
    with pytest.raises(LogError, match=r"the log has 5 joints \(q1\.\.q5\), the robot .*seed_cobot\.urdf has 6 "
                                       r"\(joint1, joint2, joint3, joint4, joint5, joint6\)"):
        identify(log, robot(), "synchronous")


def test_wrong_file_kinds(tmp_path):
    with pytest.raises(LogError, match="file not found"):
        load_log(tmp_path / "nope.mcap")
    (tmp_path / "x.txt").write_text("hello\n1,2\n")
    with pytest.raises(LogError, match="expected a header line"):
        load_log(tmp_path / "x.txt")
    (tmp_path / "x.mcap").write_bytes(b"not an mcap file at all")
    with pytest.raises(LogError, match="not a readable MCAP file"):
        load_log(tmp_path / "x.mcap")


def test_a_joint_that_never_moves_is_reported_unidentifiable():
    res = identify(load_log(sync_log("mcap")), robot(), "synchronous")
    j1 = res.joint("joint1")  # the sync plan moves joints 2 and 4 (and bends 3, 5 for the second pose)
    assert j1.torque_constant_Nm_per_A is None and all(v is None for v in j1.friction.values())
    assert "joint1 never moves in this log" in j1.reasons["coulomb_pos_A"]
    assert any("joint1 never moves" in w for w in res.warnings)


def test_too_little_excitation_reports_condition_and_nulls():
    """One speed only: Coulomb and viscous cannot be separated -> null with the reason, level kept as diagnostic."""
    res = identify(load_log(sync_log("mcap")), robot(), "synchronous")
    j3 = res.joint("joint3")  # joint 3 only moves in the transitions into the bent pose: one speed
    assert j3.friction["viscous_pos_A_s_per_rad"] is None
    assert any("not separable" in r or "one speed only" in r for r in j3.reasons.values())
    j2 = res.joint("joint2")
    assert 1.0 <= j2.diagnostics["condition_number"] < 1e3  # reported for every fitted joint


def test_gaps_split_the_log_into_stretches(tmp_path):
    t, q, i = _synthetic(seconds=30.0)
    keep = (t < 12.0) | (t > 12.5)
    log = load_log(_csv(tmp_path / "g.csv", t[keep], q[keep], i[keep]))
    p = prepare(log)
    assert len(p.segments) == 2
    assert any("1 gaps longer than 50 ms" in w for w in p.warnings)
    keep = np.ones(t.size, dtype=bool)
    keep[1000:1010] = False  # 20 ms of missed samples: interpolated over
    p = prepare(load_log(_csv(tmp_path / "h.csv", t[keep], q[keep], i[keep])))
    assert len(p.segments) == 1 and any("1 short gaps" in w for w in p.warnings)


def test_mcap_without_track_rows_is_an_error(tmp_path):
    from sim.offline import write_mcap

    t = np.arange(0, 2.0, 0.001)
    data = {k: np.zeros((t.size, 6)) for k in ("q_rad", "dq_rad_s", "current_measured_A", "current_command_A",
                                               "gravity_A", "friction_A")}
    data["t_s"] = t
    p = tmp_path / "hold.mcap"
    write_mcap(p, data, mode=1)
    with pytest.raises(LogError, match=r"no rows in mode track \(rows per mode: hold 2000\)"):
        load_log(p)
