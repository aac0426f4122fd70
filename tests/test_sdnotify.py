import os
import socket
import uuid

import pytest

from dragd.daemon import sdnotify

pytestmark = pytest.mark.unit


@pytest.fixture
def systemd_socket(tmp_path, monkeypatch):
    """A datagram socket standing in for systemd's notify socket (path form)."""
    path = str(tmp_path / "notify.sock")
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.bind(path)
    s.settimeout(2.0)
    monkeypatch.setenv("NOTIFY_SOCKET", path)
    yield s
    s.close()


def test_notify_sends_states(systemd_socket):
    assert sdnotify.ready("cycle running") is True
    assert systemd_socket.recv(4096) == b"READY=1\nSTATUS=cycle running"
    assert sdnotify.watchdog_ping() is True
    assert systemd_socket.recv(4096) == b"WATCHDOG=1"
    assert sdnotify.notify("STATUS=x", "EXTEND_TIMEOUT_USEC=5000000") is True
    assert systemd_socket.recv(4096) == b"STATUS=x\nEXTEND_TIMEOUT_USEC=5000000"
    assert sdnotify.stopping() is True
    assert systemd_socket.recv(4096) == b"STOPPING=1"


def test_abstract_socket(monkeypatch):
    name = f"dragd-test-{uuid.uuid4().hex}"
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.bind(b"\0" + name.encode())
    s.settimeout(2.0)
    monkeypatch.setenv("NOTIFY_SOCKET", "@" + name)
    try:
        assert sdnotify.status("booting drives") is True
        assert s.recv(4096) == b"STATUS=booting drives"
    finally:
        s.close()


def test_noop_without_systemd(monkeypatch):
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    assert sdnotify.notify("READY=1") is False
    assert sdnotify.notify_socket_address() is None


def test_send_failure_returns_false(tmp_path, monkeypatch):
    monkeypatch.setenv("NOTIFY_SOCKET", str(tmp_path / "nobody-listens.sock"))
    assert sdnotify.notify("READY=1") is False


def test_invalid_state_rejected():
    with pytest.raises(ValueError, match="KEY=value"):
        sdnotify.notify("READY")
    with pytest.raises(ValueError, match="KEY=value"):
        sdnotify.notify("STATUS=two\nlines")


def test_watchdog_period(monkeypatch):
    monkeypatch.delenv("WATCHDOG_USEC", raising=False)
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    assert sdnotify.watchdog_period_s() is None
    monkeypatch.setenv("WATCHDOG_USEC", "2000000")
    assert sdnotify.watchdog_period_s() == 2.0
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    assert sdnotify.watchdog_period_s() == 2.0
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid() + 1))
    assert sdnotify.watchdog_period_s() is None
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    monkeypatch.setenv("WATCHDOG_USEC", "garbage")
    assert sdnotify.watchdog_period_s() is None
