"""The control surface of dragd's processes (daemon, simulator): JSON lines over a Unix stream socket; docs/PROTOCOL.md.

`CommandTable` maps command names to functions and rejects unknown or missing fields by checking each function's
signature, so a handler gets validated keyword arguments. `ControlServer` serves any ``handler(request) -> dict``
(sync or async): one JSON object per line in, one line out; malformed input gets an error response, never a crash.
"""

from __future__ import annotations

import asyncio
import errno
import inspect
import json
import logging
import os
import socket
import stat
import threading
import types
import typing
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

from dragd.protocol import _ENVELOPE, MAX_LINE_BYTES, ControlError, ControlSocketBusy, encode_line

log = logging.getLogger(__name__)

Handler = Callable[[dict[str, Any]], "dict[str, Any] | Awaitable[dict[str, Any]]"]


# -- command table -------------------------------------------------------------------------


class CommandTable:
    """``handler`` that dispatches ``cmd`` to registered functions with checked fields.

    >>> table = CommandTable()
    >>> @table.command("status")
    ... def status() -> dict: ...
    ``{"cmd": "status", "verbose": 1}`` -> error naming the unknown field ``verbose``.
    """

    def __init__(self) -> None:
        self._commands: dict[str, tuple[Callable[..., Any], inspect.Signature]] = {}
        self._hints: dict[str, dict[str, Any]] = {}

    def command(self, name: str | None = None) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
        def register(fn: Callable[..., Any]) -> Callable[..., Any]:
            self.add(name or fn.__name__, fn)
            return fn

        return register

    def add(self, name: str, fn: Callable[..., Any]) -> None:
        sig = inspect.signature(fn)
        for p in sig.parameters.values():
            if p.kind in (p.POSITIONAL_ONLY, p.VAR_POSITIONAL):
                raise TypeError(f"command {name!r}: parameters must be keyword-compatible")
            if p.name in _ENVELOPE:
                raise TypeError(f"command {name!r}: parameter name {p.name!r} is reserved")
        self._commands[name] = (fn, sig)

    @property
    def names(self) -> list[str]:
        return sorted(self._commands)

    def describe(self) -> dict[str, list[str]]:
        """Command name -> accepted field names (for a ``help`` command)."""
        return {n: list(sig.parameters) for n, (_fn, sig) in sorted(self._commands.items())}

    async def __call__(self, request: dict[str, Any]) -> dict[str, Any]:
        cmd = request["cmd"]
        entry = self._commands.get(cmd)
        if entry is None:
            raise ControlError(f"unknown cmd {cmd!r}; expected one of: {', '.join(self.names)}")
        fn, sig = entry
        args = {k: v for k, v in request.items() if k not in _ENVELOPE}
        params = sig.parameters
        takes_kwargs = any(p.kind is p.VAR_KEYWORD for p in params.values())
        if not takes_kwargs:
            unknown = sorted(set(args) - set(params))
            if unknown:
                accepted = ", ".join(params) or "no fields"
                raise ControlError(
                    f"unknown field(s) {', '.join(map(repr, unknown))} for cmd {cmd!r}; "
                    f"accepted: {accepted}"
                )
        missing = [
            n
            for n, p in params.items()
            if p.default is p.empty and p.kind is not p.VAR_KEYWORD and n not in args
        ]
        if missing:
            raise ControlError(f"cmd {cmd!r} needs field(s): {', '.join(missing)}")
        hints = self._hints.get(cmd)
        if hints is None:
            try:
                hints = self._hints[cmd] = typing.get_type_hints(fn)
            except Exception:  # an annotation this module cannot resolve: unchecked, as before
                hints = self._hints[cmd] = {}
        for name, value in args.items():
            want = hints.get(name)
            if want is not None and not _conforms(value, want):
                raise ControlError(f"cmd {cmd!r}: field {name!r}: expected {_type_name(want)}, got "
                                   f"{json.dumps(value)[:80]}")
        result = fn(**args)
        if inspect.isawaitable(result):
            result = await result
        return {} if result is None else result


def _conforms(value: Any, want: Any) -> bool:
    """A JSON value against a handler's annotation: booleans are booleans (``"false"`` is no bool), numbers are
    numbers (never booleans), strings strings, lists of the element type; unknown annotations accept anything."""
    if want is Any or want is object:
        return True
    origin = typing.get_origin(want)
    if origin in (typing.Union, types.UnionType):
        return any(_conforms(value, a) for a in typing.get_args(want))
    if want is type(None):
        return value is None
    if want is bool:
        return isinstance(value, bool)
    if want is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if want is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if want is str:
        return isinstance(value, str)
    if origin is list or want is list:
        args = typing.get_args(want)
        return isinstance(value, list) and (not args or all(_conforms(v, args[0]) for v in value))
    if origin is dict or want is dict:
        return isinstance(value, dict)
    return True


def _type_name(want: Any) -> str:
    if typing.get_origin(want) in (typing.Union, types.UnionType):
        return " or ".join(_type_name(a) for a in typing.get_args(want))
    if want is type(None):
        return "null"
    names = {bool: "a boolean (true/false)", int: "an integer", float: "a number", str: "a string"}
    if want in names:
        return names[want]
    if typing.get_origin(want) is list:
        (arg,) = typing.get_args(want) or (Any,)
        return f"a list of {_type_name(arg)}" if arg is not Any else "a list"
    return getattr(want, "__name__", str(want))


def _depth(obj: Any, limit: int) -> int:
    """Nesting depth of a parsed JSON value, iteratively (stops counting beyond ``limit``)."""
    stack, deepest = [(obj, 1)], 0
    while stack:
        o, d = stack.pop()
        deepest = max(deepest, d)
        if deepest > limit:
            return deepest
        if isinstance(o, dict):
            stack.extend((v, d + 1) for v in o.values())
        elif isinstance(o, list):
            stack.extend((v, d + 1) for v in o)
    return deepest


# -- server --------------------------------------------------------------------------------

MAX_DEPTH = 16  # nesting of a request (a trajectory is a list of lists: depth 3)
MAX_CLIENTS = 16  # connections at once; more get an error line and are closed
IDLE_TIMEOUT_S = 600.0  # a connection that sends nothing for this long is closed
REQUEST_READ_S = 10.0  # a request line, once its first byte arrived, must be complete within this


def _probe(path: str, timeout_s: float = 0.5) -> str:
    """'live' when something accepts connections at ``path``, else 'stale'."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(timeout_s)
    try:
        s.connect(path)
        return "live"
    except (ConnectionRefusedError, FileNotFoundError):
        return "stale"
    except TimeoutError:
        return "live"  # backlog full: someone is bound and listening
    except PermissionError:
        return "denied"
    finally:
        s.close()


class ControlServer:
    """asyncio Unix-socket JSON-lines server calling ``handler(request) -> dict``.

    `start` creates the parent directory if needed, removes a stale socket file,
    refuses (ControlSocketBusy) when another live server answers at ``path``, binds
    and sets the socket mode to ``mode`` (0660: owner and group may connect).
    """

    def __init__(self, path: str | os.PathLike[str], handler: Handler, *, mode: int = 0o660) -> None:
        self.path = os.fspath(path)
        self._handler = handler
        self._mode = mode
        self._server: asyncio.AbstractServer | None = None
        self._inode: tuple[int, int] | None = None
        self._clients: set[asyncio.Task[None]] = set()
        self.requests = 0
        self.errors = 0

    async def start(self) -> ControlServer:
        parent = Path(self.path).parent
        try:
            parent.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            raise OSError(
                e.errno, f"cannot create control socket directory {parent}: {e.strerror}"
            ) from e
        if os.path.lexists(self.path):
            st = os.lstat(self.path)
            if not stat.S_ISSOCK(st.st_mode):
                raise FileExistsError(
                    errno.EEXIST,
                    f"{self.path} exists and is not a socket; refusing to replace it "
                    "(remove it or choose another control socket path)",
                )
            probe = await asyncio.to_thread(_probe, self.path)
            if probe == "denied":
                raise PermissionError(
                    errno.EACCES,
                    f"cannot check whether a server answers at {self.path}: permission denied "
                    "(socket owned by another user?)",
                )
            if probe == "live":
                raise ControlSocketBusy(
                    f"another server already answers at {self.path} (is dragd already running? "
                    "check 'systemctl status dragd'); refusing to start a second one"
                )
            os.unlink(self.path)
        self._server = await asyncio.start_unix_server(
            self._serve_client, path=self.path, limit=MAX_LINE_BYTES
        )
        os.chmod(self.path, self._mode)
        st = os.stat(self.path)
        self._inode = (st.st_dev, st.st_ino)
        return self

    async def close(self) -> None:
        """Stop accepting, drop open connections and remove our socket file."""
        if self._server is None:
            return
        self._server.close()
        for task in list(self._clients):
            task.cancel()
        if self._clients:
            await asyncio.gather(*self._clients, return_exceptions=True)
        await self._server.wait_closed()
        self._server = None
        try:
            st = os.stat(self.path)
            if (st.st_dev, st.st_ino) == self._inode:  # do not remove a successor's socket
                os.unlink(self.path)
        except FileNotFoundError:
            pass

    async def __aenter__(self) -> ControlServer:
        return await self.start()

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    async def _serve_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        if len(self._clients) >= MAX_CLIENTS:
            self.errors += 1
            writer.write(encode_line({"ok": False, "error": f"too many control connections (at most {MAX_CLIENTS} "
                                                           "at once); close one and retry"}))
            try:
                await writer.drain()
            finally:
                writer.close()
            return
        self._clients.add(task)
        try:
            while True:
                try:  # (asyncio.timeout, not wait_for: no extra task per request on the cycle's loop)
                    async with asyncio.timeout(IDLE_TIMEOUT_S):
                        first = await reader.readexactly(1)
                except TimeoutError:
                    break  # idle: the slot goes to someone else
                except asyncio.IncompleteReadError:
                    break  # closed
                try:  # a request once begun arrives whole within REQUEST_READ_S (no slot held by a trickle)
                    if first == b"\n":
                        line = first
                    else:
                        async with asyncio.timeout(REQUEST_READ_S):
                            line = first + await reader.readuntil(b"\n")
                except TimeoutError:
                    self.errors += 1
                    writer.write(encode_line({"ok": False, "error": f"request line not complete within "
                                                                   f"{REQUEST_READ_S:g} s; closing"}))
                    await writer.drain()
                    break
                except asyncio.IncompleteReadError as e:
                    if not (first + e.partial).strip():
                        break
                    line = first + e.partial  # last request without trailing newline
                except asyncio.LimitOverrunError:
                    self.errors += 1
                    writer.write(
                        encode_line(
                            {"ok": False, "error": f"request line longer than {MAX_LINE_BYTES} bytes"}
                        )
                    )
                    await writer.drain()
                    break
                if not line.strip():
                    continue
                writer.write(await self._respond(line))
                await writer.drain()
                if reader.at_eof():
                    break
        except (ConnectionResetError, BrokenPipeError):
            pass
        except asyncio.CancelledError:
            pass
        finally:
            self._clients.discard(task)
            writer.close()
            try:
                await writer.wait_closed()
            except (ConnectionError, asyncio.CancelledError):
                pass

    async def _respond(self, line: bytes) -> bytes:
        """The response line to a request line (encoded once: a status is ~3 kB of JSON)."""
        response, cmd = await self._answer(line)
        try:
            return encode_line(response)
        except (TypeError, ValueError) as e:
            self.errors += 1
            return encode_line(self._with_id({"ok": False, "error": f"cmd {cmd!r} result is not JSON: {e}"},
                                             response.get("id")))

    async def _answer(self, line: bytes) -> tuple[dict[str, Any], Any]:
        """The response dict and the request's cmd (None before it is known)."""
        self.requests += 1
        try:
            request = json.loads(line)
        except (UnicodeDecodeError, json.JSONDecodeError) as e:
            self.errors += 1
            return {"ok": False, "error": f"malformed JSON request: {e}; expected one JSON object per line"}, None
        except RecursionError:
            self.errors += 1
            return {"ok": False, "error": f"request nested too deeply (at most {MAX_DEPTH} levels)"}, None
        if _depth(request, MAX_DEPTH) > MAX_DEPTH:
            self.errors += 1
            return {"ok": False, "error": f"request nested too deeply (at most {MAX_DEPTH} levels)"}, None
        if not isinstance(request, dict):
            self.errors += 1
            return {
                "ok": False,
                "error": f"request must be a JSON object like {{\"cmd\": \"status\"}}; got {type(request).__name__}",
            }, None
        rid = request.get("id")
        cmd = request.get("cmd")
        if not isinstance(cmd, str) or not cmd:
            self.errors += 1
            return self._with_id({"ok": False, "error": "request needs a non-empty string field 'cmd'"}, rid), cmd
        try:
            result = self._handler(request)
            if inspect.isawaitable(result):
                result = await result
        except ControlError as e:
            self.errors += 1
            return self._with_id({"ok": False, "error": str(e)}, rid), cmd
        except Exception as e:  # a handler bug must not kill the server
            self.errors += 1
            log.exception("control command %r failed", cmd)
            return self._with_id({"ok": False, "error": f"cmd {cmd!r} failed: {type(e).__name__}: {e}"}, rid), cmd
        if not isinstance(result, dict):
            self.errors += 1
            return self._with_id({"ok": False, "error": f"cmd {cmd!r} returned {type(result).__name__}, expected a "
                                                        "dict"}, rid), cmd
        return self._with_id({"ok": True, **result}, rid), cmd

    @staticmethod
    def _with_id(response: dict[str, Any], rid: Any) -> dict[str, Any]:
        if rid is not None:
            response["id"] = rid
        return response


# -- the server on a thread of its own ------------------------------------------------------------------------------


class ThreadedControlServer:
    """A `ControlServer` on a thread and event loop of its own, so that no client's request delays the loop that
    owns ``handler`` (the daemon's: its 1 kHz cycle runs on it).

    The socket's I/O, the requests' parsing and the responses' encoding run on the server's thread; a request whose
    ``cmd`` is in ``here`` is answered there too (``handler`` called on the server's loop: a command that only reads
    the owner's state and hands data over through a single-writer structure, the daemon's ``stream``), every other
    one is handed to the owner's loop (``handler`` runs there, as on an unthreaded server) and its response comes
    back. Requests of one connection are answered in order, as by `ControlServer`. ``thread_init`` runs first on the
    server's thread (the daemon puts it below the cycle: dragd/realtime.py's ``demote_current_thread``).
    """

    def __init__(self, path: str | os.PathLike[str], handler: Handler, *, here: frozenset[str] | set[str] = frozenset(),
                 mode: int = 0o660, thread_init: Callable[[], object] | None = None) -> None:
        self.path = os.fspath(path)
        self._handler = handler
        self.here = frozenset(here)
        self._thread_init = thread_init
        self._owner: asyncio.AbstractEventLoop | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self.server = ControlServer(path, self._dispatch, mode=mode)
        self.handed_over = 0  # requests answered on the owner's loop
        self.answered_here = 0  # ... on the server's thread

    @property
    def requests(self) -> int:
        return self.server.requests

    @property
    def errors(self) -> int:
        return self.server.errors

    async def _dispatch(self, request: dict[str, Any]) -> dict[str, Any]:
        if request.get("cmd") in self.here:
            self.answered_here += 1
            result = self._handler(request)
            return await result if inspect.isawaitable(result) else result
        self.handed_over += 1
        assert self._owner is not None
        return await asyncio.wrap_future(asyncio.run_coroutine_threadsafe(self._on_owner(request), self._owner))

    async def _on_owner(self, request: dict[str, Any]) -> dict[str, Any]:
        result = self._handler(request)
        return await result if inspect.isawaitable(result) else result

    def _run(self, loop: asyncio.AbstractEventLoop) -> None:
        if self._thread_init is not None:
            self._thread_init()
        asyncio.set_event_loop(loop)
        try:
            loop.run_forever()
        finally:
            loop.run_until_complete(loop.shutdown_asyncgens())
            loop.close()

    async def start(self) -> ThreadedControlServer:
        """Start the thread and the server on it (as `ControlServer.start`: its errors are raised here)."""
        self._owner = asyncio.get_running_loop()
        loop = self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._run, args=(loop,), name="dragd-control", daemon=True)
        self._thread.start()
        try:
            await asyncio.wrap_future(asyncio.run_coroutine_threadsafe(self.server.start(), loop))
        except BaseException:
            self._stop_thread()
            raise
        return self

    async def close(self) -> None:
        """Stop accepting, drop open connections, remove the socket file, end the thread."""
        loop = self._loop
        if loop is None:
            return
        try:
            await asyncio.wrap_future(asyncio.run_coroutine_threadsafe(self.server.close(), loop))
        finally:
            self._stop_thread()

    def _stop_thread(self) -> None:
        loop, thread = self._loop, self._thread
        self._loop = self._thread = None
        if loop is not None and not loop.is_closed():
            loop.call_soon_threadsafe(loop.stop)
        if thread is not None:
            thread.join(5.0)

    async def __aenter__(self) -> ThreadedControlServer:
        return await self.start()

    async def __aexit__(self, *exc: object) -> None:
        await self.close()
