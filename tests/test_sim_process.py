"""The real sim process (`python -m sim run --lockstep`) on a udp_multicast group of its own, driven by a CANopen master
that steps its clock (a SYNC per period, the simulator's TIME frame awaited: test_sim_canopen.FrameLog), so the arm's
time in these tests is simulated time however busy the machine. The real-time runner itself (``--seconds``, SIGINT on
the wall clock) is tests/test_sim_realtime.py."""

from __future__ import annotations

import json
import os
import random
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import can
import canopen
import numpy as np
import pytest
from test_sim_canopen import GUARD_S, FrameLog

from dragd.hardware.bus import open_bus, parse_bus
from dragd.model import RobotModel
from dragd.protocol import ControlClient
from sim.drive import DEFAULT_EDS_PATH
from sim.truth import load_truth

pytestmark = pytest.mark.lockstep

REPO = Path(__file__).resolve().parents[1]
CST = 10
SW_STATE_MASK, SW_OPERATION_ENABLED = 0x006F, 0x0027


def unique_group() -> str:
    r = random.Random(os.getpid() * 1_000_003 + time.monotonic_ns())
    return f"239.{r.randint(1, 254)}.{r.randint(1, 254)}.{r.randint(1, 254)}"


class SimProc:
    """`python -m sim run --lockstep --json` as a child process with a control socket (``lockstep=False``: on the
    wall clock, up once its real-time loop runs)."""

    def __init__(self, tmp_path: Path, group: str, *extra: str, lockstep: bool = True) -> None:
        self.sock = str(tmp_path / "sim.sock")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "sim", "run", "--bus", f"udp_multicast:{group}", "--control", self.sock, "--json",
             *(["--lockstep"] if lockstep else []), *extra],
            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.client = ControlClient(self.sock, timeout_s=5.0)
        deadline = time.monotonic() + 60.0
        while True:
            if self.proc.poll() is not None:
                raise AssertionError(f"sim exited early ({self.proc.returncode}): {self.proc.stderr.read()}")
            if os.path.exists(self.sock):
                try:
                    st = self.client.call("state")
                    if st["ok"] and (lockstep or st["steps"] > 0):  # (lockstep: its time runs by a master's SYNCs)
                        break
                except ConnectionError:
                    pass
            if time.monotonic() > deadline:
                raise AssertionError("sim did not come up within 60 s")
            time.sleep(0.1)

    def call(self, cmd: str, **args: Any) -> dict[str, Any]:
        return self.client.call(cmd, **args)

    def finish(self, sig: int | None = signal.SIGTERM, timeout: float = 20.0) -> tuple[int, dict[str, Any], str]:
        if sig is not None:
            self.proc.send_signal(sig)
        out, err = self.proc.communicate(timeout=timeout)
        lines = [ln for ln in out.splitlines() if ln.strip()]
        return self.proc.returncode, json.loads(lines[-1]) if lines else {}, err

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.communicate(timeout=10)


class Master:
    """A minimal CANopen master at the simulator's 1 ms period: NMT + SDO via `canopen`, controlword/target torque via
    RPDO1 before each SYNC; ``run(seconds)`` steps the simulator's clock that long."""

    def __init__(self, group: str) -> None:
        self.truth = load_truth()
        self.robot = RobotModel.from_urdf("seed_cobot")
        self.joints = self.truth.joints
        self.bus = open_bus(parse_bus(f"udp_multicast:{group}", fd=True))
        self.net = canopen.Network(self.bus)
        self.net.connect()
        self.log = FrameLog(self.bus.send)
        self.net.notifier.add_listener(self.log)
        self.ids = [j.drive.node_id for j in self.joints]
        self.status = {n: 0 for n in self.ids}
        self.counts: dict[int, int | None] = {n: None for n in self.ids}
        self.tpdos = 0
        for n in self.ids:
            self.net.subscribe(0x180 + n, self._on_tpdo1)
        self.nodes = [self.net.add_node(n, str(DEFAULT_EDS_PATH)) for n in self.ids]
        for node in self.nodes:
            node.sdo.RESPONSE_TIMEOUT = GUARD_S  # (answered at once, between periods: a hang guard)
        self.controlword = 0x06
        self.zero_torque: set[int] = set()
        self.cycles = 0

    def _on_tpdo1(self, can_id: int, data: bytearray, timestamp: float) -> None:
        sw, pos, _cur = struct.unpack_from("<Hih", bytes(data))
        self.status[can_id - 0x180] = sw
        self.counts[can_id - 0x180] = pos
        self.tpdos += 1

    def configure(self) -> None:
        for node in self.nodes:
            node.sdo.download(0x6060, 0, struct.pack("<b", CST))
            assert struct.unpack("<b", node.sdo.upload(0x6061, 0))[0] == CST
        self.net.nmt.state = "OPERATIONAL"

    def q_rad(self) -> np.ndarray | None:
        if any(c is None for c in self.counts.values()):
            return None
        return np.array([self.counts[n] * 2 * np.pi / j.drive.encoder_counts_per_rev
                         for n, j in zip(self.ids, self.joints, strict=True)])

    def enabled(self) -> bool:
        return all(sw & SW_STATE_MASK == SW_OPERATION_ENABLED for sw in self.status.values())

    def _cycle(self) -> None:
        """The commands of this period (G(q)/K_t from the last TPDOs), sent before its SYNC."""
        q = self.q_rad()
        g = self.robot.gravity(q) if q is not None else np.zeros(len(self.ids))
        for i, (n, j) in enumerate(zip(self.ids, self.joints, strict=True)):
            amps = 0.0 if n in self.zero_torque else g[i] / j.torque_constant_Nm_per_A
            permille = int(np.clip(round(1000.0 * amps / j.drive.rated_current_A), -32768, 32767))
            self.bus.send(_msg(0x200 + n, struct.pack("<Hh", self.controlword, permille)))
        self.cycles += 1

    def run(self, seconds: float) -> None:
        self.log.step(round(seconds / 0.001), before=self._cycle)

    def until(self, cond: Any, timeout_s: float, what: str) -> None:
        end = self.log.t_s + timeout_s
        while not cond():
            assert self.log.t_s < end - 1e-9, f"no {what} within {timeout_s} s (simulated time)"
            self.run(0.001)

    def stop(self) -> None:
        self.net.disconnect()


def _msg(cob: int, data: bytes) -> Any:
    import can

    return can.Message(arbitration_id=cob, data=data, is_extended_id=False)


def test_cst_master_holds_the_arm_through_the_bus(tmp_path: Path) -> None:
    group = unique_group()
    sim = SimProc(tmp_path, group)
    master = None
    try:
        master = Master(group)
        master.configure()
        master.until(lambda: master.q_rad() is not None, 0.005, "TPDO1 from every drive")
        master.controlword = 0x06  # shutdown -> ready to switch on
        master.run(0.05)
        master.controlword = 0x07  # switch on
        master.run(0.05)
        master.controlword = 0x0F  # enable operation (target torque = G(q)/K_t already flowing)
        master.until(master.enabled, 0.1, "operation enabled on every drive")
        master.until(lambda: not any(sim.call("state")["brakes"]), 1.0, "brakes released")
        master.run(0.2)

        s0 = sim.call("state")
        assert s0["ok"] and all(s0["power_on"]) and not any(s0["brakes"])
        master.run(2.0)
        s1 = sim.call("state")
        assert s1["t"] - s0["t"] == pytest.approx(2.0, abs=1e-9)
        drift_deg = np.degrees(np.max(np.abs(np.array(s1["q_rad"]) - np.array(s0["q_rad"]))))
        assert drift_deg < 0.05, drift_deg
        # the drives' torque is what holds it: the currents carry G(q)
        g = master.robot.gravity(np.array(s1["q_rad"]))
        tau = np.array(s1["current_A"]) * np.array([j.torque_constant_Nm_per_A for j in master.joints])
        assert np.allclose(tau, g, atol=0.05 * np.abs(g).max())

        refused = sim.call("set_q", q_rad=[0.0] * 6)
        assert not refused["ok"] and "only while the drives are disabled" in refused["error"]

        # negative control: without joint 2's torque the arm sinks
        master.zero_torque.add(2)
        master.run(0.3)
        s2 = sim.call("state")
        assert np.degrees(abs(s2["q_rad"][1] - s1["q_rad"][1])) > 0.5
    finally:
        if master is not None:
            master.stop()
        if sim.proc.poll() is None:
            rc, summary, err = sim.finish(signal.SIGTERM)
        else:
            sim.kill()
            rc, summary, err = sim.proc.returncode, {}, ""
    assert rc == 0, err
    assert summary["ok"] and summary["dropped_steps"] == 0, summary  # (lockstep: every period runs, none dropped)
    assert all(d["state"] == "OPERATION_ENABLED" and d["syncs"] > 2000
               for d in summary["drives"].values()), summary["drives"]
    # python-canopen's SYNC and RPDOs, packed as dragd packs them, were read by their templates (sim/network.py)
    bus = summary["bus_counters"]
    assert bus["template_datagrams"] > 1000 and bus["undecodable"] == 0, bus


def test_control_socket_commands(tmp_path: Path) -> None:
    group = unique_group()
    sim = SimProc(tmp_path, group)
    truth = load_truth()
    bus = open_bus(parse_bus(f"udp_multicast:{group}", fd=True))  # the master's SYNCs: the simulator's clock
    log = FrameLog(bus.send)
    notifier = can.Notifier(bus, [log])
    try:
        log.step()  # one period: the physics steps of 1 ms
        st = sim.call("state")
        for key in ("t", "q_rad", "dq_rad_s", "current_A", "tau_ext_Nm", "brakes", "rtf", "late_steps", "steps"):
            assert key in st, key
        assert st["q_rad"] == pytest.approx([j.initial_position_rad for j in truth.joints])
        assert all(st["brakes"]) and st["steps"] == round(truth.physics_rate_Hz * 0.001)
        assert st["t"] == pytest.approx(0.001)

        q = [0.1, -1.0, 1.4, -0.3, 1.2, 0.2]
        r = sim.call("set_q", q_rad=q)
        assert r["ok"], r
        assert sim.call("state")["q_rad"] == pytest.approx(q)
        assert not sim.call("set_q", q_rad=[0.0] * 5)["ok"]
        bad = sim.call("set_q", q_rad=[9.0, 0, 0, 0, 0, 0])
        assert not bad["ok"] and "hard stops" in bad["error"]

        # the brake slips when the operator's torque exceeds holding torque + static friction
        limit = truth.joints[0].brake_holding_torque_Nm + truth.joints[0].friction.static_pos
        scen = {"name": "brake_slip", "segments": [
            {"kind": "ramp", "joint": "joint1", "start": 140.0, "rate_per_s": 40.0, "threshold_rad": 0.0005,
             "timeout_s": 5.0, "then": "release"}]}
        r = sim.call("operator", scenario=scen)
        assert r["ok"] and r["name"] == "brake_slip", r
        log.until(lambda: sim.call("operator_events")["done"], 10.0, "the ramp to end")
        ev = sim.call("operator_events")
        br = [e for e in ev["events"] if e["kind"] == "breakaway"]
        assert len(br) == 1, ev
        assert abs(br[0]["torque_Nm"] - limit) / limit < 0.05, (br, limit)

        bad = sim.call("operator", scenario={"segments": [{"kind": "push", "joint": "joint9", "torque_Nm": 1,
                                                           "duration_s": 1}]})
        assert not bad["ok"] and "joint9" in bad["error"]
        r = sim.call("operator", scenario="j1_startup_ramp")  # a bundled scenario by name
        assert r["ok"] and r["name"] == "j1_startup_ramp", r
        log.step()  # (it starts on the arm's time)
        assert not sim.call("fly")["ok"]
        drives = sim.call("drives")["drives"]
        assert sorted(drives) == [str(j.drive.node_id) for j in truth.joints]
        assert all(d["state"] == "SWITCH_ON_DISABLED" for d in drives.values())

        assert sim.call("stop")["ok"]
        rc, summary, err = sim.finish(sig=None)
    finally:
        notifier.stop()
        bus.shutdown()
        sim.kill()
    assert rc == 0, err
    assert summary["ok"] and "rtf" in summary and summary["operator_events"][0]["kind"] == "start"
    assert not os.path.exists(sim.sock)


def test_bad_truth_is_reported(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    seed = (REPO / "sim" / "config" / "seed_cobot.yaml").read_text()
    bad.write_text(seed.replace("gear_ratio: 101", "gear_ratio: abc", 1))
    proc = subprocess.run([sys.executable, "-m", "sim", "run", "--config", str(bad), "--seconds", "1"], cwd=REPO,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert f"{bad}: joints[0].gear_ratio: expected a positive number, got 'abc'" in proc.stderr


def test_released_joint_swings_with_urdf_period_over_the_bus(tmp_path: Path) -> None:
    """The sim process on udp_multicast: only the elbow's drive enabled over SDO with zero torque (brake off, no
    friction on that joint in this truth), the others braked: it swings with the small-angle period of its URDF."""
    import math

    import pinocchio as pin
    import yaml
    from test_sim_physics import _stable_equilibrium

    j = 2  # joint3
    truth_data = yaml.safe_load((Path(REPO) / "sim/config/seed_cobot.yaml").read_text())
    truth_data["joints"][j]["friction"] = {"coulomb_pos_Nm": 0.0, "coulomb_neg_Nm": 0.0, "static_pos_Nm": 0.0,
                                           "static_neg_Nm": 0.0, "viscous_pos_Nm_s_per_rad": 0.0,
                                           "viscous_neg_Nm_s_per_rad": 0.0}
    cfg = tmp_path / "frictionless_elbow.yaml"
    cfg.write_text(yaml.safe_dump(truth_data, sort_keys=False))
    truth = load_truth(cfg)
    robot = RobotModel.from_urdf("seed_cobot")
    q_eq, k = _stable_equilibrium(robot, np.array([0.0, 0.0, 1.5, 0.0, 1.5708, 0.0]), j)
    inertia = pin.crba(robot.model, robot.model.createData(), q_eq)[j, j] + truth.joints[j].armature_kgm2
    expected = 2 * math.pi * math.sqrt(inertia / k)

    group = unique_group()
    sim = SimProc(tmp_path, group, "--config", str(cfg))
    bus = open_bus(parse_bus(f"udp_multicast:{group}", fd=True))
    net = canopen.Network(bus)
    net.connect()
    log = FrameLog(bus.send)
    net.notifier.add_listener(log)
    try:
        q0 = q_eq.copy()
        q0[j] += 0.01
        sim.call("set_q", q_rad=q0.tolist())
        node = net.add_node(j + 1, str(DEFAULT_EDS_PATH))
        node.sdo.RESPONSE_TIMEOUT = GUARD_S
        node.sdo.download(0x6060, 0, struct.pack("<b", CST))
        node.sdo.download(0x6071, 0, struct.pack("<h", 0))
        for cw in (0x06, 0x07, 0x0F):  # shutdown, switch on, enable operation: brake off, zero torque
            node.sdo.download(0x6040, 0, struct.pack("<H", cw))
        t, q = [], []
        for _ in range(round((3.5 * expected + 0.3) / 0.004)):  # a sample every 4 ms of the arm's time
            st = sim.call("state")
            t.append(st["t"])
            q.append(st["q_rad"][j] - q_eq[j])
            log.sleep(0.004)
        others = [i for i in range(6) if i != j]
        assert np.allclose(np.array(sim.call("state")["q_rad"])[others], q0[others]), "braked joints moved"
    finally:
        net.disconnect()
        sim.finish()
    t_arr, q_arr = np.array(t), np.array(q)
    idx = np.flatnonzero((q_arr[:-1] > 0) & (q_arr[1:] <= 0))
    crossings = t_arr[idx] + q_arr[idx] / (q_arr[idx] - q_arr[idx + 1]) * (t_arr[idx + 1] - t_arr[idx])
    assert len(crossings) >= 3, q_arr
    period = float(np.mean(np.diff(crossings)))
    assert abs(period - expected) / expected < 0.02, (period, expected)
