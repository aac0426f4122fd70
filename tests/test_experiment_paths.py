"""An experiment's work folder given as a relative path (``dragd experiment … --work-dir w``): its rigs run their
simulator and daemon inside it, so every path they are handed must name the same file from there."""

from __future__ import annotations

from pathlib import Path

import pytest

from dragd.lab.experiment.bench import Bench

pytestmark = [pytest.mark.lockstep]


def test_a_relative_work_dir_reaches_the_rig(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    bench = Bench(Path("w"), progress=False, lockstep=True)
    with bench.rig("pose") as rig:  # the simulator's and the daemon's control sockets answer; the arm is in drag
        assert Path(rig.sim_socket).parent == tmp_path / "w" / "pose-1"
        assert rig.must("status")["mode"] == "drag"
        assert "q_rad" in rig.sim_call("state")
    assert (tmp_path / "w" / "pose-1.yaml").is_file()
