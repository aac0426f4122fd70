"""dragd.lab.bench.loop helpers: a process's CPU time from /proc and the py-spy profile summary."""

from __future__ import annotations

import subprocess
import sys

import pytest

from dragd.lab import bench
from dragd.lab.bench.loop import process_cpu_s, profile_summary

pytestmark = pytest.mark.unit


def test_process_cpu_counts_a_busy_child_not_a_sleeping_one() -> None:
    burn = ("import time\nt=time.process_time()\nwhile time.process_time()-t<0.6: pass\nprint('done', flush=True)\n"
            "time.sleep(60)")
    busy = subprocess.Popen([sys.executable, "-c", burn], stdout=subprocess.PIPE, text=True)
    idle = subprocess.Popen([sys.executable, "-c", "print('done', flush=True)\nimport time; time.sleep(60)"],
                            stdout=subprocess.PIPE, text=True)
    try:
        assert busy.stdout.readline() == "done\n" and idle.stdout.readline() == "done\n"  # type: ignore[union-attr]
        used_busy, used_idle = process_cpu_s(busy.pid), process_cpu_s(idle.pid)
    finally:
        busy.kill()
        idle.kill()
        busy.wait()
        idle.wait()
    assert used_busy >= 0.55  # its own CPU time, whatever else runs on the machine
    assert used_idle < 0.5 < used_busy


def test_process_cpu_of_a_missing_process_is_an_error() -> None:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    with pytest.raises(OSError):
        process_cpu_s(p.pid)


def test_profile_summary_self_and_inclusive_shares(tmp_path) -> None:
    stacks = tmp_path / "daemon.txt"
    stacks.write_text(
        "thread (1);run (dragd/daemon/cycle.py:120);step (dragd/daemon/cycle.py:90);"
        "compensate (dragd/control/law.py:300) 6\n"
        "thread (1);run (dragd/daemon/cycle.py:120);step (dragd/daemon/cycle.py:95) 2\n"
        "thread (1);run (dragd/daemon/cycle.py:120);select (selectors.py:468) 2\n"
        "not a stack line\n")
    text = profile_summary(stacks, top=3)
    lines = text.splitlines()
    assert lines[0] == "daemon: 10 samples"
    own = lines[lines.index("  top self:") + 1:lines.index("  top inclusive:")]
    assert own[0].split() == ["60.0", "%", "compensate", "(law.py)"]
    assert {tuple(line.split()[:1] + line.split()[2:]) for line in own[1:]} == {("20.0", "step", "(cycle.py)"),
                                                                                 ("20.0", "select", "(selectors.py)")}
    incl = lines[lines.index("  top inclusive:") + 1:]
    assert [line.split()[0] for line in incl] == ["100.0", "100.0", "80.0"]


def test_cpu_benchmarks_are_registered_beside_the_loop_figures() -> None:
    names = bench.names()
    for name in ("daemon_cpu_pct", "sim_cpu_pct", "daemon_cpu_us_per_cycle", "sim_cpu_us_per_cycle",
                 "loop_period_p99_us", "loop_missed_ratio", "loop_compute_us"):
        assert name in names
    assert bench.REGISTRY["daemon_cpu_pct"].unit == "%" and bench.REGISTRY["sim_cpu_us_per_cycle"].unit == "us"


def test_a_duration_that_is_not_positive_is_refused_before_any_session() -> None:
    from conftest import run_cli

    for value in ("-5", "0", "nan"):
        p = run_cli("bench", "host_stall_max_ms", "--seconds", value, check=False)
        assert p.returncode != 0 and "Traceback" not in p.stderr, p.stderr
        assert f"--seconds: expected a duration > 0 s, got {float(value):g}" in p.stderr, p.stderr
