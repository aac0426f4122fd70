"""python-can's own udp_multicast interface and tools on the simulated robot's bus (docs/VCAN.md, "python-can's tools").

dragd's udp_multicast bus speaks python-can's wire format (a msgpack map per frame) on a host-local socket.
A plain python-can client joins the group on the interface the kernel routes the group to; with the group
routed to the loopback interface (``ip route add 224.0.0.0/4 dev lo``) both sit on ``lo`` and talk both ways.
The test runs in a network namespace of its own (only ``lo``, the route above), so nothing leaves the host:
python-can's ``can.logger`` hears the sim's boot-ups, python-can's ``UdpMulticastBus`` reaches its drives
(SDO upload of 1000h, NMT reset node), and dragd's bus hears python-can's frames.
"""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.rig

REPO = Path(__file__).resolve().parents[1]

SCRIPT = r'''
import json, signal, subprocess, sys, threading, time
from pathlib import Path
import can
from dragd.hardware.bus import open_bus, parse_bus

group, work = sys.argv[1], Path(sys.argv[2])
out = {}
logger_err = open(work / "logger.err", "w")  # (a file: a pipe nobody reads fills and blocks the logger's writes)
logger = subprocess.Popen([sys.executable, "-u", "-m", "can.logger", "-i", "udp_multicast", "-c", group,
                           "-f", str(work / "bus.log")], stdout=subprocess.PIPE, stderr=logger_err, text=True,
                          preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
# (SIGINT ends can.logger: a Python started with SIGINT ignored, as a shell script's background jobs are, never
# raises KeyboardInterrupt, and the logger ran until the guard below)
for line in logger.stdout:  # the logger's bus is up before the sim boots (it says so once it is: a loaded host's
    if line.startswith("Can Logger"):  # python-can can take seconds to import)
        break
threading.Thread(target=logger.stdout.read, daemon=True).start()  # (its pipe never fills while it logs)
sim = subprocess.Popen([sys.executable, "-m", "sim", "run", "--bus", f"udp_multicast:{group}"],
                       stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
try:
    for line in sim.stderr:
        if line.startswith("sim: running"):
            break
    theirs = can.Bus(interface="udp_multicast", channel=group)  # python-can's own UdpMulticastBus
    ours = open_bus(parse_bus(f"udp_multicast:{group}", fd=True))

    def wait(bus, can_id, timeout=3.0):
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            m = bus.recv(0.2)
            if m is not None and m.arbitration_id == can_id:
                return m
        return None

    # SDO upload 1000h:00 (device type) from python-can's bus to node 3
    theirs.send(can.Message(arbitration_id=0x603, data=[0x40, 0x00, 0x10, 0x00, 0, 0, 0, 0], is_extended_id=False))
    r = wait(theirs, 0x583)
    out["sdo"] = None if r is None else list(r.data)
    # NMT reset node 3 from python-can: the boot-up is heard by python-can and by dragd's bus
    theirs.send(can.Message(arbitration_id=0x000, data=[0x81, 3], is_extended_id=False))
    out["nmt_seen_by_dragd"] = wait(ours, 0x000) is not None
    b = wait(theirs, 0x703, 5.0)
    out["bootup_after_reset"] = None if b is None else list(b.data)
    # dragd's bus to python-can's: a frame sent by dragd's bus arrives once at python-can's
    ours.send(can.Message(arbitration_id=0x7E5, data=[0x04], is_extended_id=False))
    got = wait(theirs, 0x7E5)
    out["dragd_to_python_can"] = None if got is None else list(got.data)
    out["dragd_counters"] = ours.counters().__dict__
    theirs.shutdown()
    ours.shutdown()
finally:
    sim.terminate()
    sim.wait(10)
    time.sleep(0.3)
    logger.send_signal(signal.SIGINT)
    logger.wait(60)  # (a guard against a hang, not a clock: the logger flushes its file and exits)
out["log"] = (work / "bus.log").read_text() if (work / "bus.log").exists() else ""
out["logger_stderr"] = (work / "logger.err").read_text()[-2000:]
print(json.dumps(out))
'''


def netns_argv(script: Path, *args: str) -> list[str]:
    return ["unshare", "-n", "sh", "-c",
            'ip link set lo up && ip route add 224.0.0.0/4 dev lo && exec "$0" "$@"', sys.executable, str(script),
            *args]


@pytest.fixture(scope="module")
def netns_ok() -> None:
    if shutil.which("unshare") is None or shutil.which("ip") is None:
        pytest.skip("needs unshare(1) and ip(8) for a private network namespace")
    probe = subprocess.run(["unshare", "-n", "sh", "-c", "ip link set lo up && ip route add 224.0.0.0/4 dev lo"],
                           capture_output=True, text=True)
    if probe.returncode != 0:
        pytest.skip(f"cannot make a network namespace here: {probe.stderr.strip()}")


def test_python_can_tools_and_the_sim_talk_both_ways(netns_ok, tmp_path):
    script = tmp_path / "interop.py"
    script.write_text(SCRIPT)
    env = {"PATH": "/usr/sbin:/usr/bin:/sbin:/bin", "PYTHONPATH": str(REPO)}
    p = subprocess.run(netns_argv(script, "239.74.163.2", str(tmp_path)), capture_output=True, text=True,
                       timeout=120, cwd=REPO, env=env)
    assert p.returncode == 0, p.stderr[-3000:]
    out = json.loads(p.stdout.strip().splitlines()[-1])
    # python-can reached node 3: expedited upload response (43h) of 1000h:00, device profile 402 (CiA 402)
    sdo = out["sdo"]
    assert sdo is not None and sdo[:4] == [0x43, 0x00, 0x10, 0x00], sdo
    assert int.from_bytes(bytes(sdo[4:8]), "little") & 0xFFFF == 402
    assert out["bootup_after_reset"] == [0x00]
    assert out["nmt_seen_by_dragd"]
    assert out["dragd_to_python_can"] == [0x04]
    # python-can's frames carry no sender stamp: dragd passes them through as foreign frames
    assert out["dragd_counters"]["foreign_frames"] >= 1 and out["dragd_counters"]["undecodable"] == 0
    # can.logger (python-can's tool) heard every drive's boot-up (701h..706h, data 00)
    log = out["log"]
    for node in range(1, 7):
        assert f"{0x700 + node:03X}#00" in log, (node, log[:2000])
