"""``python -m sim.drive_bench [--seconds S] [--eds FILE] [--json]``: the simulated drives' own CPU per 1 ms cycle.

Six drives of the seed cobot (or of FILE), in-process, configured as dragd configures them over SDO (heartbeat
producer 50 ms, master heartbeat consumer 200 ms, RPDO1 deadline 50 ms), operational, enabled, then driven as the
simulator's loop drives them on a simulated clock: each 1 ms an RPDO (controlword, target torque) and a SYNC per
drive, four physics-rate ``update`` steps, one ``comm`` tick; a master heartbeat every 100 ms. Reports the process
CPU time per 1 ms cycle for CST (steady drives) and CSP (every step computed). No bus, no physics: the drives' code.
"""

from __future__ import annotations

import argparse
import json
import math
import struct
import sys
import time
from pathlib import Path

from dragd.hardware.cia301 import (
    HEARTBEAT_BASE,
    NMT_COB_ID,
    OD_CONSUMER_HEARTBEAT,
    OD_PRODUCER_HEARTBEAT,
    OD_RPDO_COMM,
    RPDO1_BASE,
    SDO_RX_BASE,
    NmtCommand,
    NmtState,
)
from dragd.hardware.cia402 import CMD_ENABLE_OPERATION, CMD_SHUTDOWN, CMD_SWITCH_ON, OD_MODES_OF_OPERATION
from sim.axis import AxisIO
from sim.drive import SimDrive
from sim.truth import drive_params, load_truth, with_eds

STEP_S = 0.00025
MASTER_NODE_ID = 0x7F


def _sdo(drive: SimDrive, index: int, sub: int, value: int, size: int) -> None:
    command = {1: 0x2F, 2: 0x2B, 4: 0x23}[size]
    payload = value.to_bytes(size, "little", signed=value < 0).ljust(4, b"\0")
    drive.on_data(SDO_RX_BASE + drive.node_id, struct.pack("<BHB", command, index, sub) + payload)


def cycle_cpu_us(seconds: float, mode: int, eds: str | Path | None = None) -> float:
    """Process CPU µs per 1 ms cycle of six drives in ``mode`` (10 CST, 8 CSP)."""
    truth = load_truth(None)
    if eds is not None:
        truth = with_eds(truth, eds)
    drives = [SimDrive(drive_params(j, fd=False), AxisIO(), lambda m: None) for j in truth.joints]
    t = 1000.0
    for d in drives:
        d.comm(t)
        d.boot()
        _sdo(d, OD_PRODUCER_HEARTBEAT, 0, 50, 2)
        _sdo(d, OD_CONSUMER_HEARTBEAT, 1, (MASTER_NODE_ID << 16) | 200, 4)
        _sdo(d, OD_RPDO_COMM, 5, 50, 2)
        _sdo(d, OD_MODES_OF_OPERATION, 0, mode, 1)
        d.on_data(NMT_COB_ID, bytes((NmtCommand.START, d.node_id)))
        for word in (CMD_SHUTDOWN, CMD_SWITCH_ON, CMD_ENABLE_OPERATION):
            d.on_data(RPDO1_BASE + d.node_id, struct.pack("<Hh", word, 0))
            d.on_sync(t)
    steps = int(seconds * 4000)
    c0 = time.process_time()
    for k in range(steps):
        tt = k * STEP_S
        if k % 4 == 0:
            t += 0.001
            if k % 400 == 0:
                for d in drives:
                    d.on_data(HEARTBEAT_BASE + MASTER_NODE_ID, bytes((NmtState.OPERATIONAL,)))
            for d in drives:
                d.on_data(RPDO1_BASE + d.node_id, struct.pack("<Hh", CMD_ENABLE_OPERATION, (k // 4) % 200 - 100))
                d.on_sync(t)
        for d in drives:
            io = d.io
            io.position_rad, io.velocity_rad_s, io.current_measured_A = 0.1 * math.sin(tt), 0.1 * math.cos(tt), 0.5
            d.update(tt, STEP_S)
        if k % 4 == 3:
            for d in drives:
                d.comm(t)
    cpu = time.process_time() - c0
    if any(d.counters.rpdo_timeouts or d.counters.heartbeat_losses for d in drives):
        raise RuntimeError("drive_bench: a watchdog fired; the run did not measure the steady cycle")
    return cpu / (seconds * 1000.0) * 1e6


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m sim.drive_bench", description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=5.0, help="simulated seconds per mode (default 5)")
    parser.add_argument("--eds", help="every drive from this EDS (as python -m sim run --eds)")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    if not args.seconds > 0:
        print(f"drive_bench: --seconds: expected a positive number, got {args.seconds}", file=sys.stderr)
        return 2
    out = {f"sim_drives_{name}_cpu_us_per_cycle": {"value": round(cycle_cpu_us(args.seconds, mode, args.eds), 1),
                                                   "unit": "us"}
           for name, mode in (("cst", 10), ("csp", 8))}
    print(json.dumps(out) if args.json else "\n".join(f"{k}: {v['value']} us" for k, v in out.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
