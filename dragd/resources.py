"""Files dragd ships with: the drives' EDS, the example configurations, the systemd files (``dragd/data``).

``dragd/data`` holds links to the repository's top-level ``canopen_eds/``, ``config/``, ``systemd/`` and
``docs/SYSTEMD.md`` (the sources); a built wheel carries their content, so an installed daemon finds them without
a checkout beside it. ``python -m dragd.resources`` prints where they are (docs/SYSTEMD.md installs from there).
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


def systemd_path(name: str) -> Path:
    """A systemd file shipped with dragd: ``dragd.service``, ``dragd.sysusers.conf``, ``dragd.tmpfiles.conf``, the
    drop-ins ``dragd-lab-udp.conf`` and ``dragd-cpu-latency.conf`` (with the udev rule
    ``70-dragd-cpu-latency.rules``)."""
    return DATA_DIR / "systemd" / name


def main() -> int:
    """Print the data directory and every shipped file (one per line) for install scripts."""
    print(DATA_DIR)
    for path in sorted(p for p in DATA_DIR.rglob("*") if p.is_file()):
        print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
