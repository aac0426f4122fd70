"""The telemetry's well-known channels in ROS 2's encoding (dragd/telemetry/ros2.py) and ``dragd log ros2``.

Read back with the ROS 2 MCAP reader (the mcap reader with mcap-ros2-support's ROS 2 decoder, which decodes by the
schema in the file) and, where the ros2 extra is installed, decoded by ROS's own type support (rclpy's
``deserialize_message``) and the definitions compared with the installed message packages' .msg files; the daemon
writes them in a rig test.
"""

from __future__ import annotations

import json
import math
import re
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from ros2_helpers import REASON

from dragd.lab.rig import Rig
from dragd.robots import resolve_urdf
from dragd.telemetry.foxglove import FoxgloveSpec
from dragd.telemetry.layout import RowLayout
from dragd.telemetry.ros2 import DEFINITIONS
from dragd.telemetry.schema import cycle_layout
from dragd.telemetry.writer import write_file

from conftest import run_cli

JOINTS = [f"joint{i}" for i in range(1, 7)]
URDF = resolve_urdf("seed_cobot")
KT = [0.5, 0.6, 0.7, 0.8, 0.9, 1.0]


def rows_for(q: np.ndarray) -> np.ndarray:
    lay = RowLayout(cycle_layout(6))
    rows = np.zeros((len(q), lay.width))
    rows[:, lay.slices["mode"]] = 2
    rows[:, lay.slices["q_rad"]] = q
    rows[:, lay.slices["dq_rad_s"]] = 0.1
    rows[:, lay.slices["current_measured_A"]] = np.arange(1, 7) * 0.5
    return rows


def a_log(path: Path, encoding: str, seconds: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    n = int(seconds * 1000)
    t0 = 1_700_000_000_000_000_000
    stamps = t0 + np.arange(n, dtype=np.int64) * 1_000_000
    q = np.outer(np.sin(np.linspace(0, 3, n)), np.linspace(0.1, 0.6, 6))
    events = [(int(stamps[100]), "mode", {"mode": "drag", "previous": "hold"}),
              (int(stamps[500]), "fault", {"text": "EMCY 0x8130 from node 3", "code": 0x8130}),
              (int(stamps[700]), "protective_stop", {"kind": "runaway", "text": "joint2 ran away"})]
    write_file(path, cycle_layout(6), rows_for(q), stamps, events=events,
               foxglove=FoxgloveSpec(JOINTS, URDF, rate_Hz=50.0, encoding=encoding, kt_Nm_per_A=KT))
    return stamps, q


class Decoded:
    def __init__(self, schema, channel, message, ros_msg) -> None:
        self.schema, self.channel, self.ros_msg = schema, channel, ros_msg
        self.log_time_ns = message.log_time


def ros2_messages(path: Path) -> dict[str, list[Decoded]]:
    """Every CDR channel's messages decoded by the ROS 2 decoder (dragd's JSON channels beside them skipped)."""
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        topics = [c.topic for c in reader.get_summary().channels.values() if c.message_encoding == "cdr"]
        out: dict[str, list[Decoded]] = {}
        for schema, channel, message, ros_msg in reader.iter_decoded_messages(topics=topics):
            out.setdefault(channel.topic, []).append(Decoded(schema, channel, message, ros_msg))
    return out


@pytest.mark.unit
def test_ros2_channels_read_back_with_the_ros2_mcap_reader(tmp_path):
    path = tmp_path / "t.mcap"
    stamps, q = a_log(path, "ros2")
    got = ros2_messages(path)
    assert set(got) == {"/joint_states", "/tf", "/robot_description", "/rosout"}
    js = got["/joint_states"]
    assert js[0].schema.name == "sensor_msgs/msg/JointState" and js[0].schema.encoding == "ros2msg"
    assert 45 <= len(js) <= 51  # 50 Hz over a second
    for m in js:
        msg = m.ros_msg
        k = int(np.searchsorted(stamps, m.log_time_ns))
        assert list(msg.name) == JOINTS
        assert msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec == m.log_time_ns == stamps[k]
        assert np.allclose(msg.position, q[k]) and np.allclose(msg.velocity, 0.1)
        assert np.allclose(msg.effort, np.arange(1, 7) * 0.5 * np.array(KT))  # K_t x the measured current
    tf = got["/tf"][0].ros_msg.transforms
    assert len(tf) >= 6 and all(t.header.frame_id and t.child_frame_id for t in tf)
    quat = np.array([[t.transform.rotation.x, t.transform.rotation.y, t.transform.rotation.z,
                      t.transform.rotation.w] for t in tf])
    assert np.allclose(np.linalg.norm(quat, axis=1), 1.0)
    assert got["/robot_description"][0].ros_msg.data == Path(URDF).read_text()
    logs = [(m.ros_msg.level, m.ros_msg.msg) for m in got["/rosout"]]
    assert (40, logs[1][1]) == logs[1] and logs[1][1].startswith("fault ") and "EMCY 0x8130" in logs[1][1]
    assert logs[0][0] == 20 and logs[2][0] == 30


@pytest.mark.unit
def test_log_ros2_exports_a_pure_ros2_bag(tmp_path):
    src, out = tmp_path / "json.mcap", tmp_path / "bag.mcap"
    stamps, q = a_log(src, "json", seconds=2.0)
    proc = run_cli("log", "ros2", str(src), str(out), "--rate", "100", "--json")
    data = json.loads(proc.stdout)
    assert data["rows"] == 2000 and data["events"] == 3 and 195 <= data["joint_states"] <= 201
    with open(out, "rb") as fh:
        reader = make_reader(fh)
        header = reader.get_header()
        summary = reader.get_summary()
    assert header.profile == "ros2"  # what rosbag2 writes and ros2 bag play expects
    assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}  # one serialization format only
    assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
    got = ros2_messages(out)
    assert set(got) == {"/joint_states", "/tf", "/robot_description", "/rosout"}
    last = got["/joint_states"][-1]
    k = int(np.searchsorted(stamps, last.log_time_ns))
    assert np.allclose(last.ros_msg.position, q[k])
    same = run_cli("log", "ros2", str(src), str(src), check=False)
    assert same.returncode != 0 and "overwrite the input" in same.stderr


needs_ros2 = pytest.mark.skipif(REASON is not None, reason=f"the ros2 extra is not installed: {REASON}")


@pytest.mark.unit
@needs_ros2
def test_ros_type_support_decodes_what_dragd_encoded(tmp_path):
    from rcl_interfaces.msg import Log
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import JointState
    from std_msgs.msg import String

    path = tmp_path / "t.mcap"
    stamps, q = a_log(path, "ros2")
    types = {"/joint_states": JointState, "/robot_description": String, "/rosout": Log}
    seen = set()
    with open(path, "rb") as fh:
        for _schema, channel, message in make_reader(fh).iter_messages():
            if channel.topic in types:
                msg = deserialize_message(message.data, types[channel.topic])
                seen.add(channel.topic)
                if channel.topic == "/joint_states":
                    k = int(np.searchsorted(stamps, message.log_time))
                    assert list(msg.name) == JOINTS and np.allclose(msg.position, q[k])
    assert seen == set(types)


def _fields(text: str) -> list[str]:
    """The field lines of a .msg text (comments and blank lines dropped, whitespace normalised, package-local
    types qualified as the ros2msg encoding writes them)."""
    out = []
    for line in text.splitlines():
        line = re.sub(r"#.*", "", line).strip()
        if line:
            out.append(" ".join(line.split()))
    return out


@pytest.mark.unit
@needs_ros2
def test_definitions_match_the_installed_message_packages():
    import sensor_msgs

    share = Path(sensor_msgs.__file__).resolve().parents[4] / "share"
    if not (share / "sensor_msgs" / "msg" / "JointState.msg").is_file():
        pytest.skip(f"no .msg files under {share}")
    local = {"geometry_msgs": {"Transform", "Vector3", "Quaternion", "TransformStamped"}}
    for name, text in DEFINITIONS.items():
        parts = text.split("=" * 80 + "\n")
        pkg, _, typ = name.split("/")
        blocks = [(pkg, typ, parts[0])] + [(p.splitlines()[0][5:].split("/")[0], p.splitlines()[0][5:].split("/")[1],
                                            "\n".join(p.splitlines()[1:])) for p in parts[1:]]
        for bpkg, btyp, body in blocks:
            msg_file = share / bpkg / "msg" / f"{btyp}.msg"
            if not msg_file.is_file():  # (tf2_msgs is not on PyPI: its one field is checked by hand below)
                assert (bpkg, btyp) == ("tf2_msgs", "TFMessage"), msg_file
                assert _fields(body) == ["geometry_msgs/TransformStamped[] transforms"]
                continue
            want = _fields(msg_file.read_text())
            want = [" ".join([f"{bpkg}/{w.split()[0]}" if w.split()[0].rstrip("[]") in local.get(bpkg, set())
                              else w.split()[0], *w.split()[1:]]) for w in want]
            assert _fields(body) == want, (name, bpkg, btyp)


@pytest.mark.lockstep
def test_daemon_writes_joint_states_in_ros2_encoding(tmp_path):
    mcap = tmp_path / "daemon.mcap"
    with Rig("ros2-mcap", workdir=tmp_path, telemetry=mcap, daemon_args=["--foxglove-encoding", "ros2"]) as rig:
        rig.start_sim()
        rig.start_daemon()
        rig.must("start")
        rig.sleep(1.0)
        state = rig.must("state")
        t_state = round(rig.now() * 1e9)  # (on the lockstep clock, log times are the simulated time)
        rig.sleep(0.2)
        rig.must("stop")
    time.sleep(0.2)  # (the daemon's writer finished the file at exit)
    got = ros2_messages(mcap)
    assert {"/joint_states", "/tf", "/robot_description", "/rosout"} <= set(got)
    js = got["/joint_states"]
    assert len(js) > 20 and list(js[-1].ros_msg.name) == JOINTS
    at = min(js, key=lambda m: abs(m.log_time_ns - t_state)).ros_msg  # holding, as the state answer was taken
    assert np.abs(np.array(at.position) - state["q_rad"]).max() < math.radians(0.1)
    # effort: the daemon's K_t x I (the state answer's), holding the arm against gravity
    assert np.abs(np.array(at.effort) - state["effort_Nm"]).max() < 0.05 * np.abs(state["effort_Nm"]).max()
    assert any("hold" in m.ros_msg.msg for m in got["/rosout"])
