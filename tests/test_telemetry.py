"""The telemetry writer: round trip, precision, the cycle side that never blocks, I/O failures and retries,
roll-over, summaries, the writer process.

No simulator or daemon and no verdict on the wall clock (unit tier): "never blocks" is shown with a writer held
inside a write (the cycle side's calls return while it is stuck), a close budget by what close() reports, retries
by waiting (a lower bound on elapsed time) past ``retry_after_s`` and for the writer to drain each batch."""

import enum
import errno
import inspect
import json
import os
import sys
import threading
import time
import tracemalloc

import numpy as np
import pytest
from mcap.reader import make_reader

from dragd.telemetry import writer as writer_module
from dragd.telemetry.layout import RowLayout
from dragd.telemetry.reader import TelemetryFileError, summarize
from dragd.telemetry.schema import Field
from dragd.telemetry.sinks import RerunSink, RerunUnavailable, rerun_unavailable
from dragd.telemetry.writer import TelemetryError, TelemetryWriter

pytestmark = pytest.mark.unit


class Mode(enum.IntEnum):
    IDLE = 0
    DRAG = 1
    FAULT = 2


def cobot_layout(exact: bool = False) -> dict:
    f = Field(digits=17) if exact else Field()
    arr = Field(6, digits=17) if exact else 6
    return {
        "t_s": f,
        "mode": Field(labels=Mode),
        "q_rad": arr,
        "dq_rad_s": arr,
        "current_measured_A": arr,
        "current_command_A": arr,
        "gravity_A": arr,
        "friction_A": arr,
        "startup_A": arr,
        "statusword": Field(6, kind="int"),
        "period_us": f,
        "compute_us": f,
    }


ARRAYS = ["q_rad", "dq_rad_s", "current_measured_A", "current_command_A", "gravity_A", "friction_A", "startup_A"]


def fill(w: TelemetryWriter, row: np.ndarray, i: int, rng: np.random.Generator | None = None) -> dict:
    S = w.slices
    expect = {"t_s": i * 1e-3, "mode": i % 3, "period_us": 1000.0 + i % 7, "compute_us": 200.0 + i % 5}
    row[S["t_s"]] = expect["t_s"]
    row[S["mode"]] = expect["mode"]
    for k, name in enumerate(ARRAYS):
        v = rng.normal(size=6) if rng is not None else np.arange(6) + 10.0 * k + i
        row[S[name]] = v
        expect[name] = np.array(v, dtype=float)
    row[S["statusword"]] = 0x0637
    row[S["period_us"]] = expect["period_us"]
    row[S["compute_us"]] = expect["compute_us"]
    return expect


def read_all(path):
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        msgs = [(s, c, m) for s, c, m in reader.iter_messages(log_time_order=False)]
    return summary, msgs


def wait_for(pred, timeout_s=10.0):
    t0 = time.monotonic()
    while not pred():
        if time.monotonic() - t0 > timeout_s:
            raise AssertionError("condition not reached in time")
        time.sleep(0.01)


# -- round trip ------------------------------------------------------------------------------


@pytest.mark.parametrize("process", [False, True], ids=["thread", "process"])
def test_round_trip_values_schema_and_events(tmp_path, process):
    path = tmp_path / "t.mcap"
    rng = np.random.default_rng(7)
    w = TelemetryWriter(path, cobot_layout(exact=True), capacity=4096, process=process)
    expected = []
    for i in range(2000):
        row = w.begin()
        expected.append(fill(w, row, i, rng))
        w.commit(log_time_ns=1_700_000_000_000_000_000 + i * 1_000_000)
        if i == 500:
            w.event("mode_change", old="IDLE", new="DRAG", joint_limits=[1.0, 2.0])
    stats = w.close()
    assert stats["written"] == 2000 and stats["dropped"] == 0 and stats["errors"] == 0
    assert stats["events_written"] == 1
    assert stats["bytes"] == os.path.getsize(path)

    summary, msgs = read_all(path)
    assert summary is not None and summary.statistics.message_count == 2001
    assert {ci.compression for ci in summary.chunk_indexes} == {"zstd"}
    cycle = [(s, c, m) for s, c, m in msgs if c.topic == "/dragd/cycle"]
    events = [(s, c, m) for s, c, m in msgs if c.topic == "/dragd/events"]
    assert len(cycle) == 2000 and len(events) == 1

    schema, channel, _ = cycle[0]
    assert channel.message_encoding == "json"
    assert schema.encoding == "jsonschema" and schema.name == "dragd.Cycle"
    js = json.loads(schema.data)
    assert js["properties"]["q_rad"] == {
        "type": "array", "items": {"type": "number"}, "minItems": 6, "maxItems": 6,
    }
    assert js["properties"]["t_s"]["type"] == "number"
    assert js["properties"]["mode"]["type"] == "string"
    assert js["properties"]["statusword"]["items"]["type"] == "integer"
    assert list(js["properties"]) == list(cobot_layout())

    for i, ((_s, _c, m), exp) in enumerate(zip(cycle, expected, strict=True)):
        d = json.loads(m.data)
        assert m.sequence == i + 1
        assert m.log_time == 1_700_000_000_000_000_000 + i * 1_000_000
        assert d["t_s"] == exp["t_s"]
        assert d["mode"] == Mode(exp["mode"]).name
        for name in ARRAYS:
            assert d[name] == exp[name].tolist(), name  # exact with digits=17
        assert d["statusword"] == [0x0637] * 6
        assert d["period_us"] == exp["period_us"]

    ev = json.loads(events[0][2].data)
    assert ev == {"name": "mode_change", "old": "IDLE", "new": "DRAG", "joint_limits": [1.0, 2.0]}


def test_default_precision_is_12_significant_digits_and_nan_is_null(tmp_path):
    path = tmp_path / "p.mcap"
    w = TelemetryWriter(path, {"t_s": 1, "x": 3})
    row = w.begin()
    row[:] = [12345.678901234567, 1.0 / 3.0, float("nan"), float("inf")]
    w.commit()
    w.close()
    _, msgs = read_all(path)
    d = json.loads(msgs[0][2].data)
    assert d["t_s"] == pytest.approx(12345.678901234567, rel=1e-11, abs=0)
    assert d["t_s"] != 12345.678901234567  # rounded to 12 digits
    assert d["x"][0] == pytest.approx(1 / 3, rel=1e-11)
    assert d["x"][1] is None and d["x"][2] is None


# -- the cycle side never blocks ---------------------------------------------------------------


class SlowFile:
    """Binary sink whose writes block until released (a stalled disk)."""

    def __init__(self):
        self.release = threading.Event()
        self.entered = threading.Event()
        self.data = bytearray()

    def write(self, b):
        self.entered.set()
        self.release.wait()
        self.data += bytes(b)
        return len(b)

    def tell(self):
        return len(self.data)


def test_full_ring_drops_and_never_blocks():
    f = SlowFile()
    w = TelemetryWriter(f, {"t_s": 1, "q_rad": 6}, capacity=32, flush_interval_s=0.005)
    assert f.entered.wait(30.0), "the writer never wrote"  # from here the writer is stuck inside a write
    attempts = 0
    dropped_seen = 0
    for i in range(500):  # every call returns while the writer is stuck: begin/commit never wait for it
        row = w.begin()
        if row is None:
            dropped_seen += 1
        else:
            row[0] = i
            row[1:] = i
            w.commit()
        attempts += 1
    st = w.stats()
    assert not f.release.is_set() and len(f.data) == 0  # (still stuck: nothing written yet)
    assert dropped_seen == 500 - 32  # the ring's 32 rows queued, every other row dropped and counted
    assert st["dropped_ring_full"] == dropped_seen
    f.release.set()
    st = w.close()
    assert st["written"] + st["dropped"] == attempts
    assert st["written"] >= 32
    # sequence numbers reveal the gaps
    import io

    reader = make_reader(io.BytesIO(bytes(f.data)))
    seqs = [m.sequence for _s, c, m in reader.iter_messages(log_time_order=False) if c.topic == "/dragd/cycle"]
    assert len(seqs) == st["written"] and seqs == sorted(seqs) and seqs[-1] <= attempts


def test_begin_commit_do_not_retain_memory(tmp_path):
    w = TelemetryWriter(tmp_path / "m.mcap", {"t_s": 1, "q_rad": 6}, capacity=4096)
    for _ in range(100):  # warm up
        row = w.begin()
        row[:] = 1.0
        w.commit()
    lines = set()
    for fn in (TelemetryWriter.begin, TelemetryWriter.commit):
        src, start = inspect.getsourcelines(fn)
        lines.update(range(start, start + len(src)))
    tracemalloc.start()
    try:
        for i in range(3000):
            row = w.begin()
            if row is not None:
                row[0] = i
                w.commit()
        snap = tracemalloc.take_snapshot()
    finally:
        tracemalloc.stop()
        w.close()
    retained = sum(
        st.size
        for st in snap.statistics("lineno")
        if st.traceback[0].filename == writer_module.__file__ and st.traceback[0].lineno in lines
    )
    assert retained < 1024, retained


# -- I/O failures ---------------------------------------------------------------------------


class FullDisk:
    """File object on a full disk: accepts ``ok_bytes`` then raises ENOSPC."""

    def __init__(self, ok_bytes=0):
        self.ok_bytes = ok_bytes
        self.n = 0
        self.calls = 0

    def write(self, b):
        self.calls += 1
        if self.n + len(b) > self.ok_bytes:
            raise OSError(errno.ENOSPC, "No space left on device")
        self.n += len(b)
        return len(b)

    def tell(self):
        return self.n


def run_rows(w, n, pause_every=100):
    ok = 0
    for i in range(n):
        row = w.begin()
        if row is not None:
            row[:] = i
            w.commit()
            ok += 1
        if i % pause_every == 0:
            time.sleep(0.001)
    return ok


def test_full_disk_from_the_start_drops_rows_and_keeps_first_error():
    f = FullDisk(0)
    w = TelemetryWriter(f, {"t_s": 1, "q_rad": 6}, capacity=64, flush_interval_s=0.005)
    run_rows(w, 1000)
    wait_for(lambda: w.stats()["pending"] == 0)
    st = w.close()
    assert st["written"] == 0
    assert st["dropped"] == 1000
    assert st["errors"] >= 1
    assert "ENOSPC" in st["first_error"] and "starting" in st["first_error"]
    assert st["bytes"] == 0


def test_full_disk_midway_counts_are_consistent():
    f = FullDisk(ok_bytes=8_000)
    w = TelemetryWriter(f, {"t_s": 1, "q_rad": 6}, capacity=256, flush_interval_s=0.005, chunk_size=8 * 1024)
    run_rows(w, 5000)
    st = w.close()
    assert st["written"] > 0 and st["dropped_io"] > 0
    assert st["written"] + st["dropped"] == 5000
    assert st["dropped_bytes"] > 0
    assert "ENOSPC" in st["first_error"] and "writing" in st["first_error"]
    assert st["bytes"] == f.n


@pytest.mark.parametrize("process", [False, True], ids=["thread", "process"])
def test_dev_full_path(tmp_path, process):
    if not os.path.exists("/dev/full"):
        pytest.skip("/dev/full not available")
    w = TelemetryWriter("/dev/full", {"t_s": 1}, capacity=64, flush_interval_s=0.005, process=process)
    run_rows(w, 300)
    st = w.close()
    assert os.path.exists("/dev/full") and not os.path.isfile("/dev/full")  # never rotated away
    assert st["written"] == 0 and st["dropped"] == 300
    assert "ENOSPC" in st["first_error"] and "/dev/full" in st["first_error"]


class _Switched:
    """A real file whose writes fail with ``err`` while ``state["on"]`` (an I/O error or a full disk, on cue)."""

    def __init__(self, f, state, err):
        self.f, self.state, self.err = f, state, err

    def write(self, b):
        if self.state["on"]:
            raise OSError(self.err, os.strerror(self.err))
        return self.f.write(b)

    def flush(self):
        self.f.flush()

    def fileno(self):
        return self.f.fileno()

    def close(self):
        self.f.close()


def _failing_writes(monkeypatch, err):
    """The writer's files fail with ``err`` while the returned switch's "on" is true."""
    state = {"on": False}
    real_open = open
    monkeypatch.setattr(writer_module, "open", lambda *a, **k: _Switched(real_open(*a, **k), state, err), raising=False)
    return state


def test_retry_on_a_fresh_file_after_an_io_error(tmp_path, monkeypatch):
    failing = _failing_writes(monkeypatch, errno.EIO)
    path = tmp_path / "r.mcap"
    w = TelemetryWriter(path, {"t_s": 1}, capacity=256, flush_interval_s=0.005,
                        chunk_size=2048, retry_after_s=0.05)
    run_rows(w, 300)
    wait_for(lambda: w.stats()["written"] > 0)  # rows on disk: the file that fails next holds some
    failing["on"] = True
    run_rows(w, 300)
    wait_for(lambda: w.stats()["errors"] >= 1)
    failing["on"] = False
    offered = 0

    def retried() -> bool:  # rows keep coming (as from the cycle) until the writer has opened a fresh file
        nonlocal offered
        run_rows(w, 1)
        offered += 1
        return w.stats()["segments"] >= 2

    wait_for(retried)
    run_rows(w, 300)
    st = w.close()
    monkeypatch.undo()
    assert st["segments"] >= 2
    assert "EIO" in st["first_error"]
    assert st["written"] + st["dropped"] == 900 + offered
    s = summarize(path)  # the fresh file is complete
    assert s["complete"] and s["cycle"]["rows"] > 0
    assert len(list(tmp_path.glob("r.*.mcap"))) == 1  # the failed file was rotated aside


def test_max_bytes_rolls_over_and_keeps_n(tmp_path):
    path = tmp_path / "roll.mcap"
    w = TelemetryWriter(path, {"t_s": 1, "q_rad": 6}, capacity=4096, flush_interval_s=0.005,
                        chunk_size=1024, max_bytes=2_000, keep_rotated=2)
    for b in range(40):  # in batches, each drained before the next (the size is checked once per drained batch)
        for i in range(100 * b, 100 * b + 100):
            row = w.begin()
            row[:] = i
            w.commit()
        wait_for(lambda: w.stats()["pending"] == 0)
    st = w.close()
    rotated = sorted(tmp_path.glob("roll.*.mcap"))
    assert st["segments"] >= 4
    assert len(rotated) == 2  # older ones pruned
    ranges = []
    for p in rotated + [path]:
        s = summarize(p)
        assert s["complete"]
        t = s["cycle"]["fields"]["t_s"]
        ranges.append((t["min"], t["max"]))
    ranges.sort()
    assert ranges[-1][1] == 3999  # the current file holds the newest rows
    # the two newest rotated files were kept: contiguous with the current file
    assert ranges[1][1] + 1 == ranges[2][0] and ranges[0][1] + 1 == ranges[1][0]


def test_existing_file_is_rotated_or_refused(tmp_path):
    path = tmp_path / "telemetry.mcap"
    path.write_bytes(b"old run")
    w = TelemetryWriter(path, {"t_s": 1})
    w.close()
    rotated = list(tmp_path.glob("telemetry.*.mcap"))
    assert len(rotated) == 1 and rotated[0].read_bytes() == b"old run"
    with pytest.raises(TelemetryError, match="already exists"):
        TelemetryWriter(path, {"t_s": 1}, on_exists="error")
    with pytest.raises(TelemetryError, match="does not exist"):
        TelemetryWriter(tmp_path / "nope" / "t.mcap", {"t_s": 1})


def test_layout_errors():
    with pytest.raises(ValueError, match="empty"):
        RowLayout({})
    with pytest.raises(ValueError, match="width"):
        RowLayout({"q": 0})
    with pytest.raises(ValueError, match="identifier"):
        RowLayout({"q rad": 1})
    with pytest.raises(ValueError, match="kind"):
        RowLayout({"q": Field(kind="complex")})


def test_commit_without_begin_is_an_error(tmp_path):
    w = TelemetryWriter(tmp_path / "c.mcap", {"t_s": 1})
    with pytest.raises(RuntimeError, match="begin"):
        w.commit()
    w.close()


# -- sinks ----------------------------------------------------------------------------------


def test_rerun_missing_gives_clear_message(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "rerun", None)
    with pytest.raises(RerunUnavailable, match=r"dragd\[rerun\]"):
        RerunSink()
    with pytest.raises(RerunUnavailable, match=r"pip install 'dragd\[rerun\]'"):
        TelemetryWriter(tmp_path / "x.mcap", {"t_s": 1}, rerun=True)
    assert "dragd[rerun]" in rerun_unavailable()


def test_failing_sink_is_disabled_and_reported(tmp_path):
    class Broken:
        def write_rows(self, layout, rows, t):
            raise RuntimeError("viewer went away")

        def write_event(self, *a):
            pass

        def close(self):
            pass

    w = TelemetryWriter(tmp_path / "b.mcap", {"t_s": 1}, sinks=[Broken()])
    run_rows(w, 50)
    st = w.close()
    assert st["written"] == 50
    assert st["sink_errors"] and "viewer went away" in st["sink_errors"][0]


# -- summarize ------------------------------------------------------------------------------


def write_known_file(path, n=1000):
    w = TelemetryWriter(path, cobot_layout(), capacity=4096)  # >= n: nothing dropped
    for i in range(n):
        row = w.begin()
        fill(w, row, i)
        w.commit(log_time_ns=1_000_000_000 + i * 1_000_000)
    w.event("mode_change", new="DRAG")
    w.event("fault", joint=3, code="0x8611")
    w.close()


def test_summarize_good_file(tmp_path):
    path = tmp_path / "good.mcap"
    write_known_file(path, 1000)
    s = summarize(path)
    assert s["complete"] is True
    assert s["schemas"] == ["dragd.Cycle", "dragd.Event"]
    topics = {c["topic"]: c for c in s["channels"]}
    assert topics["/dragd/cycle"]["messages"] == 1000
    assert topics["/dragd/cycle"]["schema"] == "dragd.Cycle"
    assert topics["/dragd/events"]["messages"] == 2
    cyc = s["cycle"]
    assert cyc["rows"] == 1000 and cyc["sequence_gaps"] == 0
    f = cyc["fields"]
    assert f["t_s"]["min"] == 0.0 and f["t_s"]["max"] == pytest.approx(0.999)
    assert f["t_s"]["mean"] == pytest.approx(0.4995)
    # q_rad[j] = j + i  (k = 0) -> min j, max j + 999, mean j + 499.5 per joint
    assert f["q_rad"]["min"] == [0, 1, 2, 3, 4, 5]
    assert f["q_rad"]["max"] == [999 + j for j in range(6)]
    assert f["q_rad"]["mean"] == pytest.approx([499.5 + j for j in range(6)])
    assert f["gravity_A"]["min"] == [40 + j for j in range(6)]
    assert f["mode"] == {"type": "enum", "counts": {"DRAG": 333, "FAULT": 333, "IDLE": 334}}
    assert f["statusword"]["max"] == [0x0637] * 6
    assert [e["name"] for e in s["events"]] == ["mode_change", "fault"]
    assert s["events"][1]["fields"] == {"joint": 3, "code": "0x8611"}
    assert "dragd.telemetry.writer" in s["metadata"]
    assert s["metadata"]["dragd.telemetry.writer"]["written"] == "1000"
    assert s["chunks"].keys() == {"zstd"}
    json.dumps(s)  # JSON-ready for `dragd log summary --json`


def test_summarize_counts_sequence_gaps(tmp_path):
    f = SlowFile()
    w = TelemetryWriter(f, {"t_s": 1}, capacity=8, flush_interval_s=0.005)
    run_rows(w, 100, pause_every=1000)  # writer stalled: 8 rows queued, 92 dropped
    f.release.set()
    wait_for(lambda: w.stats()["pending"] == 0)
    run_rows(w, 5, pause_every=1000)
    st = w.close()
    assert st["dropped_ring_full"] == 92 and st["written"] == 13
    path = tmp_path / "gaps.mcap"
    path.write_bytes(bytes(f.data))
    s = summarize(path)
    assert s["cycle"]["rows"] == 13
    assert s["cycle"]["sequence_gaps"] == 92


def test_summarize_missing_garbage_empty_and_truncated(tmp_path):
    with pytest.raises(TelemetryFileError, match=r"nope\.mcap: no such file"):
        summarize(tmp_path / "nope.mcap")
    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(os.urandom(4096))
    with pytest.raises(TelemetryFileError, match=r"garbage\.mcap: not a readable MCAP file"):
        summarize(garbage)
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    with pytest.raises(TelemetryFileError, match="empty file"):
        summarize(empty)

    good = tmp_path / "good.mcap"
    write_known_file(good, 3000)
    cut = tmp_path / "cut.mcap"
    data = good.read_bytes()
    cut.write_bytes(data[: len(data) * 2 // 3])
    partial = summarize(cut)  # a killed writer's file: summarized up to its last complete chunk
    assert partial["complete"] is False and partial["truncated"] is True
    assert 0 < partial["cycle"]["rows"] == partial["recovered_rows"] < 3000


def test_a_disk_that_stays_full_never_costs_an_older_log(tmp_path, monkeypatch):
    """Retries on a full disk (every retry_after_s) keep every earlier log: a failed file with rows goes aside
    (no pruning for it), one without rows is removed; rows are dropped and counted, 'failing' says so; when space
    returns the writer resumes on a complete file."""
    full = _failing_writes(monkeypatch, errno.ENOSPC)
    path = tmp_path / "t.mcap"
    w = TelemetryWriter(path, {"t_s": 1, "q_rad": 6}, capacity=4096, flush_interval_s=0.005, chunk_size=1024,
                        max_bytes=3_000, keep_rotated=3, retry_after_s=0.02)
    # roll-overs: older complete logs, the newest three kept (keep_rotated). The size is checked once per drained
    # batch, so rows go in small batches, each drained before the next (a starved writer thread would take them all
    # at once into one file): at least five segments, so that pruning has run
    for _ in range(30):
        run_rows(w, 100, pause_every=50)
        wait_for(lambda: w.stats()["pending"] == 0)
    assert w.stats()["segments"] >= 5, w.stats()
    full["on"] = True
    run_rows(w, 50)
    wait_for(lambda: w.stats()["failing"])  # from here no write succeeds: no roll-over, no normal pruning
    older = sorted(tmp_path.glob("t.*.mcap"))
    assert len(older) == 3 and all(summarize(p)["complete"] for p in older)
    for _ in range(29):  # 29 retries (the old policy rotated and pruned on each: every older log gone)
        failed_at = w._failed_at
        time.sleep(0.03)  # past retry_after_s since the last failure: the next batch is a retry
        run_rows(w, 50)
        wait_for(lambda f=failed_at: w._failed_at != f)  # (the retry failed: the time of the failure is set last)
    st = w.stats()
    assert st["failing"] and "ENOSPC" in st["last_error"] and st["dropped_io"] > 0
    # each retry disposed of the file that failed before it: removed (no row), or kept aside (the one with rows)
    assert st["failed_segments_removed"] + st["failed_segments_kept"] >= 29 and st["failed_segments_kept"] <= 1, st
    now = sorted(tmp_path.glob("t.*.mcap"))
    assert set(older) <= set(now) and len(now) <= len(older) + 1  # every older log is still there
    full["on"] = False
    time.sleep(0.05)
    run_rows(w, 10)  # (fewer than a roll-over: normal retention, keep_rotated, would apply then)
    st = w.close()
    monkeypatch.undo()
    assert not st["failing"] and st["written"] + st["dropped"] == 30 * 100 + 30 * 50 + 10
    assert summarize(path)["complete"] and summarize(path)["cycle"]["rows"] > 0
    assert set(older) <= set(tmp_path.glob("t.*.mcap"))


# -- the writer process (process=True: the daemon's telemetry file and record windows) ------------------------


def test_writer_process_is_another_process_at_normal_priority(tmp_path):
    """The encoding runs in a process of its own, started by the (demoted) writer thread: SCHED_OTHER even when the
    thread that creates the writer is SCHED_FIFO (the daemon's cycle thread), so it never competes as real-time."""
    result = {}

    def make():
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))
        except PermissionError:
            result["fifo"] = False
        else:
            result["fifo"] = True
        result["w"] = TelemetryWriter(tmp_path / "p.mcap", {"t_s": 1}, process=True)

    t = threading.Thread(target=make)
    t.start()
    t.join()
    w = result["w"]
    for i in range(100):
        w.begin()[0] = i
        w.commit()
    wait_for(lambda: w.stats()["writer_pid"] is not None and w.stats()["pending"] == 0)
    pid = w.stats()["writer_pid"]
    assert pid != os.getpid()
    assert os.sched_getscheduler(pid) == os.SCHED_OTHER, "the writer process must not run real-time"
    st = w.close()
    assert st["written"] == 100 and st["dropped"] == 0 and st["errors"] == 0
    assert not os.path.exists(f"/proc/{pid}"), "the writer process must be gone (and reaped) after close()"


def test_writer_process_killed_is_reported_and_later_rows_are_counted(tmp_path):
    """A writer process that dies: its error is in the counters, the rows from then on are dropped and counted, the
    producer never blocks, and the file keeps what reached it."""
    import signal

    path = tmp_path / "k.mcap"
    w = TelemetryWriter(path, {"t_s": 1}, process=True, flush_interval_s=0.005, chunk_size=512)
    for i in range(200):
        w.begin()[0] = i
        w.commit()
    wait_for(lambda: w.stats()["writer_pid"] is not None and w.stats()["pending"] == 0 and w.stats()["written"] > 0)
    written = w.stats()["written"]  # in finished chunks; the open chunk's rows die with the process
    os.kill(w.stats()["writer_pid"], signal.SIGKILL)
    for i in range(300):  # (a producer that blocked on the dead process would hang here)
        row = w.begin()
        if row is not None:
            row[0] = i
            w.commit()
        time.sleep(0.001)
    st = w.close()
    assert st["errors"] >= 1 and "writer process" in st["first_error"] and "exit code -9" in st["first_error"]
    assert st["written"] == written and st["written"] + st["dropped"] == 500 and st["failing"], st
    assert summarize(path)["cycle"]["rows"] == written  # readable up to its last complete chunk (no summary: killed)


def test_writer_process_refuses_file_objects_and_sinks(tmp_path):
    import io

    with pytest.raises(ValueError, match="file path"):
        TelemetryWriter(io.BytesIO(), {"t_s": 1}, process=True)

    class Sink:
        def write_rows(self, *a):
            pass

    with pytest.raises(ValueError, match="sinks"):
        TelemetryWriter(tmp_path / "s.mcap", {"t_s": 1}, process=True, sinks=[Sink()])
    with pytest.raises(TelemetryError, match="does not exist"):
        TelemetryWriter(tmp_path / "missing" / "x.mcap", {"t_s": 1}, process=True)


def test_a_wedged_writer_process_cannot_hold_close_and_its_rows_are_counted(tmp_path):
    """A writer process that stops answering (SIGSTOP: a stuck disk, a debugger): close() returns within its budget,
    the process is killed, and every row is either in the file or counted as dropped — none vanishes."""
    import signal

    w = TelemetryWriter(tmp_path / "w.mcap", {"t_s": 1, "x": 64}, process=True, flush_interval_s=0.005)
    n = 0
    for i in range(200):
        row = w.begin()
        row[0] = i
        w.commit()
        n += 1
    wait_for(lambda: w.stats()["writer_pid"] is not None and w.stats()["pending"] == 0)
    pid = w.stats()["writer_pid"]
    os.kill(pid, signal.SIGSTOP)
    for i in range(3000):  # enough to fill the socket's buffer behind the stopped process
        row = w.begin()
        if row is not None:
            row[0] = i
            w.commit()
        n += 1
        if i % 100 == 0:
            time.sleep(0.005)
    st = w.close(timeout_s=3.0)  # returns: it gave up on the process after its budget and killed it
    assert "did not finish within 3 s; killed" in st["last_error"], st
    assert st["written"] + st["dropped"] == n, st
    assert "writer process" in (st["first_error"] or "") and st["failing"], st
    assert not os.path.exists(f"/proc/{pid}")

