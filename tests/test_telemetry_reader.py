"""The one reader (dragd/telemetry/reader.py): rows, events, metadata, summary; a killed writer's file is
recovered up to its last complete chunk by every reader (summary, rows, identification/gap logs, the CLI)."""

import json
import os
import warnings

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.records import Chunk
from mcap.stream_reader import StreamReader, breakup_chunk

from dragd.cli.app import main as cli_main
from dragd.control.modes import Mode
from dragd.identify.data import LogError, load_log
from dragd.telemetry.reader import (
    TelemetryFileError,
    TruncatedTelemetryWarning,
    read_events,
    read_log,
    read_metadata,
    read_rows,
    summarize,
)
from dragd.telemetry.schema import CYCLE_TOPIC, cycle_layout
from dragd.telemetry.writer import TelemetryWriter

from daemon_helpers import cycle_rows

pytestmark = pytest.mark.unit

N_ROWS = 6000
T0_NS = 1_700_000_000_000_000_000


def write_run(path, n=N_ROWS):
    """A daemon-like run: the cycle layout of 6 joints, TRACK rows 1 ms apart, start/stop events, metadata."""
    w = TelemetryWriter(path, cycle_layout(6), capacity=n + 1, chunk_size=16 * 1024, metadata={"label": "run"})
    S = w.slices
    w.event("start", joints=6)
    for i in range(n):
        row = w.begin()
        row[:] = 0.0
        t = i * 1e-3
        row[S["t_s"]] = t
        row[S["mode"]] = Mode.TRACK
        row[S["q_rad"]] = 0.3 * np.sin(2 * np.pi * 0.5 * t + np.arange(6))
        row[S["dq_rad_s"]] = 0.3 * np.pi * np.cos(2 * np.pi * 0.5 * t + np.arange(6))
        row[S["current_measured_A"]] = 0.5 + 0.1 * np.arange(6) + 0.01 * np.sin(7 * t)
        row[S["statusword"]] = 0x1237
        row[S["rx"]] = 1
        row[S["track_t_s"]] = t
        w.commit(log_time_ns=T0_NS + i * 1_000_000)
    w.event("stop", cycles=n)
    st = w.close()
    assert st["written"] == n and st["dropped"] == 0


@pytest.fixture(scope="module")
def run_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("reader") / "run.mcap"
    write_run(path)
    return path


def chunk_rows(path):
    """(start offset, length, cycle rows) of every chunk, by the mcap library's own reader."""
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        cycle_ids = {c.id for c in summary.channels.values() if c.topic == CYCLE_TOPIC}
        index = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    with open(path, "rb") as f:
        chunks = [r for r in StreamReader(f, emit_chunks=True).records if isinstance(r, Chunk)]
    counts = [sum(1 for r in breakup_chunk(c) if getattr(r, "channel_id", None) in cycle_ids) for c in chunks]
    return [(ci.chunk_start_offset, ci.chunk_length, n) for ci, n in zip(index, counts, strict=True)]


@pytest.fixture(scope="module")
def killed(run_file, tmp_path_factory):
    """The run's file as a SIGKILL leaves it: no summary, no footer, the last chunk cut in the middle."""
    chunks = chunk_rows(run_file)
    assert len(chunks) > 10
    k = len(chunks) * 3 // 4
    start, length, _ = chunks[k]
    path = tmp_path_factory.mktemp("killed") / "killed.mcap"
    path.write_bytes(run_file.read_bytes()[: start + length // 2])
    return path, sum(n for _s, _l, n in chunks[:k])


def test_complete_file_rows_events_metadata(run_file):
    log = read_log(run_file)
    assert log.complete and not log.truncated and log.warning is None
    assert list(log.rows) == list(cycle_layout(6))
    assert log.n_rows == N_ROWS
    assert log.rows["t_s"].dtype == np.float64 and log.rows["q_rad"].shape == (N_ROWS, 6)
    assert set(log.rows["mode"].tolist()) == {"track"}
    assert log.rows["statusword"].dtype == np.int64 and (log.rows["statusword"] == 0x1237).all()
    assert log.rows["rx"].dtype == bool and log.rows["rx"].all()
    assert np.allclose(log.rows["t_s"], np.arange(N_ROWS) * 1e-3)
    assert [(e.name, e.fields) for e in log.events] == [("start", {"joints": 6}), ("stop", {"cycles": N_ROWS})]
    assert log.metadata["dragd.run"] == {"label": "run"}
    assert log.metadata["dragd.telemetry.writer"]["written"] == str(N_ROWS)
    assert log.cycle_schema is not None and list(log.cycle_schema["properties"]) == list(cycle_layout(6))


def test_selected_fields_equal_the_full_rows(run_file):
    full = read_rows(run_file)
    some = read_rows(run_file, ("t_s", "mode", "q_rad", "current_measured_A", "effects_A"))
    assert list(some) == ["t_s", "mode", "q_rad", "current_measured_A", "effects_A"]
    for k, v in some.items():
        assert np.array_equal(v, full[k]), k
    with pytest.raises(TelemetryFileError, match=r"run\.mcap: /dragd/cycle: no field torque_Nm"):
        read_rows(run_file, ("t_s", "torque_Nm"))
    assert [e.name for e in read_events(run_file, "stop")] == ["stop"]
    assert read_metadata(run_file)["dragd.run"] == {"label": "run"}


def test_killed_writer_file_is_recovered_by_every_reader(run_file, killed):
    path, rows = killed
    full = read_rows(run_file)

    log = read_log(path)
    assert not log.complete and log.truncated
    assert log.n_rows == rows > N_ROWS // 2
    for k, v in log.rows.items():
        assert np.array_equal(v, full[k][:rows]), k  # every row of the complete chunks, in order
    assert log.events[0].name == "start"  # (the writer thread writes events before the rows of its batch)
    assert log.metadata["dragd.run"] == {"label": "run"}
    assert "killed.mcap" in log.warning and "truncated" in log.warning and f"recovered {rows} rows" in log.warning
    assert "inside a chunk record" in log.problem

    with pytest.warns(TruncatedTelemetryWarning, match="killed.mcap: truncated"):
        assert len(read_rows(path, ("t_s",))["t_s"]) == rows
    with pytest.warns(TruncatedTelemetryWarning):
        assert len(cycle_rows(path)["q_rad"]) == rows  # the rig tests' reader
    assert [e.name for e in read_events(path)] == [e.name for e in log.events]

    s = summarize(path)
    assert s["complete"] is False and s["truncated"] is True
    assert s["recovered_rows"] == s["cycle"]["rows"] == rows
    assert s["cycle"]["sequence_gaps"] == 0 and s["statistics_message_count"] is None
    json.dumps(s)

    ident = load_log(path)  # identification and gap analysis read through load_log
    assert ident.t.size == rows
    assert any("killed.mcap" in w and "truncated" in w for w in ident.warnings)


def test_log_summary_cli_reports_truncation(killed, capsys):
    path, rows = killed
    assert cli_main(["log", "summary", str(path), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["truncated"] is True and s["recovered_rows"] == rows


def test_cut_at_a_record_boundary_and_inside_the_header(run_file, tmp_path):
    data = run_file.read_bytes()
    start, _length, _ = chunk_rows(run_file)[2]
    at_chunk = tmp_path / "boundary.mcap"
    at_chunk.write_bytes(data[:start])
    log = read_log(at_chunk)
    assert log.truncated and "without a footer" in log.problem
    assert log.n_rows == sum(n for _s, _l, n in chunk_rows(run_file)[:2])

    tiny = tmp_path / "tiny.mcap"
    tiny.write_bytes(data[:20])
    with pytest.raises(TelemetryFileError, match=r"tiny\.mcap: truncated MCAP before its header"):
        summarize(tiny)
    magic = tmp_path / "magic.mcap"
    magic.write_bytes(data[:5])
    with pytest.raises(TelemetryFileError, match="no record to read"):
        read_log(magic)
    with pytest.raises(LogError, match=r"tiny\.mcap: truncated MCAP"):
        load_log(tiny)


def test_corrupt_chunk_is_an_error_naming_the_file(run_file, tmp_path):
    start, length, _ = chunk_rows(run_file)[3]
    data = bytearray(run_file.read_bytes())
    data[start + length - 10] ^= 0xFF  # inside the compressed records
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    with pytest.raises(TelemetryFileError, match=r"bad\.mcap: corrupt MCAP: chunk record at byte \d+"):
        summarize(bad)
    with pytest.raises(LogError, match=r"bad\.mcap: corrupt MCAP"):
        load_log(bad)


def test_missing_and_not_mcap(tmp_path):
    with pytest.raises(TelemetryFileError, match=r"nope\.mcap: no such file"):
        read_rows(tmp_path / "nope.mcap")
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(os.urandom(64))
    with pytest.raises(TelemetryFileError, match=r"junk\.mcap: not a readable MCAP file"):
        read_events(junk)


def test_no_warning_for_a_complete_file(run_file):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_rows(run_file, ("t_s",))
