"""Foxglove's well-known channels in the telemetry MCAP (dragd/telemetry/foxglove.py) and the size option.

Read back with the mcap library's own reader; every message of a well-known channel is checked against the
JSON schema the file registers for it; the transforms against the URDF's geometry.
"""

import json
import math
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from dragd.config import load_config
from dragd.daemon.recording import Recorder
from dragd.robots import resolve_urdf
from dragd.telemetry.foxglove import FoxgloveSpec, log_level
from dragd.telemetry.reader import read_log, summarize
from dragd.telemetry.schema import cycle_layout
from dragd.telemetry.writer import TelemetryWriter, write_file

pytestmark = pytest.mark.unit

JOINTS = [f"joint{i}" for i in range(1, 7)]
URDF = resolve_urdf("seed_cobot")
REPO = Path(__file__).resolve().parents[1]


def check(value, schema, where="$"):
    """The subset of JSON Schema Foxglove's schemas use: type, properties, items, oneOf/const, min/max."""
    if "oneOf" in schema:
        assert any(value == s["const"] for s in schema["oneOf"]), f"{where}: {value!r} not one of {schema['oneOf']}"
        return
    t = schema.get("type")
    if t == "object":
        assert isinstance(value, dict), where
        for k in schema.get("required", []):
            assert k in value, f"{where}: missing {k}"
        for k, v in value.items():
            assert k in schema["properties"], f"{where}: unexpected field {k}"
            check(v, schema["properties"][k], f"{where}.{k}")
    elif t == "array":
        assert isinstance(value, list), where
        for i, v in enumerate(value):
            check(v, schema["items"], f"{where}[{i}]")
    elif t == "number":
        assert isinstance(value, (int, float)) and not isinstance(value, bool), where
    elif t == "integer":
        assert isinstance(value, int) and not isinstance(value, bool), where
    elif t == "string":
        assert isinstance(value, str), where
    if "minimum" in schema:
        assert value >= schema["minimum"], where
    if "maximum" in schema:
        assert value <= schema["maximum"], where


def read_channels(path):
    out: dict[str, list] = {}
    schemas: dict[str, tuple[str, dict]] = {}
    with open(path, "rb") as fh:
        for schema, channel, message in make_reader(fh).iter_messages():
            assert channel.message_encoding == "json" and schema.encoding == "jsonschema"
            schemas[channel.topic] = (schema.name, json.loads(schema.data))
            out.setdefault(channel.topic, []).append((message.log_time, json.loads(message.data)))
    return out, schemas


def rows_for(q: np.ndarray, mode: int = 2) -> np.ndarray:
    from dragd.telemetry.layout import RowLayout

    lay = RowLayout(cycle_layout(6))
    rows = np.zeros((len(q), lay.width))
    rows[:, lay.slices["mode"]] = mode
    rows[:, lay.slices["q_rad"]] = q
    rows[:, lay.slices["current_measured_A"]] = 1.5
    return rows


def test_well_known_channels_decode_against_their_schemas(tmp_path):
    n = 2000  # 2 s at 1 kHz
    t_ns = 1_700_000_000_000_000_000 + np.arange(n, dtype=np.int64) * 1_000_000
    q = np.zeros((n, 6))
    q[:, 1] = np.linspace(-1.0, 1.0, n)  # joint2 sweeps
    events = [(int(t_ns[10]), "mode", {"mode": "drag", "previous": "hold"}),
              (int(t_ns[500]), "fault", {"text": "joint3: following error", "code": 0x8611}),
              (int(t_ns[900]), "protective_stop", {"kind": "speed", "text": "joint1 too fast"})]
    path = tmp_path / "fx.mcap"
    write_file(path, cycle_layout(6), rows_for(q), t_ns, events=events,
               foxglove=FoxgloveSpec(JOINTS, URDF, rate_Hz=25.0))
    msgs, schemas = read_channels(path)
    assert schemas["/tf"][0] == "foxglove.FrameTransforms"
    assert schemas["/log"][0] == "foxglove.Log"
    assert schemas["/joint_states"][0] == "dragd.JointState"
    assert schemas["/robot_description"][0] == "std_msgs/String"
    for topic in ("/tf", "/log", "/joint_states", "/robot_description"):
        for _t, m in msgs[topic]:
            check(m, schemas[topic][1], topic)
    # decimated to 25 Hz: 2 s -> 50 messages, the cycle channel keeps every row
    assert len(msgs["/joint_states"]) == 50 and len(msgs["/tf"]) == 50
    assert len(msgs["/dragd/cycle"]) == n
    # the URDF travels in the file (the 3D panel's URDF layer reads it from the topic)
    assert msgs["/robot_description"][0][1]["data"] == URDF.read_text()
    # logs: the events, faults as ERROR, protective stops as WARNING
    levels = {m["message"].split()[0]: m["level"] for _t, m in msgs["/log"]}
    assert levels == {"mode": 2, "fault": 4, "protective_stop": 3}
    # every URDF link on its parent link; joint2's child rotates about y by q2 at the joint's fixed offset
    for t, m in msgs["/tf"]:
        tf = {x["child_frame_id"]: x for x in m["transforms"]}
        assert set(tf) == {"link1", "link2", "link3", "link4", "link5", "link6", "tool0"}
        assert tf["link1"]["parent_frame_id"] == "base_link" and tf["tool0"]["parent_frame_id"] == "link6"
        assert m["transforms"][0]["timestamp"] == {"sec": t // 10**9, "nsec": t % 10**9}
        i = int((t - t_ns[0]) // 1_000_000)
        l2 = tf["link2"]
        assert (l2["translation"]["x"], l2["translation"]["y"], l2["translation"]["z"]) == pytest.approx(
            (0.0, 0.13585, 0.0))
        r = l2["rotation"]
        half = q[i, 1] / 2
        assert (r["x"], r["y"], r["z"], r["w"]) == pytest.approx((0.0, math.sin(half), 0.0, math.cos(half)), abs=1e-9)
    js = msgs["/joint_states"][7][1]
    assert js["name"] == JOINTS and js["mode"] == "drag" and js["current_A"] == [1.5] * 6


def test_cycle_decimation_is_the_size_option(tmp_path):
    """Every 10th row in the file; a decimated file shows no sequence gaps, a row lost on top of it does."""
    paths = {}
    for d in (1, 10):
        path = tmp_path / f"d{d}.mcap"
        w = TelemetryWriter(path, cycle_layout(6), cycle_decimation=d, flush_interval_s=0.005)
        for k in range(1000):
            row = w.begin()
            row[:] = k
            row[1] = 2
            w.commit(1_700_000_000_000_000_000 + k * 1_000_000)
        st = w.close()
        assert st["written"] == 1000 // d and st["decimated"] == 1000 - 1000 // d and st["dropped"] == 0
        paths[d] = path
    s1, s10 = summarize(paths[1]), summarize(paths[10])
    assert s10["cycle"]["rows"] == 100 and s10["cycle"]["decimation"] == 10 and s10["cycle"]["sequence_gaps"] == 0
    assert s1["cycle"]["decimation"] == 1
    assert paths[10].stat().st_size < paths[1].stat().st_size / 5
    t_s = read_log(paths[10], ["t_s"]).rows["t_s"]
    assert t_s.tolist() == [float(k) for k in range(9, 1000, 10)]  # producer rows 10, 20, ... (sequence from 1)
    with pytest.raises(ValueError, match="cycle_decimation"):
        TelemetryWriter(tmp_path / "bad.mcap", cycle_layout(6), cycle_decimation=0)


def test_writer_thread_writes_foxglove_at_its_rate(tmp_path):
    """TelemetryWriter: joint states at rate_Hz from rows committed at 1 kHz (log times), events as logs."""
    path = tmp_path / "live.mcap"
    w = TelemetryWriter(path, cycle_layout(6), foxglove=FoxgloveSpec(JOINTS, URDF, rate_Hz=40.0),
                        flush_interval_s=0.005)
    t0 = 1_700_000_000_000_000_000
    for k in range(3000):
        row = w.begin()
        row[:] = 0.0
        w.commit(t0 + k * 1_000_000)
        if k % 500 == 0:
            time.sleep(0.01)
    w.event("fault", text="x", code=1)
    st = w.close()
    assert st["written"] == 3000 and st["dropped"] == 0
    msgs, _ = read_channels(path)
    assert len(msgs["/joint_states"]) == 120 and len(msgs["/tf"]) == 120  # 3 s at 40 Hz
    stamps = [t for t, _m in msgs["/joint_states"]]
    assert np.diff(stamps).tolist() == [25_000_000] * 119
    assert [m["level"] for _t, m in msgs["/log"]] == [4]


def test_daemon_recorder_opens_foxglove_from_config(tmp_path):
    cfg = load_config(REPO / "config" / "default.yaml")
    assert cfg.telemetry.foxglove and cfg.telemetry.cycle_decimation == 1
    rec = Recorder(cfg, len(cfg.joints), str(tmp_path / "d.mcap"), rerun=False)
    rec.open_telemetry()
    st = rec.telemetry.close()
    assert st["errors"] == 0
    s = summarize(tmp_path / "d.mcap")
    assert {"/joint_states", "/tf", "/log", "/robot_description"} <= {c["topic"] for c in s["channels"]}


def test_log_levels():
    assert log_level("fault", {}) == 4
    assert log_level("mode", {"mode": "fault", "previous": "drag"}) == 4
    assert log_level("protective_stop", {}) == 3
    assert log_level("start", {}) == 2


def test_layout_file_names_the_channels():
    layout = json.loads((REPO / "docs" / "foxglove_layout.json").read_text())
    text = json.dumps(layout)
    for topic in ("/joint_states", "/log", "/robot_description", "/dragd/cycle"):
        assert topic in text, topic
    panels = {k.split("!")[0] for k in layout["configById"]}
    assert {"3D", "Plot", "Log", "StateTransitions"} <= panels
