"""The cycle row's one owner (dragd/telemetry/schema.py): the daemon and ``python -m sim log`` write the same schema."""

import numpy as np
import pytest

from dragd.config import load_config
from dragd.control.modes import MODE_NAMES
from dragd.daemon.recording import Recorder
from dragd.telemetry.layout import RowLayout
from dragd.telemetry.reader import read_log, summarize
from dragd.telemetry.schema import Field, cycle_layout
from dragd.telemetry.writer import TelemetryWriter

pytestmark = pytest.mark.unit

# (name, per joint or a fixed width, kind): the daemon's row (before the split, then #29's columns)
# (Daemon._telemetry_layout)
DAEMON_ROW = [
    ("t_s", False, "float"), ("mode", False, "enum"), ("q_rad", True, "float"), ("dq_rad_s", True, "float"),
    ("current_measured_A", True, "float"), ("current_command_A", True, "float"), ("gravity_A", True, "float"),
    ("friction_A", True, "float"), ("startup_A", True, "float"), ("damping_A", True, "float"),
    ("statusword", True, "int"), ("rx", True, "bool"), ("period_us", False, "float"), ("compute_us", False, "float"),
    ("q_ref_rad", True, "float"), ("track_t_s", False, "float"), ("residual_A", True, "float"),
    ("back_emf_A", True, "float"), ("effects_A", True, "float"),
    # the contact detector's (#29): residual and band per joint, the hand's force and the grip point (3 wide)
    ("contact_residual_A", True, "float"), ("contact_band_A", True, "float"), ("hand_force_N", 3, "float"),
    ("grip_m", 3, "float"),
]


@pytest.mark.parametrize("n", [1, 6, 7])
def test_cycle_layout_is_the_daemons_row(n):
    layout = cycle_layout(n)
    assert list(layout) == [name for name, _j, _k in DAEMON_ROW]
    cols = {c.name: c for c in RowLayout(layout).columns}
    for name, per_joint, kind in DAEMON_ROW:
        f = layout[name]
        assert isinstance(f, Field) and f.description, name
        assert cols[name].width == (per_joint if type(per_joint) is int else (n if per_joint else 1)), name
        assert cols[name].kind == kind, name
    assert cols["mode"].labels == {int(m): s for m, s in MODE_NAMES.items()}
    assert cols["mode"].labels == {0: "idle", 1: "hold", 2: "drag", 3: "track", 4: "fault"}
    with pytest.raises(ValueError, match="n_joints"):
        cycle_layout(0)


def test_the_daemon_records_cycle_layout():
    rec = Recorder(load_config(), 6, None, False)
    assert rec.layout == cycle_layout(6)
    assert rec.width == RowLayout(cycle_layout(6)).width


def test_sim_offline_mcap_has_the_daemons_schema(tmp_path):
    from sim.offline import generate, write_log
    from sim.truth import load_truth

    start = np.array([0.0, -0.6, 1.2, -0.6, 1.5708, 0.0])
    plan_t = np.array([0.0, 0.5, 1.0])
    plan_q = np.stack([start, start + 0.02, start + 0.04])
    data = generate(plan_t, plan_q, load_truth(), seconds=0.2)
    offline = tmp_path / "offline.mcap"
    write_log(offline, data)

    daemon = tmp_path / "daemon.mcap"
    w = TelemetryWriter(daemon, Recorder(load_config(), 6, None, False).layout)
    row = w.begin()
    row[:] = 0.0
    w.commit()
    w.close()

    off, dae = read_log(offline), read_log(daemon)
    assert off.complete and off.cycle_schema == dae.cycle_schema
    assert list(off.rows) == list(dae.rows)
    for k in off.rows:
        assert off.rows[k].dtype.kind == dae.rows[k].dtype.kind and off.rows[k].shape[1:] == dae.rows[k].shape[1:], k
    so, sd = summarize(offline), summarize(daemon)
    assert so["schemas"] == sd["schemas"] == ["dragd.Cycle", "dragd.Event"]
    assert [(c["topic"], c["schema"]) for c in so["channels"]] == [(c["topic"], c["schema"]) for c in sd["channels"]]

    # what the offline run does not simulate is written explicitly, as the daemon writes it in TRACK
    r = off.rows
    n = len(data["t_s"])
    assert off.n_rows == n and set(r["mode"].tolist()) == {"track"}
    assert np.allclose(r["q_ref_rad"], data["q_ref_rad"], rtol=1e-11, atol=0)
    assert np.allclose(r["track_t_s"], data["t_s"]) and np.allclose(r["t_s"], data["t_s"])
    for k in ("startup_A", "damping_A", "residual_A", "back_emf_A", "effects_A"):
        assert (r[k] == 0).all(), k
    assert r["rx"].all() and r["period_us"] == pytest.approx(1000.0)
