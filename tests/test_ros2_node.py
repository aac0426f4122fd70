"""The bridge's ROS 2 side alone (dragd/ros2/node.py), without a daemon: a stand-in for the `Bridge` on an asyncio
loop, a plain rclpy publisher in this process. What comes in on ``~/joint_commands`` reaches the bridge whole — a
burst as a controller sends after a stall, while a long service is waiting for the daemon — and the commands the
middleware lost are counted from the publishers' sequence numbers."""

from __future__ import annotations

import asyncio
import threading
from typing import Any

import pytest
from ros2_helpers import Probe, needs_ros2

from dragd.lab.rig import wait_until

pytestmark = [pytest.mark.unit, needs_ros2]

JOINTS = ["joint1", "joint2", "joint3"]
NODE = "dragd_node_test"  # (its own topics: no cross-talk with a bridge test's /dragd in the same domain)
GUARD_S = 30.0  # a hang guard in wall time (the verdicts are counts)


class StandIn:
    """What the node calls on the bridge: records the commands; ``~/payload/estimate`` waits until released (a
    service that takes the daemon half a minute)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.commands: list[tuple[float, list[str], list[float], int]] = []
        self.release = asyncio.Event()
        self.waiting = threading.Event()

    def on_keepalive(self) -> None:
        pass

    def on_command(self, stamp_s: float, names: list[str], positions: list[float], lost: int = 0) -> None:
        with self.lock:
            self.commands.append((stamp_s, names, positions, lost))

    def on_trajectory(self, stamp_s: float, names: list[str], points: list[tuple[float, list[float]]]) -> None:
        pass

    async def action(self, name: str, *args: Any) -> tuple[bool, str]:
        if name == "payload_estimate":
            self.waiting.set()
            await self.release.wait()
        return True, f"{name} done"

    def count(self) -> int:
        with self.lock:
            return len(self.commands)


@pytest.fixture
def node_and_probe():
    from dragd.ros2.node import RosNode

    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    probe = Probe()  # (sets this process's DDS domain, ros2_helpers.ros_env, before the node's context starts)
    bridge = StandIn()
    node = RosNode(bridge, loop, JOINTS, None, node_name=NODE)
    try:
        yield node, probe, bridge, loop
    finally:
        loop.call_soon_threadsafe(bridge.release.set)
        node.close()
        probe.close()
        loop.call_soon_threadsafe(loop.stop)
        thread.join(timeout=5.0)


def test_a_burst_of_commands_reaches_the_bridge_whole_while_a_service_waits(node_and_probe):
    """The command queue's depth of commands published back to back (a 1 kHz controller's 0.1 s, as after a stall
    of the bridge's process) while
    ``~/payload/estimate`` waits for the daemon: every one reaches the bridge, in order, none counted lost; the
    service then answers. (The bridge's former MultiThreadedExecutor with a depth-5 best-effort queue took a few of
    such a burst and dropped the rest without a word.)"""
    from sensor_msgs.msg import JointState
    from std_srvs.srv import Trigger

    node, probe, bridge, _loop = node_and_probe
    pub = probe.publisher(JointState, f"/{NODE}/joint_commands", 100)  # (reliable, as topic_based_ros2_control's)

    def command(k: int) -> JointState:
        msg = JointState()
        msg.header.stamp.sec, msg.header.stamp.nanosec = 1000 + k, 0
        msg.name = JOINTS
        msg.position = [0.001 * k, 0.0, 0.0]
        return msg

    # the service first: it waits in the bridge (the daemon's half minute) while the burst comes
    client = probe.node.create_client(Trigger, f"/{NODE}/payload/estimate")
    assert client.wait_for_service(timeout_sec=GUARD_S), "~/payload/estimate did not appear"
    answer = client.call_async(Trigger.Request())
    assert bridge.waiting.wait(GUARD_S), "the service did not reach the bridge"
    # matched both ways: a command reaches the bridge (as many as it takes)
    k = 0

    def one_through() -> bool:
        nonlocal k
        if bridge.count() == 0:
            pub.publish(command(k))
            k += 1
        return bridge.count() > 0

    wait_until(one_through, GUARD_S, "a first command through the middleware")
    from dragd.ros2.node import COMMANDS_DEPTH

    burst, base = COMMANDS_DEPTH, 5000  # (stamped apart from the first ones, some of which may still be on the way)

    def of_burst() -> list[tuple[float, list[str], list[float], int]]:
        with bridge.lock:
            return [c for c in bridge.commands if c[0] >= 1000 + base]

    for i in range(burst):
        pub.publish(command(base + i))
    try:
        wait_until(lambda: len(of_burst()) >= burst, GUARD_S, f"the burst of {burst} commands")
    except Exception:  # noqa: BLE001 - the verdict is the count (below)
        pass
    got = of_burst()
    assert len(got) == burst, f"{len(got)} of a burst of {burst} commands reached the bridge"
    assert [c[0] for c in got] == [1000.0 + base + i for i in range(burst)]  # in order, none twice
    assert sum(c[3] for c in got[1:]) == 0  # (the first may count the first commands' losses before the match)
    assert not answer.done()  # the service still waits for the daemon: it held up none of the burst
    _loop.call_soon_threadsafe(bridge.release.set)
    done = threading.Event()
    answer.add_done_callback(lambda _f: done.set())
    assert done.wait(GUARD_S), "the service did not answer once the bridge did"
    assert answer.result().success and answer.result().message == "payload_estimate done"


def test_commands_the_middleware_lost_are_counted_per_publisher(node_and_probe):
    """A gap in a publisher's sequence numbers is the number of its commands lost before this one; each publisher
    (its gid) counts on its own; a middleware that gives no sequence number counts none."""
    node, _probe, _bridge, _loop = node_and_probe

    def info(gid: int, seq: int | None) -> dict[str, Any]:
        return {"source_timestamp": 0, "received_timestamp": 0, "publication_sequence_number": seq,
                "reception_sequence_number": None, "publisher_gid": {"data": [gid] * 16}}

    assert [node._lost_before(info(1, s)) for s in (1, 2, 5, 6, 10)] == [0, 0, 2, 0, 3]
    assert [node._lost_before(info(2, s)) for s in (7, 8, 8, 9)] == [0, 0, 0, 0]  # another publisher; a repeat
    assert node._lost_before(info(1, None)) == 0 and node._lost_before(info(1, 0)) == 0
