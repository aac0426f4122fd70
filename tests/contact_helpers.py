"""The contact modules' calibration (tests/test_contact_daemon.py, tests/test_contact_daemon_runs.py): the contact
demo's first session as a user runs it (dragd/lab/demo_contact.py ``calibrate_session``: a free-motion run of the
simulated arm on the lockstep clock, recorded, then ``dragd contact calibrate`` on it), and the identified model of
its recording (``identify_session``: ``dragd identify fit --method full``).

Made once per source tree by the first test process that needs it (under a lock: another worker waits for its file)
and kept beside the identification tests' offline logs (tests/identify_helpers.py: a folder named by a hash of
dragd/, sim/, config/ and the versions; this file's hash names the subfolder). On the lockstep clock the session is
the same bit for bit from the same sources (tests/test_lockstep.py), so a later run of the same sources reads what an
earlier one made and any change makes it again. ``DRAGD_TEST_CACHE=off``: a folder per test run."""

from __future__ import annotations

import fcntl
import hashlib
import json
import shutil
from pathlib import Path
from typing import Any

from dragd.config import load_config
from dragd.lab.demo_contact import calibrate_session, detection_config, identify_session
from dragd.lab.rig import Rig

from identify_helpers import TMP

FOLDER = TMP / f"contact-calibration-{hashlib.sha256(Path(__file__).read_bytes()).hexdigest()[:12]}"
_DONE = "report.json"  # written last: the calibration is complete


def calibration() -> tuple[Path, dict[str, Any]]:
    """The params file with the calibrated bands, and ``dragd contact calibrate``'s report."""
    with open(f"{FOLDER}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # (another process calibrating: wait for its files)
        if not (FOLDER / _DONE).is_file():
            shutil.rmtree(FOLDER, ignore_errors=True)  # (an interrupted attempt)
            FOLDER.mkdir(parents=True)
            params, report = calibrate_session(None, FOLDER, lockstep=True)
            assert params == FOLDER / "contact.yaml", params
            (FOLDER / f"{_DONE}.tmp").write_text(json.dumps(report))
            (FOLDER / f"{_DONE}.tmp").replace(FOLDER / _DONE)
    report = json.loads((FOLDER / _DONE).read_text())
    assert report["margin"] == 1.5 and set(report["joints"]) == set(load_config().joint_names), report
    return FOLDER / "contact.yaml", report


def identified() -> Path:
    """The identified model of the calibration's recording (rigid-body base parameters, friction, rotor inertias)."""
    calibration()
    out = FOLDER / "identified.yaml"
    with open(f"{FOLDER}-identified.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not out.is_file():
            got = identify_session(None, FOLDER)
            assert got == out, got
    return out


def contact_rig(tmp_path: Path, bands: Path, reactions: dict[str, str] | None = None, **contact: object) -> Rig:
    """Simulator and daemon (lockstep) with the bands, the reactions per mode and ``contact`` settings; started."""
    cfg = detection_config(None, bands, tmp_path, reactions)
    if contact:
        import yaml

        data = yaml.safe_load(cfg.read_text())
        data["contact"].update(contact)
        cfg.write_text(yaml.safe_dump(data, sort_keys=False))
    rig = Rig("contact", workdir=tmp_path / "rig", config=cfg, telemetry=tmp_path / "t.mcap", lockstep=True,
              allow_dirs=[tmp_path])
    rig.start_sim()
    rig.start_daemon()
    rig.must("start")
    return rig
