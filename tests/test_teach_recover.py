"""Teach recordings are autosaved: a session the daemon never finished (SIGKILL mid-teach) is recovered from its raw
MCAP by ``dragd teach recover`` — marks, path and rate as ``teach stop`` would have written them (docs/TEACH.md)."""

from __future__ import annotations

import json
import math
import signal
import time
from pathlib import Path

import numpy as np
import pytest
from test_teach_daemon import _cli_json, _config

from dragd.lab.demo import TEACH_STEPS_RAD, guide_and_settle
from dragd.lab.rig import Rig
from dragd.teach.program import ProgramError, load_program
from dragd.teach.recorder import TeachRecorder
from dragd.teach.recover import recover, sample_rows
from dragd.telemetry.schema import cycle_layout
from dragd.telemetry.writer import TelemetryWriter

from conftest import run_cli


@pytest.mark.unit
def test_recovery_samples_the_rows_the_recorder_keeps():
    """The same rule as the live recorder (one sample per period of the daemon's clock, no burst after a stall)."""
    rng = np.random.default_rng(3)
    dt = np.where(rng.random(5000) < 0.1, 0.001 * rng.integers(2, 6, 5000), 0.001)  # missed cycles
    t = 12.0 + np.cumsum(dt)
    rec = TeachRecorder("x", Path("x.yaml"), None, ["a"], 90.0, 0.001, 60.0, t0=12.0)
    for tk in t:
        rec.add(float(tk), np.array([tk]))
    keep = sample_rows(t, rec.period_s, 12.0)
    assert keep.size == rec.count > 300
    assert np.array_equal(t[keep], rec.buf[:rec.count, 1])


@pytest.mark.unit
def test_recover_refuses_what_is_not_a_teach_recording(tmp_path):
    path = tmp_path / "run.mcap"
    w = TelemetryWriter(str(path), cycle_layout(1))
    w.event("record_start", label="identify", joints=["joint1"])
    w.close()
    with pytest.raises(ProgramError, match=r"run\.mcap: not a teach recording"):
        recover(path)
    with pytest.raises(ProgramError, match="no such teach recording"):
        recover(tmp_path / "missing.mcap")
    proc = run_cli("teach", "recover", str(path), check=False)
    assert proc.returncode != 0 and "not a teach recording" in proc.stderr and "Traceback" not in proc.stderr


def _on_disk_until_s(mcap: Path) -> float:
    """The session time of the last cycle row ``mcap`` holds in complete chunks so far (-inf before any)."""
    import warnings

    from dragd.teach.recover import teach_info
    from dragd.telemetry.reader import TelemetryFileError, read_log

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # (still being written: no footer yet)
            t = read_log(mcap, ["t_s"]).rows["t_s"]
            return float(t[-1]) - float(teach_info(mcap)["t0_s"]) if len(t) else -math.inf
    except (OSError, ProgramError, TelemetryFileError, KeyError, TypeError):
        return -math.inf  # (not there yet, or no complete chunk)


@pytest.mark.slow
def test_killed_daemon_mid_teach_the_session_is_recovered(tmp_path):
    cfg = _config(tmp_path, "recover")
    programs = tmp_path / "programs"
    with Rig("recover", workdir=tmp_path, config=cfg) as rig:
        rig.start_sim()
        rig.start_daemon()
        rig.must("start")
        time.sleep(0.3)
        started = _cli_json(rig, "teach", "start", "crash", "--rate", "50")
        marks = []
        for i, step in enumerate(TEACH_STEPS_RAD[:2]):
            guide_and_settle(rig, step, 2.0, f"p{i + 1}")
            marks.append(_cli_json(rig, "teach", "mark"))
        # past the last mark: the writer's flushes carry the session to the file (its complete chunks hold rows
        # after the mark)
        raw = programs / "crash.mcap"
        rig.wait_for(lambda: _on_disk_until_s(raw) > marks[-1]["t_s"], 30.0, "the rows after the last mark on disk")
        last = rig.must("status")["teach"]
        rig.daemon.proc.send_signal(signal.SIGKILL)  # no 'teach stop': the program file is never written
        rig.daemon.proc.wait(10)
    assert started["program"] == str(programs / "crash.yaml") and not (programs / "crash.yaml").exists()
    listed = run_cli("teach", "list", "--dir", str(programs), "--json")
    entry = json.loads(listed.stdout)["programs"]
    assert [(Path(p["path"]).name, p.get("interrupted")) for p in entry] == [("crash.mcap", True)]

    proc = run_cli("teach", "recover", "crash", "--dir", str(programs), "--json")
    res = json.loads(proc.stdout)
    # the raw window's MCAP is written by the telemetry writer process, which outlives the killed daemon and finishes
    # the file when its input ends: complete, not truncated (the program file is what the kill lost)
    assert res["program"] == str(programs / "crash.yaml") and res["truncated"] is False
    prog = load_program(programs / "crash.yaml")
    assert [w.name for w in prog.waypoints] == ["p1", "p2"]
    assert np.allclose(prog.waypoint_array(), [m["q_rad"] for m in marks], atol=1e-6)
    assert prog.recording.rate_Hz == pytest.approx(50.0) and "recovered" in prog.notes
    t, q = prog.path_arrays()
    # the autosave loses at most the last unflushed chunk: the path reaches past the last mark
    assert t[-1] >= marks[-1]["t_s"] and t[-1] >= last["t_s"] - 1.0
    assert np.all(np.diff(t) > 0) and abs(np.median(np.diff(t)) - 0.02) < 1e-3
    k = int(np.searchsorted(t, marks[-1]["t_s"]))
    assert np.abs(q[min(k, len(t) - 1)] - np.array(marks[-1]["q_rad"])).max() < math.radians(0.5)
    again = run_cli("teach", "recover", "crash", "--dir", str(programs), check=False)
    assert again.returncode != 0 and "exists" in again.stderr
