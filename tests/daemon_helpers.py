"""Helpers for the daemon integration tests: configs derived from the default, MCAP rows, waiting."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import yaml

from dragd.telemetry.reader import read_rows

from conftest import DEFAULT_CONFIG

# Rigs whose telemetry feeds identification run as deployed: the daemon's cycle thread SCHED_FIFO 70, the simulator
# 60 (where permitted; otherwise both say so in their status and run SCHED_OTHER). Under SCHED_OTHER on 2 cores a
# busy moment leaves stretches of missed cycles, whose CSP jerks a short log's fit can mistake for friction effects.
AS_DEPLOYED = {"daemon_args": ["--realtime-priority", "70"], "sim_args": ["--realtime-priority", "60"]}


def derived_config(tmp: Path, name: str, edit: Callable[[dict], None]) -> Path:
    """A copy of config/default.yaml with ``edit`` applied, written next to the test's files."""
    data = yaml.safe_load(DEFAULT_CONFIG.read_text())
    data["robot"]["urdf"] = "seed_cobot"
    edit(data)
    path = tmp / f"{name}.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def cycle_rows(mcap_path: Path) -> dict[str, np.ndarray]:
    """Every /dragd/cycle row of a telemetry file as arrays (one row per cycle)."""
    return read_rows(mcap_path)


def wait_for(cond: Callable[[], bool], timeout_s: float, what: str) -> None:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if cond():
            return
        time.sleep(0.02)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


def deg(x: float) -> float:
    return math.degrees(x)
