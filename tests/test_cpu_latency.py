"""The PM QoS request on every CPU's wake-up latency (dragd/realtime.py ``CpuLatencyRequest``, config
``loop.cpu_latency_us``): held while its descriptor is open, withdrawn on close and when the process ends; where it
cannot be made, it says why instead of raising."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from dragd.config import ConfigError, load_config
from dragd.realtime import CPU_LATENCY_DEVICE, CpuLatencyRequest

ROOT = Path(__file__).resolve().parents[1]

writable = pytest.mark.skipif(not os.access(CPU_LATENCY_DEVICE, os.W_OK),
                              reason=f"{CPU_LATENCY_DEVICE} is not writable here (root or the unit's group grants it)")


def _current_us() -> int:
    """The latency the kernel holds every CPU to now (the strictest request of all processes)."""
    with open(CPU_LATENCY_DEVICE, "rb") as fh:
        return int.from_bytes(fh.read(4), sys.byteorder, signed=True)


@writable
@pytest.mark.unit
def test_a_request_holds_every_cpu_to_its_latency_until_it_is_closed() -> None:
    before = _current_us()
    req = CpuLatencyRequest(3)
    try:
        assert req.held and req.info == {"requested_us": 3, "applied": True, "reason": None}
        assert req.effective_us() is not None and req.effective_us() <= 3
        assert _current_us() <= 3  # seen by every reader of the device, not only through our descriptor
    finally:
        req.close()
    assert not req.held and req.effective_us() is None
    assert req.status() == {"requested_us": 3, "applied": False, "reason": "withdrawn", "effective_us": None}
    if before > 3:  # (another process may hold the CPUs at 3 µs or less itself)
        assert _current_us() == before, "close did not withdraw the request"
    req.close()  # (idempotent)


@writable
@pytest.mark.unit
def test_a_process_that_ends_without_closing_leaves_no_request_behind() -> None:
    """The kernel withdraws a request with its descriptor: a daemon killed with SIGKILL cannot pin the CPUs."""
    before = _current_us()
    if before <= 1:
        pytest.skip(f"another process holds the CPUs to {before} µs: a withdrawal of ours could not be seen")
    child = subprocess.run([sys.executable, "-c", (
        "import os, sys\nfrom dragd.realtime import CpuLatencyRequest\nr = CpuLatencyRequest(1)\n"
        "print(r.effective_us(), flush=True)\nos._exit(0)  # no close, no finaliser")],
        capture_output=True, text=True, timeout=60)
    assert child.returncode == 0, child.stderr
    assert int(child.stdout) <= 1  # held while the child ran
    assert _current_us() > 1, "the request outlived its process"


@pytest.mark.unit
def test_a_request_that_cannot_be_made_says_why(tmp_path) -> None:
    missing = CpuLatencyRequest(0, str(tmp_path / "no_such_device"))
    assert not missing.held and missing.effective_us() is None
    assert missing.info["applied"] is False and "no_such_device" in missing.info["reason"]
    assert "No such file" in missing.info["reason"] and "systemd/dragd-cpu-latency.conf" in missing.info["reason"]
    directory = CpuLatencyRequest(0, str(tmp_path))
    assert not directory.held and str(tmp_path) in directory.info["reason"]
    with pytest.raises(ValueError, match="expected 0..2000000000"):
        CpuLatencyRequest(-1)


@pytest.mark.unit
def test_the_configured_latency_is_checked(tmp_path) -> None:
    data = yaml.safe_load((ROOT / "config" / "default.yaml").read_text())
    cfg = tmp_path / "bad.yaml"
    data.setdefault("loop", {})["cpu_latency_us"] = -5
    cfg.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError) as err:
        load_config(cfg)
    assert "cpu_latency_us" in str(err.value) and str(cfg) in str(err.value)
    data["loop"]["cpu_latency_us"] = None
    cfg.write_text(yaml.safe_dump(data))
    assert load_config(cfg).loop.cpu_latency_us is None
    assert load_config(ROOT / "config" / "default.yaml").loop.cpu_latency_us is None  # opt-in


@writable
@pytest.mark.rig
def test_a_daemon_that_asks_for_it_holds_the_request_while_it_runs(tmp_path) -> None:
    """``loop.cpu_latency_us: 0`` as deployed: the status shows the request held (every CPU at 0 µs); once the
    daemon has stopped the request is gone."""
    from dragd.lab.rig import Rig

    before = _current_us()
    data = yaml.safe_load((ROOT / "config" / "default.yaml").read_text())
    data["loop"]["cpu_latency_us"] = 0
    cfg = tmp_path / "qos.yaml"
    cfg.write_text(yaml.safe_dump(data))
    with Rig("qos", workdir=tmp_path / "rig", config=cfg, as_deployed=True) as rig:
        rig.start_sim()
        rig.start_daemon()
        status = rig.must("status")
        if not str(status["scheduler"]).startswith("SCHED_FIFO"):
            pytest.skip(f"no real-time priority here ({status['scheduler']}): the request goes with it")
        assert status["cpu_latency"] == {"requested_us": 0, "applied": True, "reason": None, "effective_us": 0}
        assert _current_us() == 0
        codes = rig.close()
    assert codes["dragd"] == 0, codes
    if before > 0:  # (another process may hold the CPUs at 0 itself)
        assert _current_us() == before, "the daemon's request outlived it"


@pytest.mark.rig
def test_a_daemon_without_a_realtime_priority_says_it_did_not_apply_the_latency(tmp_path) -> None:
    """The request goes with a real-time priority: asked for without one, it is not made, and status and log say
    why (never silently ignored)."""
    from dragd.lab.rig import Rig

    data = yaml.safe_load((ROOT / "config" / "default.yaml").read_text())
    data["loop"]["cpu_latency_us"] = 0
    cfg = tmp_path / "qos.yaml"
    cfg.write_text(yaml.safe_dump(data))
    with Rig("qos-other", workdir=tmp_path / "rig", config=cfg) as rig:
        rig.start_sim()
        rig.start_daemon()
        status = rig.must("status")
        assert status["scheduler"] == "SCHED_OTHER", status["scheduler"]
        qos = status["cpu_latency"]
        assert qos["requested_us"] == 0 and qos["applied"] is False and qos["effective_us"] is None, qos
        assert "real-time priority" in qos["reason"], qos
        assert "loop.cpu_latency_us 0 not applied" in rig.daemon.tail(), rig.daemon.tail()
