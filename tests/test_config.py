"""Configuration: the shipped files load; bad values, unknown keys and missing files give the promised messages."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from dragd.config import ConfigError, load_config, load_params

from conftest import DEFAULT_CONFIG, REPO, run_cli

pytestmark = pytest.mark.unit


def _write(tmp_path: Path, data: dict, name: str = "c.yaml") -> Path:
    p = tmp_path / name
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    return p


@pytest.fixture
def base() -> dict:
    return yaml.safe_load(DEFAULT_CONFIG.read_text())


@pytest.mark.parametrize("path", sorted((REPO / "config").glob("*.yaml")))
def test_shipped_configs_load(path):
    """Every shipped config loads and names its robot's joints, in the URDF's order (config/dual_arm.yaml: two arms,
    ``left_joint1`` … ``right_joint6``)."""
    from dragd.model import RobotModel

    cfg = load_config(path)
    assert cfg.joint_names == list(RobotModel.from_config(cfg).joint_names)


def test_bad_value_names_file_key_and_expectation(tmp_path, base):
    base["joints"][2]["gear_ratio"] = "abc"
    p = _write(tmp_path, base)
    with pytest.raises(ConfigError) as e:
        load_config(p)
    assert str(e.value) == f"{p}: joints[2].gear_ratio: expected a positive number, got 'abc'"


def test_breakout_slip_is_at_least_one_encoder_count(tmp_path, base):
    """Below one count, encoder jitter alone would fire the start-up latch; the default is 1.25 counts."""
    base["joints"][2]["startup"]["breakout_slip_rad"] = 1e-6
    p = _write(tmp_path, base)
    with pytest.raises(ConfigError) as e:
        load_config(p)
    assert str(e.value) == (f"{p}: joints[2]: startup.breakout_slip_rad: expected 0 (off) or at least one encoder "
                            f"count (1.2e-05 rad), got 1e-06")
    base["joints"][2]["startup"]["breakout_slip_rad"] = 0.0  # off
    base["joints"][3]["encoder_counts_per_rev"] = 2**17
    cfg = load_config(_write(tmp_path, base, "ok.yaml"))
    assert cfg.joints[2].breakout_slip_rad == 0.0
    assert cfg.joints[3].breakout_slip_rad == pytest.approx(1.25 * 2 * 3.141592653589793 / 2**17)


def test_negative_and_out_of_range(tmp_path, base):
    base["joints"][0]["current_limit_A"] = -1
    base["joints"][1]["node_id"] = 300
    base["joints"][1]["friction"]["coulomb_neg_A"] = 0.5
    p = _write(tmp_path, base)
    with pytest.raises(ConfigError) as e:
        load_config(p)
    msg = str(e.value)
    assert f"{p}: joints[0].current_limit_A: expected a positive number, got -1" in msg
    assert f"{p}: joints[1].node_id: expected a CANopen node id 1..127, got 300" in msg
    assert "joints[1].friction.coulomb_neg_A: expected a number <= 0" in msg


def test_unknown_key(tmp_path, base):
    base["joints"][1]["gear_ratoi"] = 100
    base["loop"]["rate"] = 5
    p = _write(tmp_path, base)
    with pytest.raises(ConfigError) as e:
        load_config(p)
    msg = str(e.value)
    assert f"{p}: joints[1].gear_ratoi: unknown key; expected one of: name, node_id" in msg
    assert f"{p}: loop.rate: unknown key" in msg


def test_missing_file_and_bad_yaml(tmp_path):
    with pytest.raises(ConfigError, match=r"nope\.yaml: file not found"):
        load_config(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("joints: [\n  - name: joint1\n   node_id: 1\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml: not valid YAML \(line"):
        load_config(bad)


def test_missing_required_and_cross_checks(tmp_path, base):
    del base["joints"][0]["rated_current_A"]
    base["joints"][4]["bus"] = "nonexistent"
    p = _write(tmp_path, base)
    msg = str(pytest.raises(ConfigError, load_config, p).value)
    assert "joints[0].rated_current_A: missing required key" in msg
    base = yaml.safe_load(DEFAULT_CONFIG.read_text())
    base["joints"][4]["bus"] = "nonexistent"
    msg = str(pytest.raises(ConfigError, load_config, _write(tmp_path, base)).value)
    assert "joints[4].bus: expected one of the buses ['arm'], got 'nonexistent'" in msg
    base = yaml.safe_load(DEFAULT_CONFIG.read_text())
    base["joints"][3]["torque_constant_Nm_per_A"] = None
    msg = str(pytest.raises(ConfigError, load_config, _write(tmp_path, base)).value)
    assert "expected exactly one of torque_constant_Nm_per_A" in msg


def test_params_file_overrides_config(tmp_path, base):
    params = {"version": 1, "method": "synchronous",
              "joints": {"joint2": {"torque_constant_Nm_per_A": 9.5,
                                    "friction": {"coulomb_pos_A": 0.8, "coulomb_neg_A": -1.2,
                                                 "viscous_A_s_per_rad": 0.4,
                                                 "static_pos_A": None}}}}
    pp = _write(tmp_path, params, "params.yaml")
    base["params"] = "params.yaml"
    cfg = load_config(_write(tmp_path, base))
    j2 = cfg.joints[1]
    assert j2.kt_Nm_per_A == 9.5
    assert j2.friction.coulomb_pos_A == 0.8 and j2.friction.coulomb_neg_A == -1.2
    assert j2.friction.viscous_pos_A_s_per_rad == 0.4 == j2.friction.viscous_neg_A_s_per_rad
    assert j2.friction.static_pos_A == base["joints"][1]["friction"]["static_pos_A"]  # null keeps the config's value
    # explicit --params wins over the file's own reference, and errors name the params file
    params["joints"]["joint9"] = {}
    bad = _write(tmp_path, params, "bad_params.yaml")
    with pytest.raises(ConfigError, match=r"bad_params\.yaml: joints: expected joint names among"):
        load_config(DEFAULT_CONFIG, bad)
    params["joints"] = {"joint2": {"friction": {"coulomb_pos_A": "x"}}}
    with pytest.raises(ConfigError, match=r"joints\.joint2\.friction\.coulomb_pos_A: expected a number >= 0, got 'x'"):
        load_params(_write(tmp_path, params, "p3.yaml"))
    assert pp.exists()


def test_cli_reports_config_errors(tmp_path, base):
    base["joints"][2]["gear_ratio"] = "abc"
    p = _write(tmp_path, base)
    proc = run_cli("model", "current", "--q", "0,0,0,0,0,0", "--dq", "0,0,0,0,0,0", "--config", str(p), check=False)
    assert proc.returncode == 2
    assert f"{p}: joints[2].gear_ratio: expected a positive number, got 'abc'" in proc.stderr
    proc = run_cli("config", "check", "--config", str(tmp_path / "missing.yaml"), check=False)
    assert proc.returncode == 2 and "missing.yaml: file not found" in proc.stderr
    assert run_cli("config", "check", "--config", str(DEFAULT_CONFIG)).returncode == 0


def test_telemetry_ring_must_hold_two_hand_overs(tmp_path, base):
    base["telemetry"]["capacity_rows"] = 400  # 1 kHz, rows handed to the writer process every 0.25 s
    msg = str(pytest.raises(ConfigError, load_config, _write(tmp_path, base)).value)
    assert "telemetry.capacity_rows: expected at least 500" in msg and "forward_interval_s 0.25" in msg
    base["telemetry"]["forward_interval_s"] = 0.1
    assert load_config(_write(tmp_path, base)).telemetry.forward_interval_s == 0.1
    base["telemetry"]["forward_interval_s"] = 0
    msg = str(pytest.raises(ConfigError, load_config, _write(tmp_path, base)).value)
    assert "telemetry.forward_interval_s: expected an interval in (0, 2] s" in msg


def test_friction_keys_have_one_owner() -> None:
    """The identified friction (FrictionParams) is the configured friction's fields (FrictionConfig), each optional,
    plus one viscous slope for both directions; identification's keys are those fields (identify/results.py)."""
    from dragd.config import FrictionConfig, FrictionParams
    from dragd.identify.results import FRICTION_KEYS

    assert set(FrictionParams.model_fields) == set(FrictionConfig.model_fields) | {"viscous_A_s_per_rad"}
    assert all(FrictionParams.model_fields[k].default is None for k in FrictionParams.model_fields)
    assert FRICTION_KEYS == tuple(FrictionParams.model_fields)
