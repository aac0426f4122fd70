"""The fault matrix, one rig (sim + daemon processes) per fault, on the lockstep clock: every fault the sim injects is
detected, the daemon reacts as docs/SAFETY.md documents, no joint runs faster than its speed cap, nothing falls more
than 1°, the policy's recovery happens and no telemetry row is lost. Asserted on the daemon's status and the sim's
truth; the injection lands between two cycles, so no host's timing takes part (a late TPDO *in time*, against the
read deadline on the wall clock, is tests/test_fault_timing.py)."""

from __future__ import annotations

import pytest

from dragd.lab.faults import CASES, hand_rig_kwargs, run_fault
from dragd.lab.rig import Rig

# a hang guard of wall time: on a loaded machine the lockstep clock runs slower, never wrong
pytestmark = [pytest.mark.lockstep, pytest.mark.slow, pytest.mark.timeout(1200)]

SPEED_CAP_RAD_S = 1.0  # the lowest joints[].velocity_limit_rad_s of config/default.yaml

# injection → detection on the lockstep clock, exact to the cycle (1 ms), by config/default.yaml's policy (the status
# is looked at after every cycle): a new row states its own
DETECTED_MS = {
    "drive_silent": 50.0,  # its TPDO stale for loop.stale_cycles_disable (50) cycles: fault "feedback lost"
    "burst_loss": 10.0,  # TPDOs stale for loop.stale_cycles_hold (10) cycles: a feedback hold
    "burst_loss_short": 1.0,  # the first cycle without them (late_tpdo_cycles)
    "duplicates": 1.0,  # the first cycle with a position TPDO twice (duplicate_tpdos)
    "late_tpdo": 1.0,  # the first period whose TPDOs miss its end (late_tpdo_cycles)
    "emcy": 0.0,  # the EMCY leaves at once and is handled before the next cycle
    "drive_fault": 0.0,  # likewise (its EMCY)
    "switched_on": 1.0,  # the next TPDO's statusword
    "node_reboot": 10.0,  # its boot-up heartbeat, seen by the heartbeat consumer's 10 ms check: within 10 ms
    "bus_off": 50.0,  # every TPDO stale for loop.stale_cycles_disable cycles
    "encoder_jump": 10.0,  # samples rejected for loop.stale_cycles_hold cycles in a row: fault "encoder jump"
    "garbage": 0.0,  # counted as the frames are decoded (rejected_frames)
    # (#30's hand rig: 250 Hz, a 4 ms cycle)
    "stuck_enable": 56.0,  # the channels disagreeing longer than hand.discrepancy_ms (50), at the cycles' 4 ms grid
    "chattering_contact": 36.0,  # the 9th edge (more than hand.chatter_edges, 8) of an 8 ms chatter: 4 ms apart
    "inputs_lost": 36.0,  # the inputs' event TPDO older than 2.5 event timers (hand.event_timer_ms), on the grid
}


def _run(tmp_path, name: str) -> tuple[dict, dict, str]:
    kw = hand_rig_kwargs(tmp_path) if CASES[name].rig == "hand" else {}  # (#30: the guiding device wired)
    with Rig(f"fault-{name}", workdir=tmp_path, telemetry=tmp_path / "t.mcap", **kw) as rig:
        rig.start_sim()
        rig.start_daemon()
        r = run_fault(rig, name)
        return r, rig.must("status"), rig.daemon.tail(40)


@pytest.mark.parametrize("name", list(CASES))
def test_fault(tmp_path, name):
    case = CASES[name]
    r, status, log = _run(tmp_path, name)
    assert r["detected_ms"] is not None, (r, log)
    if name == "node_reboot":  # (where in the check's 10 ms the boot-up falls is the rig's start's phase)
        assert 0.0 < r["detected_ms"] <= DETECTED_MS[name] + 1e-6, (r, log)
    else:
        assert r["detected_ms"] == pytest.approx(DETECTED_MS[name], abs=1e-6), (r, log)
    assert r["reaction"] == case.reaction, (r, log)
    assert r["recovered"], (r, log)
    assert r["max_joint_speed_rad_s"] <= SPEED_CAP_RAD_S, r
    assert r["max_drift_deg"] <= 1.0, r
    assert r["rows_lost"] == 0, r
    assert r["sim_behind_ms"] == 0.0, r  # (the simulated robot never falls behind the lockstep clock)
    for word in case.expect_fault:
        assert any(word in t for t in r["faults"]), (word, r)
    if case.recover == "auto":  # rejoined in HOLD with every drive operational, no daemon restart
        assert status["mode"] == "hold" and status["drives_enabled"], status
        assert all(n["nmt"] == "operational" for n in status["comms"]["nodes"].values()), status["comms"]
    if name == "node_reboot":
        assert status["comms"]["reboots"] == 1 and "reconfigured after its reboot" in log, log
    if name == "bus_off":
        assert status["comms"]["outages"] == 1 and any("bus outage" in t for t in r["faults"]), r
    if case.rig == "hand":  # (#30) out of drag at once, into a hold, the fault named where it is
        assert r["out_of_drag_ms"] is not None and r["out_of_drag_ms"] <= r["detected_ms"], r
        assert status["mode"] == "drag" and r["feedback_holds"] == 0, (status["mode"], r)
    if name == "garbage":
        # the short and the RTR frame reach the decoder and are rejected; the 29-bit ones never pass the bus filter
        assert status["rejected_frames"] >= 2 and status["fault_count"] == 0, status
