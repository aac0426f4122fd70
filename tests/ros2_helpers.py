"""The ROS 2 side of the bridge tests: a plain rclpy client (its own context, executor thread) and the bridge as a
process beside a rig's simulator and daemon. Skips with the reason where the ros2 extra is not installed."""

from __future__ import annotations

import functools
import os
import socket
import sys
import threading
import time
from typing import Any

import pytest

from dragd.lab.rig import Child, Rig, wait_until
from dragd.ros2 import unavailable

REASON = unavailable()
needs_ros2 = pytest.mark.skipif(REASON is not None, reason=f"the ros2 extra is not installed: {REASON}")


_domain_claims: list[socket.socket] = []  # held until this process exits


@functools.cache
def claim_domain(first: int = 1, last: int = 99) -> int:
    """A DDS domain in ``first``..``last`` claimed for this process on the whole machine: an abstract Unix socket named
    for it, which the kernel frees when the process exits (as dragd/lab/rig.py claims multicast groups); another test
    run's worker, at the same time, gets another."""
    n = last - first + 1
    for i in range(n):
        d = first + (os.getpid() + i) % n
        claim = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        try:
            claim.bind(f"\0dragd-test-ros-domain-{d}")
        except OSError:
            claim.close()
            continue
        _domain_claims.append(claim)
        return d
    raise RuntimeError(f"every DDS domain {first}-{last} is held by another test process")


def _domain() -> int:
    return claim_domain(1, 99)


def ros_env() -> dict[str, str]:
    """A DDS domain of this test process's own (`_domain`), discovery on this host only (no cross-talk with other
    runs): 1-99, apart from the documented commands' 100-199 (tests/test_docs_commands.py), which may run at the same
    time in another worker. The bridge tests of one run share a worker (their module's xdist group)."""
    return {"ROS_DOMAIN_ID": str(_domain()), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}


def start_bridge(rig: Rig, *ros_args: str, name: str = "bridge") -> Child:
    argv = [sys.executable, "-m", "dragd", "ros2", "--socket", rig.socket]
    if ros_args:
        argv += ["--ros-args", *ros_args]
    child = Child(name, argv, rig.workdir, ros_env())
    wait_until(lambda: "bridging the daemon" in child.output(), 30.0, "the bridge's start", child)
    return child


class Probe:
    """A plain rclpy node in the test process: what it hears, the services it calls, what it publishes."""

    def __init__(self) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor

        for k, v in ros_env().items():
            os.environ[k] = v  # (read by the middleware at init)
        self.rclpy = rclpy
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=int(ros_env()["ROS_DOMAIN_ID"]))
        self.node = rclpy.create_node("dragd_test_probe", context=self.context)
        self.lock = threading.Lock()
        self.heard: dict[str, list[Any]] = {}
        self.subscriptions: dict[str, Any] = {}
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        try:
            self.executor.spin()
        except Exception:  # noqa: BLE001 - shut down under it
            pass

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=2.0)
        self.node.destroy_node()
        self.rclpy.shutdown(context=self.context)

    def listen(self, msg_type: Any, topic: str, qos: Any = 10) -> None:
        self.heard.setdefault(topic, [])

        def got(msg: Any) -> None:
            with self.lock:
                self.heard[topic].append((time.monotonic(), msg))

        self.subscriptions[topic] = self.node.create_subscription(msg_type, topic, got, qos)

    def matched(self) -> bool:
        """Every topic listened to has a publisher matched (what is published from now on reaches this node: a
        message published before the match is not delivered, a latched one excepted)."""
        return all(sub.get_publisher_count() > 0 for sub in self.subscriptions.values())

    def messages(self, topic: str) -> list[Any]:
        with self.lock:
            return [m for _t, m in self.heard.get(topic, [])]

    def call(self, srv_type: Any, name: str, request: Any = None, timeout_s: float = 60.0) -> Any:
        client = self.node.create_client(srv_type, name)
        try:
            end = time.monotonic() + 20.0
            while not client.service_is_ready():
                if time.monotonic() > end:
                    raise AssertionError(f"service {name} did not appear")
                client.wait_for_service(timeout_sec=0.2)
            done = threading.Event()
            fut = client.call_async(request if request is not None else srv_type.Request())
            fut.add_done_callback(lambda _f: done.set())
            if not done.wait(timeout_s):
                raise AssertionError(f"service {name}: no answer within {timeout_s} s")
            return fut.result()
        finally:
            self.node.destroy_client(client)

    def publisher(self, msg_type: Any, topic: str, qos: Any = 10) -> Any:
        return self.node.create_publisher(msg_type, topic, qos)

    def now_ns(self) -> int:
        return int(self.node.get_clock().now().nanoseconds)
