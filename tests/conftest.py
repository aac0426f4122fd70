"""Shared fixtures: paths, the default config, a CLI runner that runs the real `dragd` entry point."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DEFAULT_CONFIG = REPO / "config" / "default.yaml"


def run_cli(*args: str, check: bool = True, timeout: float = 120.0, env: dict | None = None) -> subprocess.CompletedProcess:
    """Run ``python -m dragd ARGS`` as a real process."""
    proc = subprocess.run([sys.executable, "-m", "dragd", *args], capture_output=True, text=True, timeout=timeout, env=env)
    if check and proc.returncode != 0:
        raise AssertionError(f"dragd {' '.join(args)} failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}")
    return proc


def cli_json(*args: str) -> dict:
    return json.loads(run_cli(*args, "--json").stdout)


@pytest.fixture
def default_config_path() -> Path:
    return DEFAULT_CONFIG
