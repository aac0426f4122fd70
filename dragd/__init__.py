"""dragd: sensorless hand-guiding (zero-force drag teaching) daemon for CANopen CiA 402 cobot arms."""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

_SOURCE_VERSION = "0.1.0"  # keep equal to pyproject's [project] version; used when dragd is not installed

try:
    __version__: str = version("dragd")
except PackageNotFoundError:  # a source tree on PYTHONPATH, never installed
    __version__ = _SOURCE_VERSION

__all__ = ["__version__"]
