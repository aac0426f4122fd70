"""Files dragd ships with: the drives' EDS and the example configurations (``dragd/data``), the bundled URDFs.

``dragd/data`` holds links to the repository's top-level ``canopen_eds/`` and ``config/`` (the sources); a built
wheel carries their content, so an installed daemon finds them without a checkout beside it.
"""

from __future__ import annotations

from pathlib import Path

DATA_DIR = Path(__file__).resolve().parent / "data"
EDS_FILE = "joint_drive.eds"


def eds_path(name: str = EDS_FILE) -> Path:
    """The EDS of the joint drives (CiA 402) that the master and the simulated drives load."""
    return DATA_DIR / "canopen_eds" / name


def config_path(name: str = "default.yaml") -> Path:
    """An example configuration shipped with dragd (``default.yaml``: the bundled seed cobot)."""
    return DATA_DIR / "config" / name


def shipped_configs() -> list[Path]:
    return sorted((DATA_DIR / "config").glob("*.yaml"))
