"""The bridge's logic on its asyncio loop: the daemon's connections, the pollers, the command stream, the actions.

Six connections to the daemon's control socket (``dragd.client``; the daemon answers a connection's requests in
order): ``poll`` (state and events at the joint states' rate), ``stream`` (the command topic's samples, never
queued behind anything), ``act`` (the services: some take half a minute), ``side`` (status for the diagnostics),
``lists`` (the program list where the bridge cannot read the program folder: the daemon lists programs in
its planner process, which it may have to start first) and ``keep`` (the drag lease's renewals, never queued behind
a service). The bridge adds no safety of its own that the daemon
would lack, and removes none: every limit, check and monitor is the daemon's; a refusal comes back with the
daemon's reason and goes out on ``~/status``.

What needs a living client:

- **streamed commands**: the bridge forwards each ``~/joint_commands`` message at most once, as it arrives, in order,
  at most ``STREAM_IN_FLIGHT`` requests in flight on the stream's connection (the daemon answers them in order) and
  as many waiting (beyond, the oldest waiting one gives way: no backlog that could reach the arm late), and never
  repeats one; a silent
  controller, a dead bridge or a partitioned DDS all end in the daemon's stream deadline (``stream.timeout_s``)
  and HOLD.
- **drag**: ``~/drag`` and ``~/teach/start`` need ``~/drag_keepalive`` (std_msgs/Empty, at least every
  ``drag.keepalive_timeout_s``): the bridge opens a drag lease in the daemon with that period (docs/HAND.md) and
  each keepalive renews it (``renew_drag``). When the keepalives stop — the client, the bridge or the DDS link
  died — the daemon's lease lapses and the daemon ends drag into HOLD; the bridge only reports it on ``~/status``.

Time: the bridge's clock is the daemon's (``now``). On the wall clock that is CLOCK_MONOTONIC (the daemon's cycle
reads the same) and the stamps are ROS time. On the lockstep clock (``dragd run --lockstep``, docs/LOCKSTEP.md) it
is the daemon's simulated time, read from every ``state`` answer: the stamps, the keepalive's timeout, the rates of
``/joint_states`` and ``/diagnostics``, the retry of a refused stream and a trajectory's start time all run on it;
the bridge publishes it on ``/clock`` and its node runs with ``use_sim_time``, as a simulator's ROS side does. The
bridge waits for the arm only through the daemon's own waiting commands (``replay_stop`` with ``wait``, ``mode``),
which ask the lockstep clock for the time they need: it never sleeps for arm time itself.
"""

from __future__ import annotations

import asyncio
import collections
import datetime
import faulthandler
import json
import os
import signal
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from dragd.client import Client, CommandError, DaemonUnavailable
from dragd.ros2 import convert

CONNECT_RETRY_S = 1.0
TEARDOWN_STEP_S = 1.0  # SIGTERM: each step of the teardown at most this long (Bridge._bounded)
SHUTDOWN_GUARD_S = 15.0  # SIGTERM: the teardown ends within ~9 s (Bridge._bounded); a process stuck longer ends here
OPEN_RETRY_S = 1.0  # a stream_open the daemon refused (not in hold) is tried again after this long
RESUMABLE = ("timeout", "closed")  # stream ends after which new commands may open a new stream by themselves
# stream samples sent and not yet answered, at most: a 1 kHz stream's 8 ms (far inside stream.delay_s), so that the
# stream's rate is not one sample per round trip to the daemon (~1-5 ms on a loaded 2-core host) and none is
# coalesced away while the daemon keeps up
STREAM_IN_FLIGHT = 8


class Bridge:
    """``await Bridge(socket).run()`` until SIGINT/SIGTERM (or ``stop``)."""

    def __init__(self, socket: str, ros_args: Sequence[str] = (), node_name: str = "dragd",
                 joint_states_rate_Hz: float | None = None) -> None:
        self.socket = socket
        self.ros_args = list(ros_args)
        self.node_name = node_name
        self.rate_override = joint_states_rate_Hz
        self.poll = Client(socket, timeout_s=5.0)
        self.stream = Client(socket, timeout_s=5.0)
        self.act = Client(socket, timeout_s=180.0)
        self.side = Client(socket, timeout_s=30.0)
        self.lists = Client(socket, timeout_s=60.0)
        self.keep = Client(socket, timeout_s=5.0)
        self.node: Any = None
        self.joints: list[str] = []
        self.program_dir = ""
        self.state: dict[str, Any] | None = None
        self.mode: str | None = None
        self.event_seq = 0
        self.connected = False
        # the command stream
        self.stream_enabled = True
        self.stream_id: int | None = None
        self.opening = False
        self.ending = False  # a stream's refusal is being looked into: no command opens a new stream meanwhile
        self.open_refused_at = -1e9
        self.latched: str | None = None  # why commands are not forwarded until ~/streaming true
        self.forwarded = self.dropped = self.refused = self.coalesced = 0
        self.lost = 0  # commands the middleware lost before the bridge (gaps in their publishers' sequence numbers)
        # commands not yet sent, oldest first (at most STREAM_IN_FLIGHT: beyond, the oldest is dropped, coalesced)
        self._pending: collections.deque[tuple[int, float, list[float]]] = collections.deque()
        self._command_ready = asyncio.Event()
        self._stream_error_seen: int | None = None
        # drag by the bridge: the daemon's drag lease it holds, renewed per keepalive
        self.drag_by_bridge = False
        self.drag_gen = 0  # counts the bridge's drags: a state asked for before the latest one began says nothing of it
        self.last_keepalive = -1e9
        self.lease = 0
        self.renewing = False  # a renewal in flight (keepalives meanwhile are coalesced)
        self.renewals = 0
        self.keepalive_present = False  # said on ~/status when it changes (dragd/keepalive)
        # the bridge's clock: the daemon's (lockstep: its simulated time from the latest state answer)
        self.lockstep = False
        self.daemon_t = 0.0
        self._time_moved = asyncio.Condition()
        self._stop = asyncio.Event()
        self._programs_changed = asyncio.Event()
        self._tasks: set[asyncio.Task[Any]] = set()

    def now(self) -> float:
        """The bridge's clock for its timeouts and rates (keepalive, retries, the topics' rates): the daemon's.
        Wall: CLOCK_MONOTONIC (the daemon's WallClock reads the same); lockstep: the daemon's simulated time as of
        its latest ``state`` answer."""
        return self.daemon_t if self.lockstep else time.monotonic()

    def ros_now_ns(self) -> int:
        """ROS time for stamps: the node's clock (system time) on the wall clock, the daemon's simulated time (also
        on ``/clock``) on the lockstep clock."""
        return round(self.daemon_t * 1e9) if self.lockstep else self.node.now_ns()

    async def sleep(self, seconds: float) -> None:
        """Sleep on the bridge's clock (lockstep: until the daemon's time moved on that far; asks for no time)."""
        if not self.lockstep:
            await asyncio.sleep(seconds)
            return
        start = self.now()
        until = start + seconds
        async with self._time_moved:  # (a daemon that restarted starts its time again: that wakes it too)
            await self._time_moved.wait_for(lambda: self.now() >= until - 1e-9 or self.now() < start)

    async def _daemon_time(self, t_s: float) -> bool:
        """A ``state`` answer's time (lockstep: the bridge's clock moves, ``/clock`` says so); True if it moved (back
        only for a daemon that restarted)."""
        if not self.lockstep or t_s == self.daemon_t:
            return False
        self.daemon_t = t_s
        self.node.publish_clock(round(t_s * 1e9))
        async with self._time_moved:
            self._time_moved.notify_all()
        return True

    # ------------------------------------------------------------------------------------------ running

    def stop(self) -> None:
        if not self._stop.is_set():
            guard = threading.Timer(SHUTDOWN_GUARD_S, self._stuck)
            guard.daemon = True
            guard.start()
        self._stop.set()

    @staticmethod
    def _stuck() -> None:
        """The teardown after SIGTERM (daemon connections, the middleware) did not end: say where, then exit (the
        daemon's stream deadline and lease end what the bridge held, as for a bridge that died)."""
        print(f"dragd ros2: the shutdown did not finish within {SHUTDOWN_GUARD_S:g} s; exiting (where it stood:)",
              file=sys.stderr, flush=True)
        faulthandler.dump_traceback(file=sys.stderr, all_threads=True)
        os._exit(1)

    async def run(self) -> int:
        from dragd.ros2.node import RosNode

        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, self.stop)
        robot = await self._robot()
        if robot is None:
            return 0
        self.joints = list(robot["joint_names"])
        self.program_dir = str(robot.get("program_dir") or "")
        clock = (await self.poll.call("clock"))["clock"]
        self.lockstep = bool(clock.get("lockstep"))
        self.daemon_t = float((await self.poll.call("state"))["t_s"]) if self.lockstep else 0.0  # (the polls' source)
        self.node = RosNode(self, loop, self.joints, robot.get("urdf"), self.ros_args, self.node_name,
                            sim_time=self.lockstep)
        if self.lockstep:
            self.node.publish_clock(round(self.daemon_t * 1e9))  # (the graph's use_sim_time nodes: the time at once)
        if self.rate_override is not None:
            self.node.set_parameter("joint_states_rate_Hz", float(self.rate_override))
        self.stream_enabled = bool(self.node.param("stream.enabled"))
        print(f"dragd ros2: bridging the daemon at {self.socket} as node {self.node.node.get_fully_qualified_name()} "
              f"({len(self.joints)} joints{', on its lockstep clock: /clock, use_sim_time' if self.lockstep else ''})",
              flush=True)
        tasks = [loop.create_task(self._forever(p)) for p in (self._poll_state, self._poll_diagnostics,
                                                               self._poll_programs, self._forward)]
        try:
            await self._stop.wait()
        finally:
            for t in tasks:
                t.cancel()
            await self._bounded(asyncio.gather(*tasks, return_exceptions=True), "the pollers' end", tasks)
            if self.stream_id is not None:  # a clean exit ends its stream at once (a dead bridge: the deadline)
                try:
                    await self.stream.call("stream_close", stream=self.stream_id, timeout_s=1.0)
                except (CommandError, DaemonUnavailable):
                    pass
            if self.lease:  # ... and its drag lease (the arm holds; a dead bridge: the lease lapses)
                try:
                    await self.keep.call("lease", action="close", lease=self.lease, timeout_s=1.0)
                except (CommandError, DaemonUnavailable):
                    pass
            for c in (self.poll, self.stream, self.act, self.side, self.lists, self.keep):
                await self._bounded(c.close(), "a daemon connection's close")
            self.node.close()
        return 0

    @staticmethod
    async def _bounded(aw: Any, what: str, tasks: Sequence[asyncio.Task[Any]] = ()) -> None:
        """One step of the teardown after SIGTERM, at most ``TEARDOWN_STEP_S``: the stream and the lease are closed
        by then (or end by their deadlines in the daemon, as for a bridge that died), and a step that does not end is
        said with where its tasks stood instead of holding the exit up."""
        fut = asyncio.ensure_future(aw)
        done, _ = await asyncio.wait({fut}, timeout=TEARDOWN_STEP_S)  # (not wait_for: it would wait for the cancel)
        if done:
            fut.result()
            return
        print(f"dragd ros2: {what} did not end within {TEARDOWN_STEP_S:g} s of the shutdown; going on",
              file=sys.stderr, flush=True)
        for t in tasks:
            if not t.done():
                t.print_stack(file=sys.stderr)

    async def _forever(self, poller: Any) -> None:
        """A poller that fails (a bug, an answer of an unexpected shape) says why and starts again."""
        while True:
            try:
                await poller()
            except asyncio.CancelledError:
                raise
            except Exception as exc:  # noqa: BLE001 - the bridge keeps serving; the log says what broke
                print(f"dragd ros2: {poller.__name__} failed: {type(exc).__name__}: {exc}; restarting it", flush=True)
                await asyncio.sleep(1.0)

    async def _robot(self) -> dict[str, Any] | None:
        """The daemon's ``robot`` answer, waiting for the daemon to come up (a bridge may start first)."""
        said = False
        while not self._stop.is_set():
            try:
                robot = await self.poll.call("robot")
                self.connected = True
                return robot
            except DaemonUnavailable as exc:
                if not said:
                    print(f"dragd ros2: waiting for the daemon: {exc}", flush=True)
                    said = True
                await self.poll.close()
                try:
                    await asyncio.wait_for(self._stop.wait(), CONNECT_RETRY_S)
                except TimeoutError:
                    pass
        return None

    def _spawn(self, coro: Any) -> None:
        task = asyncio.get_running_loop().create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _call(self, client: Client, cmd: str, **args: Any) -> dict[str, Any]:
        """A request; a lost daemon resets the connection (the next call reconnects) and the stream."""
        try:
            resp = await client.call(cmd, **args)
            self.connected = True
            return resp
        except DaemonUnavailable:
            self.connected = False
            self.stream_id = None
            await client.close()
            raise

    # ------------------------------------------------------------------------------------------ pollers

    def _period(self, rate_param: str) -> float:
        rate = float(self.node.param(rate_param))
        return 1.0 / rate if rate > 0 else 1.0

    async def _every(self, rate_param: str, due: list[float]) -> None:
        """Sleep until the next period of the rate parameter on the bridge's clock (absolute deadlines; a late one is
        not caught up)."""
        period = self._period(rate_param)
        now = self.now()
        due[0] = max(due[0] + period, now)
        await self.sleep(due[0] - now)

    async def _poll_state(self) -> None:
        """The daemon's state at the joint states' rate. Lockstep: the requests go out at that rate of wall time (the
        daemon's time may stand still: then nothing is published but changes of mode and events) and a
        ``/joint_states`` goes out when the daemon's time reached its next period (at most the rate, on its clock)."""
        wall_due = [time.monotonic()]
        sim_due = self.daemon_t
        while True:
            try:
                t_ns = self.ros_now_ns()  # (the state is the newest cycle's as the request is answered)
                gen, sid = self.drag_gen, self.stream_id
                st = await self._call(self.poll, "state")
                self.state = st
                if self.lockstep:
                    restarted = float(st["t_s"]) < self.daemon_t
                    await self._daemon_time(float(st["t_s"]))
                    if restarted:
                        sim_due = self.daemon_t
                    if self.daemon_t >= sim_due - 1e-9:  # (on the grid of its periods; behind it: no catching up)
                        self.node.publish_joint_states(st, round(float(st["t_s"]) * 1e9))
                        sim_due += self._period("joint_states_rate_Hz")
                        if sim_due <= self.daemon_t + 1e-9:
                            sim_due = self.daemon_t + self._period("joint_states_rate_Hz")
                else:
                    self.node.publish_joint_states(st, t_ns)
                if st["mode"] != self.mode:
                    self.mode = st["mode"]
                    self.node.publish_mode(self.mode)
                if st["event_seq"] < self.event_seq:  # a daemon that restarted numbers its events from 1 again
                    self.event_seq = 0
                if st["event_seq"] != self.event_seq:
                    await self._events()
                await self._watch_drag(st, gen)
                self._watch_stream(st.get("stream"), sid)
                self._watch_keepalive()
            except DaemonUnavailable:
                self.state = None
                await asyncio.sleep(CONNECT_RETRY_S)
                continue
            except CommandError as exc:
                print(f"dragd ros2: state: {exc}", flush=True)
            period = self._period("joint_states_rate_Hz")  # (wall time: the requests' pace on either clock)
            now = time.monotonic()
            wall_due[0] = max(wall_due[0] + period, now)
            await asyncio.sleep(wall_due[0] - now)

    async def _events(self) -> None:
        ev = await self._call(self.poll, "events", since=self.event_seq)
        if ev["lost"]:
            self.node.publish_event({"name": "events_lost", "count": ev["lost"]})
        for e in ev["events"]:
            self.node.publish_event(e)
        self.event_seq = ev["event_seq"] if not ev["events"] else max(e["seq"] for e in ev["events"])

    async def _poll_diagnostics(self) -> None:
        due = [self.now()]
        while True:
            try:
                status = await self._call(self.side, "status")
            except (DaemonUnavailable, CommandError) as exc:
                status = {"mode": None}
                self.connected = not isinstance(exc, DaemonUnavailable)
            self.node.publish_diagnostics(convert.diagnostics(status, self.summary()), self.ros_now_ns())
            await self._every("diagnostics_rate_Hz", due)

    async def _poll_programs(self) -> None:
        """The taught programs (``~/replay/<name>``): at the start, after ``~/teach/stop`` and every 5 s, from the
        program folder's listing (the bridge runs beside the daemon; a folder it may not read: the daemon's ``teach
        list``, which parses every program in the daemon's planner process)."""
        known: list[str] | None = None
        while True:
            try:
                folder = Path(self.program_dir)
                if folder.is_dir() and os.access(folder, os.R_OK | os.X_OK):
                    programs = sorted(f.stem for f in folder.glob("*.yaml"))
                else:
                    listed = (await self._call(self.lists, "teach", action="list"))["programs"]
                    programs = sorted(Path(p["path"]).stem for p in listed if "error" not in p)
                if programs != known:
                    self.node.set_programs(programs)
                    known = programs
            except (DaemonUnavailable, CommandError, KeyError, TypeError, OSError):
                pass
            self._programs_changed.clear()
            try:
                await asyncio.wait_for(self._programs_changed.wait(), 5.0)
            except TimeoutError:
                pass

    def summary(self) -> dict[str, Any]:
        """The bridge's own figures (diagnostics)."""
        latched = self.latched
        return {"daemon": self.connected, "message": (f"not connected to the daemon at {self.socket}"
                                                      if not self.connected else latched or "ok"),
                "stream_enabled": self.stream_enabled, "stream": self.stream_id, "stream_latched": latched,
                "commands_forwarded": self.forwarded, "commands_dropped": self.dropped,
                "commands_coalesced": self.coalesced, "commands_lost": self.lost,
                "commands_refused": self.refused, "drag_by_bridge": self.drag_by_bridge, "drag_lease": self.lease,
                "lease_renewals": self.renewals, "keepalive_present": self.keepalive_present,
                "clock": "lockstep (the daemon's simulated time, on /clock)" if self.lockstep else "wall"}

    # ------------------------------------------------------------------------------------------ drag keepalive

    def on_keepalive(self) -> None:
        self.last_keepalive = self.now()
        if not self.keepalive_present:
            self.keepalive_present = True
            self._status(convert.OK, "dragd/keepalive", "~/drag_keepalive present: ~/drag and ~/teach/start may "
                                     "be called")
        self.renew_drag()

    def _watch_keepalive(self) -> None:
        """A keepalive that stopped coming is said once (drag itself ends in the daemon, when its lease lapses)."""
        if self.keepalive_present and not self.keepalive_fresh():
            self.keepalive_present = False
            timeout = float(self.node.param("drag.keepalive_timeout_s"))
            self._status(convert.WARN if self.lease else convert.OK, "dragd/keepalive",
                         f"~/drag_keepalive silent for more than {timeout:g} s")

    def renew_drag(self) -> None:
        """A keepalive becomes the daemon's drag lease renewal (one in flight at a time: keepalives that come
        meanwhile are coalesced into it)."""
        if self.lease and not self.renewing:
            self.renewing = True
            self._spawn(self._renew(self.lease))

    async def _renew(self, lease: int) -> None:
        try:
            await self._call(self.keep, "lease", action="renew", lease=lease)
            self.renewals += 1
        except (CommandError, DaemonUnavailable) as exc:
            if self.lease == lease:  # lapsed or closed in the daemon: drag (if it was) has ended there
                self.lease = 0
                self._status(convert.WARN, "dragd/drag", f"drag lease {lease} ended: {exc}")
        finally:
            self.renewing = False

    async def _open_lease(self) -> int:
        """The bridge's drag lease: the one it holds if still active, else a new one with the keepalive's period."""
        if self.lease:
            try:
                await self._call(self.keep, "lease", action="renew", lease=self.lease)
                return self.lease
            except CommandError:
                self.lease = 0
        ans = await self._call(self.keep, "lease", action="open", holder=f"ros2 bridge {self.node_name}",
                               period_s=float(self.node.param("drag.keepalive_timeout_s")))
        self.lease = int(ans["lease"])
        return self.lease

    def keepalive_fresh(self) -> bool:
        return self.now() - self.last_keepalive <= float(self.node.param("drag.keepalive_timeout_s"))

    async def _watch_drag(self, st: dict[str, Any], gen: int) -> None:
        """The daemon ends drag (its lease lapsed, a hold, a guard trip, a fault ...): said on ``~/status``. A
        feedback hold (late TPDOs) is not an end: the daemon returns to drag by itself. ``gen``: the bridge's drag
        count when the state was asked for (a state asked for before the drag began, answered after, is no end)."""
        if not self.drag_by_bridge or gen != self.drag_gen or st.get("requested_mode", st["mode"]) == "drag":
            return
        self.drag_by_bridge = False
        try:
            status = await self._call(self.side, "status")
            why = ((status.get("drag") or {}).get("last_drag_end") or {}).get("reason") or f"mode {st['mode']}"
        except (CommandError, DaemonUnavailable) as exc:
            why = str(exc)
        self._status(convert.WARN, "dragd/drag", f"drag ended: {why}; the arm holds")

    # ------------------------------------------------------------------------------------------ the command stream

    def on_command(self, stamp_s: float, names: list[str], positions: list[float], lost: int = 0) -> None:
        """A ``~/joint_commands`` message (the topic_based_ros2_control pair): forwarded once, never repeated.
        ``lost``: its publisher's commands the middleware lost before it (counted, said in the diagnostics)."""
        self.lost += lost
        if not self.stream_enabled or self.latched is not None or not self.joints:
            self.dropped += 1
            return
        try:
            q = convert.order(names, positions, self.joints, "~/joint_commands")
        except ValueError as exc:
            self.dropped += 1
            self._latch(str(exc))
            return
        t = stamp_s if stamp_s > 0.0 else self.ros_now_ns() * 1e-9
        if self.stream_id is None:
            self.dropped += 1  # (the first command opens the stream; the next ones start at the arm's pose)
            if not self.opening and not self.ending and self.now() - self.open_refused_at >= OPEN_RETRY_S:
                self.opening = True
                self._spawn(self._open())
            return
        if len(self._pending) >= STREAM_IN_FLIGHT:
            self._pending.popleft()  # the daemon is that far behind: the oldest not yet sent gives way (no backlog)
            self.coalesced += 1
        self._pending.append((self.stream_id, t, q))
        self._command_ready.set()

    async def _forward(self) -> None:
        """Each command as it comes, in order, at most ``STREAM_IN_FLIGHT`` unanswered (the connection keeps their
        order; the daemon answers them in order) and as many waiting (``on_command``: beyond, the oldest waiting one
        is dropped, counted as coalesced: no backlog that could reach the arm late); none is sent twice."""
        slots = asyncio.Semaphore(STREAM_IN_FLIGHT)
        while True:
            await self._command_ready.wait()
            await slots.acquire()
            if not self._pending:
                self._command_ready.clear()
                slots.release()
                continue
            pending = self._pending.popleft()
            if pending[0] != self.stream_id:  # (a command of a stream that ended meanwhile)
                slots.release()
                continue
            self.forwarded += 1
            self._spawn(self._sample_in(slots, pending))

    async def _sample_in(self, slots: asyncio.Semaphore, pending: tuple[int, float, list[float]]) -> None:
        try:
            await self._sample(*pending)
        finally:
            slots.release()

    async def _open(self) -> None:
        try:
            resp = await self._call(self.stream, "stream_open", label="ros2 joint_commands")
            self.stream_id = resp["stream"]
            self._stream_error_seen = None
            self._status(convert.OK, "dragd/stream", f"stream {self.stream_id} open: commands go to "
                                     f"the arm ({resp['delay_s']:g} s behind)")
        except CommandError as exc:
            self.open_refused_at = self.now()
            self._status(convert.WARN, "dragd/stream", f"commands not followed: {exc.error}")
        except DaemonUnavailable:
            self.open_refused_at = self.now()
        finally:
            self.opening = False

    async def _sample(self, sid: int, t: float, q: list[float]) -> None:
        try:
            await self._call(self.stream, "stream", stream=sid, t_s=t, q_rad=q)
        except CommandError as exc:
            if sid != self.stream_id or self._stream_error_seen == sid:
                return  # samples in flight after the first error of this stream
            self._stream_error_seen = sid
            self.stream_id = None
            # until the daemon says how the stream ended (resumable, or a refusal that latches), the commands that
            # come are dropped: one of them must not open a new stream past a refusal
            self.ending = True
            try:
                try:
                    info = (await self._call(self.stream, "state"))["stream"] or {}
                except (CommandError, DaemonUnavailable):
                    info = {}
                end = info.get("end") if info.get("stream") == sid else None
                self._stream_ended(sid, end, info.get("outcome"), exc.error)
            finally:
                self.ending = False
        except DaemonUnavailable:
            pass

    def _stream_ended(self, sid: int, end: str | None, outcome: object, reason: str) -> None:
        if end in RESUMABLE:
            self._status(convert.WARN, "dragd/stream", f"stream {sid} ended ({outcome}); "
                                     "the next command opens a new one")
        else:
            self.refused += 1
            self._latch(reason)

    def _watch_stream(self, info: dict[str, Any] | None, sid: int | None) -> None:
        """The daemon ended the bridge's stream (its deadline, a refused sample, a monitor, a fault): seen in the
        state polls, so that the next command opens a new stream at once (or the refusal is said) rather than meeting
        the ended one. ``sid``: the bridge's stream when the state was asked for (a state asked for before the
        stream opened says nothing of it)."""
        if sid is None or sid != self.stream_id or not info or info.get("stream") != sid or \
                info.get("state") == "running":
            return
        self.stream_id = None
        self._stream_error_seen = sid
        self._stream_ended(sid, info.get("end"), info.get("outcome"), str(info.get("outcome")))

    def _latch(self, reason: str) -> None:
        self.latched = reason
        self._status(convert.ERROR, "dragd/stream", f"commands not followed until ~/streaming true: "
                                 f"{reason}")

    async def _end_stream(self) -> None:
        """Stop a running stream, trajectory or replay (controlled stop), then HOLD with the drives back in CST. The
        waits are the daemon's (``replay_stop`` with ``wait``, ``mode hold``): they take the arm's time on either
        clock, the bridge reads none."""
        sid, self.stream_id = self.stream_id, None
        if sid is not None:
            try:
                await self._call(self.stream, "stream_close", stream=sid)
            except CommandError:
                pass
        st = await self._call(self.act, "status")
        if st["mode"] == "track":
            try:
                await self._call(self.act, "replay_stop", wait=True)
            except CommandError:
                pass
            st = await self._call(self.act, "status")
        if st["mode"] == "hold" and st.get("drive_mode") != "cst":
            await self._call(self.act, "mode", mode="hold")  # (waits for the drives' return to CST)

    # ------------------------------------------------------------------------------------------ trajectories

    def on_trajectory(self, stamp_s: float, names: list[str], points: list[tuple[float, list[float]]]) -> None:
        self._spawn(self._trajectory(stamp_s, names, points))

    async def _trajectory(self, stamp_s: float, names: list[str], points: list[tuple[float, list[float]]]) -> None:
        name = "dragd/trajectory"
        try:
            if not points:  # joint_trajectory_controller: an empty trajectory stops (hold)
                await self._call(self.act, "replay_stop", wait=True)
                self._status(convert.OK, name, "empty trajectory: the motion stops, the arm holds")
                return
            q_now = self.state["q_rad"] if self.state else None
            t_s, q_rad = convert.trajectory_samples(names, points, self.joints, q_now)
            if stamp_s > 0.0:  # a start time in the future: wait for it (one in the past: start now)
                wait = stamp_s - self.ros_now_ns() * 1e-9
                if wait > 10.0:
                    raise ValueError(f"trajectory: header.stamp lies {wait:.1f} s ahead (more than 10 s)")
                if wait > 0.0:
                    await self.sleep(wait)
            resp = await self._call(self.act, "track", t_s=t_s, q_rad=q_rad, label="ros2 trajectory")
            self._status(convert.OK, name, f"trajectory accepted: {len(points)} points, "
                                     f"{resp.get('duration_s', t_s[-1]):g} s", {"points": len(points)})
        except (ValueError, CommandError) as exc:
            text = exc.error if isinstance(exc, CommandError) else str(exc)
            self._status(convert.ERROR, name, f"trajectory refused: {text}")
        except DaemonUnavailable as exc:
            self._status(convert.ERROR, name, f"trajectory refused: {exc}")

    # ------------------------------------------------------------------------------------------ services

    async def action(self, name: str, *args: Any) -> tuple[bool, str]:
        """A service: (success, message); the message carries the daemon's answer or its reason."""
        p = self.node.param
        try:
            if name == "streaming":
                return self._streaming(bool(args[0]))
            if name == "start":
                resp = await self._call(self.act, "start")
            elif name == "stop":
                self._hold_streaming("stop")
                resp = await self._call(self.act, "stop")
            elif name == "hold":
                self._hold_streaming("hold")
                await self._end_stream()
                resp = await self._call(self.act, "mode", mode="hold")
            elif name in ("drag", "teach_start"):
                if not self.keepalive_fresh():
                    return False, (f"{name}: refused: no ~/drag_keepalive within the last "
                                   f"{float(p('drag.keepalive_timeout_s')):g} s (std_msgs/Empty, published while "
                                   "the arm is to stay in drag)")
                self._hold_streaming(name)
                await self._end_stream()
                lease = await self._open_lease()  # the keepalives renew it; drag ends in the daemon when they stop
                if name == "drag":
                    resp = await self._call(self.act, "mode", mode="drag", accept=bool(p("drag.accept")),
                                            lease=lease)
                else:
                    args_: dict[str, Any] = {"name": str(p("teach.name")) or
                                             datetime.datetime.now().strftime("ros2_%Y%m%d_%H%M%S"),
                                             "overwrite": bool(p("teach.overwrite"))}
                    if float(p("teach.rate_Hz")) > 0:
                        args_["rate_Hz"] = float(p("teach.rate_Hz"))
                    resp = await self._call(self.act, "teach", action="start", lease=lease, **args_)
                self.drag_by_bridge = resp.get("mode") == "drag"
                self.drag_gen += self.drag_by_bridge
            elif name == "teach_mark":
                mark = str(p("teach.mark_name"))
                resp = await self._call(self.act, "teach", action="mark", **({"name": mark} if mark else {}))
            elif name == "teach_stop":
                resp = await self._call(self.act, "teach", action="stop")
                self._programs_changed.set()
            elif name == "replay":
                self._hold_streaming("replay")
                resp = await self._call(self.act, "replay", program=str(args[0]), speed=float(p("replay.speed")),
                                        interp=str(p("replay.interp")), cycles=int(p("replay.cycles")))
            elif name == "replay_stop":
                resp = await self._call(self.act, "replay_stop", wait=True)
            elif name == "payload_set":
                resp = await self._call(self.act, "payload", action="set", mass_kg=float(p("payload.mass_kg")),
                                        com_m=[float(x) for x in p("payload.com_m")])
            elif name == "payload_clear":
                resp = await self._call(self.act, "payload", action="clear")
            elif name == "payload_estimate":
                resp = await self._call(self.act, "payload", action="estimate", poses=int(p("payload.poses")),
                                        apply=bool(p("payload.apply")))
            elif name == "check_model":
                resp = await self._call(self.act, "check_model", step_rad=float(p("check_model.step_rad")))
            else:
                return False, f"unknown action {name!r}"
        except CommandError as exc:
            return False, exc.error
        except DaemonUnavailable as exc:
            return False, str(exc)
        resp.pop("ok", None)
        resp.pop("id", None)
        return True, json.dumps(resp, default=str)[:4000]

    def _streaming(self, on: bool) -> tuple[bool, str]:
        self.stream_enabled = on
        if on:
            self.latched = None
            self.open_refused_at = -1e9
            return True, "commands on ~/joint_commands are followed (the next one opens a stream from hold)"
        self._hold_streaming("~/streaming false")
        if self.stream_id is not None:
            self._spawn(self._close_quietly(self.stream_id))
            self.stream_id = None
        return True, "commands on ~/joint_commands are ignored"

    async def _close_quietly(self, sid: int) -> None:
        try:
            await self._call(self.stream, "stream_close", stream=sid)
        except (CommandError, DaemonUnavailable):
            pass

    def _hold_streaming(self, why: str) -> None:
        """An operator's action takes the arm: commands wait for ~/streaming true (a controller that keeps
        publishing must not take it back by itself)."""
        if self.latched is None:
            self._latch(f"{why} (an operator's action)")

    def _status(self, level: int, name: str, message: str, values: dict[str, Any] | None = None) -> None:
        """``~/status`` and the bridge's log (the journal under systemd) say the same."""
        print(f"dragd ros2: {name}: {message}", flush=True)
        self.node.publish_status(level, name, message, values)
