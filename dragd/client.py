"""asyncio client of the daemon's control socket (docs/PROTOCOL.md).

::

    import asyncio
    from dragd.client import Client

    async def main():
        async with Client("/run/dragd/dragd.sock") as d:
            print((await d.status())["mode"])
            await d.start()
            await d.mode("drag")

    asyncio.run(main())

One connection carries any number of requests; each request gets an ``id`` and its response is matched by it,
so concurrent calls on one client are fine. ``call`` returns the response (``ok`` true) or raises `CommandError`
(``ok`` false: the daemon's error text); `DaemonUnavailable` when no daemon answers.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import os
from typing import Any

from dragd.protocol import DEFAULT_SOCKET_PATH, MAX_LINE_BYTES, DaemonTimeout, DaemonUnavailable, encode_line

__all__ = ["Client", "CommandError", "DaemonUnavailable", "DaemonTimeout"]


class CommandError(RuntimeError):
    """The daemon refused a command (``{"ok": false, "error": ...}``)."""

    def __init__(self, cmd: str, error: str, response: dict[str, Any]) -> None:
        super().__init__(f"{cmd}: {error}")
        self.cmd = cmd
        self.error = error
        self.response = response


class Client:
    """One connection to the daemon; use ``async with`` or `connect` / `close`."""

    def __init__(self, path: str | os.PathLike[str] | None = None, timeout_s: float = 10.0) -> None:
        self.path = os.fspath(path or os.environ.get("DRAGD_SOCKET") or DEFAULT_SOCKET_PATH)
        self.timeout_s = timeout_s
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._pending: dict[int, asyncio.Future[dict[str, Any]]] = {}
        self._ids = itertools.count(1)
        self._task: asyncio.Task[None] | None = None
        self._lock = asyncio.Lock()

    async def connect(self) -> Client:
        try:
            self._reader, self._writer = await asyncio.wait_for(
                asyncio.open_unix_connection(self.path, limit=MAX_LINE_BYTES * 16), self.timeout_s)
        except (TimeoutError, FileNotFoundError, ConnectionRefusedError, PermissionError, OSError) as exc:
            reason = {FileNotFoundError: "socket file does not exist",
                      ConnectionRefusedError: "connection refused (stale socket file)",
                      PermissionError: "permission denied (is your user in group 'dragd'?)"}.get(
                type(exc), str(exc) or type(exc).__name__)
            raise DaemonUnavailable(f"no dragd daemon answers at {self.path}: {reason}") from None
        self._task = asyncio.create_task(self._read_loop())
        return self

    async def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            try:
                await self._writer.wait_closed()
            except (ConnectionError, OSError):
                pass
        if self._task is not None:
            self._task.cancel()
            try:
                await self._task
            except (asyncio.CancelledError, Exception):  # noqa: BLE001
                pass
        self._fail_pending(DaemonUnavailable(f"connection to {self.path} closed"))
        self._writer = self._reader = self._task = None

    async def __aenter__(self) -> Client:
        return await self.connect()

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    def _fail_pending(self, exc: BaseException) -> None:
        for fut in self._pending.values():
            if not fut.done():
                fut.set_exception(exc)
        self._pending.clear()

    async def _read_loop(self) -> None:
        assert self._reader is not None
        try:
            while True:
                line = await self._reader.readline()
                if not line:
                    break
                try:
                    response = json.loads(line)
                except json.JSONDecodeError:
                    continue
                rid = response.get("id") if isinstance(response, dict) else None
                fut = self._pending.pop(rid, None) if isinstance(rid, int) else None
                if fut is not None and not fut.done():
                    fut.set_result(response)
        except (ConnectionError, OSError, asyncio.LimitOverrunError, ValueError) as exc:
            self._fail_pending(DaemonUnavailable(f"connection to {self.path} lost: {exc}"))
            return
        self._fail_pending(DaemonUnavailable(f"the daemon at {self.path} closed the connection"))

    async def call(self, cmd: str, timeout_s: float | None = None, **args: Any) -> dict[str, Any]:
        """Send ``{"cmd": cmd, **args}``; the response (``ok`` true) or `CommandError`."""
        if self._writer is None:
            await self.connect()
        assert self._writer is not None
        rid = next(self._ids)
        fut: asyncio.Future[dict[str, Any]] = asyncio.get_running_loop().create_future()
        self._pending[rid] = fut
        async with self._lock:
            self._writer.write(encode_line({"cmd": cmd, "id": rid, **args}))
            await self._writer.drain()
        try:
            response = await asyncio.wait_for(fut, timeout_s or self.timeout_s)
        except TimeoutError:
            self._pending.pop(rid, None)
            raise DaemonTimeout(f"dragd at {self.path} did not answer {cmd!r} within {timeout_s or self.timeout_s} s"
                                ) from None
        if not response.get("ok"):
            raise CommandError(cmd, str(response.get("error")), response)
        return response

    # the commands (docs/PROTOCOL.md)
    async def status(self) -> dict[str, Any]:
        return await self.call("status")

    async def start(self) -> dict[str, Any]:
        return await self.call("start")

    async def stop(self) -> dict[str, Any]:
        return await self.call("stop")

    async def mode(self, mode: str) -> dict[str, Any]:
        return await self.call("mode", mode=mode)

    async def record_start(self, path: str, label: str = "") -> dict[str, Any]:
        return await self.call("record", action="start", path=path, label=label)

    async def record_stop(self) -> dict[str, Any]:
        return await self.call("record", action="stop")

    async def teach(self, action: str, **args: Any) -> dict[str, Any]:
        return await self.call("teach", action=action, **args)

    async def replay(self, program: str, **args: Any) -> dict[str, Any]:
        return await self.call("replay", program=program, **args)

    async def replay_pause(self) -> dict[str, Any]:
        return await self.call("replay_pause")

    async def replay_resume(self) -> dict[str, Any]:
        return await self.call("replay_resume")

    async def replay_stop(self) -> dict[str, Any]:
        return await self.call("replay_stop")

    async def replay_speed(self, speed: float) -> dict[str, Any]:
        return await self.call("replay_speed", speed=speed)

    async def track(self, **args: Any) -> dict[str, Any]:
        return await self.call("track", **args)

    async def state(self) -> dict[str, Any]:
        return await self.call("state")

    async def events(self, since: int = 0) -> dict[str, Any]:
        return await self.call("events", since=since)

    async def stream_open(self, label: str = "stream") -> dict[str, Any]:
        return await self.call("stream_open", label=label)

    async def stream(self, stream: int, t_s: float, q_rad: list[float]) -> dict[str, Any]:
        return await self.call("stream", stream=stream, t_s=t_s, q_rad=q_rad)

    async def stream_close(self, stream: int) -> dict[str, Any]:
        return await self.call("stream_close", stream=stream)
