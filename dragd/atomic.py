"""Files written whole or not at all: a temporary file in the same directory, fsync, rename, fsync the directory.

A crash or power loss leaves either the previous file or the new one, never half of one (params, taught programs).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path


def write_atomic(path: str | os.PathLike[str], data: str | bytes, mode: int = 0o644) -> Path:
    """Replace ``path`` with ``data`` atomically and durably; the temporary file is removed on any error."""
    path = Path(path)
    raw = data.encode() if isinstance(data, str) else data
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(raw)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    try:
        dfd = os.open(path.parent, os.O_RDONLY | os.O_DIRECTORY)
    except OSError:
        return path
    try:
        os.fsync(dfd)  # the rename itself survives a power loss
    finally:
        os.close(dfd)
    return path
