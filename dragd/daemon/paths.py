"""Where control-socket requests may make the daemon read or write files: inside its folders, nowhere else.

A request names files (``record`` path, ``track`` file, ``teach``/``replay`` programs given as paths). The daemon
runs as its own user with its own rights: without a bound, anyone allowed on the socket could have it overwrite or
read any file it can reach (``teach start /etc/... --overwrite``). Every such path is resolved (``..`` and symbolic
links followed) and must lie inside one of ``control.allowed_dirs`` (default: the program folder, the telemetry
folder, /var/lib/dragd, the spool folder and the daemon's temporary folder — private under systemd's PrivateTmp) or
a ``dragd run --allow-dir DIR``.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from dragd.config import Config

STATE_DIR = "/var/lib/dragd"  # the systemd unit's StateDirectory


def allowed_dirs(cfg: Config, telemetry_path: str | None = None, extra: list[str] | None = None) -> list[Path]:
    """The folders socket requests may use, resolved (configured, or the defaults above; plus ``extra``)."""
    if cfg.control.allowed_dirs is not None:
        dirs = [Path(d).expanduser() for d in cfg.control.allowed_dirs]
        dirs = [d if d.is_absolute() else cfg.base_dir / d for d in dirs]
    else:
        dirs = [cfg.program_dir, Path(STATE_DIR), _spool_path(cfg), Path(tempfile.gettempdir())]
        tel = telemetry_path or cfg.telemetry.path
        if tel:
            dirs.append(Path(tel).expanduser().absolute().parent)
    dirs += [Path(d).expanduser().absolute() for d in (extra or [])]
    out: list[Path] = []
    for d in dirs:
        r = Path(os.path.realpath(d))
        if r not in out:
            out.append(r)
    return out


def _spool_path(cfg: Config) -> Path:
    p = Path(cfg.control.spool_dir).expanduser()
    return p if p.is_absolute() else cfg.base_dir / p


def spool_dir(cfg: Config) -> str | None:
    """The folder clients leave trajectory files in for this daemon (``control.spool_dir``), when it exists."""
    p = _spool_path(cfg)
    return str(p) if p.is_dir() else None


class PathPolicy:
    """``check(what, path)``: the resolved path when it lies inside an allowed folder, else ValueError naming both."""

    def __init__(self, dirs: list[Path]) -> None:
        self.dirs = dirs

    def check(self, what: str, path: str | os.PathLike[str]) -> Path:
        p = Path(os.path.realpath(Path(path).expanduser()))
        if any(p == d or d in p.parents for d in self.dirs):
            return p
        raise ValueError(f"{what}: {path} is outside the folders the daemon may use ({', '.join(map(str, self.dirs))}"
                         "; control.allowed_dirs in the configuration, or dragd run --allow-dir DIR)")
