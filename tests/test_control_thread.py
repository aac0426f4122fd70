"""The control socket on a thread of its own (dragd/server.py's `ThreadedControlServer`): the commands it answers
there never wait for the owner's loop (the daemon's cycle), every other one runs on the owner's loop, in order, with
its errors; closing ends the thread and removes the socket. Real sockets, no clock: the owner's loop is blocked
outright while the off-loop requests are answered."""

from __future__ import annotations

import asyncio
import json
import os
import socket
import threading

import pytest

from dragd.protocol import ControlError
from dragd.server import CommandTable, ThreadedControlServer

pytestmark = pytest.mark.unit

N = 200


def table(seen: list[str]) -> CommandTable:
    t = CommandTable()

    @t.command("sample")
    async def sample(k: int) -> dict:
        seen.append(threading.current_thread().name)
        return {"k": k, "thread": threading.current_thread().name}

    @t.command("whoami")
    def whoami() -> dict:
        return {"thread": threading.current_thread().name}

    @t.command("bad")
    def bad(x: int) -> dict:
        raise ControlError(f"x: expected 1, got {x}")

    return t


def exchange(path: str, requests: list[dict]) -> list[dict]:
    """Every request sent at once on one connection, the responses read in order."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(60.0)
        s.connect(path)
        s.sendall(b"".join(json.dumps(r).encode() + b"\n" for r in requests))
        f = s.makefile("rb")
        return [json.loads(f.readline()) for _ in requests]


def test_off_loop_commands_are_answered_while_the_owners_loop_is_blocked(tmp_path):
    path = str(tmp_path / "c.sock")
    seen: list[str] = []
    got: dict[str, list[dict]] = {}
    answered, release = threading.Event(), threading.Event()

    def client() -> None:
        got["here"] = exchange(path, [{"cmd": "sample", "k": k, "id": k} for k in range(N)]
                               + [{"cmd": "sample", "k": "x"}])
        answered.set()
        release.wait(60.0)  # (the owner's loop has counted what was handed over while it was blocked)
        got["owner"] = exchange(path, [{"cmd": "whoami"}, {"cmd": "bad", "x": 2}, {"cmd": "sample", "k": N}])

    async def main() -> tuple[bool, int, int]:
        server = ThreadedControlServer(path, table(seen), here={"sample"})
        await server.start()
        try:
            th = threading.Thread(target=client)
            th.start()
            # the owner's loop blocked outright (no await): only the server's thread can answer
            ok = answered.wait(60.0)
            handed_while_blocked = server.handed_over
            release.set()
            await asyncio.to_thread(th.join, 60.0)
            return ok, handed_while_blocked, server.answered_here
        finally:
            await server.close()

    ok, handed, here = asyncio.run(main())
    assert ok, "the off-loop requests waited for the owner's blocked loop"
    assert handed == 0 and here == N + 2
    assert [r["k"] for r in got["here"][:N]] == list(range(N)) and [r["id"] for r in got["here"][:N]] == list(range(N))
    assert set(seen) == {"dragd-control"}
    assert not got["here"][N]["ok"] and "field 'k': expected an integer" in got["here"][N]["error"]
    who, bad, last = got["owner"]
    assert who == {"ok": True, "thread": "MainThread"}  # handed to the owner's loop, answered once it ran
    assert not bad["ok"] and bad["error"] == "x: expected 1, got 2"
    assert last["ok"] and last["thread"] == "dragd-control"
    assert not os.path.exists(path)  # closed: the socket file removed
    assert not any(t.name == "dragd-control" for t in threading.enumerate())


def test_a_live_socket_refuses_a_second_threaded_server(tmp_path):
    path = str(tmp_path / "c.sock")

    async def main() -> str:
        async with ThreadedControlServer(path, table([])):
            try:
                async with ThreadedControlServer(path, table([])):
                    return "started"
            except Exception as exc:  # noqa: BLE001 - the refusal is the point
                return f"{type(exc).__name__}: {exc}"

    got = asyncio.run(main())
    assert got.startswith("ControlSocketBusy: another server already answers at"), got
    assert not any(t.name == "dragd-control" for t in threading.enumerate())


def test_the_daemons_off_cycle_commands_are_the_streams_samples_and_close():
    from dragd.daemon.stream import OFF_CYCLE_COMMANDS

    assert OFF_CYCLE_COMMANDS == {"stream", "stream_close"}  # stream_open switches the drives: the cycle's loop
