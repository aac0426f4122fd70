"""docs/ROS2.md's ros2_control route checked against the code of what we did not make: the URDF's ``<ros2_control>``
tag against topic_based_ros2_control (the hardware plugin: its class, the parameters it reads, how it parses them,
the interfaces it offers, its topics' QoS) and ros2_control (the tags and attributes its URDF parser reads), the
controllers' YAML against ros2_control's controller_manager and ros2_controllers (the plugin types, every parameter
declared with its type and validation) on the branches of the ROS 2 releases the docs name.

The sources are public repositories fetched beside the project, never committed: ``$DRAGD_ROS2_SOURCES`` (default
/work/.mirror) holds ``PickNikRobotics+topic_based_ros2_control/repo``, ``ros-controls+ros2_control/repo`` and
``ros-controls+ros2_controllers/repo`` (git repositories, bare or cloned); the test skips without them. What only an
integrator's ROS 2 install can show (the controller manager loading the plugin, MoveIt executing through it) is said
in docs/ROS2.md."""

from __future__ import annotations

import os
import re
import subprocess
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import pytest
import yaml

pytestmark = pytest.mark.unit

ROOT = Path(__file__).resolve().parent.parent
SOURCES = Path(os.environ.get("DRAGD_ROS2_SOURCES", "/work/.mirror"))
TBR, RC, RCS = "PickNikRobotics+topic_based_ros2_control", "ros-controls+ros2_control", "ros-controls+ros2_controllers"
RELEASES = ("jazzy", "kilted")  # the ROS 2 releases docs/ROS2.md names (branches of ros2_control, ros2_controllers)


class Repo:
    def __init__(self, name: str) -> None:
        self.path = SOURCES / name / "repo"

    def available(self) -> bool:
        return subprocess.run(["git", "-C", str(self.path), "rev-parse", "--git-dir"],
                              capture_output=True).returncode == 0

    def show(self, path: str, ref: str = "HEAD") -> str:
        for r in (ref, f"origin/{ref}"):
            got = subprocess.run(["git", "-C", str(self.path), "show", f"{r}:{path}"], capture_output=True, text=True)
            if got.returncode == 0:
                return got.stdout
        raise AssertionError(f"{self.path}: no {path} at {ref}")

    def commit(self, ref: str = "HEAD") -> str:
        return subprocess.run(["git", "-C", str(self.path), "rev-parse", "--short", ref], capture_output=True,
                              text=True).stdout.strip()


REPOS = {n: Repo(n) for n in (TBR, RC, RCS)}
MISSING = [n for n, r in REPOS.items() if not r.available()]
needs_sources = pytest.mark.skipif(bool(MISSING), reason=f"the fetched sources are not at {SOURCES}: {MISSING} "
                                                         "(set $DRAGD_ROS2_SOURCES)")


def doc_block(lang: str, contains: str) -> str:
    text = (ROOT / "docs" / "ROS2.md").read_text(encoding="utf-8")
    blocks = [b for b in re.findall(rf"```{lang}\n(.*?)```", text, re.S) if contains in b]
    assert len(blocks) == 1, f"docs/ROS2.md: expected one ```{lang} block with {contains!r}, found {len(blocks)}"
    return blocks[0]


def urdf_tag() -> ET.Element:
    return ET.fromstring(doc_block("xml", "<ros2_control"))


def controllers() -> dict[str, Any]:
    return yaml.safe_load(doc_block("yaml", "controller_manager:"))


def constant(source: str, name: str) -> str:
    m = re.search(rf"\b{name}(?:\[\])?\s*=\s*\"([^\"]*)\"", source)
    assert m, f"no constant {name} in the source"
    return m.group(1)


def test_the_doc_blocks_parse_without_the_sources():
    tag = urdf_tag()
    assert tag.tag == "ros2_control" and tag.find("hardware/plugin") is not None
    assert {j.get("name") for j in tag.findall("joint")} == {"joint1"}  # (the others "alike")
    c = controllers()
    assert "controller_manager" in c and "joint_trajectory_controller" in c


@needs_sources
def test_urdf_tag_as_ros2_control_parses_it():
    errors = []
    tag = urdf_tag()
    for release in RELEASES:
        src = REPOS[RC].show("hardware_interface/src/component_parser.cpp", release)
        tags = {k: constant(src, k) for k in ("kROS2ControlTag", "kHardwareTag", "kPluginNameTag", "kParamTag",
                                              "kJointTag", "kCommandInterfaceTag", "kStateInterfaceTag",
                                              "kNameAttribute", "kTypeAttribute")}
        system = constant(REPOS[RC].show("hardware_interface/src/resource_manager.cpp", release), "system_type")
        if tag.tag != tags["kROS2ControlTag"]:
            errors.append(f"{release}: root tag {tag.tag!r}, the parser reads {tags['kROS2ControlTag']!r}")
        if tag.get(tags["kTypeAttribute"]) != system or not tag.get(tags["kNameAttribute"]):
            errors.append(f"{release}: <ros2_control> needs name and type={system!r}, got {tag.attrib}")
        for child in tag:
            if child.tag not in (tags["kHardwareTag"], tags["kJointTag"]):
                errors.append(f"{release}: <{child.tag}> is not a child the parser reads")
        for child in tag.find(tags["kHardwareTag"]):
            if child.tag not in (tags["kPluginNameTag"], tags["kParamTag"]):
                errors.append(f"{release}: <hardware><{child.tag}> is not read")
        for joint in tag.findall(tags["kJointTag"]):
            for child in joint:
                if child.tag not in (tags["kCommandInterfaceTag"], tags["kStateInterfaceTag"]):
                    errors.append(f"{release}: <joint><{child.tag}> is not read")
                elif not child.get(tags["kNameAttribute"]):
                    errors.append(f"{release}: <{child.tag}> without a name")
    assert not errors, "\n".join(errors)


@needs_sources
def test_urdf_tag_against_topic_based_ros2_control():
    repo = REPOS[TBR]
    src = repo.show("src/topic_based_system.cpp")
    header = repo.show("include/topic_based_ros2_control/topic_based_system.hpp")
    plugins = ET.fromstring(repo.show("topic_based_ros2_control_plugin_description.xml"))
    tag = urdf_tag()
    errors = []
    plugin = tag.findtext("hardware/plugin")
    classes = [c.get("name") for c in plugins.iter("class")]
    if plugin not in classes:
        errors.append(f"plugin {plugin!r}: the package exports {classes}")
    read = set(re.findall(r'get_hardware_parameter\("(\w+)"', src)) | \
        set(re.findall(r'hardware_parameters\.find\("(\w+)"\)', src))
    params = {p.get("name"): (p.text or "").strip() for p in tag.findall("hardware/param")}
    for name in params:
        if name not in read:
            errors.append(f"<param name={name!r}>: TopicBasedSystem reads only {sorted(read)} (at {repo.commit()})")
    # the topics: the bridge's pair (docs: the bridge's states remapped to /dragd/joint_states)
    if params.get("joint_commands_topic") != "/dragd/joint_commands":
        errors.append(f"joint_commands_topic {params.get('joint_commands_topic')!r}: the bridge (node /dragd) "
                      "subscribes ~/joint_commands")
    if params.get("joint_states_topic") != "/dragd/joint_states" or \
            "-r /joint_states:=/dragd/joint_states" not in (ROOT / "docs" / "ROS2.md").read_text(encoding="utf-8"):
        errors.append("joint_states_topic: expected /dragd/joint_states with the bridge's remap in the docs")
    # trigger_joint_command_threshold: std::stod, and write() skips an update only while diff <= threshold, diff a
    # sum of absolute values (>= 0): a negative threshold publishes every update, as the docs' comment says
    if "trigger_joint_command_threshold_ = std::stod(it->second)" not in src:
        errors.append("trigger_joint_command_threshold is no longer parsed with std::stod")
    if not re.search(r"std::abs\(d1\) \+ std::abs\(d2\)", src) or "if (diff <= trigger_joint_command_threshold_)" \
            not in src:
        errors.append("write(): the skip rule changed (diff <= trigger_joint_command_threshold_, diff >= 0)")
    threshold = params.get("trigger_joint_command_threshold", "")
    try:
        if float(threshold) >= 0:
            errors.append(f"trigger_joint_command_threshold {threshold}: a command equal to the state would not be "
                          "published (the stream's samples are its keepalive)")
    except ValueError:
        errors.append(f"trigger_joint_command_threshold {threshold!r}: not a number std::stod parses")
    # interfaces: the standard ones it maps (position, velocity, acceleration, effort: ros2_control's HW_IF_*)
    hw_if = REPOS[RC].show("hardware_interface/include/hardware_interface/types/hardware_interface_type_values.hpp",
                           RELEASES[-1])
    offered = {constant(hw_if, n) for n in re.findall(r"hardware_interface::(HW_IF_\w+)",
                                                     header.split("standard_interfaces_", 1)[1].split(";", 1)[0])}
    for joint in tag.findall("joint"):
        for child in joint:
            if child.get("name") not in offered:
                errors.append(f"{joint.get('name')} {child.tag} {child.get('name')!r}: TopicBasedSystem maps {offered}")
    # read(): the states are matched by joint name (the bridge publishes the URDF's names)
    if "joint_name == info.name" not in src:
        errors.append("read(): no longer matches the states by joint name")
    assert not errors, "\n".join(errors)


@needs_sources
def test_topic_qos_pairs_are_compatible():
    """TopicBasedSystem publishes commands with ``rclcpp::QoS(1)`` (reliable, keep last 1) and subscribes states with
    ``rclcpp::SensorDataQoS()`` (best effort); the bridge's ends (dragd/ros2/node.py) must match them."""
    from dragd.ros2 import unavailable

    if (why := unavailable()) is not None:
        pytest.skip(why)
    from rclpy.qos import QoSCompatibility, QoSProfile, qos_check_compatible, qos_profile_sensor_data

    src = REPOS[TBR].show("src/topic_based_system.cpp")
    assert re.search(r'get_hardware_parameter\("joint_commands_topic"[^)]*\)\s*,\s*rclcpp::QoS\(1\)', src)
    assert re.search(r'get_hardware_parameter\("joint_states_topic"[^)]*\)\s*,\s*rclcpp::SensorDataQoS\(\)', src)
    from rclpy.qos import ReliabilityPolicy

    from dragd.ros2.node import COMMANDS_QOS

    node_src = (ROOT / "dragd" / "ros2" / "node.py").read_text(encoding="utf-8")
    assert re.search(r'create_subscription\(JointState, "~/joint_commands", self._on_command, COMMANDS_QOS', node_src)
    assert 'create_publisher(JointState, "/joint_states", 10)' in node_src
    # best effort takes a reliable publisher (theirs) and a best-effort one (a controller's sensor-data QoS) alike
    assert COMMANDS_QOS.reliability == ReliabilityPolicy.BEST_EFFORT
    commands = qos_check_compatible(QoSProfile(depth=1), COMMANDS_QOS)  # their publisher, our reader
    states = qos_check_compatible(QoSProfile(depth=10), qos_profile_sensor_data)  # our publisher, their reader
    # (WARNING: only that liveliness is the middleware's default on both sides, which rclpy cannot judge)
    for verdict, why in (commands, states):
        assert verdict == QoSCompatibility.OK or (verdict == QoSCompatibility.WARNING and "liveliness" in why and
                                                  "reliab" not in why.lower() and "durab" not in why.lower()), why


def _declared(params: dict[str, Any], prefix: str = "") -> dict[str, dict[str, Any]]:
    """generate_parameter_library's YAML: every leaf (a dict with ``type``) by its dotted name."""
    out: dict[str, dict[str, Any]] = {}
    for k, v in params.items():
        if isinstance(v, dict) and "type" in v:
            out[prefix + k] = v
        elif isinstance(v, dict):
            out.update(_declared(v, f"{prefix}{k}."))
    return out


def _leaves(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_leaves(v, f"{prefix}{k}."))
        else:
            out[prefix + k] = v
    return out


TYPES = {"string_array": lambda v: isinstance(v, list) and all(isinstance(x, str) for x in v),
         "bool": lambda v: isinstance(v, bool), "double": lambda v: isinstance(v, float),
         "int": lambda v: isinstance(v, int) and not isinstance(v, bool), "string": lambda v: isinstance(v, str)}


def _check(name: str, value: Any, spec: dict[str, Any]) -> list[str]:
    """A ROS 2 parameter's type is strict (an integer literal for a double is refused); the validations we use."""
    errors = []
    if not TYPES.get(spec["type"], lambda _v: False)(value):
        errors.append(f"{name}: {value!r} is not of the declared type {spec['type']}")
        return errors
    for rule, arg in (spec.get("validation") or {}).items():
        bound = arg[0] if isinstance(arg, list) else arg
        if rule == "subset_of<>" and not set(value) <= set(arg[0]):
            errors.append(f"{name}: {value} not a subset of {arg[0]}")
        elif rule == "gt<>" and not value > bound:
            errors.append(f"{name}: {value} not > {bound}")
        elif rule in ("gt_eq", "gt_eq<>") and not value >= bound:
            errors.append(f"{name}: {value} not >= {bound}")
    return errors


@needs_sources
@pytest.mark.parametrize("release", RELEASES)
def test_controllers_yaml_against_controller_manager_and_ros2_controllers(release):
    c = controllers()
    errors = []
    cm = yaml.safe_load(REPOS[RC].show("controller_manager/src/controller_manager_parameters.yaml", release))
    cm_declared = _declared(cm["controller_manager"])
    cm_params = c["controller_manager"]["ros__parameters"]
    cm_src = REPOS[RC].show("controller_manager/src/controller_manager.cpp", release)
    if '"{}.type"' not in cm_src:
        errors.append("controller_manager no longer reads '<controller>.type'")
    types: dict[str, str] = {}
    for plugin_xml in ("joint_trajectory_controller/joint_trajectory_plugin.xml",
                       "joint_state_broadcaster/joint_state_plugin.xml"):
        for cls in ET.fromstring(REPOS[RCS].show(plugin_xml, release)).iter("class"):
            types[cls.get("name")] = plugin_xml.split("/")[0]
    for name, value in cm_params.items():
        if isinstance(value, dict):  # a controller: its type is a plugin ros2_controllers exports
            if set(value) != {"type"} or value["type"] not in types:
                errors.append(f"controller_manager.{name}: {value} (exported: {sorted(types)})")
        elif name in cm_declared:
            errors += _check(f"controller_manager.{name}", value, cm_declared[name])
        else:
            errors.append(f"controller_manager.{name}: not a parameter of the controller manager")
    jtc = yaml.safe_load(REPOS[RCS].show("joint_trajectory_controller/src/joint_trajectory_controller_parameters.yaml",
                                         release))
    declared = _declared(jtc["joint_trajectory_controller"])
    ours = _leaves(c["joint_trajectory_controller"]["ros__parameters"])
    for name, value in ours.items():
        if name not in declared:
            errors.append(f"joint_trajectory_controller.{name}: not a parameter of the controller in {release}")
        else:
            errors += _check(f"joint_trajectory_controller.{name}", value, declared[name])
    tag = urdf_tag()
    commands = {ci.get("name") for j in tag.findall("joint") for ci in j.findall("command_interface")}
    states = {si.get("name") for j in tag.findall("joint") for si in j.findall("state_interface")}
    if set(ours.get("command_interfaces", [])) != commands or not set(ours.get("state_interfaces", [])) <= states:
        errors.append(f"the controller's interfaces {ours.get('command_interfaces')} / {ours.get('state_interfaces')} "
                      f"against the URDF tag's {commands} / {states}")
    from dragd.config import load_config

    if ours.get("joints") != list(load_config(None).joint_names):
        errors.append(f"joints {ours.get('joints')}: the default robot's are {list(load_config(None).joint_names)}")
    assert not errors, f"{release}:\n" + "\n".join(errors)
