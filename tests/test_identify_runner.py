"""``identify run``'s hand-over of motion files to the daemon (without processes): the spool folder under systemd."""

from __future__ import annotations

import pytest

pytestmark = pytest.mark.unit


def test_motion_files_go_to_the_daemons_spool_when_it_has_one(tmp_path):
    """Under systemd the daemon has a private /tmp: 'identify run' leaves its motion files in the daemon's spool
    folder (status: spool_dir), readable by the daemon's group; without one, in a temporary folder."""
    import stat
    import tempfile
    from pathlib import Path

    from dragd.identify.runner import motion_workdir

    spool = tmp_path / "spool"
    spool.mkdir()
    work = motion_workdir({"spool_dir": str(spool)})
    assert work.parent == spool and stat.S_IMODE(work.stat().st_mode) == 0o750
    for gone in (None, str(tmp_path / "missing")):  # no spool (a daemon outside systemd), or none here
        assert motion_workdir({"spool_dir": gone}).parent == Path(tempfile.gettempdir())


def test_status_names_the_spool_folder_and_requests_may_use_it(tmp_path):
    from dragd.config import load_config

    from inproc import InProcess

    cfg = load_config(None)
    spool = tmp_path / "spool"
    spool.mkdir()
    cfg = cfg.model_copy(update={"control": cfg.control.model_copy(update={"spool_dir": str(spool)})})
    ip = InProcess(cfg)
    assert ip.d.status()["spool_dir"] == str(spool)
    assert ip.d.paths.check("track", spool / "x" / "chunk0.npz") == spool.resolve() / "x" / "chunk0.npz"
    missing = cfg.model_copy(update={"control": cfg.control.model_copy(update={"spool_dir": str(tmp_path / "no")})})
    assert InProcess(missing).d.status()["spool_dir"] is None
