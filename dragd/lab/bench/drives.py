"""Benchmarks of the drives' process data and profiles.

``io_cycle_us``: the cycle's process-data path alone (hardware/io.py): every joint's TPDO decoded into the feedback
arrays and every command frame packed, on the configured layout, without a bus (a send that does nothing), so the
figure is the decode/encode cost that the drive profiles could change (A/B against main: docs/PERFORMANCE.md).

``drive_profiles``: every EDS file of ``--eds-dir`` through ``dragd config init --eds``, ``config check`` and, for
the drives that can do torque control, the simulated drive built from that EDS with the daemon beside it: boot,
start, drag, a hand push (drift after release), ``identify run`` of a short plan (docs/DRIVES.md).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from dragd.lab.bench import BenchError, benchmark


class _NullBus:
    """A bus that accepts every frame and sends nothing (the cost of the bus is not this benchmark's)."""

    channel_info = "null"

    def send(self, msg: Any, timeout: float | None = None) -> None:
        pass


@benchmark("io_cycle_us", "us")
def io_cycle_us(opts: dict) -> tuple[float, dict[str, Any]]:
    """Median time of one cycle's process data on the configured layout: every TPDO decoded, every command frame
    packed (no bus)."""
    import struct

    from dragd.config import load_config
    from dragd.daemon.core import bus_layouts
    from dragd.hardware.io import BusIO

    cfg = load_config(opts.get("config"))
    layouts = bus_layouts(cfg)
    buses = {name: _NullBus() for name in layouts}
    n = len(cfg.joints)
    io = BusIO(layouts, buses, [j.node_id for j in cfg.joints], cfg.master.node_id, lambda *a: None)  # type: ignore[arg-type]
    decoders = {name: io.tpdo_decoder(name) for name in layouts}
    rng = np.random.default_rng(3)
    frames = []
    for name, lay in layouts.items():
        for fr in lay.frames:
            if fr.direction == "tpdo":
                size = struct.Struct(fr.slots[0].fmt).size
                frames.append((decoders[name], fr.cob_id, bytes(rng.integers(0, 256, size, dtype=np.uint8))))
    cw = np.full(n, 0x0F, dtype=np.int64)
    counts = rng.integers(-2**20, 2**20, n).astype(np.int64)
    torque = rng.integers(-3000, 3000, n).astype(np.int64)
    cycles = int(opts.get("cycles", 20000))
    times = np.empty(cycles)
    clock = time.perf_counter_ns
    t = 0.0
    for k in range(cycles):
        t0 = clock()
        io.begin_cycle()
        for decode, cob, data in frames:
            decode(cob, data)
        io.end_read()
        io.statuswords_seen()
        io.write(cw, counts, torque, t)
        times[k] = clock() - t0
        t += 1e-3
    if io.feedback.rx_count != n:
        raise BenchError(f"io_cycle_us: {io.feedback.rx_count} of {n} joints decoded: the layout's TPDOs are not "
                         "all position TPDOs")
    med = float(np.median(times[cycles // 10:])) / 1e3
    return med, {"p90_us": round(float(np.percentile(times[cycles // 10:], 90)) / 1e3, 3), "cycles": cycles,
                 "tpdo_frames": len(frames), "buses": {k: v.kind for k, v in layouts.items()}}


# ------------------------------------------------------------------------------------------------ drive_profiles

PUSH_NM = 7.0  # the operator's push on the shoulder (joint 2), as the daemon flow test pushes joint 1
DRIFT_WINDOW_S = 2.0  # after the arm came to rest: how far it creeps in this long


@benchmark("drive_profiles", "per file")
def drive_profiles(opts: dict) -> dict[str, Any]:
    """Each EDS of --eds-dir: config init, config check, and with the simulated drive built from it the boot, drag
    drift after a push and identify run; drives without torque control refused with the reason."""
    from pathlib import Path

    eds_dir = opts.get("eds_dir")
    if eds_dir is None:
        raise BenchError("drive_profiles: give --eds-dir DIR (the vendors' EDS files; docs/DRIVES.md says where they "
                         "are)")
    files = sorted(p for p in Path(eds_dir).iterdir() if p.suffix.lower() == ".eds")
    if not files:
        raise BenchError(f"drive_profiles: no .eds file in {eds_dir}")
    out: dict[str, Any] = {}
    for path in files:
        out[path.name] = _one_drive(path, opts)
    return {"files": out}


def _cli(*args: str, timeout_s: float = 120.0) -> Any:
    import subprocess
    import sys

    return subprocess.run([sys.executable, "-m", "dragd", *args], capture_output=True, text=True, timeout=timeout_s)


def _one_drive(eds: Any, opts: dict) -> dict[str, Any]:
    import json
    import subprocess
    import sys
    import tempfile
    from pathlib import Path

    import yaml

    from dragd.lab.rig import ProcessError, Rig, multicast_group
    from dragd.model import RobotModel

    row: dict[str, Any] = {"config_check": None, "boot": None, "drag_drift_deg": None, "identify": None,
                           "refused_reason": None}
    work = Path(tempfile.mkdtemp(prefix=f"dragd-drive-{eds.stem}-"))
    robot = opts.get("robot") or str(RobotModel.from_urdf("seed_cobot").urdf_path)  # a URDF file: a generated truth
    cfg_path = work / "cfg.yaml"
    init = _cli("config", "init", "--robot", robot, "--eds", str(eds), "--out", str(cfg_path))
    if init.returncode != 0:
        row["config_check"] = f"config init failed: {init.stderr.strip()}"
        return row
    check = _cli("config", "check", "--config", str(cfg_path), "--json")
    try:
        report = json.loads(check.stdout)
    except json.JSONDecodeError:
        row["config_check"] = f"config check failed: {check.stderr.strip()}"
        return row
    errors = [f["text"] for f in report["findings"] if f["level"] == "error"]
    row["config_check"] = "ok" if report["ok"] else errors
    if report["refused"]:
        row["refused_reason"] = "; ".join(report["refused"])
    if not report["ok"]:
        return row
    # the simulated robot: its truth generated from the URDF as config init sized it, every drive built from the EDS
    truth = subprocess.run([sys.executable, "-m", "sim.truth", "--robot", robot], capture_output=True, text=True,
                           timeout=120)
    if truth.returncode != 0:
        row["boot"] = f"no simulator truth for {robot}: {truth.stderr.strip()}"
        return row
    data = yaml.safe_load(truth.stdout)
    cfg = yaml.safe_load(cfg_path.read_text())
    bus_names = [b["name"] for b in cfg["buses"]]
    for tj, cj in zip(data["joints"], cfg["joints"]):
        tj["bus_index"] = bus_names.index(cj.get("bus", bus_names[0]))
    truth_path = work / "truth.yaml"
    truth_path.write_text(yaml.safe_dump(data, sort_keys=False))
    bus = ",".join(f"udp_multicast:{multicast_group(f'{eds.stem}-{k}')}" for k in range(len(bus_names)))
    rig = Rig(f"drive-{eds.stem}", workdir=work, config=cfg_path, sim_config=truth_path, bus=bus,
              sim_args=["--eds", str(eds)])
    try:
        try:
            rig.start_sim(timeout_s=60.0)
        except ProcessError as exc:
            row["boot"] = f"the simulated drive did not start: {exc}"
            return row
        try:
            rig.start_daemon(timeout_s=60.0)
            row["boot"] = "ok"
        except ProcessError as exc:
            row["boot"] = str(exc)
            return row
        row["drag_drift_deg"] = _drag_drift(rig)
        row["identify"] = _identify(rig, work)
    except ProcessError as exc:
        if row["drag_drift_deg"] is None:
            row["drag_drift_deg"] = f"failed: {exc}"
        else:
            row["identify"] = f"failed: {exc}"
    finally:
        rig.close()
    return row


def _drag_drift(rig: Any) -> float:
    """Start, drag, push the shoulder, let go: the largest joint motion [deg] over DRIFT_WINDOW_S after rest."""
    from dragd.lab.rig import ProcessError

    rig.must("start")
    rig.wait_for(lambda: rig.must("status")["mode"] == "hold", 5.0, "hold after start")
    rig.sleep(0.5)
    p = rig.cli("mode", "drag")
    if p.returncode != 0:
        raise ProcessError(f"mode drag refused: {p.stderr.strip()}")
    rig.sleep(0.5)
    before = np.array(rig.sim_call("state")["q_rad"])
    from dragd.config import load_config

    joint = load_config(rig.config).joint_names[1]
    rig.sim_call("operator", scenario={"name": "push", "segments": [
        {"kind": "push", "joint": joint, "torque_Nm": PUSH_NM, "duration_s": 0.6},
        {"kind": "release", "duration_s": 0.0}]})
    rig.sleep(0.7)
    rig.wait_for(lambda: max(abs(v) for v in rig.sim_call("state")["dq_rad_s"]) < 1e-4, 15.0,
                 "the arm to come to rest after the push")
    rig.sleep(0.2)
    rest = np.array(rig.sim_call("state")["q_rad"])
    rig.sleep(DRIFT_WINDOW_S)
    later = np.array(rig.sim_call("state")["q_rad"])
    if float(np.degrees(np.abs(rest - before)).max()) < 0.5:
        raise ProcessError(f"the push did not move the arm ({np.degrees(np.abs(rest - before)).max():.2f}°)")
    status = rig.must("status")
    if status["mode"] != "drag":
        raise ProcessError(f"left drag after the push: {status['mode']}, faults {status['faults']}")
    return round(float(np.degrees(np.abs(later - rest)).max()), 4)


def _identify(rig: Any, work: Any) -> str:
    """``dragd identify run`` of a short plan (the shoulder lifted 0.3 rad and back at two speeds): "ok" or why not."""
    import json

    from dragd.config import load_config
    from dragd.identify import excitation as E
    from dragd.model import RobotModel

    p = rig.cli("mode", "hold")
    if p.returncode != 0:
        return f"mode hold: {p.stderr.strip()}"
    rig.sleep(0.5)
    cfg = load_config(rig.config)
    q0 = np.array(rig.must("status")["q_rad"])
    model = RobotModel.from_config(cfg)
    b = E.PlanBuilder(q0, E.Limits.from_model(model, cfg))
    lo = q0.copy()
    lo[1] += 0.3 if q0[1] + 0.3 < model.position_limits_rad[1][1] - 0.1 else -0.3  # (upper limit of joint 2)
    for v in (0.15, 0.3):
        b.move(lo, speed=v, acceleration=0.8, kind="synchronous", joint=1)
        b.move(q0, speed=v, acceleration=0.8, kind="synchronous", joint=1)
    plan = b.build("drive-profiles")
    pf = work / "plan.npz"
    plan.save(pf)
    out = work / "run.mcap"
    proc = rig.cli("identify", "run", "--plan", str(pf), "--out", str(out), "--no-progress", "--json", timeout_s=180.0)
    if proc.returncode != 0:
        return f"identify run failed: {(proc.stderr or proc.stdout).strip()}"
    res = json.loads(proc.stdout)
    if res.get("faults"):
        return f"identify run faulted: {res['faults']}"
    return "ok"


