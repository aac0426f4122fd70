"""A killed daemon leaves the drives safe through their own watchdogs (RPDO deadline, 1400h sub 5; heartbeat).

On the wall clock: the simulated drives' watchdogs must fire without a master, and on the lockstep clock the
master's SYNCs are the arm's time (a killed daemon stops it); this is their real-time behaviour.
"""

from __future__ import annotations

import signal
import time

import numpy as np
import pytest

from dragd.hardware.bus import open_bus, parse_bus
from dragd.lab.rig import Rig

from daemon_helpers import wait_for

pytestmark = pytest.mark.rig


def test_killed_daemon_leaves_drives_safe(tmp_path):
    with Rig("kill", workdir=tmp_path) as rig:
        rig.start_sim()
        rig.start_daemon()
        rig.must("start")
        rig.sleep(0.3)
        rig.must("mode", mode="drag")
        rig.sleep(0.3)
        q0 = np.array(rig.sim_call("state")["q_rad"])
        listener = open_bus(parse_bus(rig.bus, fd=True))
        try:
            rig.daemon.proc.send_signal(signal.SIGKILL)
            emcy: set[tuple[int, int]] = set()
            end = time.monotonic() + 2.0
            while time.monotonic() < end:
                msg = listener.recv(0.05)
                if msg is not None and 0x81 <= msg.arbitration_id <= 0x86 and len(msg.data) >= 2:
                    emcy.add((msg.arbitration_id - 0x80, msg.data[0] | msg.data[1] << 8))
        finally:
            listener.shutdown()
        assert {n for n, code in emcy if code == 0x8250} == set(range(1, 7)), emcy  # RPDO timeout on every drive
        wait_for(lambda: all(rig.sim_call("state")["brakes"]), 3.0, "every brake engaged")
        drives = rig.sim_call("drives")["drives"]
        assert all(d["state"] != "OPERATION_ENABLED" for d in drives.values())
        q1 = np.array(rig.sim_call("state")["q_rad"])
        assert np.degrees(np.abs(q1 - q0)).max() < 1.0
