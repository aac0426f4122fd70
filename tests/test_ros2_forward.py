"""The bridge's forwarding of ``~/joint_commands`` into the daemon's stream (dragd/ros2/bridge.py), without ROS and
without a daemon: a stand-in for the stream's connection that holds its answers until told. Commands go in order, up
to ``STREAM_IN_FLIGHT`` unanswered, as many waiting; beyond, the oldest waiting gives way (counted); none twice."""

from __future__ import annotations

import asyncio
from typing import Any

import pytest

from dragd.client import CommandError
from dragd.ros2.bridge import STREAM_IN_FLIGHT, Bridge

pytestmark = pytest.mark.unit

J = ["joint1", "joint2", "joint3"]


class HeldConnection:
    """The stream's connection: records each ``stream`` request and answers once ``gate`` is set (the daemon's
    round trip, as long as the test wants)."""

    def __init__(self) -> None:
        self.sent: list[float] = []
        self.in_flight = 0
        self.most_in_flight = 0
        self.gate = asyncio.Event()
        self.turns = 0  # loop turns an answer takes besides the gate

    async def call(self, cmd: str, timeout_s: float | None = None, **args: Any) -> dict[str, Any]:
        assert cmd == "stream" and args["stream"] == 1
        self.sent.append(args["t_s"])
        self.in_flight += 1
        self.most_in_flight = max(self.most_in_flight, self.in_flight)
        await self.gate.wait()
        for _ in range(self.turns):
            await asyncio.sleep(0)
        self.in_flight -= 1
        return {"ok": True, "samples": len(self.sent)}

    async def close(self) -> None:
        pass


async def _settle() -> None:
    for _ in range(50):  # (the loop runs what is ready: the forwarder, the requests' tasks)
        await asyncio.sleep(0)


def test_commands_go_in_order_several_in_flight_and_the_oldest_waiting_gives_way():
    async def scenario() -> tuple[Bridge, HeldConnection]:
        bridge = Bridge("/nonexistent/dragd.sock")
        bridge.joints, bridge.stream_id = J, 1
        conn = HeldConnection()
        bridge.stream = conn  # type: ignore[assignment]
        forward = asyncio.create_task(bridge._forward())

        def command(k: int) -> None:
            bridge.on_command(1000.0 + k, J, [1e-3 * k, 0.0, 0.0])

        for k in range(STREAM_IN_FLIGHT):  # commands that came together (handed to the loop in one batch)
            command(k)
        await _settle()
        assert conn.sent == [1000.0 + k for k in range(STREAM_IN_FLIGHT)]  # all sent, none waiting for another
        extra = 2 * STREAM_IN_FLIGHT + 6  # while the daemon has not answered: as many wait, the older give way
        for k in range(STREAM_IN_FLIGHT, STREAM_IN_FLIGHT + extra):
            command(k)
        await _settle()
        assert len(conn.sent) == STREAM_IN_FLIGHT  # no more than that many unanswered
        conn.gate.set()  # the daemon answers
        await _settle()
        forward.cancel()
        return bridge, conn

    bridge, conn = asyncio.run(scenario())
    last = STREAM_IN_FLIGHT + 2 * STREAM_IN_FLIGHT + 6
    kept = [1000.0 + k for k in range(last - STREAM_IN_FLIGHT, last)]  # the newest waiting ones
    assert conn.sent == [1000.0 + k for k in range(STREAM_IN_FLIGHT)] + kept  # in order, none twice
    assert conn.most_in_flight == STREAM_IN_FLIGHT
    assert bridge.forwarded == 2 * STREAM_IN_FLIGHT
    assert bridge.coalesced == last - 2 * STREAM_IN_FLIGHT  # every command is sent or counted
    assert bridge.dropped == 0 and bridge.summary()["commands_coalesced"] == bridge.coalesced


def test_a_steady_stream_is_forwarded_whole_when_the_daemon_keeps_up():
    """One command per loop turn while each answer takes a few turns (a round trip longer than the command
    period): every command is sent, none coalesced."""

    async def scenario() -> tuple[Bridge, HeldConnection]:
        bridge = Bridge("/nonexistent/dragd.sock")
        bridge.joints, bridge.stream_id = J, 1
        conn = HeldConnection()
        conn.gate.set()
        conn.turns = 4
        bridge.stream = conn  # type: ignore[assignment]
        forward = asyncio.create_task(bridge._forward())
        for k in range(500):
            bridge.on_command(1000.0 + k, J, [1e-4 * k, 0.0, 0.0])
            await asyncio.sleep(0)
        await _settle()
        forward.cancel()
        return bridge, conn

    bridge, conn = asyncio.run(scenario())
    assert conn.sent == [1000.0 + k for k in range(500)]
    assert bridge.coalesced == 0 and bridge.forwarded == 500
    assert 1 < conn.most_in_flight <= STREAM_IN_FLIGHT


class RefusingConnection:
    """The stream's connection when the daemon refuses a sample: ``stream`` is refused, ``state`` (how the stream
    ended) is answered once ``gate`` is set, ``stream_open`` is counted and answered with stream 2."""

    def __init__(self, end: str) -> None:
        self.end = end
        self.gate = asyncio.Event()
        self.opens = 0

    async def call(self, cmd: str, timeout_s: float | None = None, **args: Any) -> dict[str, Any]:
        if cmd == "stream":
            raise CommandError(cmd, f"stream {args['stream']}: the first sample is 11.46° from the arm's pose", {})
        if cmd == "state":
            await self.gate.wait()
            return {"stream": {"stream": 1, "state": "ended", "end": self.end, "outcome": f"stream {self.end}"}}
        assert cmd == "stream_open", cmd
        self.opens += 1
        return {"stream": 2, "delay_s": 0.05}

    async def close(self) -> None:
        pass


class SaidStatus:
    """The node's ``~/status`` as the bridge publishes it (level, name, message)."""

    def __init__(self) -> None:
        self.said: list[tuple[int, str, str]] = []

    def publish_status(self, level: int, name: str, message: str, values: dict[str, Any] | None = None) -> None:
        self.said.append((level, name, message))


@pytest.mark.parametrize("end", ["refused", "timeout"])
def test_no_command_opens_a_stream_while_a_refusal_is_looked_into(end):
    """The daemon refuses a sample; until its ``state`` says how the stream ended (here held as long as a loaded
    host may take), the commands that come are dropped. A refusal then latches (nothing opens a stream until
    ~/streaming true); a resumable end (a timeout) lets the next command open a new stream."""

    async def scenario() -> tuple[Bridge, RefusingConnection, SaidStatus]:
        bridge = Bridge("/nonexistent/dragd.sock")
        bridge.joints, bridge.stream_id = J, 1
        conn, node = RefusingConnection(end), SaidStatus()
        bridge.stream, bridge.node = conn, node  # type: ignore[assignment]
        forward = asyncio.create_task(bridge._forward())
        bridge.on_command(1000.0, J, [0.2, 0.2, 0.2])
        await _settle()
        assert bridge.stream_id is None and bridge.ending  # refused, its end asked for and not yet answered
        for k in range(1, 4):  # the controller's next updates meanwhile
            bridge.on_command(1000.0 + 0.01 * k, J, [0.2, 0.2, 0.2])
            await _settle()
        assert conn.opens == 0 and bridge.dropped == 3
        conn.gate.set()
        await _settle()
        assert not bridge.ending
        bridge.on_command(1000.04, J, [0.2, 0.2, 0.2])
        await _settle()
        forward.cancel()
        return bridge, conn, node

    bridge, conn, node = asyncio.run(scenario())
    texts = [m for _lv, name, m in node.said if name == "dragd/stream"]
    if end == "refused":
        assert conn.opens == 0 and bridge.latched is not None and bridge.dropped == 4 and bridge.refused == 1
        assert texts == ["commands not followed until ~/streaming true: stream 1: the first sample is 11.46° from "
                         "the arm's pose"], texts
    else:
        assert conn.opens == 1 and bridge.latched is None and bridge.stream_id == 2 and bridge.refused == 0
        assert texts == ["stream 1 ended (stream timeout); the next command opens a new one",
                         "stream 2 open: commands go to the arm (0.05 s behind)"], texts
