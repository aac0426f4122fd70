"""The vcan selection: simulated drives, the daemon and the test's CANopen client on real SocketCAN.

Collected only when ``tests/vcan`` (or a file in it) is named on the pytest command line -- ``tests/vcan/run``
does that, inside a guest where the host kernel has no CAN. The main suite (``./dev test``, pytest over
``tests/``) never collects it.

Settings (environment, filled in by the harness): ``DRAGD_VCAN_BUS`` (daemon and test client, default
``socketcan:vcan0``), ``DRAGD_VCAN_SIM_BUS`` (simulated drives, default the same), ``DRAGD_VCAN_LOOP_HZ``
(daemon loop, default 100) and ``DRAGD_VCAN_PHYSICS_HZ`` (simulator physics, default 1000).
"""

from __future__ import annotations

import ctypes
import os
import socket
from collections.abc import Callable
from pathlib import Path

import pytest

from dragd.hardware.bus import parse_bus, socketcan_available
from dragd.lab.rig import Rig

HERE = Path(__file__).resolve().parent
BUS = os.environ.get("DRAGD_VCAN_BUS", "socketcan:vcan0")
SIM_BUS = os.environ.get("DRAGD_VCAN_SIM_BUS", BUS)
LOOP_HZ = float(os.environ.get("DRAGD_VCAN_LOOP_HZ", "100"))
PHYSICS_HZ = int(os.environ.get("DRAGD_VCAN_PHYSICS_HZ", "1000"))
START_TIMEOUT_S = 600.0  # a hang guard for a process's start-up in the guest: imports run ~20x slower than on the
# host, and the guest's clock (icount, sleep=off) leaps ahead while it waits idle for the host's 9p reads: a first
# start took 152 s of guest time in one run and more than 180 s in the next (host load 14-18, same code)


def _named_on_command_line(config: pytest.Config) -> bool:
    base = Path(config.invocation_params.dir)
    for arg in config.args:
        path = (base / str(arg).split("::")[0]).resolve()
        if path == HERE or HERE in path.parents:
            return True
    return False


def pytest_ignore_collect(collection_path: Path, config: pytest.Config) -> bool | None:
    if HERE in collection_path.parents and not _named_on_command_line(config):
        return True  # the main suite: tests/vcan runs only under tests/vcan/run
    return None


def channel(bus: str) -> str:
    spec = parse_bus(bus)
    assert spec.interface == "socketcan", f"the vcan selection runs on SocketCAN only, got {bus}"
    return spec.channel


# checks that only make sense on a virtual interface (sending error frames, vcan's own packet counters)
vcan_only = pytest.mark.skipif(not parse_bus(BUS).channel.startswith("vcan"),
                               reason=f"{BUS} is a real CAN interface: only on vcan")


@pytest.fixture(scope="session", autouse=True)
def socketcan_ready() -> None:
    """Every test here needs the real thing: AF_CAN sockets and the channels up, CAN FD capable."""
    for bus in dict.fromkeys((BUS, SIM_BUS)):
        chan = channel(bus)
        ok, reason = socketcan_available(chan)
        assert ok, f"{bus}: {reason} (run the selection with tests/vcan/run)"
        if chan.startswith("vcan"):
            mtu = (Path("/sys/class/net") / chan / "mtu").read_text().strip()
            assert mtu == "72", f"{chan}: MTU {mtu}, CAN FD needs 72 (ip link set {chan} mtu 72)"


def loop_edit(data: dict) -> None:
    """The daemon configuration at the selection's loop rate (TPDO window: half a period)."""
    data["loop"]["rate_Hz"] = LOOP_HZ
    data["loop"]["tpdo_deadline_us"] = int(0.5e6 / LOOP_HZ)


def vcan_config(tmp: Path, name: str, edit: Callable[[dict], None] | None = None) -> Path:
    from daemon_helpers import derived_config

    def both(data: dict) -> None:
        loop_edit(data)
        if edit is not None:
            edit(data)

    return derived_config(tmp, name, both)


def vcan_rig(tag: str, tmp: Path, **kw: object) -> Rig:
    """A Rig whose simulator and daemon talk SocketCAN (the simulator at the selection's physics rate)."""
    kw.setdefault("config", vcan_config(tmp, tag))
    return Rig(tag, workdir=tmp, bus=BUS, sim_args=["--bus", SIM_BUS, "--physics-rate-Hz", str(PHYSICS_HZ)],
               **kw)  # type: ignore[arg-type]


def net_stat(chan: str, name: str) -> int:
    return int((Path("/sys/class/net") / chan / "statistics" / name).read_text())


_SYS_PIDFD_GETFD = 438  # x86_64 (and the generic table): Linux >= 5.6
_CAN_RAW_ERR_FILTER = 2
_CAN_RAW_FD_FRAMES = 5


def process_can_sockets(pid: int) -> list[dict[str, object]]:
    """The AF_CAN sockets another process holds, read from copies of its descriptors (pidfd_getfd; root).

    Each: {"fd", "proto" ("CAN_RAW" or "AF_CAN type N"), "ifname" (bound interface), "fd_frames"
    (CAN_RAW_FD_FRAMES), "err_filter" (CAN_RAW_ERR_FILTER mask)} -- python-can's SocketcanBus(fd=True) is a
    CAN_RAW socket bound to its channel with FD frames on and every error class subscribed.
    """
    libc = ctypes.CDLL(None, use_errno=True)
    pidfd = os.pidfd_open(pid)
    found: list[dict[str, object]] = []
    try:
        for entry in sorted(Path(f"/proc/{pid}/fd").iterdir(), key=lambda p: int(p.name)):
            try:
                if not os.readlink(entry).startswith("socket:"):
                    continue
            except OSError:
                continue
            dup = libc.syscall(_SYS_PIDFD_GETFD, pidfd, int(entry.name), 0)
            if dup < 0:
                err = ctypes.get_errno()
                raise OSError(err, f"pidfd_getfd({pid}, {entry.name}): {os.strerror(err)}")
            sock = socket.socket(fileno=dup)
            try:
                if sock.family != socket.AF_CAN:
                    continue
                item: dict[str, object] = {"fd": int(entry.name)}
                # (AF_CAN leaves SO_PROTOCOL at 0; CAN_RAW is the SOCK_RAW one, CAN_BCM a SOCK_DGRAM)
                if sock.type == socket.SOCK_RAW:
                    item["proto"] = "CAN_RAW"
                    item["fd_frames"] = sock.getsockopt(socket.SOL_CAN_RAW, _CAN_RAW_FD_FRAMES)
                    item["err_filter"] = sock.getsockopt(socket.SOL_CAN_RAW, _CAN_RAW_ERR_FILTER)
                    item["ifname"] = sock.getsockname()[0]
                else:
                    item["proto"] = f"AF_CAN type {int(sock.type)}"
                found.append(item)
            finally:
                sock.close()
    finally:
        os.close(pidfd)
    return found


def assert_python_can_socketcan(pid: int, what: str, chan: str) -> list[dict[str, object]]:
    """``pid`` talks CAN through python-can SocketcanBus(fd=True) sockets on ``chan`` (and nothing else)."""
    socks = process_can_sockets(pid)
    raw = [s for s in socks if s["proto"] == "CAN_RAW"]
    assert raw, f"{what} (pid {pid}) holds no CAN_RAW socket: {socks}"
    for s in raw:
        assert s["ifname"] == chan, f"{what}: CAN_RAW socket bound to {s['ifname']!r}, expected {chan!r}: {socks}"
        assert s["fd_frames"] == 1, f"{what}: CAN FD frames off on {s}"
        assert s["err_filter"] == 0x1FFFFFFF, f"{what}: error frames not subscribed as python-can does: {s}"
    return socks
