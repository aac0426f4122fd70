"""Benchmarks of the drives' process data and profiles.

``io_cycle_us``: the cycle's process-data path alone (hardware/io.py): every joint's TPDO decoded into the feedback
arrays and every command frame packed, on the configured layout, without a bus (a send that does nothing), so the
figure is the decode/encode cost that the drive profiles could change (A/B against main: docs/PERFORMANCE.md).

``drive_profiles``: every EDS file of ``--eds-dir`` through ``dragd config init --eds``, ``config check`` and, for
the drives that can do torque control, the simulated drive built from that EDS with the daemon beside it: boot,
start, drag, a hand push (drift after release), ``identify run`` of a short plan (docs/DRIVES.md). On the lockstep
clock (``--clock wall``: real time, as deployed): what it measures is the drive profile's behaviour, which a loaded
machine's stalled wall clock must not decide.
"""

from __future__ import annotations

import time
from typing import Any, cast

import can
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
    buses = cast(dict[str, can.BusABC], {name: _NullBus() for name in layouts})  # duck-typed: BusIO only sends
    n = len(cfg.joints)
    io = BusIO(layouts, buses, [j.node_id for j in cfg.joints], cfg.master.node_id, lambda *a: None)
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

HAND_STEP_RAD = 0.15  # the operator's hand moves every joint by this much (the third the other way)
HAND_MAX_LOAD_NM = 25.0  # ... pulling with at most this torque per joint (the demo's hand)
DRIFT_WINDOW_S = 2.0  # after the arm came to rest: how far it creeps in this long


@benchmark("drive_profiles", "per file")
def drive_profiles(opts: dict) -> dict[str, Any]:
    """Each EDS of --eds-dir: config init, config check, and with the simulated drive built from it the boot, drag
    drift after a push and identify run; drives without torque control refused with the reason."""
    from pathlib import Path

    eds_dir = opts.get("eds_dir")
    if eds_dir is None and "drive_profiles" not in opts.get("selected", ["drive_profiles"]):  # `dragd bench` (all)
        return {"skipped": "the vendors' EDS files are not given (--eds-dir DIR; docs/DRIVES.md says where they are)"}
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
    # the simulated robot's truth, generated from the URDF as config init sized it (bus per joint as configured)
    truth_path = work / "truth.yaml"
    err = _truth(robot, cfg_path, truth_path)
    if err is not None:
        row["boot"] = err
        return row
    row["datasheet"] = _datasheet(eds, cfg_path, truth_path)  # what the EDS cannot say, from the drive's manual
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
    cfg = yaml.safe_load(cfg_path.read_text())
    bus_names = [b["name"] for b in cfg["buses"]]
    bus = ",".join(f"udp_multicast:{multicast_group(f'{eds.stem}-{k}')}" for k in range(len(bus_names)))
    lockstep = opts.get("clock", "lockstep") == "lockstep"
    rig = Rig(f"drive-{eds.stem}", workdir=work, config=cfg_path, sim_config=truth_path, bus=bus,
              sim_args=["--eds", str(eds)], lockstep=lockstep,
              as_deployed=not lockstep)  # wall: SCHED_FIFO 70 / 60 where permitted, as deployed
    try:
        try:
            rig.start_sim()
        except ProcessError as exc:
            row["boot"] = f"the simulated drive did not start: {exc}"
            return row
        try:
            rig.start_daemon()
            row["boot"] = "ok"
        except ProcessError as exc:
            row["boot"] = str(exc)
            return row
        try:
            row["drag_drift_deg"] = _drag_drift(rig)
            row["identify"] = _identify(rig, work)
        finally:  # the daemon's longest stalls (a fault from a missed deadline is the machine's or the daemon's)
            if not lockstep:
                eps = rig.call("missed_ticks").get("episodes") or []
                row["longest_missed_ticks"] = sorted((int(n) for _, n in eps), reverse=True)[:3]
        st = rig.must("status")
        row["loop"] = {k: st.get(k) for k in ("cycles", "missed_cycles", "late_tpdo_cycles", "feedback_holds",
                                              "period_p99_us", "bus_load_pct")}
        row["clock"] = "lockstep" if lockstep else "wall"
    except ProcessError as exc:
        if row["drag_drift_deg"] is None:
            row["drag_drift_deg"] = f"failed: {exc}"
        else:
            row["identify"] = f"failed: {exc}"
    finally:
        rig.close()
    return row


def _truth(robot: str, cfg_path: Any, truth_path: Any) -> str | None:
    """The simulator's truth for ``robot`` (``python -m sim.truth``: drives sized as config init sizes them), each
    joint on the bus the configuration puts it on; None, or why not."""
    import subprocess
    import sys

    import yaml

    proc = subprocess.run([sys.executable, "-m", "sim.truth", "--robot", robot], capture_output=True, text=True,
                          timeout=120)
    if proc.returncode != 0:
        return f"no simulator truth for {robot}: {proc.stderr.strip()}"
    data = yaml.safe_load(proc.stdout)
    cfg = yaml.safe_load(cfg_path.read_text())
    names = [b["name"] for b in cfg["buses"]]
    for tj, cj in zip(data["joints"], cfg["joints"], strict=True):
        tj["bus_index"] = names.index(cj.get("bus", names[0]))
    truth_path.write_text(yaml.safe_dump(data, sort_keys=False))
    return None


def _datasheet(eds: Any, cfg_path: Any, truth_path: Any) -> dict[str, Any]:
    """The integrator's step after ``config init`` (docs/DRIVES.md step 4): what the EDS cannot say, set from the
    drive's documentation — for a simulated drive its datasheet, ``python -m sim drives --eds FILE --json``: the
    rated current where the drive keeps it in no object dragd reads, the object and unit of the rated current and
    torque. Returns what was set (nothing for a drive whose EDS says it all)."""
    import json
    import subprocess
    import sys

    import yaml

    proc = subprocess.run([sys.executable, "-m", "sim", "drives", "--eds", str(eds), "--config", str(truth_path),
                           "--json"], capture_output=True, text=True, timeout=120)
    if proc.returncode != 0:
        return {"error": proc.stderr.strip()}
    sheet = json.loads(proc.stdout)
    cfg = yaml.safe_load(cfg_path.read_text())
    name = cfg["joints"][0]["drive"]
    drive = cfg["drives"][name]
    changed: dict[str, Any] = {}
    first = next(iter(sheet.values()))
    for key in ("rated_current", "rated_torque"):
        obj = first["objects"][key]
        have = drive.get(key, {}) or {}
        if obj["object"] is not None and (have.get("object", "6075h" if key == "rated_current" else "6076h")
                                          != obj["object"] or have.get("unit") not in (None, obj["unit"])):
            drive[key] = {**have, "object": obj["object"], "unit": obj["unit"]}
            changed[f"drives.{name}.{key}"] = drive[key]
    for i, (j, (_, row)) in enumerate(zip(cfg["joints"], sheet.items(), strict=True)):
        if first["objects"]["rated_current"]["object"] is None and j["rated_current_A"] != row["rated_current_A"]:
            changed[f"joints[{i}].rated_current_A"] = row["rated_current_A"]
            j["rated_current_A"] = row["rated_current_A"]
    if changed:
        text = cfg_path.read_text()
        cfg_path.write_text(text.split("\nrobot:")[0] + "\n# values the EDS cannot give, set from the drive's "
                            "datasheet (docs/DRIVES.md step 4)\n" + yaml.safe_dump(cfg, sort_keys=False))
    return changed


def _drag_drift(rig: Any) -> float:
    """Start, drag, the operator's hand moves the arm and lets go: the largest joint motion [deg] over DRIFT_WINDOW_S
    after the arm came to rest."""
    from dragd.config import load_config
    from dragd.lab.rig import ProcessError

    rig.must("start")
    rig.wait_for(lambda: rig.must("status")["mode"] == "hold", 5.0, "hold after start")
    rig.sleep(0.5)
    p = rig.cli("mode", "drag")
    if p.returncode != 0:
        raise ProcessError(f"mode drag refused: {p.stderr.strip()}")
    rig.sleep(0.5)
    before = np.array(rig.sim_call("state")["q_rad"])

    n = len(load_config(rig.config).joints)
    step = [HAND_STEP_RAD * s for s in (1.0, 1.0, -1.0, 1.0, 1.0, 1.0)[:n]] + [0.0] * max(0, n - 6)
    # the demo's hand (dragd/lab/demo.py): it pulls the joints by ``step`` and lets go
    rig.sim_call("operator", scenario={"name": "hand", "segments": [
        {"kind": "hand", "q_rad": step, "relative": True, "stiffness": 60.0, "damping": 12.0,
         "max_load": HAND_MAX_LOAD_NM, "duration_s": 1.5},
        {"kind": "release", "ramp_down_s": 0.1, "duration_s": 0.3}]})
    rig.sleep(1.9)
    rig.wait_for(lambda: max(abs(v) for v in rig.sim_call("state")["dq_rad_s"]) < 1e-4, 15.0,
                 "the arm to come to rest after the push")
    rig.sleep(0.2)
    rest = np.array(rig.sim_call("state")["q_rad"])
    rig.sleep(DRIFT_WINDOW_S)
    later = np.array(rig.sim_call("state")["q_rad"])
    if float(np.degrees(np.abs(rest - before)).max()) < 0.5:
        raise ProcessError(f"the push did not move the arm ({np.degrees(np.abs(rest - before)).max():.2f}°)")
    status = rig.must("status")
    if status["requested_mode"] != "drag" or status["faults"]:
        raise ProcessError(f"left drag after the push: {status['mode']}, faults {status['faults']}")
    return round(float(np.degrees(np.abs(later - rest)).max()), 4)


def _identify(rig: Any, work: Any) -> str:
    """``dragd identify run`` of a short plan (the shoulder lifted 0.2 rad and back at two speeds): "ok" or why not."""
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
    lo[1] += 0.2 if q0[1] + 0.2 < model.position_limits_rad[1][1] - 0.1 else -0.2  # (upper limit of joint 2)
    for v in (0.1, 0.2):  # slow: a fresh configuration believes no friction (the drives' CSP loops meet all of it)
        b.move(lo, speed=v, acceleration=0.5, kind="synchronous", joint=1)
        b.move(q0, speed=v, acceleration=0.5, kind="synchronous", joint=1)
    plan = b.build("drive-profiles")
    pf = work / "plan.npz"
    plan.save(pf)
    out = work / "run.mcap"
    with rig.running():  # (lockstep: time runs freely while the CLI paces itself on the wall clock)
        proc = rig.cli("identify", "run", "--plan", str(pf), "--out", str(out), "--no-progress", "--json",
                       timeout_s=300.0)
    if proc.returncode != 0:
        return f"identify run failed: {(proc.stderr or proc.stdout).strip()}"
    res = json.loads(proc.stdout)
    if res.get("faults"):
        return f"identify run faulted: {res['faults']}"
    return "ok"


