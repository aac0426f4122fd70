"""asyncio client of the daemon's control socket (docs/PROTOCOL.md).

::

    import asyncio
    from dragd.client import Client

    async def main():
        async with Client("/run/dragd/dragd.sock") as d:
            print((await d.status())["mode"])
            await d.start()
            async with d.drag():        # a drag lease, renewed in the background (docs/HAND.md)
                await asyncio.sleep(30)  # ... the operator guides the arm; leaving the block holds it

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

from dragd.lease import PACED_TIMEOUT_S
from dragd.protocol import DEFAULT_SOCKET_PATH, MAX_LINE_BYTES, DaemonTimeout, DaemonUnavailable, encode_line

__all__ = ["Client", "CommandError", "DaemonUnavailable", "DaemonTimeout", "DragLease"]


async def _cancelled(task: asyncio.Task | None) -> None:
    """Cancel ``task`` (if any) and wait until it has ended, whatever it ended with."""
    if task is None:
        return
    task.cancel()
    try:
        await task
    except (asyncio.CancelledError, Exception):  # noqa: BLE001
        pass


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
        await _cancelled(self._task)
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

    async def mode(self, mode: str, **args: Any) -> dict[str, Any]:
        return await self.call("mode", mode=mode, **args)

    async def lease(self, action: str, **args: Any) -> dict[str, Any]:
        """The drag lease: ``open`` (holder, period_s), ``renew``/``close`` (lease), ``status``."""
        return await self.call("lease", action=action, **args)

    def drag(self, holder: str = "dragd.client", period_s: float | None = None, accept: bool = False) -> DragLease:
        """``async with client.drag() as lease:`` the arm drags while the block runs: a lease is opened, drag
        requested with it and the lease renewed every third of its period; leaving the block closes it (the arm
        holds). ``lease.ended`` is set when drag ended otherwise (``lease.reason``)."""
        return DragLease(self, holder, period_s, accept)

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


class DragLease:
    """A drag lease held by an asyncio client (``Client.drag``); see docs/HAND.md."""

    def __init__(self, client: Client, holder: str, period_s: float | None, accept: bool) -> None:
        self.client, self.holder, self.requested_period_s, self.accept = client, holder, period_s, accept
        self.lease = 0
        self.period_s = 0.0
        self.renewals = 0
        self.reason: str | None = None  # why drag (or the lease) ended, when it ended before the block did
        self.ended = asyncio.Event()
        self._task: asyncio.Task[None] | None = None

    async def __aenter__(self) -> DragLease:
        kw: dict[str, Any] = {"holder": self.holder}
        if self.requested_period_s is not None:
            kw["period_s"] = self.requested_period_s
        ans = await self.client.lease("open", **kw)
        self.lease, self.period_s = int(ans["lease"]), float(ans["period_s"])
        try:
            await self.client.mode("drag", lease=self.lease, **({"accept": True} if self.accept else {}))
        except BaseException:
            await self._close()
            raise
        self._task = asyncio.get_running_loop().create_task(self._renew())
        return self

    async def __aexit__(self, *exc: object) -> None:
        await _cancelled(self._task)
        await self._close()

    async def _close(self) -> None:
        try:
            await self.client.lease("close", lease=self.lease)
        except (CommandError, DaemonUnavailable):
            pass  # lapsed or gone: nothing left to close

    async def _renew(self) -> None:
        """Renew paced: the daemon answers when the next renewal is due on its clock (docs/HAND.md); renew again. On
        a connection of its own (the daemon answers one request of a connection at a time)."""
        keep = Client(self.client.path, self.client.timeout_s)
        try:
            await self._renew_on(keep)
        finally:
            await keep.close()

    async def _renew_on(self, keep: Client) -> None:
        while True:
            try:
                ans = await keep.call("lease", timeout_s=PACED_TIMEOUT_S, action="renew", lease=self.lease, paced=True)
            except (CommandError, DaemonUnavailable) as exc:
                self.reason = str(exc)
                self.ended.set()
                return
            self.renewals += 1
            if not ans.get("drag") and ans.get("require") != "both":
                st = await self.client.status()
                self.reason = ((st.get("drag") or {}).get("last_drag_end") or {}).get("reason") or \
                    f"the arm left drag ({ans.get('mode')})"
                self.ended.set()
                return
