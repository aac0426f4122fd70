"""What the wheel is built from, checked in the source tree (tests/wheel/run checks an installed wheel itself)."""

from __future__ import annotations

import fnmatch
import tomllib
from pathlib import Path

import pytest

import dragd
from dragd import resources

REPO = Path(__file__).resolve().parents[2]
PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())

pytestmark = pytest.mark.unit


def test_source_version_matches_pyproject() -> None:
    assert dragd._SOURCE_VERSION == PYPROJECT["project"]["version"]
    assert isinstance(dragd.__version__, str) and dragd.__version__


def test_license_is_apache_2() -> None:
    assert PYPROJECT["project"]["license"] == "Apache-2.0"
    assert PYPROJECT["project"]["license-files"] == ["LICENSE"]
    assert (REPO / "LICENSE").read_text().lstrip().startswith("Apache License")


def test_data_links_resolve_and_are_packaged() -> None:
    """Each file under dragd/data (links to the top-level sources) exists and matches the package-data globs."""
    globs = PYPROJECT["tool"]["setuptools"]["package-data"]["dragd"]
    files = sorted(p for p in resources.DATA_DIR.rglob("*") if not p.is_dir())
    assert files, resources.DATA_DIR
    for path in files:
        assert path.exists(), f"{path} -> {path.resolve()}: dangling link"
        rel = path.relative_to(REPO / "dragd").as_posix()
        assert any(fnmatch.fnmatch(rel, g) for g in globs), f"{rel} is not in package-data {globs}"
    assert (REPO / "dragd" / "py.typed").exists() and "py.typed" in globs


def test_resources_name_the_shipped_files() -> None:
    assert resources.eds_path().is_file()
    assert resources.config_path().is_file()
    assert {p.name for p in resources.shipped_configs()} >= {"default.yaml"}
    for name in ("dragd.service", "dragd-ros2.service", "dragd.sysusers.conf", "dragd.tmpfiles.conf",
                 "dragd-lab-udp.conf", "dragd-cpu-latency.conf", "70-dragd-cpu-latency.rules"):
        assert resources.systemd_path(name).is_file(), name
    assert (resources.DATA_DIR / "docs" / "SYSTEMD.md").is_file()
    assert (resources.DATA_DIR / "docs" / "ROS2.md").is_file()  # dragd-ros2.service's Documentation=


def test_sim_data_is_packaged() -> None:
    globs = PYPROJECT["tool"]["setuptools"]["package-data"]["sim"]
    for rel in ("config/seed_cobot.yaml", "scenarios/flange_drag.yaml"):
        assert (REPO / "sim" / rel).is_file()
        assert any(fnmatch.fnmatch(rel, g) for g in globs), rel
