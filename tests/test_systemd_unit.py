"""The systemd unit: key settings parsed from the file, plus systemd's own checks."""

import shutil
import subprocess
from pathlib import Path

import pytest

pytestmark = pytest.mark.unit

ROOT = Path(__file__).resolve().parents[1]
UNIT = ROOT / "systemd" / "dragd.service"
SYSUSERS = ROOT / "systemd" / "dragd.sysusers.conf"
TMPFILES = ROOT / "systemd" / "dragd.tmpfiles.conf"


def parse_unit(text: str) -> dict[str, dict[str, list[str]]]:
    """systemd unit syntax: [Section], Key=Value (repeatable), #/; comments, '\\' continuation."""
    sections: dict[str, dict[str, list[str]]] = {}
    current = None
    pending = ""
    for raw in text.splitlines():
        line = pending + raw.strip()
        pending = ""
        if line.endswith("\\"):
            pending = line[:-1] + " "
            continue
        if not line or line[0] in "#;":
            continue
        if line.startswith("[") and line.endswith("]"):
            current = sections.setdefault(line[1:-1], {})
            continue
        assert current is not None, f"key outside a section: {line!r}"
        key, sep, value = line.partition("=")
        assert sep, f"not a Key=Value line: {line!r}"
        current.setdefault(key.strip(), []).append(value.strip())
    return sections


@pytest.fixture(scope="module")
def unit():
    return parse_unit(UNIT.read_text())


def one(section: dict, key: str) -> str:
    assert key in section, f"{key}= missing"
    return section[key][-1]


def test_service_type_watchdog_restart(unit):
    s = unit["Service"]
    assert one(s, "Type") == "notify"
    assert one(s, "NotifyAccess") == "main"
    assert one(s, "WatchdogSec") == "2s"
    assert one(s, "Restart") == "on-failure"
    assert one(s, "KillSignal") == "SIGTERM"
    # the daemon's longest orderly stop (teach program write 15 s + telemetry close 10 s + ramp) fits in it
    assert one(s, "TimeoutStopSec").endswith("s") and int(one(s, "TimeoutStopSec")[:-1]) >= 15 + 10 + 1
    assert "StartLimitIntervalSec" in unit["Unit"]  # belongs to [Unit], not [Service]


def test_exec_start(unit):
    assert one(unit["Service"], "ExecStart") == (
        "/opt/dragd/.venv/bin/dragd run --config /etc/dragd/dragd.yaml --realtime-priority 70 "
        "--telemetry /var/lib/dragd/telemetry.mcap"
    )


def test_user_directories_and_socket_dir(unit):
    s = unit["Service"]
    assert one(s, "User") == "dragd" and one(s, "Group") == "dragd"
    assert one(s, "RuntimeDirectory") == "dragd"  # /run/dragd/dragd.sock lives here
    assert one(s, "RuntimeDirectoryMode") == "0750"
    assert one(s, "StateDirectory") == "dragd"
    assert "/var/lib/dragd" in one(s, "ReadWritePaths").split()


def test_realtime_limits(unit):
    s = unit["Service"]
    assert int(one(s, "LimitRTPRIO")) >= 1
    assert one(s, "LimitMEMLOCK") == "infinity"
    assert one(s, "RestrictRealtime") == "no"
    # the cycle thread gets FIFO from set_realtime(); not the whole process
    assert "CPUSchedulingPolicy" not in s
    prio = int(one(s, "ExecStart").split("--realtime-priority ")[1].split()[0])
    assert 1 <= prio <= int(one(s, "LimitRTPRIO"))  # what the daemon asks for is within what the unit allows


def test_hardening(unit):
    s = unit["Service"]
    assert one(s, "NoNewPrivileges") == "yes"
    assert one(s, "ProtectSystem") == "strict"
    assert one(s, "ProtectHome") == "yes"
    assert one(s, "PrivateTmp") == "yes"
    families = set(one(s, "RestrictAddressFamilies").split())
    assert families == {"AF_UNIX", "AF_CAN", "AF_NETLINK"}  # a production arm: SocketCAN, no IP
    lab = parse_unit((ROOT / "systemd" / "dragd-lab-udp.conf").read_text())
    assert lab == {"Service": {"RestrictAddressFamilies": ["AF_INET"]}}  # a lab's drop-in adds IP (udp_multicast)
    assert one(s, "CapabilityBoundingSet") == ""
    assert one(s, "PrivateDevices") == "yes"  # SocketCAN needs no device node
    # the PM QoS drop-in (loop.cpu_latency_us) lets one device through, under the device cgroup instead
    qos = parse_unit((ROOT / "systemd" / "dragd-cpu-latency.conf").read_text())
    assert qos == {"Service": {"PrivateDevices": ["no"], "DevicePolicy": ["closed"],
                               "DeviceAllow": ["/dev/cpu_dma_latency rw"]}}
    rules = [line for line in (ROOT / "systemd" / "70-dragd-cpu-latency.rules").read_text().splitlines()
             if line and not line.startswith("#")]
    assert rules == ['KERNEL=="cpu_dma_latency", SUBSYSTEM=="misc", GROUP="dragd", MODE="0660"']  # group dragd writes
    from dragd.realtime import CPU_LATENCY_DEVICE

    assert CPU_LATENCY_DEVICE == "/dev/cpu_dma_latency"


def test_bound_to_the_can_device(unit):
    u = unit["Unit"]
    assert "sys-subsystem-net-devices-can0.device" in one(u, "BindsTo").split()
    assert "sys-subsystem-net-devices-can0.device" in " ".join(u["After"]).split()


def test_shutdown_bounds_in_the_code_match_the_unit():
    core = (ROOT / "dragd" / "daemon" / "core.py").read_text()
    assert "asyncio.wait_for(self.teaching.stop(), 15.0)" in core  # the 15 s the unit's stop timeout counts on


def test_install_section(unit):
    assert one(unit["Install"], "WantedBy") == "multi-user.target"


def test_sysusers_and_tmpfiles_content():
    users = [line.split() for line in SYSUSERS.read_text().splitlines() if line and not line.startswith("#")]
    assert users[0][:3] == ["u", "dragd", "-"]
    tmp = [line.split() for line in TMPFILES.read_text().splitlines() if line and not line.startswith("#")]
    assert ["d", "/var/lib/dragd", "0750", "dragd", "dragd", "-"] in tmp
    from dragd.config import ControlConfig

    spool = ControlConfig().spool_dir  # the daemon's default, made group-writable (setgid) for operators
    assert ["d", spool, "2770", "dragd", "dragd", "1d"] in tmp


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
def test_systemd_analyze_verify(tmp_path):
    # verify insists that ExecStart's binary exists; /opt/dragd is not installed on a
    # development machine, so check a copy whose ExecStart points at an existing file.
    exe = shutil.which("true") or "/bin/true"
    text = UNIT.read_text().replace("ExecStart=/opt/dragd/.venv/bin/dragd", f"ExecStart={exe}")
    copy = tmp_path / "dragd.service"
    copy.write_text(text)
    out = subprocess.run(
        ["systemd-analyze", "verify", str(copy)], capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 0, out.stdout + out.stderr
    assert "dragd.service" not in out.stderr, out.stderr  # no warnings about our unit


@pytest.mark.skipif(shutil.which("systemd-sysusers") is None, reason="systemd-sysusers not installed")
def test_sysusers_and_tmpfiles_apply_to_a_scratch_root(tmp_path):
    (tmp_path / "etc").mkdir()
    for src, sub in ((SYSUSERS, "sysusers.d"), (TMPFILES, "tmpfiles.d")):
        d = tmp_path / "usr" / "lib" / sub
        d.mkdir(parents=True)
        shutil.copy(src, d / "dragd.conf")
    out = subprocess.run(
        ["systemd-sysusers", f"--root={tmp_path}", "dragd.conf"],
        capture_output=True, text=True, timeout=60,
    )
    assert out.returncode == 0, out.stderr
    passwd = (tmp_path / "etc" / "passwd").read_text()
    assert passwd.startswith("dragd:x:") and ":/var/lib/dragd:" in passwd
    if shutil.which("systemd-tmpfiles") is None:
        return
    out = subprocess.run(
        ["systemd-tmpfiles", f"--root={tmp_path}", "--create", "dragd.conf"],
        capture_output=True, text=True, timeout=60,
    )
    assert out.returncode == 0, out.stderr
    st = (tmp_path / "var" / "lib" / "dragd").stat()
    assert oct(st.st_mode & 0o777) == "0o750"


# -- the ROS 2 bridge's unit (systemd/dragd-ros2.service) -----------------------------------------------------------

ROS2_UNIT = ROOT / "systemd" / "dragd-ros2.service"
# the daemon's hardening the bridge's unit keeps as it is (RestrictRealtime and RestrictAddressFamilies differ, below)
SAME_HARDENING = ("NoNewPrivileges", "ProtectSystem", "ProtectHome", "PrivateTmp", "PrivateDevices",
                  "ProtectKernelTunables", "ProtectKernelModules", "ProtectKernelLogs", "ProtectControlGroups",
                  "ProtectClock", "ProtectHostname", "ProtectProc", "RestrictNamespaces", "RestrictSUIDSGID",
                  "LockPersonality", "MemoryDenyWriteExecute", "SystemCallArchitectures", "SystemCallFilter",
                  "SystemCallErrorNumber", "CapabilityBoundingSet", "AmbientCapabilities", "User", "Group", "UMask")


@pytest.fixture(scope="module")
def ros2_unit():
    return parse_unit(ROS2_UNIT.read_text())


def test_ros2_unit_after_the_daemon_restarting_on_failure(ros2_unit, unit):
    u, s = ros2_unit["Unit"], ros2_unit["Service"]
    assert "dragd.service" in " ".join(u["After"]).split() and "dragd.service" in " ".join(u["Wants"]).split()
    assert "Requires" not in u and "BindsTo" not in u  # it reconnects to a restarted daemon by itself
    assert one(s, "Restart") == "on-failure" and one(s, "KillSignal") == "SIGTERM"
    argv = one(s, "ExecStart").split()
    assert argv[:2] == ["/opt/dragd/.venv/bin/dragd", "ros2"]  # the daemon's venv
    # the daemon's socket, in the directory the daemon's unit creates (and the bridge's does not own)
    assert argv[argv.index("--socket") + 1] == "/run/dragd/dragd.sock"
    assert one(unit["Service"], "RuntimeDirectory") == "dragd" and "RuntimeDirectory" not in s
    from dragd.ros2.bridge import SHUTDOWN_GUARD_S

    assert int(one(s, "TimeoutStopSec")[:-1]) > SHUTDOWN_GUARD_S  # the bridge's own guard ends it first
    assert one(ros2_unit["Install"], "WantedBy") == "multi-user.target"


def test_ros2_unit_has_the_daemons_hardening(ros2_unit, unit):
    s, d = ros2_unit["Service"], unit["Service"]
    for key in SAME_HARDENING:
        assert s.get(key) == d.get(key), (key, s.get(key), d.get(key))
    assert one(s, "RestrictRealtime") == "yes"  # no real-time scheduling for the bridge
    assert set(one(s, "RestrictAddressFamilies").split()) == {"AF_UNIX", "AF_INET", "AF_INET6", "AF_NETLINK"}  # DDS
    # ROS writes its logs and home where ProtectSystem=strict lets it: the unit's own directories
    env = dict(kv.split("=", 1) for line in s["Environment"] for kv in line.split())
    assert env["ROS_LOG_DIR"] == "/var/log/" + one(s, "LogsDirectory")
    assert env["ROS_HOME"] == "/var/lib/" + one(s, "StateDirectory")


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
def test_ros2_unit_systemd_analyze_verify(tmp_path):
    exe = shutil.which("true") or "/bin/true"
    copy = tmp_path / "dragd-ros2.service"
    copy.write_text(ROS2_UNIT.read_text().replace("ExecStart=/opt/dragd/.venv/bin/dragd", f"ExecStart={exe}"))
    out = subprocess.run(["systemd-analyze", "verify", str(copy)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "dragd-ros2.service" not in out.stderr, out.stderr  # no warnings about our unit
