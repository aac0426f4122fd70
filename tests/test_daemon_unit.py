"""Daemon pieces that need no processes: frame decoding, bus-spec overrides."""

from __future__ import annotations

import can
import pytest

from dragd.config import load_config
from dragd.daemon import Daemon

from conftest import DEFAULT_CONFIG


@pytest.fixture
def daemon() -> Daemon:
    d = Daemon(load_config(DEFAULT_CONFIG), bus_override="udp_multicast:239.74.200.1")
    d._tpdo["arm"] = {0x181: (0, __import__("struct").Struct("<HiH"), ("statusword", "position", "current"))}
    d._emcy = {0x80 + j.node_id: i for i, j in enumerate(d.cfg.joints)}
    return d


def test_error_frames_are_never_decoded(daemon: Daemon) -> None:
    table = daemon._tpdo["arm"]
    for cob in (0x081, 0x181):  # error class bits that equal node 1's EMCY and TPDO1 COB-IDs
        daemon._on_frame(can.Message(arbitration_id=cob, is_error_frame=True, data=bytes(8), is_extended_id=False), table)
    assert daemon.error_frames == 2 and daemon.faults == [] and daemon.counts[0] == 0
    daemon._on_frame(can.Message(arbitration_id=0x081, data=bytes([0x10, 0x23, 0x01, 0, 0, 0, 0, 0]),
                                 is_extended_id=False), table)
    assert daemon.faults and "EMCY 0x2310" in daemon.faults[0]["text"]


def test_bus_override_count_must_match(daemon: Daemon) -> None:
    with pytest.raises(ValueError, match="expected 1 INTERFACE:CHANNEL"):
        Daemon(load_config(DEFAULT_CONFIG), bus_override="virtual:a,virtual:b")
