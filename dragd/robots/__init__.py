"""Bundled robot descriptions (URDF) and name resolution."""

from __future__ import annotations

from pathlib import Path

ROBOTS_DIR = Path(__file__).resolve().parent
BUNDLED = {p.stem: p for p in ROBOTS_DIR.glob("*.urdf")}


def resolve_urdf(name_or_path: str | Path, base_dir: Path | None = None) -> Path:
    """Return the URDF file for a bundled robot name (e.g. ``seed_cobot``) or a path.

    A relative path is taken relative to ``base_dir`` (the config file's folder) when given.
    """
    text = str(name_or_path)
    if text in BUNDLED:
        return BUNDLED[text]
    path = Path(text).expanduser()
    if not path.is_absolute() and base_dir is not None:
        path = base_dir / path
    if not path.is_file():
        names = ", ".join(sorted(BUNDLED))
        raise FileNotFoundError(f"robot '{text}': no such URDF file ({path}) and no bundled robot of that name "
                                f"(bundled: {names})")
    return path


def urdf_reference(name_or_path: str | Path, base_dir: Path | None = None) -> str:
    """How a configuration or sim truth names a robot: a bundled name as is, a URDF file by its absolute path."""
    text = str(name_or_path)
    return text if text in BUNDLED else str(resolve_urdf(name_or_path, base_dir).resolve())
