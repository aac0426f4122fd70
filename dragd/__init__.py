"""dragd: sensorless hand-guiding (zero-force drag teaching) daemon for CANopen CiA 402 cobot arms."""

from __future__ import annotations

_SOURCE_VERSION = "0.1.0"  # keep equal to pyproject's [project] version; used when dragd is not installed

__all__ = ["__version__"]


def __getattr__(name: str) -> str:
    """``__version__``: the installed distribution's, else the source tree's (looked up on first use only: every
    process imports this package, few ask for the version)."""
    if name != "__version__":
        raise AttributeError(f"module 'dragd' has no attribute {name!r}")
    from importlib.metadata import PackageNotFoundError, version

    try:
        v = version("dragd")
    except PackageNotFoundError:  # a source tree on PYTHONPATH, never installed
        v = _SOURCE_VERSION
    globals()["__version__"] = v
    return v
