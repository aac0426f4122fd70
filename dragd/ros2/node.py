"""The bridge's ROS 2 side (rclpy): its topics, services and parameters, spun by one executor in its own thread.

Everything it receives goes to the `Bridge` on the asyncio loop (``call_soon_threadsafe`` for topics,
``run_coroutine_threadsafe`` for services); the bridge publishes through the ``publish_*`` methods from its loop.

One `SingleThreadedExecutor`, and services as coroutines: a service awaits the daemon's answer without holding the
executor (a payload estimate moves the arm for half a minute), so the command topic is taken as it arrives meanwhile;
services still run one at a time (their callback group is held while one awaits). rclpy's `MultiThreadedExecutor`,
which the bridge used before, took only a few hundred messages a second on this 2-core machine (rclpy#1452: its hand-
offs between threads under the GIL) and the command subscription's queue silently dropped the rest — 77 % of a 1 kHz
stream and 5 % of a 100 Hz one under load never reached the bridge. The command topic's queue holds
``COMMANDS_DEPTH`` messages (a burst after a stall of this process is taken, not dropped), and the commands the
middleware lost anyway are counted from the publishers' sequence numbers (``commands_lost`` in the diagnostics).
"""

from __future__ import annotations

import asyncio
import json
import threading
from collections.abc import Callable, Coroutine, Sequence
from typing import Any, Protocol

import rclpy
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.clock import Clock, ClockType
from rclpy.event_handler import QoSSubscriptionMatchedInfo, SubscriptionEventCallbacks
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rclpy.signals import SignalHandlerOptions
from rclpy.subscription import MessageInfo
from rclpy.task import Future
from rosgraph_msgs.msg import Clock as ClockMsg
from sensor_msgs.msg import JointState
from std_msgs.msg import Empty, String
from std_srvs.srv import SetBool, Trigger
from trajectory_msgs.msg import JointTrajectory

from dragd.ros2.convert import service_name


class Bridge(Protocol):
    """What the node calls on the bridge (dragd/ros2/bridge.py's ``Bridge``; typed here, not imported: no circle)."""

    def on_keepalive(self) -> None: ...
    def on_command(self, stamp_s: float, names: list[str], positions: list[float], lost: int = 0) -> None: ...
    def on_trajectory(self, stamp_s: float, names: list[str], points: list[tuple[float, list[float]]]) -> None: ...
    def action(self, name: str, *args: Any) -> Coroutine[Any, Any, tuple[bool, str]]: ...


LATCHED = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
SERVICE_WAIT_S = 180.0  # the longest a service waits for the daemon (a payload estimate visits several poses)
# the command topic's queue (best effort: takes reliable and best-effort publishers, as topic_based_ros2_control's
# reliable depth-1 one): a 1 kHz stream's 0.1 s, so that a stall of the bridge's process loses none of it
COMMANDS_DEPTH = 100
COMMANDS_QOS = QoSProfile(depth=COMMANDS_DEPTH, reliability=ReliabilityPolicy.BEST_EFFORT)

# name -> (default, description): read when a service is called (the arguments std_srvs' types cannot carry)
PARAMETERS: dict[str, tuple[Any, str]] = {
    "joint_states_rate_Hz": (100.0, "rate of /joint_states (polls of the daemon's state)"),
    "diagnostics_rate_Hz": (1.0, "rate of /diagnostics"),
    "stream.enabled": (True, "forward ~/joint_commands into the daemon's position stream (also ~/streaming)"),
    "drag.keepalive_timeout_s": (0.5, "~/drag and ~/teach/start need ~/drag_keepalive; silent this long, the "
                                      "daemon's drag lease lapses: hold (at most the daemon's drag.lease_s)"),
    "drag.accept": (False, "~/drag as 'dragd mode drag --accept' (the measured hold currents as gravity offset)"),
    "teach.name": ("", "program name of ~/teach/start (empty: ros2_<date>_<time>)"),
    "teach.rate_Hz": (0.0, "recording rate of ~/teach/start (0: the daemon's replay.record_rate_Hz)"),
    "teach.overwrite": (False, "~/teach/start may replace a program of that name"),
    "teach.mark_name": ("", "waypoint name of ~/teach/mark (empty: p1, p2, ...)"),
    "replay.speed": (1.0, "speed override of ~/replay/<program> in (0, 1]"),
    "replay.interp": ("linear", "interpolation of ~/replay/<program> (dragd replay --interp)"),
    "replay.cycles": (1, "repetitions of ~/replay/<program> (0: until ~/replay_stop)"),
    "payload.mass_kg": (0.0, "mass of ~/payload/set"),
    "payload.com_m": ([0.0, 0.0, 0.0], "centre of mass of ~/payload/set in the flange frame"),
    "payload.poses": (6, "poses visited by ~/payload/estimate"),
    "payload.apply": (False, "~/payload/estimate applies its estimate"),
    "check_model.step_rad": (0.25, "joint step of ~/check_model"),
}

# Trigger services: name -> (bridge action, what it does)
TRIGGERS: dict[str, tuple[str, str]] = {
    "start": ("start", "enable the drives and hold the pose (dragd start)"),
    "stop": ("stop", "ramp to hold, disable the drives, brakes on (dragd stop)"),
    "hold": ("hold", "hold where the arm is (a running motion or stream stops first)"),
    "drag": ("drag", "weightless under the hand while ~/drag_keepalive keeps coming (dragd mode drag)"),
    "teach/start": ("teach_start", "start teaching (parameter teach.name): drag and record"),
    "teach/mark": ("teach_mark", "mark the present pose as a waypoint"),
    "teach/stop": ("teach_stop", "stop teaching and write the program"),
    "replay_stop": ("replay_stop", "controlled stop of a replay, trajectory or stream, then hold"),
    "payload/set": ("payload_set", "set the flange payload (parameters payload.mass_kg, payload.com_m)"),
    "payload/clear": ("payload_clear", "clear the flange payload"),
    "payload/estimate": ("payload_estimate", "estimate the payload from hold currents (moves the arm)"),
    "check_model": ("check_model", "check signs and torque constants joint by joint (moves the arm)"),
}


def stamp(ns: int) -> Time:
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


class RosNode:
    """The node ``dragd`` (``--ros-args`` may rename or namespace it) and its executor thread."""

    def __init__(self, bridge: Bridge, loop: asyncio.AbstractEventLoop, joints: Sequence[str], urdf: str | None,
                 ros_args: Sequence[str] = (), node_name: str = "dragd", sim_time: bool = False) -> None:
        self.bridge, self.loop, self.joints = bridge, loop, list(joints)
        self.context = rclpy.Context()
        rclpy.init(args=["dragd", "--ros-args", *ros_args] if ros_args else None, context=self.context,
                   signal_handler_options=SignalHandlerOptions.NO)
        node = self.node = rclpy.create_node(node_name, context=self.context)
        for name, (default, text) in PARAMETERS.items():
            from rcl_interfaces.msg import ParameterDescriptor

            node.declare_parameter(name, default, ParameterDescriptor(description=text))
        self._services_group = MutuallyExclusiveCallbackGroup()
        self._topics_group = MutuallyExclusiveCallbackGroup()
        self._housekeeping = MutuallyExclusiveCallbackGroup()
        # a daemon on the lockstep clock: its simulated time on /clock, this node on it (use_sim_time), as the ROS
        # side of a simulator does; the graph's other nodes follow with use_sim_time:=true
        self.clock = node.create_publisher(ClockMsg, "/clock", 10) if sim_time else None
        if sim_time:
            node.set_parameters([Parameter("use_sim_time", value=True)])
        self.joint_states = node.create_publisher(JointState, "/joint_states", 10)
        self.description = node.create_publisher(String, "/robot_description", LATCHED)
        self.mode = node.create_publisher(String, "~/mode", LATCHED)
        self.events = node.create_publisher(String, "~/events", 100)
        self.status = node.create_publisher(DiagnosticStatus, "~/status", 20)
        self.diagnostics = node.create_publisher(DiagnosticArray, "/diagnostics", 10)
        g = self._topics_group
        node.create_subscription(JointState, "~/joint_commands", self._on_command, COMMANDS_QOS, callback_group=g,
                                 event_callbacks=self._matched("~/joint_commands"))
        self._seq: dict[str, int] = {}  # a command publisher (its gid) -> its newest publication sequence number
        node.create_subscription(JointTrajectory, "~/joint_trajectory", self._on_trajectory, 10, callback_group=g,
                                 event_callbacks=self._matched("~/joint_trajectory"))
        node.create_subscription(Empty, "~/drag_keepalive", self._on_keepalive, qos_profile_sensor_data,
                                 callback_group=g, event_callbacks=self._matched("~/drag_keepalive"))
        for name, (action, _text) in TRIGGERS.items():
            node.create_service(Trigger, f"~/{name}", self._trigger(action), callback_group=self._services_group)
        node.create_service(SetBool, "~/streaming", self._on_streaming, callback_group=self._services_group)
        self._replay_services: dict[str, Any] = {}
        self._programs: list[str] | None = None
        self._programs_lock = threading.Lock()
        node.create_timer(0.5, self._apply_programs, callback_group=self._housekeeping,
                          clock=Clock(clock_type=ClockType.STEADY_TIME))  # (housekeeping: wall time on either clock)
        if urdf is not None:
            self.description.publish(String(data=urdf))
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(node)
        self._thread = threading.Thread(target=self._spin, name="dragd-ros2-executor", daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        try:
            self.executor.spin()
        except Exception:  # noqa: BLE001 - the context shut down under it
            pass

    def close(self) -> None:
        """The context first (the executor's wait returns, its spin ends), then the executor and the node."""
        try:
            if self.context.ok():
                rclpy.shutdown(context=self.context)
        finally:
            self._thread.join(timeout=3.0)
            try:
                self.executor.shutdown(timeout_sec=1.0)
                self.node.destroy_node()
            except Exception:  # noqa: BLE001 - the context is gone: nothing left to release cleanly
                pass

    # ------------------------------------------------------------------------------------------ parameters

    def param(self, name: str) -> Any:
        return self.node.get_parameter(name).value

    def now_ns(self) -> int:
        return int(self.node.get_clock().now().nanoseconds)

    # ------------------------------------------------------------------------------------------ incoming

    def _to_loop(self, fn: Callable[..., None], *args: Any) -> None:
        try:
            self.loop.call_soon_threadsafe(fn, *args)
        except RuntimeError:  # the loop closed: the bridge is ending
            pass

    def _on_command(self, msg: JointState, info: MessageInfo) -> None:
        st = msg.header.stamp
        self._to_loop(self.bridge.on_command, st.sec + st.nanosec * 1e-9, list(msg.name), list(msg.position),
                      self._lost_before(info))

    def _lost_before(self, info: MessageInfo) -> int:
        """Commands of this message's publisher the middleware lost before it (a gap in its publication sequence
        numbers; 0 where the middleware gives none)."""
        seq, gid = info.get("publication_sequence_number"), info.get("publisher_gid")
        if not seq or gid is None:
            return 0
        key = str(gid.get("data") if isinstance(gid, dict) else gid)
        last = self._seq.get(key)
        self._seq[key] = seq
        return max(0, seq - last - 1) if last is not None and seq > last else 0

    def _on_trajectory(self, msg: JointTrajectory) -> None:
        st = msg.header.stamp
        points = [(p.time_from_start.sec + p.time_from_start.nanosec * 1e-9, list(p.positions)) for p in msg.points]
        self._to_loop(self.bridge.on_trajectory, st.sec + st.nanosec * 1e-9, list(msg.joint_names), points)

    def _on_keepalive(self, _msg: Empty) -> None:
        self._to_loop(self.bridge.on_keepalive)

    async def _wait(self, coro: Coroutine[Any, Any, tuple[bool, str]]) -> tuple[bool, str]:
        """The bridge's answer to a service, awaited in the executor without holding it (an rclpy `Future` that the
        asyncio loop completes; its done callback, run as a task of the executor, wakes it)."""
        answer: Future[Any] = Future(executor=self.executor)
        answer.add_done_callback(lambda _f: None)
        try:
            cf = asyncio.run_coroutine_threadsafe(asyncio.wait_for(coro, SERVICE_WAIT_S), self.loop)
        except RuntimeError:  # the loop closed: the bridge is ending
            coro.close()
            return False, "the bridge is shutting down"
        cf.add_done_callback(answer.set_result)
        done: Any = await answer
        try:
            ok, text = done.result()
            return bool(ok), str(text)
        except TimeoutError:
            return False, f"no answer within {SERVICE_WAIT_S:g} s"
        except Exception as exc:  # noqa: BLE001 - a service answers, it never takes the executor down
            return False, f"{type(exc).__name__}: {exc}"

    def _trigger(self, action: str, *args: Any) -> Callable[[Trigger.Request, Trigger.Response],
                                                            Coroutine[Any, Any, Trigger.Response]]:
        async def serve(_req: Trigger.Request, resp: Trigger.Response) -> Trigger.Response:
            resp.success, resp.message = await self._wait(self.bridge.action(action, *args))
            return resp

        return serve

    async def _on_streaming(self, req: SetBool.Request, resp: SetBool.Response) -> SetBool.Response:
        resp.success, resp.message = await self._wait(self.bridge.action("streaming", bool(req.data)))
        return resp

    # ------------------------------------------------------------------------------------------ replay services

    def set_programs(self, programs: Sequence[str]) -> None:
        """The taught programs: one ``~/replay/<name>`` Trigger each (created in the executor's thread)."""
        with self._programs_lock:
            self._programs = list(programs)

    def _apply_programs(self) -> None:
        with self._programs_lock:
            programs, self._programs = self._programs, None
        if programs is None:
            return
        wanted = {service_name(p): p for p in programs}
        for token in [t for t in self._replay_services if t not in wanted]:
            self.node.destroy_service(self._replay_services.pop(token))
        for token, program in wanted.items():
            if token not in self._replay_services:
                self._replay_services[token] = self.node.create_service(
                    Trigger, f"~/replay/{token}", self._trigger("replay", program),
                    callback_group=self._services_group)

    # ------------------------------------------------------------------------------------------ outgoing

    def publish_joint_states(self, state: dict[str, Any], stamp_ns: int) -> None:
        msg = JointState()
        msg.header.stamp = stamp(stamp_ns)
        msg.name = self.joints
        msg.position = state["q_rad"]
        msg.velocity = state["dq_rad_s"]
        msg.effort = state["effort_Nm"]
        self.joint_states.publish(msg)

    def _matched(self, topic: str) -> SubscriptionEventCallbacks:
        """Say on ~/status (name ``dragd/publishers``) each time a publisher of ``topic`` matches this node's
        subscription or leaves it: an integrator sees the controller connected, and a client can wait for it before
        its first message (DDS discovery is two-sided: a publisher that already sees this subscription can send
        before the subscription has matched it, and that message is dropped)."""
        def said(info: QoSSubscriptionMatchedInfo) -> None:
            self.publish_status(0, "dragd/publishers", f"{topic}: {info.current_count} publisher(s) matched",
                                {"topic": topic, "count": info.current_count})
        return SubscriptionEventCallbacks(matched=said)

    def publish_mode(self, mode: str) -> None:
        self.mode.publish(String(data=mode))

    def publish_event(self, event: dict[str, Any]) -> None:
        self.events.publish(String(data=json.dumps(event, default=str)))

    def publish_status(self, level: int, name: str, message: str, values: dict[str, Any] | None = None) -> None:
        self.status.publish(DiagnosticStatus(level=bytes([level]), name=name, message=message, hardware_id="dragd",
                                             values=[KeyValue(key=k, value=str(v)) for k, v in (values or {}).items()]))

    def publish_clock(self, t_ns: int) -> None:
        if self.clock is not None:
            self.clock.publish(ClockMsg(clock=stamp(t_ns)))

    def publish_diagnostics(self, entries: Sequence[tuple[int, str, str, Sequence[tuple[str, str]]]],
                            stamp_ns: int) -> None:
        arr = DiagnosticArray()
        arr.header.stamp = stamp(stamp_ns)
        arr.status = [DiagnosticStatus(level=bytes([lv]), name=name, message=msg, hardware_id="dragd",
                                       values=[KeyValue(key=k, value=v) for k, v in kv])
                      for lv, name, msg, kv in entries]
        self.diagnostics.publish(arr)

    def set_parameter(self, name: str, value: Any) -> None:
        self.node.set_parameters([Parameter(name, value=value)])
