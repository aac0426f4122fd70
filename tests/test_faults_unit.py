"""Fault detection pieces without processes: frame filtering, duplicates, the 402 drop-out, encoder plausibility,
the sim's fault injector on an in-process bus, the configuration's timing cross-checks (docs/SAFETY.md)."""

from __future__ import annotations

import math
import threading
import time
from pathlib import Path

import can
import numpy as np
import pytest
import yaml

from dragd.config import ConfigError, load_config
from dragd.control.modes import Mode
from dragd.daemon.core import Daemon
from dragd.hardware.cia402 import State
from dragd.hardware.drives import DriveSupervisor, Target
from sim.faults import FaultError, FaultInjector

from conftest import DEFAULT_CONFIG
from inproc import InProcess

pytestmark = pytest.mark.unit

SW_ENABLED, SW_SWITCHED_ON = 0x0237, 0x0233


@pytest.fixture
def daemon() -> Daemon:
    d = Daemon(load_config(DEFAULT_CONFIG), bus_override="udp_multicast:239.74.200.2", log=lambda msg: None)
    d.attach({"arm": can.Bus(interface="virtual", channel="unit-faults")})
    return d


def test_extended_rtr_and_short_frames_are_rejected_never_decoded(daemon: Daemon) -> None:
    rx = daemon.io.listener("arm")
    fb = daemon.io.feedback
    rx.on_message_received(can.Message(arbitration_id=0x181, data=bytes([1, 0, 0, 0, 0, 0, 0, 0]), is_extended_id=True))
    rx.on_message_received(can.Message(arbitration_id=0x181, is_remote_frame=True, dlc=8, is_extended_id=False))
    rx.on_message_received(can.Message(arbitration_id=0x181, data=b"\x01\x02", is_extended_id=False))
    rx.on_message_received(can.Message(arbitration_id=0x081, data=bytes([0x10, 0x23, 1, 0, 0, 0, 0, 0]),
                                       is_extended_id=True))  # an "EMCY" with a 29-bit id
    assert daemon.io.rejected_frames == 4
    assert fb.counts[0] == 0 and not fb.rx[0] and daemon.faults == []


def test_a_duplicate_tpdo_is_counted_once_per_extra_copy(daemon: Daemon) -> None:
    rx = daemon.io.listener("arm")
    daemon.io.begin_cycle()
    frame = can.Message(arbitration_id=0x181, data=bytes([7, 0, 0, 0, 0, 0, 0x37, 0x02]), is_extended_id=False)
    rx.on_message_received(frame)
    rx.on_message_received(frame)
    assert daemon.io.duplicate_tpdos == 1 and daemon.io.feedback.rx_count == 1


def test_a_drive_dropping_to_switched_on_is_a_fault_not_re_enabled() -> None:
    sup = DriveSupervisor([1, 2], enable_timeout_s=1.0)
    sw = np.array([SW_ENABLED, SW_ENABLED])
    sup.request_enable(0.0)
    for k in range(4):
        sup.update(sw, Target.ENABLED, 0.001 * k)
    assert sup.enable_t0 is None and sup.all_enabled
    sw[1] = SW_SWITCHED_ON
    fault = sup.update(sw, Target.ENABLED, 0.01)
    assert fault is not None and fault[0] == 1 and "switched_on" in fault[1] and "not re-enabled" in fault[1]
    assert sup.states[1] == State.SWITCHED_ON
    assert sup.cw[1] == 0x0000  # disable voltage, never enable operation (0x000F) on its own


def test_an_encoder_jump_is_rejected_then_faults_when_it_persists() -> None:
    ip = InProcess(load_config(DEFAULT_CONFIG))
    q = np.array([0.0, -0.5, 0.8, 0.0, 0.5, 0.0])
    ip.hold(q)
    for _ in range(5):
        ip.feed(q)
        ip.cycle()
    assert ip.c.mode == Mode.HOLD
    jumped = q.copy()
    jumped[2] += 0.2  # 0.2 rad in 1 ms: 200 rad/s
    ip.feed(jumped)
    ip.cycle()
    assert ip.cy.encoders.rejects == 1 and abs(ip.cy.est.q_rad[2] - q[2]) < 1e-3  # rejected: the estimate stays
    ip.feed(q)  # a glitch: the next sample is plausible again
    ip.cycle()
    assert ip.c.mode == Mode.HOLD and ip.d.faults == []
    for _ in range(ip.cy.hold_after):
        ip.feed(jumped)
        ip.cycle()
    assert ip.c.mode == Mode.FAULT
    assert any("encoder jump on node 3" in f["text"] for f in ip.d.faults), ip.d.faults
    ip.feed(jumped)
    ip.cycle()  # the new position is the baseline: one fault, not one per cycle
    assert sum("encoder jump" in f["text"] for f in ip.d.faults) == 1


def test_plausible_motion_is_never_rejected() -> None:
    ip = InProcess(load_config(DEFAULT_CONFIG))
    q = np.zeros(6)
    ip.hold(q)
    for k in range(200):  # 3 rad/s on every joint: fast, but physical
        ip.feed(q + 3.0 * 0.001 * k)
        ip.cycle()
    assert ip.cy.encoders.rejects == 0


def test_motion_across_missed_ticks_is_judged_by_the_time_elapsed() -> None:
    """A host that stalls the cycle for 50 periods while a hand moves the arm at 3 rad/s: the next sample is 0.15 rad
    on, plausible for 50 ms (counted as one step it would be a 150 rad/s "jump", then a fault). A jump as fast
    after the same stall is still rejected."""
    ip = InProcess(load_config(DEFAULT_CONFIG))
    q = np.zeros(6)
    ip.hold(q)
    for k in range(20):
        ip.feed(q + 3.0 * 0.001 * k)
        ip.cycle()
    q1 = q + 3.0 * 0.001 * 19
    ip.feed(q1 + 3.0 * 0.050)
    ip.cycle(ticks=50)
    assert ip.cy.encoders.rejects == 0 and ip.d.faults == []
    assert ip.cy.est.q_rad[0] == pytest.approx(q1[0] + 0.15, abs=1e-3)
    ip.feed(q1 + 3.0 * 0.050 + 0.6)  # 0.6 rad within 50 ms: 12 rad/s, beyond the 6 rad/s bound
    ip.cycle(ticks=50)
    assert ip.cy.encoders.rejects == 6


def _cycle_without(ip: InProcess, silent: int, ticks: int = 1) -> None:
    """One cycle of ``ip`` in which joint ``silent``'s position TPDO does not arrive."""
    cy, io, fb = ip.cy, ip.d.io, ip.fb
    cy.tick(cy.dt * ticks * 1e6, ticks)
    io.begin_cycle()
    fb.rx[:] = True
    fb.rx[silent] = False
    fb.rx_count = fb.rx.shape[0] - 1
    if cy.step(io.end_read()):
        cy.cycles += 1
        for fn in cy.after_cycle:
            fn()  # type: ignore[operator]


def test_lost_feedback_is_judged_by_the_time_elapsed_across_missed_ticks() -> None:
    """A joint silent for 20 periods, then a 40-period host stall: it has been silent 60 ms, beyond the 50 of
    stale_cycles_disable — a fault naming 60 cycles (counted as steps it would be 21, and the arm kept going blind).
    The same stall with every joint reporting afterwards is no fault."""
    cfg = load_config(DEFAULT_CONFIG)
    assert (cfg.loop.stale_cycles_hold, cfg.loop.stale_cycles_disable) == (10, 50)
    for silent_after_stall in (True, False):
        ip = InProcess(cfg)
        q = np.zeros(6)
        ip.hold(q)
        for _ in range(20):
            _cycle_without(ip, 2)
        assert ip.d.faults == [] and int(ip.fb.stale[2]) == 20
        if silent_after_stall:
            _cycle_without(ip, 2, ticks=40)
            assert int(ip.fb.stale[2]) == 60
            assert [f["text"] for f in ip.d.faults] == ["feedback lost: no TPDO from node 3 for 60 cycles"]
        else:
            ip.cycle(ticks=40)
            assert ip.d.faults == [] and int(ip.fb.stale.max()) == 0


def _bus_pair(name: str) -> tuple[can.BusABC, can.BusABC]:
    return can.Bus(interface="virtual", channel=name), can.Bus(interface="virtual", channel=name)


class _Drive:
    def __init__(self, node_id: int) -> None:
        self.node_id = node_id


def test_sim_injector_drops_duplicates_and_silences_frames() -> None:
    sim_bus, master = _bus_pair("unit-injector")
    try:
        inj = FaultInjector(sim_bus)
        tx = {n: inj.sender(n) for n in (1, 2)}
        drives = {1: _Drive(1), 2: _Drive(2)}
        lock = threading.Lock()

        def frame(n: int) -> can.Message:
            return can.Message(arbitration_id=0x180 + n, data=bytes(8), is_extended_id=False)

        def received() -> list[int]:
            out = []
            while (m := master.recv(0.01)) is not None:
                out.append(m.arbitration_id)
            return out

        inj.inject("burst_loss", drives, {"frames": 2}, lock)
        for n in (1, 2, 1, 2):
            tx[n](frame(n))
        assert received() == [0x181, 0x182]
        inj.inject("duplicates", drives, {"frames": 1}, lock)
        tx[1](frame(1))
        tx[2](frame(2))
        assert received() == [0x181, 0x181, 0x182]
        inj.inject("drive_silent", drives, {"node_id": 2, "seconds": 0.05}, lock)
        tx[1](frame(1))
        tx[2](frame(2))
        assert received() == [0x181]
        time.sleep(0.06)
        tx[2](frame(2))
        assert received() == [0x182] and not inj.active
        inj.inject("bus_off", drives, {"seconds": 0.05}, lock)
        assert inj.rx_muted()
        tx[1](frame(1))
        assert received() == []
        time.sleep(0.06)
        assert not inj.rx_muted()
        out = inj.inject("garbage", drives, {"node_id": 1}, lock)
        got = []
        while (m := master.recv(0.01)) is not None:
            got.append(m)
        assert len(got) == out["frames"] and any(m.is_extended_id for m in got) and any(m.is_remote_frame for m in got)
        with pytest.raises(FaultError, match="node_id: expected one of"):
            inj.inject("drive_silent", drives, {"node_id": 9}, lock)
        with pytest.raises(FaultError, match="frames: expected a number"):
            inj.inject("burst_loss", drives, {"frames": "many"}, lock)
    finally:
        sim_bus.shutdown()
        master.shutdown()


@pytest.mark.parametrize("edit, match", [
    (lambda d: d.setdefault("master", {}).update(heartbeat_consumer_ms=150), "heartbeat_consumer_ms: expected >= 2 x"),
    (lambda d: d.setdefault("safety", {}).update(rpdo_timeout_ms=1), "rpdo_timeout_ms: expected 5..1000"),
    (lambda d: d.setdefault("safety", {}).update(rpdo_timeout_ms=60000), "rpdo_timeout_ms: expected 5..1000"),
    (lambda d: d.setdefault("loop", {}).update(tpdo_deadline_us=1500), "tpdo_deadline_us: expected below"),
    (lambda d: d.setdefault("master", {}).update(node_id=3), "master.node_id: expected a node id no drive uses"),
])
def test_config_refuses_dangerous_timing(tmp_path, edit, match) -> None:
    data = yaml.safe_load(DEFAULT_CONFIG.read_text())
    data["robot"]["urdf"] = "seed_cobot"
    edit(data)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=match):
        load_config(path)


def test_default_config_passes_the_cross_checks() -> None:
    cfg = load_config(DEFAULT_CONFIG)
    assert cfg.master.heartbeat_consumer_ms >= 2 * cfg.master.heartbeat_ms
    assert math.isfinite(cfg.safety.encoder_plausible_speed_rad_s)


def test_log_lines_carry_journald_priorities_under_systemd() -> None:
    from dragd.daemon.faults import LOG_ERR, journal_line

    assert journal_line("fault at t=1.000 s: EMCY", LOG_ERR, journal=True) == "<3>dragd: fault at t=1.000 s: EMCY"
    assert journal_line("running", journal=True) == "<6>dragd: running"
    assert journal_line("running", journal=False) == "dragd: running"  # a terminal gets no prefix
    lines: list[tuple] = []
    d = Daemon(load_config(DEFAULT_CONFIG), bus_override="udp_multicast:239.74.200.3",
               log=lambda text, priority=6: lines.append((text, priority)))
    d.attach({"arm": can.Bus(interface="virtual", channel="unit-journal")})
    d.fault_sink.fault(2, "EMCY 0x2310 from node 3")
    assert any(p == LOG_ERR and "fault at" in t for t, p in lines), lines


def test_atomic_write_replaces_whole_or_leaves_the_old_file(tmp_path, monkeypatch) -> None:
    import os as _os

    from dragd.atomic import write_atomic

    target = tmp_path / "params.yaml"
    write_atomic(target, "old: 1\n")
    assert target.read_text() == "old: 1\n"

    def boom(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(_os, "fsync", boom)
    with pytest.raises(OSError, match="No space"):
        write_atomic(target, "new: 2\n" * 1000)
    monkeypatch.undo()
    assert target.read_text() == "old: 1\n"  # the previous file, whole
    assert [p.name for p in tmp_path.iterdir()] == ["params.yaml"]  # no temporary left behind
    write_atomic(target, "new: 2\n")
    assert target.read_text() == "new: 2\n"


def test_trajectories_are_validated_before_motion() -> None:
    from dragd.control.trajectory import Trajectory

    ip = InProcess(load_config(DEFAULT_CONFIG))
    dt = ip.cy.dt
    n = 6
    t = np.array([0.0, 1.0, 2.0])
    ok = Trajectory(t, np.zeros((3, n)), dt)
    ip.m.validate(ok)  # at rest, inside every limit: accepted
    far = np.zeros((3, n))
    far[1:, 2] = 50.0  # beyond the limits (and the encoding)
    with pytest.raises(ValueError, match="joint3 leaves its position limits"):
        ip.m.validate(Trajectory(t, far, dt))
    step = np.zeros((3, n))
    step[1:, 1] = 0.3
    fast = Trajectory(np.array([0.0, 0.01, 0.02]), step, dt)  # 0.3 rad in 10 ms: a step target
    with pytest.raises(ValueError, match="joint2 would move at .* rad/s"):
        ip.m.validate(fast)


def test_trajectories_accelerating_too_hard_or_needing_too_much_current_are_refused() -> None:
    from dragd.control.trajectory import Trajectory
    from dragd.teach.plan import rigid_body_effort

    ip = InProcess(load_config(DEFAULT_CONFIG))
    dt, n = ip.cy.dt, 6
    q0 = np.array([0.0, -0.6, 1.2, -0.6, 1.5708, 0.0])

    def swing(amp_rad: float, period_s: float) -> Trajectory:
        t = np.linspace(0.0, period_s, 41)
        q = np.tile(q0, (t.size, 1))
        q[:, 1] += amp_rad * (1 - np.cos(2 * np.pi * t / period_s)) / 2  # joint2: peak accel amp·2π²/T²
        return Trajectory(t, q, dt)

    gentle = swing(0.2, 4.0)  # 0.25 rad/s², 0.16 rad/s
    ip.m.validate(gentle)
    eff = rigid_body_effort(str(ip.d.model.urdf_path), tuple(ip.d.cfg.robot.gravity_m_s2), gentle.table, dt)
    assert eff[0].shape == gentle.table.shape and eff[1].shape == (n,)
    ip.m.check_current(gentle, eff[1], eff[2])  # gravity and a slow swing: within every current limit
    gentle_need = eff[1] / ip.d.controller.kt
    hard = swing(0.3, 0.7)  # 0.3·2π²/0.49 ≈ 12 rad/s² (under the 20 rad/s² limit), 1.35 rad/s
    ip.m.validate(hard)
    eff = rigid_body_effort(str(ip.d.model.urdf_path), tuple(ip.d.cfg.robot.gravity_m_s2), hard.table, dt)
    c = ip.d.controller
    need = eff[1] / c.kt
    assert need[1] > gentle_need[1] + 0.1  # the swing's inertia needs current on top of the gravity's
    limit = c.params.current_limit_A.copy()
    c.params.current_limit_A[:] = np.maximum(limit, need * 1.01)
    c.params.current_limit_A[1] = 0.9 * need[1]  # the drive of joint 2 could not give what the swing needs
    try:
        with pytest.raises(ValueError, match=r"joint2 would need .* A at t = .* beyond its current_limit_A"):
            ip.m.check_current(hard, eff[1], eff[2])
    finally:
        c.params.current_limit_A[:] = limit
    too_hard = swing(0.5, 0.6)  # 0.5·2π²/0.36 ≈ 27 rad/s²
    with pytest.raises(ValueError, match=r"joint2 would accelerate at 2\d\.\d rad/s² at t = "
                                         r".*safety\.track_acceleration_limit_rad_s2 20"):
        ip.m.validate(too_hard)


def test_socket_paths_are_confined_to_the_daemons_folders(tmp_path) -> None:
    """record / track / teach / replay paths from the socket: inside control.allowed_dirs (after resolving '..' and
    symbolic links) or refused with the folders named — the daemon never writes or reads elsewhere for a client."""
    import asyncio
    import os

    from dragd.daemon.commands import command_table
    from dragd.daemon.paths import PathPolicy, allowed_dirs
    from dragd.protocol import ControlError

    cfg = load_config(DEFAULT_CONFIG)
    dirs = allowed_dirs(cfg, str(tmp_path / "tel" / "t.mcap"), [str(tmp_path / "lab")])
    assert cfg.program_dir in dirs or Path(os.path.realpath(cfg.program_dir)) in dirs
    assert Path(os.path.realpath(tmp_path / "tel")) in dirs and Path(os.path.realpath(tmp_path / "lab")) in dirs
    pol = PathPolicy([Path(os.path.realpath(tmp_path / "lab"))])
    (tmp_path / "lab").mkdir()
    assert pol.check("x", tmp_path / "lab" / "a.mcap") == Path(os.path.realpath(tmp_path / "lab" / "a.mcap"))
    for bad in (tmp_path / "lab" / ".." / "b.mcap", "/etc/passwd"):
        with pytest.raises(ValueError, match="outside the folders the daemon may use"):
            pol.check("x", bad)
    (tmp_path / "lab" / "link.mcap").symlink_to("/etc/dragd-escape.mcap")
    with pytest.raises(ValueError, match="link.mcap is outside"):
        pol.check("record start", tmp_path / "lab" / "link.mcap")

    ip = InProcess(cfg)
    ip.d.paths = PathPolicy([Path(os.path.realpath(tmp_path / "lab"))])
    table = command_table(ip.d)

    def ask(**req: object) -> str:
        with pytest.raises(ControlError) as e:
            asyncio.run(table(req))
        return str(e.value)

    assert "record start: /etc/dragd.mcap is outside" in ask(cmd="record", action="start", path="/etc/dragd.mcap")
    assert not Path("/etc/dragd.mcap").exists()
    err = ask(cmd="track", file="/etc/passwd")
    assert "track: /etc/passwd is outside" in err and "root:" not in err  # refused before reading anything
    assert "control.allowed_dirs" in ask(cmd="teach", action="start", name="/root/prog.yaml", overwrite=True)


@pytest.mark.parametrize("arrives", ["before the next SYNC", "with the next cycle's"])
def test_a_drive_that_left_operation_enabled_in_a_late_tpdo_is_seen(arrives: str) -> None:
    """Node 5 drops to switched on for one sample and the master's cyclic enable-operation brings it back at the
    next SYNC. The TPDO that reports it comes late (after the cycle's deadline): it must not be overwritten by the
    next one before a step has judged it — the supervisor sees switched on, then enabled again, in order."""
    ip = InProcess(load_config(DEFAULT_CONFIG))
    q0 = np.array([0.0, -0.5, 0.9, -0.4, 0.5, 0.1])
    io, bus = ip.d.io, next(iter(ip.d.layouts))
    rx, table = io.listener(bus), io._decoders[bus]

    def report(joint: int, statusword: int) -> None:  # the joint's TPDO through the decoder
        cob, codec = next((c, e[1]) for c, e in table.items() if e[0] == joint)
        fields = next(fr.slots[0].fields for fr in ip.d.layouts[bus].frames if fr.cob_id == cob)
        values = {"position": int(ip.counts(q0)[joint]), "current": 0, "statusword": statusword}
        rx.on_message_received(can.Message(arbitration_id=cob, data=codec.pack(*(values[f] for f in fields)),
                                           is_extended_id=False))

    def step() -> None:  # the step after a read, and what the cycle runs after it (the daemon's fault list)
        ip.cy.step(io.end_read())
        for fn in ip.cy.after_cycle:
            fn()

    def read_step(late: dict[int, int] | None = None) -> None:  # one cycle; ``late``: reports after the deadline
        ip.cy.tick(ip.cy.dt * 1e6, 1)
        io.begin_cycle()
        for j in range(6):
            if late is None:
                report(j, SW_ENABLED)
        step()
        for j, sw in (late or {}).items():
            report(j, sw)

    ip.hold(q0)
    for _ in range(5):
        read_step()
    assert ip.c.mode == Mode.HOLD and ip.d.faults == []
    # the cycle whose TPDOs come late: node 5 (joint 4) reports switched on after the deadline
    late = {j: (SW_SWITCHED_ON if j == 4 else SW_ENABLED) for j in range(6)}
    if arrives == "before the next SYNC":
        read_step(late)  # decoded between the deadline's step and the next cycle
        read_step()  # ... whose own TPDOs say enabled again
    else:
        ip.cy.tick(ip.cy.dt * 1e6, 1)
        io.begin_cycle()
        step()  # the deadline: nothing came
        ip.cy.tick(ip.cy.dt * 1e6, 1)
        io.begin_cycle()
        for j, sw in late.items():  # the late ones inside the next cycle's read, then that cycle's own
            report(j, sw)
        for j in range(6):
            report(j, SW_ENABLED)
        step()
    assert io.deferred_statuswords == 1
    assert ip.c.mode == Mode.FAULT, ip.d.faults
    assert any("node 5 left operation enabled" in f["text"] for f in ip.d.faults), ip.d.faults
    read_step()  # the deferred report (enabled) is the next step's: nothing is held back any longer
    assert int(ip.fb.statusword[4]) == SW_ENABLED and not io._sw_holding
