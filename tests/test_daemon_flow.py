"""The daemon as a product: CLI flow start → drag → status → stop → SIGTERM against the simulated robot.

Real processes (``python -m sim run`` and ``python -m dragd run``) over udp_multicast on a private group, on the
lockstep clock (the arm's time passes only through ``rig.sleep`` / ``rig.wait_for``); the CLI is the real ``dragd``
entry point. Physical truth (brakes, power stages) is read from the simulator.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from dragd.lab.rig import Rig

from daemon_helpers import cycle_rows

pytestmark = pytest.mark.lockstep

STATUS_KEYS = {"mode", "drives_enabled", "cycles", "period_p99_us", "missed_cycles", "q_rad", "current_A", "faults"}


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """One drag session; the tests below check what it recorded."""
    tmp = tmp_path_factory.mktemp("flow")
    mcap = tmp / "flow.mcap"
    rig = Rig("flow", workdir=tmp, telemetry=mcap)
    out: dict = {"mcap": mcap}
    try:
        rig.start_sim()
        rig.start_daemon()
        p = rig.cli("start", "--json")
        assert p.returncode == 0, p.stderr
        out["start"] = json.loads(p.stdout)
        rig.sleep(0.3)  # (start answers once the drives are enabled; the hold current builds up after the brakes)
        out["status_hold"] = json.loads(rig.cli("status", "--json").stdout)
        rig.sleep(0.2)
        p = rig.cli("mode", "drag")
        assert p.returncode == 0, (p.stderr, rig.daemon.tail())
        rig.sleep(0.5)
        s0 = rig.must("status")
        sim0 = rig.sim_call("state")
        rig.sleep(4.0)  # nobody touching
        s1 = rig.must("status")
        sim1 = rig.sim_call("state")
        out["untouched"] = (s0, s1, sim0, sim1)
        # a scripted push on joint 1, then let go
        rig.sim_call("operator", scenario={"name": "push_j1", "segments": [
            {"kind": "push", "joint": "joint1", "torque_Nm": 7.0, "duration_s": 0.6},
            {"kind": "release", "duration_s": 0.0}]})
        rig.sleep(0.7)
        # let go: the virtual damping brings the joint to rest, friction then holds it
        rig.wait_for(lambda: max(abs(v) for v in rig.sim_call("state")["dq_rad_s"]) < 1e-4, 8.0,
                     "the arm to come to rest")
        rig.sleep(0.2)
        rel = rig.sim_call("state")
        rig.sleep(2.0)
        rel2 = rig.sim_call("state")
        out["push"] = (sim1, rel, rel2)
        out["status_drag"] = json.loads(rig.cli("status", "--json").stdout)
        # mode switches both ways, then stop
        p = rig.cli("mode", "hold")
        assert p.returncode == 0, (p.stderr, rig.daemon.tail())
        rig.sleep(0.6)
        p = rig.cli("mode", "drag")
        assert p.returncode == 0, (p.stderr, rig.daemon.tail())
        rig.sleep(0.6)
        p = rig.cli("stop", "--json")
        assert p.returncode == 0, p.stderr
        out["stop"] = json.loads(p.stdout)
        rig.sleep(0.2)
        out["sim_after_stop"] = rig.sim_call("state")
        out["status_stopped"] = rig.must("status")
        assert rig.cli("start").returncode == 0  # enabled again, then SIGTERM must ramp down and disable
        rig.sleep(0.5)
        out["daemon_rc"] = rig.daemon.terminate(120.0)  # (its ramp down runs on the clock, at the machine's pace)
        out["daemon_log"] = rig.daemon.output()
        out["sim_after_exit"] = rig.sim_call("state")
        out["drives_after_exit"] = rig.sim_call("drives")["drives"]
        yield out
    finally:
        rig.close()


def test_start_holds_and_status_has_promised_keys(session):
    assert session["start"]["mode"] == "hold"
    st = session["status_hold"]
    assert STATUS_KEYS <= st.keys()
    assert st["drives_enabled"] is True and st["mode"] == "hold" and st["faults"] == []
    assert len(st["q_rad"]) == 6 and len(st["current_A"]) == 6
    assert st["scheduler"] == "SCHED_OTHER"  # the default config asks for no real-time priority
    assert st["cpu_latency"] == {"requested_us": None, "applied": False, "reason": "not requested",
                                 "effective_us": None}  # (nor PM QoS)
    # holding the arm against gravity: joint 2 carries tens of N·m, i.e. several amperes
    assert abs(st["current_A"][1]) > 2.0


def test_the_cycles_tpdos_are_read_by_their_template(session):
    """On the udp_multicast bus the simulator's SYNC answer (six TPDOs, one datagram) is read by comparing bytes
    with the frames' templates, not by unpacking six maps (hardware/bus.py ``expect``): every cycle's."""
    st = session["status_drag"]
    bus = st["bus_counters"]["arm"]
    assert bus["template_datagrams"] >= 0.95 * st["cycles"] > 0, (bus, st["cycles"])
    assert bus["undecodable"] == bus["gaps"] == bus["duplicates_dropped"] == 0


def test_drag_untouched_arm_stays(session):
    s0, s1, sim0, sim1 = session["untouched"]
    assert s0["mode"] == s1["mode"] == "drag"
    moved = np.degrees(np.abs(np.array(sim1["q_rad"]) - np.array(sim0["q_rad"])))
    assert moved.max() < 0.5, moved


def test_push_moves_joint_and_it_stays_where_released(session):
    before, released, later = (np.array(s["q_rad"]) for s in session["push"])
    assert math.degrees(released[0] - before[0]) > 2.0  # the push moved joint 1 forward
    assert np.degrees(np.abs(later - released)).max() < 0.1  # and it stays where it came to rest
    assert session["status_drag"]["mode"] == "drag" and session["status_drag"]["faults"] == []


def test_stop_disables_with_brakes(session):
    assert session["stop"]["mode"] == "idle"
    assert session["status_stopped"]["drives_enabled"] is False
    assert all(session["sim_after_stop"]["brakes"])


def test_sigterm_ramps_down_disables_and_exits_zero(session):
    assert session["daemon_rc"] == 0, session["daemon_log"][-2000:]
    assert all(session["sim_after_exit"]["brakes"])
    assert all(d["state"] != "OPERATION_ENABLED" for d in session["drives_after_exit"].values())


def test_mode_switches_have_no_current_jump(session):
    rows = cycle_rows(session["mcap"])
    mode = rows["mode"]
    cmd = np.array(rows["current_command_A"])
    switches = [k for k in range(1, len(mode)) if mode[k] != mode[k - 1] and {mode[k], mode[k - 1]} <= {"hold", "drag"}]
    assert len(switches) >= 3  # hold→drag, drag→hold, hold→drag
    # change per elapsed cycle of the law's clock (which advances by the timer's expirations): after a late
    # tick (machine load) the time-based sine legitimately moves further
    elapsed = np.maximum(1.0, np.round(np.diff(np.asarray(rows["t_s"], dtype=float)) / 1e-3))
    steps = np.abs(np.diff(cmd, axis=0)) / elapsed[:, None]
    for k in switches:
        nxt = next((j for j in range(k + 1, len(mode)) if mode[j] != mode[k]), len(mode))
        window = steps[k - 5:min(k + 250, nxt - 1)]  # the switch and the blend after it (not the stop's disable)
        # the start-up sine alone changes joint 2's command by up to 2π·16 Hz·0.9 A·1 ms ≈ 0.09 A per cycle; an
        # un-blended hold↔drag switch steps by the friction + sine level (0.5-1 A)
        assert window.max() < 0.25, (k, mode[k - 1], mode[k], window.max(axis=0))


def test_run_refuses_a_bad_realtime_priority(tmp_path):
    from conftest import run_cli

    p = run_cli("run", "--realtime-priority", "120", "--socket", str(tmp_path / "d.sock"), check=False)
    assert p.returncode == 2
    assert "--realtime-priority" in p.stderr and "1..99" in p.stderr and "120" in p.stderr


def test_cli_without_daemon_says_so(tmp_path):
    from conftest import run_cli

    p = run_cli("status", "--socket", str(tmp_path / "none.sock"), check=False)
    assert p.returncode == 1
    assert "no dragd daemon answers at" in p.stderr and "none.sock" in p.stderr
