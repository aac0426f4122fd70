"""``dragd can scan``, ``dragd sdo read|write``, ``dragd nmt`` against the simulated robot's process (docs/TOOLS.md).

Real processes on a private udp_multicast group: the sim alone (the tools act), then with the daemon driving the
bus (the tools refuse, unless --force). The sim and the daemon run on the lockstep clock: alone, the sim answers SDO
and NMT at once without time passing; with the daemon, time runs freely (``Rig.running``) while a tool or ``dragd view``
(wall-paced clients) watches the bus.
"""

import asyncio
import json
import subprocess
import sys
from pathlib import Path

import pytest

from dragd.client import Client
from dragd.lab.rig import Rig

pytestmark = [pytest.mark.lockstep, pytest.mark.slow]  # ~2 min: each CLI process starts in seconds here

REPO = Path(__file__).resolve().parents[1]


def dragd(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "dragd", *args], capture_output=True, text=True, timeout=timeout,
                          cwd=REPO)


def ok_json(*args: str) -> dict:
    p = dragd(*args, "--json")
    assert p.returncode == 0, p.stderr
    return json.loads(p.stdout)


@pytest.fixture(scope="module")
def rig():
    with Rig("cantools") as r:
        r.start_sim()
        yield r


def test_scan_sdo_nmt_against_the_sim(rig):
    bus = ["--bus", rig.bus]
    nodes = ok_json("can", "scan", *bus)["nodes"]
    assert [n["node_id"] for n in nodes] == [1, 2, 3, 4, 5, 6]
    for n in nodes:
        assert n["profile"] == 402 and n["device_type"] & 0xFFFF == 402
        assert n["name"] == "dragd-sim joint drive"
        assert n["serial"] == n["node_id"] and n["product_code"] == 1 and n["revision"] == 0x00010000
        assert n["eds"] == "joint_drive.eds", n  # identity matches the shipped EDS's [DeviceInfo]
        assert not n["errors"], n
    # SDO read with the EDS's type (6041h statusword: UNSIGNED16) and a forced type
    sw = ok_json("sdo", "read", "3", "6041", *bus)
    assert sw["type"] == "u16" and isinstance(sw["value"], int) and len(sw["raw"]) == 4
    ident = ok_json("sdo", "read", "4", "0x1018:4", "--type", "u32", *bus)
    assert ident["value"] == 4
    # SDO write, read back; NMT reset node brings the default back (the drive really reset)
    w = ok_json("sdo", "write", "3", "1017", "250", *bus)
    assert w["written"] and w["raw"] == "fa00"
    assert ok_json("sdo", "read", "3", "1017", *bus)["value"] == 250
    assert ok_json("nmt", "reset", "3", *bus)["sent"] == "000#8103"  # (acted on when received: before the next read)
    assert ok_json("sdo", "read", "3", "1017", *bus)["value"] == 0
    # bad input: one line naming what was expected
    p = dragd("sdo", "read", "3", "zz", *bus)
    assert p.returncode == 2 and "INDEX[:SUB]" in p.stderr and p.stderr.count("\n") == 1
    p = dragd("sdo", "read", "200", "1000", *bus)
    assert p.returncode == 2 and "1..127" in p.stderr
    p = dragd("sdo", "read", "9", "1000", *bus, "--timeout", "0.3")  # no node 9
    assert p.returncode == 1 and "no SDO answer" in p.stderr and p.stderr.count("\n") == 1
    p = dragd("sdo", "write", "3", "6040", "nope", *bus)
    assert p.returncode == 2 and "u16" in p.stderr


def test_tools_refuse_while_the_daemon_drives_the_bus(rig):
    rig.start_daemon()
    try:
        with rig.running():  # the daemon's SYNCs on the bus, as the tools meet a running daemon
            _tools_beside_the_daemon(rig)
    finally:
        rig.daemon.terminate()
        rig.daemon = None


def _tools_beside_the_daemon(rig: Rig) -> None:
    bus = ["--bus", rig.bus]
    for args in (("can", "scan"), ("sdo", "read", "3", "6041"), ("nmt", "stop", "all")):
        p = dragd(*args, *bus)
        assert p.returncode == 1, (args, p.stdout, p.stderr)
        assert "a CANopen master drives it" in p.stderr and "--force" in p.stderr, p.stderr
    # told explicitly: a read beside the daemon
    p = dragd("sdo", "read", "3", "1000", *bus, "--force", "--json")
    assert p.returncode == 0, p.stderr
    assert json.loads(p.stdout)["value"] & 0xFFFF == 402
    assert "acting beside it (--force)" in p.stderr
    assert rig.must("status")["cycles"] > 0  # the daemon ran on

    async def status() -> dict:  # dragd.client (asyncio) against the real daemon
        async with Client(rig.socket) as d:
            return await d.status()

    st = asyncio.run(status())
    assert st["ok"] and st["mode"] in ("idle", "hold", "fault") and st["cycles"] > 0

    # dragd view: the running daemon in Rerun, saved to a recording read back with rerun's own reader
    pytest.importorskip("rerun")
    from rerun.chunk import RrdReader

    rrd = rig.workdir / "live.rrd"
    p = dragd("view", "--seconds", "2", "--save", str(rrd), "--socket", rig.socket, "--json")
    assert p.returncode == 0, p.stderr
    assert json.loads(p.stdout)["polls"] > 20
    chunks = RrdReader(rrd).stream().to_chunks()
    paths = {c.entity_path for c in chunks}
    assert {"/arm/skeleton", "/current/joint2/gravity", "/mode"} <= paths
    assert sum(c.num_rows for c in chunks if c.entity_path == "/current/joint2/measured") > 20
