"""A golden trace recorded in lockstep from the real processes: ``python -m sim run --lockstep`` and ``python -m dragd
run --lockstep`` over the udp_multicast bus (dragd/clock.py, sim/lockstep.py), read by a third party on the bus.

The tap sees every frame in the order the bus carried it. On the lockstep clock that order is the run's own: SYNC k
(the daemon) → the simulator's answer for period k (its TPDOs, heartbeats, EMCYs) → its TIME frame → the daemon's
command frames of cycle k (they leave with SYNC k+1). So cycle k's inputs are what the simulator sent between
SYNC k and TIME k, its outputs what the daemon sent between TIME k and SYNC k+1; the operator's requests are
placed at the clock tick they were made at (``status.clock.ticks``); the telemetry is the daemon's MCAP, whose rows
on this clock carry the clock's period and time. The trace has the fields of the synthetic ones (golden/trace.py),
so the same replay and the same bit-for-bit comparison apply: what the real daemon did, cycle by cycle, from the
real simulated drives' frames."""

from __future__ import annotations

import json
import tempfile
import threading
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from golden.trace import REPO, _pack_frames, arithmetic

TIME_COB = 0x100
SYNC_COB = 0x080
CONFIG = "default.yaml"


def _config_text() -> str:
    data = yaml.safe_load((REPO / "config" / CONFIG).read_text())
    data["robot"]["urdf"] = "seed_cobot"
    return yaml.safe_dump(data, sort_keys=False)


class Tap:
    """Every frame on the rig's bus, in order (a third receiver on the multicast group)."""

    def __init__(self, bus_spec: str) -> None:
        from dragd.hardware.bus import open_bus, parse_bus

        self.bus = open_bus(parse_bus(bus_spec, fd=True))
        self.frames: list[tuple[int, bytes]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _take(self, timeout_s: float) -> bool:
        msg = self.bus.recv(timeout_s)
        if msg is None:
            return False
        if not msg.is_error_frame:
            self.frames.append((int(msg.arbitration_id), bytes(msg.data)))
        return True

    def _run(self) -> None:
        while not self._stop.is_set():
            self._take(0.05)
        # then what is queued: the clock stands still after the last grant, so every frame of the cycles that ran is
        # in this socket already (a tap behind on a loaded machine lost the last cycles' frames when it stopped here)
        while self._take(0.2):
            pass

    def close(self) -> dict[str, Any]:
        self._stop.set()
        self._thread.join(60.0)
        if self._thread.is_alive():
            raise RuntimeError("the tap: the bus did not go quiet after the last grant (something sends on its own)")
        counters = vars(self.bus.counters()) if hasattr(self.bus, "counters") else {}
        self.bus.shutdown()
        return counters


def _script(rig: Any, events: list[dict[str, Any]]) -> None:
    """Enable, drag with a push and its release, hold, an EMCY on one drive, start again, drag, stop."""

    def req(name: str, **args: Any) -> None:
        ticks = rig.call("clock")["clock"]["ticks"]
        rig.must(name, **args)
        events.append({"cycle": int(ticks), "request": name, "args": args, "error": None})

    req("start")
    rig.sleep(0.3)
    req("mode", mode="drag")
    rig.sleep(0.2)
    rig.sim_call("operator", scenario={"name": "push", "segments": [
        {"kind": "push", "joint": "joint2", "torque_Nm": 10.0, "duration_s": 0.4},
        {"kind": "push", "joint": "joint1", "torque_Nm": 6.0, "duration_s": 0.3},
        {"kind": "release", "duration_s": 0.0}]})
    rig.sleep(1.0)
    req("mode", mode="hold")
    rig.sleep(0.4)
    rig.sim_call("fault", node_id=3, code=0x2310)  # a drive's over-current: EMCY and its fault reaction
    rig.sleep(0.3)
    req("start")
    rig.sleep(0.2)
    req("mode", mode="drag")
    rig.sleep(0.3)
    req("stop")
    rig.sleep(0.1)


def record_lockstep(workdir: Path | None = None) -> dict[str, Any]:
    """Run the script on the real processes in lockstep; the trace's fields (golden/trace.py ``_record``'s)."""
    from dragd.config import load_config
    from dragd.daemon.core import bus_layouts
    from dragd.lab.rig import Rig
    from dragd.telemetry.reader import read_rows

    from golden.adapter import TELEMETRY_SKIP

    workdir = Path(workdir or tempfile.mkdtemp(prefix="golden-lockstep-"))
    workdir.mkdir(parents=True, exist_ok=True)
    text = _config_text()
    cfg_path = workdir / "golden.yaml"
    cfg_path.write_text(text)
    cfg = load_config(cfg_path)
    layouts = bus_layouts(cfg)
    (bus_name,) = list(layouts)
    tpdo = {fr.cob_id for fr in layouts[bus_name].frames if fr.direction == "tpdo"}
    master_hb = 0x700 + cfg.master.node_id
    mcap = workdir / "golden.mcap"
    events: list[dict[str, Any]] = []
    with Rig("golden", workdir=workdir, config=cfg_path, telemetry=mcap, lockstep=True) as rig:
        rig.start_sim()
        tap = Tap(rig.bus)
        try:
            rig.start_daemon()
            _script(rig, events)
            faults = [f["text"] for f in rig.must("status")["faults"]]
        finally:
            counters = tap.close()
    if counters.get("gaps") or counters.get("kernel_drops"):
        raise RuntimeError(f"the tap lost frames ({counters}): record again on a quieter machine")
    # cycles: SYNC k ... TIME k (the simulator's answer) ... SYNC k+1 (the daemon's frames in between); a frame of the
    # simulator's between TIME k and SYNC k+1 (an injected EMCY, sent as the rig asked) is an input of cycle k+1
    rpdo = {fr.cob_id for fr in layouts[bus_name].frames if fr.direction == "rpdo"}
    nodes = [j.node_id for j in cfg.joints]
    daemons = rpdo | {SYNC_COB, 0x000, master_hb} | {0x600 + n for n in nodes}
    frames_in: list[list[tuple[str, int, bytes]]] = []
    frames_out: list[list[tuple[str, int, bytes]]] = []
    pending: list[tuple[str, int, bytes]] = []
    state = "boot"
    for cob, data in tap.frames:
        if cob == SYNC_COB and not data:
            frames_in.append(pending)
            frames_out.append([])
            pending = []
            state = "answer"
        elif state == "boot":
            continue
        elif cob == TIME_COB:
            state = "commands"
        elif cob == master_hb:
            continue
        elif state == "answer":
            frames_in[-1].append((bus_name, cob, data))
        elif cob in daemons:
            frames_out[-1].append((bus_name, cob, data))
        else:
            pending.append((bus_name, cob, data))
    frames_in, frames_out = frames_in[:-1], frames_out[:-1]  # (a cycle is whole once the next SYNC came)
    cycles = len(frames_in)
    rows = read_rows(mcap)
    first = next(k for k, fr in enumerate(frames_in) if {c for _, c, _ in fr} >= tpdo)  # primed: every TPDO in
    n_rows = min(len(rows["t_s"]), cycles - first)
    cycles = first + n_rows
    frames_in, frames_out = frames_in[:cycles], frames_out[:cycles]
    mode_names = {"idle": 0, "hold": 1, "drag": 2, "track": 3, "fault": 4}
    mode = np.full(cycles, -1, dtype=np.int8)
    mode[first:] = [mode_names[m] for m in rows["mode"][:n_rows]]
    computed = np.zeros(cycles, dtype=bool)
    computed[first:] = True
    drive_mode = np.zeros(cycles, dtype=np.int8)
    drive_mode[first:] = 10  # (CST throughout: no motion in the script)
    tele = {f"tele_{k}": np.asarray(v[:n_rows], dtype=float).reshape(n_rows, -1) if k != "mode" else
            np.asarray([mode_names[m] for m in v[:n_rows]], dtype=float).reshape(n_rows, 1)
            for k, v in rows.items() if k not in TELEMETRY_SKIP}
    period = np.full(cycles, (1.0 / cfg.loop.rate_Hz) * 1e6)
    return {"config": text, "arithmetic": arithmetic(), "telemetry_as_written": True, "buses": json.dumps([bus_name]),
            "events": json.dumps([e for e in events if e["cycle"] < cycles]), "period_us": period,
            "expirations": np.ones(cycles, dtype=np.int64), "mode": mode, "drive_mode": drive_mode,
            "computed": computed, "faults": json.dumps(faults), "log": json.dumps([]),
            **{f"in_{k}": v for k, v in _pack_frames(frames_in, [bus_name]).items()},
            **{f"out_{k}": v for k, v in _pack_frames(frames_out, [bus_name]).items()}, **tele}
