"""Item 6's proof, end to end: for an EDS, ``dragd config init --robot R.urdf --eds FILE``, ``config check``, the
simulated drive built from that EDS (``python -m sim run --eds FILE``) with ``dragd run --config cfg.yaml`` beside
it, ``start``, ``mode drag``, the operator's hand moving the arm (drift after release), ``identify run`` of a short
plan — what ``dragd bench drive_profiles --eds-dir DIR`` runs per file (dragd/lab/bench/drives.py). Drives that cannot
do torque control are refused by ``config check`` with the reason.

In-repo EDS variants run always; the vendors' files (never committed) from ``$DRAGD_EDS_DIR`` where present.
On the lockstep clock (the benchmark's default): the drive profile decides the row, not the machine's load.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from dragd.lab.bench.drives import _one_drive

from conftest import REPO

# a hang guard of wall time: on a loaded machine the lockstep clock runs slower, never wrong
pytestmark = [pytest.mark.lockstep, pytest.mark.slow, pytest.mark.timeout(1200)]

EDS_DIR = Path(os.environ.get("DRAGD_EDS_DIR", "/work/eds"))
REFUSED = {"technosoft_ipos": "no CST: 6502h supported modes 0x001F0065 lack cyclic synchronous torque",
           "schunk_prl120": "no target torque 6071h: the drive cannot be commanded in torque (CST)",
           "no_cst": "no CST: 6502h supported modes 0x00000080 lack cyclic synchronous torque"}
CASES = [REPO / "tests" / "data" / "eds" / f"{v}.eds" for v in ("only_6077h", "no_cst")] + \
    [EDS_DIR / f"{v}.eds" for v in ("maxon_epos4", "zeroerr_erob", "eyou_euservo", "wittenstein_simco",
                                   "technosoft_ipos", "schunk_prl120")]


# (Eyou has no 60B2h: its motions run in CST with dragd's position loop, docs/DRIVES.md; the in-repo no_60b2h variant's
# motions: tests/test_drive_motion_cst.py)
@pytest.mark.parametrize("eds", CASES, ids=[p.stem for p in CASES])
def test_config_init_check_boot_drag_identify(eds: Path) -> None:
    if not eds.is_file():
        pytest.skip(f"{eds} absent (set DRAGD_EDS_DIR to the fetched vendors' EDS files)")
    row = _one_drive(eds, {"clock": "lockstep"})
    assert row.get("clock", "lockstep") == "lockstep", row
    if eds.stem in REFUSED:
        assert row["refused_reason"] == REFUSED[eds.stem], row
        assert row["boot"] is None
        return
    assert row["config_check"] == "ok", row
    assert row["refused_reason"] is None
    assert row["boot"] == "ok", row
    assert isinstance(row["drag_drift_deg"], float) and row["drag_drift_deg"] <= 0.1, row
    assert row["identify"] == "ok", row
