"""The Rerun views (dragd/telemetry/sinks.py RerunSink, dragd/telemetry/view.py): real recordings written by
rerun-sdk and read back with rerun's own reader (rerun.chunk.RrdReader)."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pa = pytest.importorskip("pyarrow")

rr = pytest.importorskip("rerun", reason="needs the optional extra dragd[rerun] (rerun-sdk)")
from rerun.chunk import RrdReader  # noqa: E402

from dragd.robots import resolve_urdf  # noqa: E402
from dragd.telemetry.layout import RowLayout  # noqa: E402
from dragd.telemetry.schema import cycle_layout  # noqa: E402
from dragd.telemetry.sinks import RerunSink  # noqa: E402
from dragd.telemetry.writer import TelemetryWriter, write_file  # noqa: E402

pytestmark = pytest.mark.unit

JOINTS = [f"joint{i}" for i in range(1, 7)]
REPO = Path(__file__).resolve().parents[1]
T0 = 1_700_000_000_000_000_000


def entities(path: Path) -> dict[str, dict[str, list]]:
    """entity path -> column -> values (all chunks of the recording)."""
    out: dict[str, dict[str, list]] = {}
    for chunk in RrdReader(path).stream().to_chunks():
        cols = out.setdefault(chunk.entity_path, {})
        batch = chunk.to_record_batch()
        for name, col in zip(batch.schema.names, batch.columns, strict=True):
            if pa.types.is_timestamp(col.type):  # nanoseconds: as integers
                col = col.cast(pa.int64())
            cols.setdefault(name, []).extend(col.to_pylist())
    return out


def drag_rows(n: int) -> tuple[RowLayout, np.ndarray]:
    lay = RowLayout(cycle_layout(6))
    rows = np.zeros((n, lay.width))
    k = np.arange(n)
    rows[:, lay.slices["t_s"]] = (k / 1000.0)[:, None]
    rows[:, lay.slices["mode"]] = 2
    rows[:, lay.slices["q_rad"].start + 1] = np.linspace(-1, 1, n)
    rows[:, lay.slices["gravity_A"].start + 1] = 2.0 + k / 1000.0
    rows[:, lay.slices["friction_A"].start + 1] = 0.25
    rows[:, lay.slices["current_measured_A"]] = 1.5
    return lay, rows


def check_recording(path: Path, seconds: float, rate_Hz: float = 100.0) -> dict:
    e = entities(path)
    n = int(round(seconds * rate_Hz))
    grav = e["/current/joint2/gravity"]["Scalars:scalars"]
    assert len(grav) == n
    assert [v[0] for v in grav][:3] == pytest.approx([2.0, 2.01, 2.02])  # every 10th 1 kHz row
    assert {v[0] for v in e["/current/joint2/friction"]["Scalars:scalars"]} == {0.25}
    assert {v[0] for v in e["/mode"]["Scalars:scalars"]} == {2.0}
    for comp in ("measured", "command", "gravity", "friction", "startup", "damping", "back_emf", "effects"):
        assert f"/current/joint6/{comp}" in e
    # the arm in 3D: link origins from the URDF, 30 Hz; base_link at the origin, link1 0.089159 m above it
    strips = e["/arm/skeleton"]["LineStrips3D:strips"]
    assert len(strips) == int(round(seconds * 30))
    pts = np.array(strips[0][0])
    assert pts.shape == (8, 3) and pts[0] == pytest.approx([0, 0, 0]) and pts[1] == pytest.approx([0, 0, 0.089159])
    labels = e["/arm/links"]["Points3D:labels"][0]
    assert labels[0] == "base_link" and labels[-1] == "tool0"
    return e


def test_live_sink_in_the_writer_thread_makes_a_real_recording(tmp_path):
    rrd = tmp_path / "live.rrd"
    sink = RerunSink(save_path=rrd, joint_names=JOINTS, urdf=resolve_urdf("seed_cobot"))
    lay, rows = drag_rows(2000)
    w = TelemetryWriter(tmp_path / "t.mcap", cycle_layout(6), sinks=[sink], flush_interval_s=0.005)
    for k in range(len(rows)):
        row = w.begin()
        row[:] = rows[k]
        w.commit(T0 + k * 1_000_000)
    w.event("fault", text="joint3: following error", code=0x8611)
    st = w.close()
    assert st["sink_errors"] == [] and st["written"] == 2000
    e = check_recording(rrd, 2.0)
    levels = e["/faults"]["TextLog:level"]
    assert levels == [["ERROR"]] and "following error" in e["/faults"]["TextLog:text"][0][0]


def test_log_view_exports_a_recorded_mcap_to_rrd(tmp_path):
    lay, rows = drag_rows(3000)
    t = T0 + np.arange(3000, dtype=np.int64) * 1_000_000
    mcap = tmp_path / "rec.mcap"
    write_file(mcap, cycle_layout(6), rows, t, events=[(T0, "start", {"joints": JOINTS}),
                                                       (T0 + 1_500_000_000, "protective_stop", {"kind": "speed"})])
    rrd = tmp_path / "rec.rrd"
    p = subprocess.run([sys.executable, "-m", "dragd", "log", "view", str(mcap), "--save", str(rrd), "--json"],
                       capture_output=True, text=True, timeout=600, cwd=REPO)  # (a hang guard: see run_cli)
    assert p.returncode == 0, p.stderr
    out = json.loads(p.stdout)
    assert out["rows"] == 3000 and out["joints"] == JOINTS and out["rrd"] == str(rrd)
    e = check_recording(rrd, 3.0)
    assert e["/faults"]["TextLog:level"] == [["WARN"]]
    assert len(e["/events"]["TextLog:text"]) == 2
