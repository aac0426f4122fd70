"""The daemon's control surface: JSON lines over a Unix stream socket (no network).

Request: one JSON object per line, ``{"cmd": "<name>", "id": <optional>, ...args}``.
Response: one line, ``{"ok": true, ...}`` or ``{"ok": false, "error": "..."}``; an
``id`` in the request is echoed. Malformed input gets an error response, never a
crash; the connection stays open for further requests (except after an over-long
line, which closes it).

The server (command table, socket server) is dragd/server.py; `ControlClient`
here is the synchronous client for the CLI.
"""

from __future__ import annotations

import json
import math
import os
import socket
from collections.abc import Mapping
from typing import Any

__all__ = [
    "DEFAULT_SOCKET_PATH",
    "ControlError",
    "ControlSocketBusy",
    "DaemonUnavailable",
    "DaemonTimeout",
    "ControlClient",
]

DEFAULT_SOCKET_PATH = "/run/dragd/dragd.sock"
MAX_LINE_BYTES = 1 << 20
_ENVELOPE = ("cmd", "id")


class ControlError(Exception):
    """Raise from a handler to answer ``{"ok": false, "error": str(exc)}``."""


class ControlSocketBusy(RuntimeError):
    """Another live server already answers on the socket path."""


class DaemonUnavailable(ConnectionError):
    """No dragd daemon answers on the control socket."""


class DaemonTimeout(DaemonUnavailable):
    """The daemon accepted the connection but did not answer in time."""


def _json_default(obj: Any) -> Any:
    """Encode numpy scalars/arrays, paths, sets and enums in responses."""
    tolist = getattr(obj, "tolist", None)
    if callable(tolist):
        return tolist()
    if isinstance(obj, (set, frozenset, tuple)):
        return list(obj)
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    name = getattr(obj, "name", None)
    if isinstance(name, str) and hasattr(obj, "value"):
        return name
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def _sanitize(obj: Any) -> Any:
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {k: _sanitize(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_sanitize(v) for v in obj]
    return obj


def encode_line(obj: Mapping[str, Any]) -> bytes:
    """One JSON line; NaN/inf become null so every peer can parse it."""
    try:
        text = json.dumps(obj, default=_json_default, allow_nan=False)
    except ValueError:
        text = json.dumps(
            _sanitize(json.loads(json.dumps(obj, default=_json_default))), allow_nan=False
        )
    return text.encode() + b"\n"


# -- client --------------------------------------------------------------------------------


class ControlClient:
    """Synchronous client: one connection per `call`."""

    def __init__(self, path: str | os.PathLike[str] = DEFAULT_SOCKET_PATH, timeout_s: float = 2.0) -> None:
        self.path = os.fspath(path)
        self.timeout_s = timeout_s

    def _unavailable(self, reason: str) -> DaemonUnavailable:
        return DaemonUnavailable(
            f"no dragd daemon answers at {self.path}: {reason}; "
            "start it with 'dragd run' or 'systemctl start dragd'"
        )

    def call(self, cmd: str, **args: Any) -> dict[str, Any]:
        """Send ``{"cmd": cmd, **args}``; return the response dict (``ok`` may be false)."""
        request = {"cmd": cmd, **args}
        data = encode_line(request)
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.settimeout(self.timeout_s)
        try:
            try:
                s.connect(self.path)
            except FileNotFoundError:
                raise self._unavailable("socket file does not exist") from None
            except ConnectionRefusedError:
                raise self._unavailable("connection refused (stale socket file)") from None
            except PermissionError:
                raise self._unavailable(
                    "permission denied (is your user in group 'dragd'?)"
                ) from None
            except TimeoutError:
                raise self._unavailable(f"connect timed out after {self.timeout_s} s") from None
            except OSError as e:
                raise self._unavailable(e.strerror or str(e)) from None
            try:
                s.sendall(data)
                buf = bytearray()
                while not buf.endswith(b"\n"):
                    chunk = s.recv(65536)
                    if not chunk:
                        break
                    buf += chunk
                    if len(buf) > MAX_LINE_BYTES * 16:
                        raise DaemonUnavailable(f"response from {self.path} is too long")
            except TimeoutError:
                raise DaemonTimeout(
                    f"dragd at {self.path} did not answer {cmd!r} within {self.timeout_s} s"
                ) from None
            except OSError as e:
                raise self._unavailable(f"connection lost: {e.strerror or e}") from None
        finally:
            s.close()
        if not buf.strip():
            raise self._unavailable(f"connection closed without an answer to {cmd!r}")
        try:
            response = json.loads(buf)
        except json.JSONDecodeError as e:
            raise DaemonUnavailable(f"unreadable response from {self.path}: {e}") from None
        if not isinstance(response, dict):
            raise DaemonUnavailable(f"unexpected response from {self.path}: {response!r}")
        return response
