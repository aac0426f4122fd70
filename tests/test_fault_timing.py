"""A late TPDO *in time* (wall clock, rig tier): the simulated drives send their TPDOs 15 ms after the SYNC for 0.3 s,
far past the daemon's read deadline (``loop.tpdo_deadline_us``, below the 1 ms period): the deadline finds them
missing, the arm goes to a feedback hold and drag resumes by itself once they are on time again. The deadline is
real time, so this stays on the wall clock; the margin is physical (a delay 15 × the period, a hold for a 300 ms
outage). Every other fault of the matrix is tests/test_fault_matrix.py, on the lockstep clock."""

from __future__ import annotations

import pytest

from dragd.lab.faults import CASES, run_fault
from dragd.lab.rig import Rig

pytestmark = [pytest.mark.rig, pytest.mark.slow]


def test_a_late_tpdo_in_time_holds_the_arm_and_drag_resumes(tmp_path):
    with Rig("fault-late", workdir=tmp_path, telemetry=tmp_path / "t.mcap", as_deployed=True) as rig:
        rig.start_sim()
        rig.start_daemon()
        r = run_fault(rig, "late_tpdo")
        log = rig.daemon.tail(40)
    assert r["detected_ms"] is not None and r["reaction"] == CASES["late_tpdo"].reaction == "hold", (r, log)
    assert r["recovered"], (r, log)
    assert r["max_drift_deg"] <= 1.0 and r["rows_lost"] == 0, r
