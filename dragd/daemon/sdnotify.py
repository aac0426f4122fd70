"""systemd ``sd_notify`` without dependencies (READY / WATCHDOG / STATUS / STOPPING).

Every function is a no-op returning False/None when the process was not started by
systemd with ``Type=notify`` (no ``$NOTIFY_SOCKET``). Sending never raises: a failed
send returns False. Not for the 1 kHz cycle (a syscall per call); the daemon pings
the watchdog from a slower task at half of `watchdog_period_s`.
"""

from __future__ import annotations

import os
import socket

__all__ = [
    "notify",
    "ready",
    "stopping",
    "status",
    "watchdog_ping",
    "watchdog_period_s",
    "notify_socket_address",
]

_sock: socket.socket | None = None


def notify_socket_address() -> str | bytes | None:
    """Address from ``$NOTIFY_SOCKET`` (abstract ``@name`` -> ``b"\\0name"``), or None."""
    addr = os.environ.get("NOTIFY_SOCKET")
    if not addr:
        return None
    if addr.startswith("@"):
        return b"\0" + addr[1:].encode()
    if addr.startswith("/"):
        return addr
    return None  # e.g. "vsock:..." (systemd >= 253 VMs): not supported here


def notify(*states: str) -> bool:
    """Send ``states`` (e.g. ``"READY=1"``, ``"STATUS=..."``) to systemd; True if sent."""
    if not states:
        raise ValueError("notify() needs at least one state such as 'READY=1'")
    for s in states:
        if "=" not in s or "\n" in s:
            raise ValueError(f"sd_notify state must be one 'KEY=value' line; got {s!r}")
    addr = notify_socket_address()
    if addr is None:
        return False
    global _sock
    try:
        if _sock is None:
            _sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
        _sock.sendto("\n".join(states).encode(), addr)
        return True
    except OSError:
        if _sock is not None:
            _sock.close()
            _sock = None
        return False


def _status(text: str | None) -> tuple[str, ...]:
    return (f"STATUS={text}",) if text else ()


def ready(status_text: str | None = None) -> bool:
    """``READY=1`` (plus ``STATUS=``) once the daemon serves requests."""
    return notify("READY=1", *_status(status_text))


def stopping(status_text: str | None = None) -> bool:
    """``STOPPING=1`` at the start of an orderly shutdown."""
    return notify("STOPPING=1", *_status(status_text))


def status(text: str) -> bool:
    """Free-form status line shown by ``systemctl status``."""
    return notify(f"STATUS={text}")


def watchdog_ping() -> bool:
    """``WATCHDOG=1`` keep-alive."""
    return notify("WATCHDOG=1")


def watchdog_period_s() -> float | None:
    """``WatchdogSec=`` of the unit in seconds, or None when no watchdog applies to us.

    Reads ``$WATCHDOG_USEC``; honours ``$WATCHDOG_PID`` (the watchdog is for another
    process when it names a different PID). Ping at half this period.
    """
    usec = os.environ.get("WATCHDOG_USEC")
    if not usec:
        return None
    pid = os.environ.get("WATCHDOG_PID")
    if pid:
        try:
            if int(pid) != os.getpid():
                return None
        except ValueError:
            return None
    try:
        value = int(usec)
    except ValueError:
        return None
    return value / 1e6 if value > 0 else None
