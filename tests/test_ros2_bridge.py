"""The ROS 2 bridge as a process (``dragd ros2``) beside the simulator and the daemon, against a plain rclpy client:
what it publishes (against the simulator's truth), its services, the topic_based_ros2_control command pair,
JointTrajectory, the drag keepalive, refusals with their reasons, and losing the bridge (killed) mid-motion.

On the lockstep clock (docs/LOCKSTEP.md): the bridge follows the daemon's simulated time (its stamps, rates and
keepalive timeout; ``/clock``). The client acts between grants: what it publishes periodically (the commands at
100 Hz, the keepalive at 20 Hz) goes out at exact simulated times through ``Rig.every``, and each message is waited
for, in wall time, until it has had its effect in the daemon (a stream sample counted, a lease renewal counted) before
the arm's time goes on; what the bridge publishes is waited for in wall time where the arm's time need not run for it.
So every verdict is the same however the host schedules the five processes."""

from __future__ import annotations

import math
import signal
from collections.abc import Callable

import numpy as np
import pytest
from ros2_helpers import Probe, needs_ros2, start_bridge

from dragd.lab.rig import Child, Rig, wait_until

# one worker for the module: every bridge is node /dragd in this process's DDS domain (ros2_helpers.ros_env)
pytestmark = [pytest.mark.lockstep, needs_ros2, pytest.mark.xdist_group("ros2_bridge")]

STEP = np.array([0.25, -0.15, 0.2, 0.3, -0.25, 0.3])
HEARD_S = 60.0  # a hang guard in wall time for what the bridge says (no verdict: the arm's time stands still meanwhile)


def _msgs():
    from builtin_interfaces.msg import Duration
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    from rclpy.qos import DurabilityPolicy, QoSProfile
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import JointState
    from std_msgs.msg import Empty, String
    from std_srvs.srv import SetBool, Trigger
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    return {"Duration": Duration, "DiagnosticArray": DiagnosticArray, "DiagnosticStatus": DiagnosticStatus,
            "JointState": JointState, "Empty": Empty, "String": String, "SetBool": SetBool, "Trigger": Trigger,
            "JointTrajectory": JointTrajectory, "JointTrajectoryPoint": JointTrajectoryPoint, "latched": latched,
            "Clock": Clock}


def listening(m) -> Probe:
    p = Probe()
    p.listen(m["JointState"], "/joint_states")
    p.listen(m["String"], "/robot_description", m["latched"])
    p.listen(m["String"], "/dragd/mode", m["latched"])
    p.listen(m["String"], "/dragd/events", 100)
    p.listen(m["DiagnosticStatus"], "/dragd/status", 20)
    p.listen(m["DiagnosticArray"], "/diagnostics")
    p.listen(m["Clock"], "/clock")
    return p


def status_texts(p: Probe, name: str) -> list[tuple[int, str]]:
    return [(s.level[0], s.message) for s in p.messages("/dragd/status") if s.name == name]


def bridging(rig: Rig, p: Probe, *ros_args: str) -> Child:
    """``dragd ros2`` beside the rig's daemon, its topics matched to the probe's subscriptions (what it publishes from
    then on arrives: the arm's time stands still until the test grants it, and with it the bridge's publishing)."""
    bridge = start_bridge(rig, *ros_args)
    heard(p.matched, "the bridge's topics matched to the probe", bridge)
    return bridge


def matched_publishers(p: Probe, topic: str) -> int:
    """How many publishers of ``topic`` the bridge's subscription says it has matched (its newest word on it)."""
    said = [s for s in p.messages("/dragd/status") if s.name == "dragd/publishers"
            and {v.key: v.value for v in s.values}.get("topic") == topic]
    return int({v.key: v.value for v in said[-1].values}["count"]) if said else 0


def publisher(p: Probe, msg_type, topic: str, bridge: Child):
    """A publisher of the probe, matched both ways before anything is published: the probe's side sees the bridge's
    subscription, and the bridge says its subscription matched one more publisher (discovery is two-sided: a
    message sent before the subscription has matched its publisher is dropped)."""
    private = "~/" + topic.rsplit("/", 1)[1]
    before = matched_publishers(p, private)
    pub = p.publisher(msg_type, topic)
    heard(lambda: pub.get_subscription_count() > 0, f"the bridge's subscription of {topic}", bridge)
    heard(lambda: matched_publishers(p, private) > before, f"the bridge's subscription of {topic} matched", bridge)
    return pub


def heard(cond: Callable[[], object], what: str, bridge: Child) -> None:
    """Wait (wall time, the arm's time standing still) for what the bridge says or does without needing arm time."""
    wait_until(lambda: bool(cond()), HEARD_S, what, bridge, interval_s=0.005)


def mode_of(rig: Rig) -> str:
    return rig.must("state")["mode"]


def stamp_ns(msg) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def trajectory(m, names, points):
    msg = m["JointTrajectory"]()
    msg.joint_names = list(names)
    for t, q in points:
        pt = m["JointTrajectoryPoint"]()
        pt.positions = [float(x) for x in q]
        pt.time_from_start = m["Duration"](sec=int(t), nanosec=int(round((t - int(t)) * 1e9)))
        msg.points.append(pt)
    return msg


class Streamer:
    """What topic_based_ros2_control does: a JointState of position commands on every controller update (100 Hz of
    the arm's time), stamped with that time. ``follow``: each command is waited for until the daemon has it (the
    first opens the stream, the bridge says so on ~/status; every later one is a sample of it, or the stream ended)."""

    def __init__(self, rig: Rig, p: Probe, m, bridge: Child, names, q0: np.ndarray, T: float,
                 path: Callable[[float], np.ndarray] | None = None) -> None:
        self.rig, self.p, self.m, self.bridge, self.names, self.q0, self.T = rig, p, m, bridge, list(names), q0, T
        self.path = path or self.q
        self.pub = publisher(p, m["JointState"], "/dragd/joint_commands", bridge)
        self.follow = True
        self.sent = 0
        self.first: int | None = None  # commands sent when the stream opened
        self.t_last = self.t0 = rig.now()
        self._opened = self._open_count()
        self.timer = rig.every(0.01, self._tick)

    def _open_count(self) -> int:
        return sum(" open: commands go to the arm" in t for _lv, t in status_texts(self.p, "dragd/stream"))

    def q(self, t: float) -> np.ndarray:
        x = min(max(t / self.T, 0.0), 1.0)
        return self.q0 + STEP * (1.0 - math.cos(math.pi * x)) / 2.0

    def _tick(self) -> None:
        t = self.rig.now()
        msg = self.m["JointState"]()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(round(t * 1e9), 1_000_000_000)
        msg.name = self.names
        msg.position = self.path(t - self.t0).tolist()
        self.pub.publish(msg)
        self.sent += 1
        self.t_last = t
        if not self.follow:
            return
        if self.first is None:
            heard(lambda: self._open_count() > self._opened, "the stream's opening on ~/status", self.bridge)
            self.first = self.sent
            return
        n = self.sent - self.first

        def landed() -> bool:
            st = self.rig.must("state")["stream"]
            return st["samples"] >= n or st["state"] != "running"

        heard(landed, f"command {self.sent} in the daemon's stream", self.bridge)

    def stop(self) -> None:
        self.timer.stop()


class Keepalive:
    """A ROS client's ~/drag_keepalive every 50 ms of the arm's time. ``follow``: the first is waited for until the
    bridge says it is present; the later ones, while the bridge holds a drag lease, until the daemon counted the
    renewal (or the lease ended)."""

    def __init__(self, rig: Rig, p: Probe, m, bridge: Child) -> None:
        self.rig, self.p, self.m, self.bridge = rig, p, m, bridge
        self.pub = publisher(p, m["Empty"], "/dragd/drag_keepalive", bridge)
        self.follow = True
        self.first = True
        self._present = self._present_count()
        self.timer = rig.every(0.05, self._tick)

    def _present_count(self) -> int:
        return sum("present" in t for _lv, t in status_texts(self.p, "dragd/keepalive"))

    def _lease(self) -> dict:
        return self.rig.must("lease", action="status")["lease"]

    def _tick(self) -> None:
        before = self._lease() if self.follow else {}
        if self.follow and self.first:  # the bridge's clock is at this time (it stamps the keepalive with it)
            t = round(self.rig.now() * 1e9)
            heard(lambda: stamp_ns_clock(self.p) == t, "the bridge's clock at this time", self.bridge)
        self.pub.publish(self.m["Empty"]())
        if not self.follow:
            return
        if self.first:
            self.first = False
            heard(lambda: self._present_count() > self._present, "the keepalive's presence on ~/status", self.bridge)
            return
        if before["state"] == "active" and str(before.get("holder", "")).startswith("ros2 bridge"):
            def renewed() -> bool:
                now = self._lease()
                return now["renewals"] > before["renewals"] or now["state"] != "active" or now["id"] != before["id"]

            heard(renewed, "the keepalive's lease renewal in the daemon", self.bridge)

    def stop(self) -> None:
        self.timer.stop()


def test_bridge_publishes_serves_follows_commands_and_trajectories(tmp_path):
    m = _msgs()
    with Rig("ros2", workdir=tmp_path) as rig:
        rig.start_sim()
        rig.start_daemon()
        robot = rig.must("robot")
        names = robot["joint_names"]
        p = listening(m)
        bridge = bridging(rig, p)
        try:
            # --- what it publishes, on the daemon's clock
            heard(lambda: p.messages("/robot_description") and p.messages("/dragd/mode"), "the latched topics", bridge)
            assert p.messages("/robot_description")[-1].data == open(robot["urdf_path"]).read()
            assert p.messages("/dragd/mode")[-1].data == "idle"
            t0 = rig.now()
            rig.sleep(1.0)  # (/diagnostics at 1 Hz of the daemon's time, /joint_states at 100 Hz)
            heard(lambda: p.messages("/diagnostics") and p.messages("/joint_states"), "the bridge's first", bridge)
            start = p.call(m["Trigger"], "/dragd/start")
            assert start.success and '"mode": "hold"' in start.message, start
            heard(lambda: p.messages("/dragd/mode")[-1].data == "hold", "mode hold on ~/mode", bridge)
            rig.sleep(0.5)
            t1 = rig.now()
            # the bridge saw this time (/clock) and published the state of its latest period of 10 ms
            heard(lambda: stamp_ns_clock(p) == round(t1 * 1e9), "/clock at this time", bridge)
            heard(lambda: stamp_ns(p.messages("/joint_states")[-1]) > round((t1 - 0.01) * 1e9), "the state now", bridge)
            js = p.messages("/joint_states")[-1]
            sim = rig.sim_call("state")
            assert list(js.name) == names  # the URDF's joint names, in its order
            assert np.abs(np.array(js.position) - sim["q_rad"]).max() < math.radians(0.05)
            # effort: K_t x the measured current, against the simulated motors' torque
            tau = np.array(sim["tau_motor_Nm"])
            assert (np.abs(np.array(js.effort) - tau) <= 0.05 * np.abs(tau) + 0.5).all(), (js.effort, tau)
            # stamps and /clock are the daemon's simulated time; /joint_states at most 100 Hz of it
            stamps = [stamp_ns(j) for j in p.messages("/joint_states")]
            assert all(b > a for a, b in zip(stamps, stamps[1:], strict=False)), np.diff(stamps).min()
            assert round(t0 * 1e9) <= stamps[0] and stamps[-1] <= round(t1 * 1e9)
            assert len(stamps) <= (stamps[-1] - stamps[0]) / 10_000_000 + 1, len(stamps)
            diag = {s.name: s for s in p.messages("/diagnostics")[-1].status}
            assert {"dragd: loop", "dragd: faults", "dragd: drives", "dragd: ros2 bridge"} <= set(diag)
            assert any(n.startswith("dragd: bus ") for n in diag)
            assert {kv.key for kv in diag["dragd: loop"].values} >= {"period_p99_us", "missed_cycles"}
            assert "lockstep" in {kv.key: kv.value for kv in diag["dragd: ros2 bridge"].values}["clock"]
            # --- drag needs the keepalive; when it lapses the daemon's drag lease lapses and the arm holds
            no = p.call(m["Trigger"], "/dragd/drag")
            assert not no.success and "drag_keepalive" in no.message, no
            alive = Keepalive(rig, p, m, bridge)
            rig.sleep(0.3)
            yes = p.call(m["Trigger"], "/dragd/drag")
            assert yes.success, yes
            rig.wait_for(lambda: mode_of(rig) == "drag", 5.0, "drag")
            rig.sleep(1.0)
            lease = rig.must("lease", action="status")["lease"]
            assert rig.must("state")["requested_mode"] == "drag" and lease["holder"].startswith("ros2 bridge")
            assert lease["renewals"] >= 20, lease  # (one per keepalive: 1.0 s at 20 Hz)
            alive.stop()
            t_silent = rig.now()
            rig.wait_for(lambda: rig.must("state")["requested_mode"] == "hold", 3.0, "hold after the keepalive stopped")
            lapsed_after_s = rig.now() - t_silent
            heard(lambda: status_texts(p, "dragd/drag"), "the bridge reporting the end of drag", bridge)
            assert any("drag ended: the drag lease lapsed" in t for _lv, t in status_texts(p, "dragd/drag")), \
                p.messages("/dragd/status")
            assert rig.must("status")["faults"][-1]["kind"] == "lease"
            ensure_streaming = p.call(m["SetBool"], "/dragd/streaming", m["SetBool"].Request(data=True))
            assert ensure_streaming.success  # (~/drag held the command stream back: an operator's action)
            # --- the topic_based_ros2_control pair: commands at 100 Hz followed, the arm where they end
            rig.wait_for(lambda: rig.must("status")["drive_mode"] == "cst", 5.0, "CST")
            q0 = np.array(rig.must("state")["q_rad"])
            s = Streamer(rig, p, m, bridge, names, q0, 2.0)
            assert mode_of(rig) == "track"  # (the first command opened the stream)
            rig.sleep(2.6 - (rig.now() - s.t0))
            mid = rig.must("state")["stream"]
            truth = np.array(rig.sim_call("state")["q_rad"])
            s.stop()  # the controller stops publishing: the stream's deadline ends it, the arm holds
            rig.wait_for(lambda: mode_of(rig) == "hold", 3.0, "hold after the commands stopped")
            why = f"{mid}\n{bridge.tail()}"
            assert mid["state"] == "running" and mid["dry_cycles"] == 0, why
            assert np.degrees(np.abs(truth - s.q(2.0))).max() < 0.5, (np.degrees(truth - s.q(2.0)), why)
            ended = rig.must("status")["stream"]
            # every command but the first (it opened the stream) is a sample: none dropped, none coalesced
            assert ended["end"] == "timeout" and ended["samples"] == s.sent - 1 == 260, (ended, s.sent)
            heard(lambda: any("ended (stream timeout" in t for _lv, t in status_texts(p, "dragd/stream")),
                  "the bridge seeing its stream end", bridge)  # (the next command opens a new one)
            # --- a JointTrajectory (as joint_trajectory_controller's topic): from here back to q0
            rig.wait_for(lambda: rig.must("status")["drive_mode"] == "cst", 5.0, "CST")
            here = np.array(rig.must("state")["q_rad"])
            mid_q = (here + q0) / 2
            pub_t = publisher(p, m["JointTrajectory"], "/dragd/joint_trajectory", bridge)
            # (the joints in another order than the URDF's: the bridge reorders by name)
            order = list(reversed(range(len(names))))
            pub_t.publish(trajectory(m, [names[i] for i in order], [(1.5, mid_q[order]), (3.0, q0[order])]))
            heard(lambda: any("trajectory accepted" in t for _lv, t in status_texts(p, "dragd/trajectory")),
                  "the trajectory's acceptance", bridge)
            assert mode_of(rig) == "track"
            rig.wait_for(lambda: mode_of(rig) == "hold", 8.0, "the end of the trajectory")
            rig.sleep(0.3)
            truth = np.array(rig.sim_call("state")["q_rad"])
            assert np.degrees(np.abs(truth - q0)).max() < 0.5, np.degrees(truth - q0)
            # --- ~/hold takes the arm from a running stream; commands wait for ~/streaming true
            rig.wait_for(lambda: rig.must("status")["drive_mode"] == "cst", 5.0, "CST")
            s = Streamer(rig, p, m, bridge, names, np.array(rig.must("state")["q_rad"]), 3.0)
            assert mode_of(rig) == "track"
            rig.sleep(0.5)
            s.follow = False  # (from here on the bridge must not forward them)
            held = p.call(m["Trigger"], "/dragd/hold")
            assert held.success and mode_of(rig) == "hold", held
            rig.sleep(0.5)
            assert mode_of(rig) == "hold"  # the controller still publishes: not followed
            assert rig.must("state")["stream"]["state"] == "ended"
            assert any("until ~/streaming true" in t for _lv, t in status_texts(p, "dragd/stream"))
            s.stop()
            assert p.call(m["SetBool"], "/dragd/streaming", m["SetBool"].Request(data=True)).success
            # --- the bridge killed mid-stream: the daemon's deadline, not the bridge, ends the motion
            rig.wait_for(lambda: rig.must("status")["drive_mode"] == "cst", 5.0, "CST")
            faults_before = rig.must("status")["faults"]  # (the lapsed drag lease above: kept until `start`)
            q1 = np.array(rig.must("state")["q_rad"])
            s = Streamer(rig, p, m, bridge, names, q1, 3.0)
            assert mode_of(rig) == "track"
            rig.sleep(1.0)
            bridge.proc.send_signal(signal.SIGKILL)
            bridge.proc.wait(5)
            s.follow = False
            t_last = s.t_last  # (the last command the daemon has: the bridge was alive until then)
            rig.wait_for(lambda: mode_of(rig) == "hold", 3.0, "hold after the bridge was killed")
            held_after_s = rig.now() - t_last
            s.stop()
            killed = rig.must("status")
            rig.must("stop")
        finally:
            bridge.terminate()
            p.close()
    assert killed["stream"]["end"] == "timeout" and killed["faults"] == faults_before, killed["stream"]
    print(f"lease lapsed {lapsed_after_s:.3f} s after the last keepalive; hold {held_after_s:.3f} s after the last "
          "command")
    assert 0.5 <= lapsed_after_s <= 0.5 + 0.02, lapsed_after_s  # the lease's period (drag.keepalive_timeout_s)
    timeout_s = robot["stream"]["timeout_s"]
    assert timeout_s <= held_after_s <= timeout_s + 0.02, held_after_s  # stream.timeout_s of the cycle's time
    events = [e.data for e in p.messages("/dragd/events")]
    assert any('"name": "stream_open"' in e for e in events) and any('"name": "track_end"' in e for e in events)


def stamp_ns_clock(p: Probe) -> int | None:
    clocks = p.messages("/clock")
    return clocks[-1].clock.sec * 1_000_000_000 + clocks[-1].clock.nanosec if clocks else None


def test_bridge_refuses_what_the_daemon_refuses_with_the_reason(tmp_path):
    m = _msgs()
    with Rig("ros2-refuse", workdir=tmp_path) as rig:
        rig.start_sim()
        rig.start_daemon()
        robot = rig.must("robot")
        names = robot["joint_names"]
        p = listening(m)
        bridge = bridging(rig, p)
        try:
            assert p.call(m["Trigger"], "/dragd/start").success
            rig.sleep(0.5)
            q0 = np.array(rig.must("state")["q_rad"])
            pub_t = publisher(p, m["JointTrajectory"], "/dragd/joint_trajectory", bridge)
            beyond = q0.copy()
            beyond[1] = robot["position_limits_rad"][1][0] - 0.05  # joint2 below its lower limit
            pub_t.publish(trajectory(m, names, [(2.0, beyond)]))
            heard(lambda: status_texts(p, "dragd/trajectory"), "the trajectory's answer", bridge)
            level, text = status_texts(p, "dragd/trajectory")[-1]
            partial = trajectory(m, names[:5], [(2.0, q0[:5])])
            pub_t.publish(partial)
            heard(lambda: len(status_texts(p, "dragd/trajectory")) > 1, "the second answer", bridge)
            level2, text2 = status_texts(p, "dragd/trajectory")[-1]
            rig.sleep(0.5)
            mode = mode_of(rig)
            truth = np.array(rig.sim_call("state")["q_rad"])
            # a command stream that starts away from the arm is never followed
            s = Streamer(rig, p, m, bridge, names, q0, 1.0, path=lambda _t: q0 + 0.2)
            rig.sleep(0.3)
            s.stop()
            heard(lambda: any("first sample" in t for _lv, t in status_texts(p, "dragd/stream")), "the refusal",
                  bridge)
            rig.wait_for(lambda: rig.must("state")["mode"] == "hold", 5.0, "the refused stream")
            stream = rig.must("state")["stream"]
            stream_texts = [t for _lv, t in status_texts(p, "dragd/stream")]
            truth2 = np.array(rig.sim_call("state")["q_rad"])
        finally:
            bridge.terminate()
            p.close()
    assert level == 2 and "trajectory refused" in text and "joint2" in text and "position limits" in text, text
    assert level2 == 2 and "missing joint(s) joint6" in text2, text2
    assert mode == "hold" and np.degrees(np.abs(truth - q0)).max() < 0.1
    assert any("first sample" in t and "until ~/streaming true" in t for t in stream_texts), stream_texts
    assert stream["end"] == "refused" and stream["samples"] == 0, stream
    assert np.degrees(np.abs(truth2 - q0)).max() < 0.1  # nothing refused moved the arm


@pytest.mark.slow
def test_bridge_killed_mid_drag_ends_drag(tmp_path):
    """The bridge's keepalives renew the daemon's drag lease; killed, it renews nothing and the daemon holds the arm
    within the lease period (drag.require: lease, as configured; not the lab's flag)."""
    m = _msgs()
    with Rig("ros2-drag", workdir=tmp_path, drag_guard="config") as rig:
        rig.start_sim()
        rig.start_daemon()
        p = listening(m)
        bridge = bridging(rig, p)
        try:
            assert p.call(m["Trigger"], "/dragd/start").success
            alive = Keepalive(rig, p, m, bridge)  # the client stays alive: only the bridge dies
            rig.sleep(0.5)
            assert p.call(m["Trigger"], "/dragd/drag").success
            rig.wait_for(lambda: mode_of(rig) == "drag", 5.0, "drag")
            rig.sleep(0.5)
            lease = rig.must("lease", action="status")["lease"]
            assert lease["holder"].startswith("ros2 bridge") and lease["renewals"] >= 10, lease
            bridge.proc.send_signal(signal.SIGKILL)
            bridge.proc.wait(5)
            alive.follow = False  # (the keepalives go on; nobody renews)
            t_kill = rig.now()
            rig.wait_for(lambda: mode_of(rig) == "hold", 2.0, "hold after the bridge was killed")
            held_after_s = rig.now() - t_kill
            mode = mode_of(rig)
            status = rig.must("status")
            alive.stop()
        finally:
            bridge.terminate()
            p.close()
    assert mode == "hold", mode
    assert 0.5 <= held_after_s <= 0.5 + 0.02, held_after_s  # the lease's period after its last renewal
    end = status["drag"]["last_drag_end"]
    assert "lease lapsed" in end["reason"] and status["faults"][-1]["kind"] == "lease", status["faults"]


@pytest.mark.slow
def test_bridge_services_teach_replay_payload_and_check(tmp_path):
    from dragd.lab.demo import TEACH_STEPS_RAD, guide_and_settle

    from daemon_helpers import derived_config

    m = _msgs()
    cfg = derived_config(tmp_path, "ros2", lambda d: d.__setitem__("replay", {**d.get("replay", {}),
                                                                               "program_dir": str(tmp_path / "p")}))
    with Rig("ros2-services", workdir=tmp_path, config=cfg) as rig:
        rig.start_sim()
        rig.start_daemon()
        p = listening(m)
        # arguments std_srvs cannot carry are the node's parameters (here given on the command line)
        bridge = bridging(rig, p, "-p", "teach.name:=ros2prog", "-p", "payload.mass_kg:=0.5", "-p",
                              "payload.com_m:=[0.0, 0.0, 0.05]", "-p", "payload.poses:=3", "-p",
                              "check_model.step_rad:=0.1", "-p", "replay.speed:=0.5")
        T = m["Trigger"]
        got: dict[str, object] = {}
        try:
            assert p.call(T, "/dragd/start").success
            alive = Keepalive(rig, p, m, bridge)
            rig.sleep(0.5)
            # teach by hand: start (drag), three marks where the hand left the arm, stop (the program file)
            got["teach_start"] = p.call(T, "/dragd/teach/start")
            for i, step in enumerate(TEACH_STEPS_RAD):
                guide_and_settle(rig, step, 2.5, f"p{i + 1}")
                got[f"mark{i}"] = p.call(T, "/dragd/teach/mark")
            got["teach_stop"] = p.call(T, "/dragd/teach/stop", timeout_s=60.0)
            # replay by name: one service per taught program, appears after teach/stop
            heard(lambda: "/dragd/replay/ros2prog" in dict(p.node.get_service_names_and_types()),
                  "the program's replay service", bridge)
            got["replay"] = p.call(T, "/dragd/replay/ros2prog", timeout_s=60.0)
            replaying = rig.must("status")["replay"]
            rig.sleep(0.5)
            got["replay_stop"] = p.call(T, "/dragd/replay_stop")
            rig.wait_for(lambda: mode_of(rig) == "hold" and rig.must("status")["drive_mode"] == "cst", 10.0,
                         "hold after the replay's stop")
            alive.stop()
            got["set"] = p.call(T, "/dragd/payload/set")
            got["payload_after_set"] = rig.must("payload", action="show")["mass_kg"]
            got["clear"] = p.call(T, "/dragd/payload/clear")
            got["payload_after_clear"] = rig.must("payload", action="show")["mass_kg"]
            got["estimate"] = p.call(T, "/dragd/payload/estimate", timeout_s=170.0)
            got["check"] = p.call(T, "/dragd/check_model", timeout_s=170.0)
            got["stop"] = p.call(T, "/dragd/stop")
            end = rig.must("status")
        finally:
            bridge.terminate()
            p.close()
    for k, v in got.items():
        if hasattr(v, "success"):
            assert v.success, (k, v.message)
    assert '"mode": "drag"' in got["teach_start"].message and "ros2prog" in got["teach_start"].message
    assert '"name": "p1"' in got["mark0"].message and '"name": "p3"' in got["mark2"].message
    assert (tmp_path / "p" / "ros2prog.yaml").is_file() and '"waypoints": 3' in got["teach_stop"].message
    assert replaying is not None and replaying["name"] == "ros2prog" and replaying["speed"] == 0.5, replaying
    assert got["payload_after_set"] == 0.5 and got["payload_after_clear"] == 0.0
    import json

    est = json.loads(got["estimate"].message)
    assert est["poses"] == 3 and abs(est["mass_kg"]) < 0.3, est  # no load on the simulated flange
    verdicts = [j["verdict"] for j in json.loads(got["check"].message)["joints"]]
    assert len(verdicts) == 6 and "ok" in verdicts and set(verdicts) <= {"ok", "not checkable here"}, verdicts
    assert end["mode"] == "idle" and end["faults"] == [], end["faults"]
