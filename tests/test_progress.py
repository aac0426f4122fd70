"""Progress of long offline commands on stderr, quiet with --json (dragd/cli/common.py Stages)."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dragd.telemetry.layout import RowLayout
from dragd.telemetry.schema import cycle_layout
from dragd.telemetry.writer import write_file

pytestmark = pytest.mark.unit

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_identify_fit_reports_its_stages_on_stderr_and_is_quiet_with_json(tmp_path):
    lay = RowLayout(cycle_layout(6))
    n = 4000
    rows = np.zeros((n, lay.width))
    t = np.arange(n) / 1000.0
    rows[:, lay.slices["t_s"]] = t[:, None]
    rows[:, lay.slices["mode"]] = 3
    q = 0.4 * np.sin(2 * np.pi * 0.5 * t)[:, None] * np.ones(6)
    rows[:, lay.slices["q_rad"]] = q
    rows[:, lay.slices["dq_rad_s"]] = np.gradient(q, axis=0) * 1000
    rng = np.random.default_rng(1)
    rows[:, lay.slices["current_measured_A"]] = 0.3 * np.sign(rows[:, lay.slices["dq_rad_s"]]) + \
        0.02 * rng.normal(size=(n, 6))
    log = tmp_path / "log.mcap"
    write_file(log, cycle_layout(6), rows, (t * 1e9).astype(np.int64) + 1_700_000_000_000_000_000)

    def fit(*extra, env=None):
        return subprocess.run([sys.executable, "-m", "dragd", "identify", "fit", "--log", str(log), "--out",
                               str(tmp_path / "p.yaml"), *extra], capture_output=True, text=True, timeout=300, cwd=REPO,
                              env=env)

    import os

    p = fit(env={**os.environ, "DRAGD_PROGRESS": "1"})  # stderr is a pipe here: asked for explicitly
    stages = [line for line in p.stderr.splitlines() if line.startswith("identify fit: ")]
    if p.returncode != 0:  # a fit that fails still said how far it came
        assert stages, p.stderr
        pytest.skip(f"this synthetic log does not fit: {p.stderr.strip().splitlines()[-1]}")
    assert [s.split(" ... ")[0] for s in stages][:3] == [
        "identify fit: loading the robot model", f"identify fit: reading {log}", "identify fit: fitting (auto)"]
    assert all(s.endswith(" s") for s in stages)
    q = fit("--json", env={**os.environ, "DRAGD_PROGRESS": "1"})
    assert q.returncode == 0 and "identify fit:" not in q.stderr
    json.loads(q.stdout)
    r = fit()  # a pipe, not asked: silent (an error stays one line)
    assert r.returncode == 0 and "identify fit:" not in r.stderr
