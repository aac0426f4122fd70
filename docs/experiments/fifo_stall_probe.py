"""Probe for the daemon's FIFO cycle stalls when the simulator's operator scenario starts (docs/PERFORMANCE.md,
session 11): a rig (sim + daemon processes), ``start``, ``mode drag``, optionally the sim's ``operator
flange_drag``, then the daemon's status after 1 s (``period_max_us``, mode: 'fault' after an RPDO watchdog EMCY).

    PYTHONPATH=. .venv/bin/python docs/experiments/fifo_stall_probe.py [--operator] [--daemon-prio N] [--sim-prio N]

Priority 0: SCHED_OTHER. Session 11: with ``--operator`` and the daemon at FIFO 70 the period max was 78–105 ms in
most runs; without the operator or with the daemon SCHED_OTHER at most 5 ms.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

from dragd.lab.rig import Rig


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--operator", action="store_true")
    ap.add_argument("--daemon-prio", type=int, default=70)
    ap.add_argument("--sim-prio", type=int, default=60)
    ap.add_argument("--spy", help="py-spy the daemon into this file (raw collapsed stacks)")
    a = ap.parse_args()
    d_args = ["--realtime-priority", str(a.daemon_prio)]
    s_args = ["--realtime-priority", str(a.sim_prio)] if a.sim_prio else []
    with Rig("probe", daemon_args=d_args, sim_args=s_args) as rig:
        rig.start_sim()
        rig.start_daemon()
        spy = None
        if a.spy:
            spy = subprocess.Popen([str(Path(sys.executable).with_name("py-spy")), "record", "-r", "1000", "-d", "3", "-f", "raw", "-o", a.spy, "--nonblocking",
                                    "-p", str(rig.daemon.proc.pid)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            time.sleep(0.5)
        rig.must("start")
        time.sleep(0.5)
        rig.must("mode", mode="drag")
        if a.operator:
            rig.sim_call("operator", scenario="flange_drag")
        time.sleep(1.0)
        st = rig.must("status")
        print({k: st.get(k) for k in ("mode", "period_max_us", "missed_cycles", "scheduler")})
        print({k: v for k, v in st.items() if "max" in k or "p99" in k})
        if spy is not None:
            spy.wait(30)


if __name__ == "__main__":
    main()
