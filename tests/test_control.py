import asyncio
import json
import os
import socket
import stat
import threading

import numpy as np
import pytest

from dragd.protocol import (
    DEFAULT_SOCKET_PATH,
    ControlClient,
    ControlError,
    ControlSocketBusy,
    DaemonTimeout,
    DaemonUnavailable,
)
from dragd.server import CommandTable, ControlServer

pytestmark = pytest.mark.unit


def make_table():
    table = CommandTable()
    state = {"mode": "idle"}

    @table.command("status")
    def status():
        return {"mode": state["mode"], "q_rad": np.zeros(6), "period_us": float("nan")}

    @table.command("set_mode")
    async def set_mode(mode: str, reason: str = ""):
        if mode not in ("idle", "drag"):
            raise ControlError(f"unknown mode {mode!r}; expected idle or drag")
        await asyncio.sleep(0)
        state["mode"] = mode
        return {"mode": mode, "reason": reason}

    @table.command("crash")
    def crash():
        raise ZeroDivisionError("division by zero")

    @table.command("slow")
    async def slow(seconds: float):
        await asyncio.sleep(seconds)
        return {}

    return table


class ServerThread:
    """A real ControlServer on its own event loop in a thread (the CLI client is sync)."""

    def __init__(self, path, handler):
        self.path = path
        self.handler = handler
        self.loop = asyncio.new_event_loop()
        self.ready = threading.Event()
        self.error = None
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        asyncio.set_event_loop(self.loop)

        async def main():
            try:
                self.server = await ControlServer(self.path, self.handler).start()
            except BaseException as e:  # noqa: BLE001
                self.error = e
                self.ready.set()
                return
            self.stop = asyncio.Event()
            self.ready.set()
            await self.stop.wait()
            await self.server.close()

        self.loop.run_until_complete(main())

    def __enter__(self):
        self.thread.start()
        self.ready.wait(5)
        if self.error:
            raise self.error
        return self

    def __exit__(self, *exc):
        if self.error is None:
            self.loop.call_soon_threadsafe(self.stop.set)
        self.thread.join(5)
        self.loop.close()


@pytest.fixture
def sock_path(tmp_path):
    return str(tmp_path / "run" / "dragd" / "dragd.sock")  # parents do not exist yet


def test_commands_round_trip(sock_path):
    with ServerThread(sock_path, make_table()):
        c = ControlClient(sock_path)
        r = c.call("status")
        assert r == {"ok": True, "mode": "idle", "q_rad": [0.0] * 6, "period_us": None}
        assert c.call("set_mode", mode="drag", reason="test") == {
            "ok": True, "mode": "drag", "reason": "test",
        }
        assert c.call("status")["mode"] == "drag"
        r = c.call("set_mode", mode="fly")
        assert r["ok"] is False and "unknown mode 'fly'" in r["error"]


def test_socket_file_mode_and_parent_created(sock_path):
    with ServerThread(sock_path, make_table()):
        st = os.stat(sock_path)
        assert stat.S_ISSOCK(st.st_mode)
        assert stat.S_IMODE(st.st_mode) == 0o660
    assert not os.path.exists(sock_path)  # removed on close


def test_bad_requests_get_error_responses_and_server_survives(sock_path):
    with ServerThread(sock_path, make_table()):
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.settimeout(5)
        s.connect(sock_path)
        f = s.makefile("rwb")

        def ask(raw: bytes) -> dict:
            f.write(raw + b"\n")
            f.flush()
            return json.loads(f.readline())

        r = ask(b"{not json")
        assert r["ok"] is False and "malformed JSON" in r["error"]
        r = ask(b"[1, 2]")
        assert r["ok"] is False and "JSON object" in r["error"]
        r = ask(b'{"id": 4}')
        assert r == {"ok": False, "error": "request needs a non-empty string field 'cmd'", "id": 4}
        r = ask(b'{"cmd": "status", "verbose": true, "id": "a"}')
        assert r["ok"] is False and "unknown field(s) 'verbose'" in r["error"] and r["id"] == "a"
        r = ask(b'{"cmd": "set_mode"}')
        assert r["ok"] is False and "needs field(s): mode" in r["error"]
        r = ask(b'{"cmd": "nope"}')
        assert r["ok"] is False and "unknown cmd 'nope'" in r["error"] and "status" in r["error"]
        r = ask(b'{"cmd": "crash"}')
        assert r["ok"] is False and "ZeroDivisionError" in r["error"]
        r = ask(b"\xff\xfe")
        assert r["ok"] is False
        # same connection still works afterwards
        assert ask(b'{"cmd": "status", "id": 9}')["id"] == 9
        s.close()
        assert ControlClient(sock_path).call("status")["ok"] is True


def test_handler_returning_non_dict_or_unserialisable(sock_path):
    async def handler(req):
        if req["cmd"] == "list":
            return [1, 2]
        return {"obj": object()}

    with ServerThread(sock_path, handler):
        c = ControlClient(sock_path)
        assert "expected a dict" in c.call("list")["error"]
        assert "not JSON" in c.call("obj")["error"]


def test_client_when_nothing_listens(tmp_path):
    path = str(tmp_path / "dragd.sock")
    with pytest.raises(DaemonUnavailable) as ei:
        ControlClient(path).call("status")
    msg = str(ei.value)
    assert msg.startswith(f"no dragd daemon answers at {path}: socket file does not exist")
    assert "'dragd run'" in msg and "'systemctl start dragd'" in msg
    # stale socket file: bound once, nobody listening now
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.bind(path)
    s.close()
    with pytest.raises(DaemonUnavailable, match="connection refused"):
        ControlClient(path).call("status")


def test_default_path_message():
    assert DEFAULT_SOCKET_PATH == "/run/dragd/dragd.sock"
    if os.path.exists(DEFAULT_SOCKET_PATH):
        pytest.skip("a daemon socket exists on this machine")
    with pytest.raises(DaemonUnavailable, match="no dragd daemon answers at /run/dragd/dragd.sock"):
        ControlClient().call("status")


def test_client_timeout(sock_path):
    with ServerThread(sock_path, make_table()):
        with pytest.raises(DaemonTimeout, match="did not answer 'slow' within 0.2 s"):
            ControlClient(sock_path, timeout_s=0.2).call("slow", seconds=2)


def test_stale_socket_replaced_and_live_server_refused(sock_path):
    os.makedirs(os.path.dirname(sock_path))
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.bind(sock_path)  # stale: nobody listens
    s.close()
    with ServerThread(sock_path, make_table()):
        assert ControlClient(sock_path).call("status")["ok"]

        async def second():
            await ControlServer(sock_path, make_table()).start()

        with pytest.raises(ControlSocketBusy, match="another server already answers"):
            asyncio.run(second())
        assert ControlClient(sock_path).call("status")["ok"]  # first one untouched


def test_refuses_to_replace_a_regular_file(tmp_path):
    path = tmp_path / "dragd.sock"
    path.write_text("important")

    async def main():
        await ControlServer(str(path), make_table()).start()

    with pytest.raises(FileExistsError, match="not a socket"):
        asyncio.run(main())
    assert path.read_text() == "important"


def test_server_in_running_loop_with_async_client(sock_path):
    """The daemon's shape: server task on the loop, a client in a worker thread."""

    async def main():
        async with ControlServer(sock_path, make_table()):
            r = await asyncio.to_thread(ControlClient(sock_path).call, "set_mode", mode="drag")
            assert r["ok"]
            reader, writer = await asyncio.open_unix_connection(sock_path)
            writer.write(b'{"cmd": "status"}')  # no newline, then EOF
            writer.write_eof()
            line = await reader.readline()
            writer.close()
            return json.loads(line)

    assert asyncio.run(main())["mode"] == "drag"


def test_typed_fields_deep_nesting_and_the_client_cap(sock_path):
    from dragd import server as srv

    table = make_table()

    @table.command("teach")
    def teach(action: str, overwrite: bool = False, rate_Hz: float | None = None, joints: list[int] | None = None):
        return {"overwrite": overwrite}

    with ServerThread(sock_path, table):
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.settimeout(5)
        s.connect(sock_path)
        f = s.makefile("rwb")

        def ask(raw: bytes) -> dict:
            f.write(raw + b"\n")
            f.flush()
            return json.loads(f.readline())

        r = ask(b'{"cmd": "teach", "action": "start", "overwrite": "false"}')
        assert r["ok"] is False and "field 'overwrite': expected a boolean" in r["error"], r
        assert ask(b'{"cmd": "teach", "action": "start", "overwrite": false}') == {"ok": True, "overwrite": False}
        r = ask(b'{"cmd": "teach", "action": 3}')
        assert r["ok"] is False and "field 'action': expected a string" in r["error"], r
        r = ask(b'{"cmd": "teach", "action": "x", "rate_Hz": true}')
        assert r["ok"] is False and "rate_Hz" in r["error"], r
        assert ask(b'{"cmd": "teach", "action": "x", "rate_Hz": 50}')["ok"] is True  # an integer is a number
        r = ask(b'{"cmd": "teach", "action": "x", "joints": [1, "2"]}')
        assert r["ok"] is False and "a list of an integer" in r["error"], r
        r = ask(b'{"cmd": "status", "x": ' + b"[" * 100_000 + b"]" * 100_000 + b"}")
        assert r["ok"] is False and "nested too deeply" in r["error"], r
        r = ask(b'{"cmd": "status", "x": ' + b"[" * 40 + b"]" * 40 + b"}")
        assert r["ok"] is False and "nested too deeply" in r["error"], r
        assert ask(b'{"cmd": "status"}')["ok"] is True  # the connection survived
        extra = []
        try:
            for _ in range(srv.MAX_CLIENTS - 1):  # the cap counts this test's own open connection
                c = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
                c.settimeout(5)
                c.connect(sock_path)
                c.sendall(b'{"cmd": "status"}\n')
                assert json.loads(c.makefile("rb").readline())["ok"] is True
                extra.append(c)
            over = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            over.settimeout(5)
            over.connect(sock_path)
            r = json.loads(over.makefile("rb").readline())
            assert r["ok"] is False and "too many control connections" in r["error"], r
            over.close()
        finally:
            for c in extra:
                c.close()
        s.close()


def test_a_trickled_request_loses_its_slot(sock_path, monkeypatch):
    """A request once begun must arrive whole within REQUEST_READ_S: a client that sends half a line and stalls
    gets an error line and is closed (it cannot hold one of the MAX_CLIENTS slots); a whole request is answered."""
    from dragd import server as srv

    monkeypatch.setattr(srv, "REQUEST_READ_S", 0.3)
    with ServerThread(sock_path, make_table()):
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.settimeout(5)
        s.connect(sock_path)
        f = s.makefile("rwb")
        f.write(b'{"cmd": "sta')
        f.flush()
        r = json.loads(f.readline())
        assert r["ok"] is False and "not complete within 0.3 s" in r["error"], r
        assert f.readline() == b""  # then closed
        s.close()
        ok = ControlClient(sock_path).call("status")
        assert ok["ok"] is True
