"""Telemetry ring, rotating CSV files, the writer thread, and journald-friendly logging."""

from __future__ import annotations

import csv
import io
import logging
import math
import os
import sys
import threading
import time
import tracemalloc
from pathlib import Path

import pytest

from ddrt.service.telemetry import (
    DdrtLogHandler,
    JournalFormatter,
    RotatingCsvWriter,
    TelemetryLogger,
    TelemetryRing,
    configure_logging,
    stderr_is_journal,
)

COLS = ("t", "v", "w")


# ----- TelemetryRing -----------------------------------------------------------------------

def test_ring_drains_in_order_and_wraps() -> None:
    ring = TelemetryRing(COLS, capacity=5)
    for i in range(3):
        ring.append((i, 2.0 * i, -i))
    assert len(ring) == 3
    assert ring.drain() == [(0.0, 0.0, 0.0), (1.0, 2.0, -1.0), (2.0, 4.0, -2.0)]
    assert ring.drain() == []
    for i in range(3, 8):  # wraps around the end of the buffer
        ring.append((i, 2.0 * i, -i))
    assert ring.drain(max_rows=2) == [(3.0, 6.0, -3.0), (4.0, 8.0, -4.0)]
    assert [r[0] for r in ring.drain()] == [5.0, 6.0, 7.0]
    assert ring.dropped == 0 and ring.appended == 8


def test_full_ring_overwrites_oldest_and_counts() -> None:
    ring = TelemetryRing(COLS, capacity=4)
    for i in range(10):
        ring.append((i, i, i))
    assert len(ring) == 4
    assert ring.dropped == 6
    assert [r[0] for r in ring.drain()] == [6.0, 7.0, 8.0, 9.0]
    ring.append((10, 10, 10))
    assert ring.drain() == [(10.0, 10.0, 10.0)] and ring.dropped == 6


def test_ring_keeps_nan_and_rejects_wrong_width() -> None:
    ring = TelemetryRing(COLS, capacity=2)
    ring.append((float("nan"), 1.0, 2.0))
    row = ring.drain()[0]
    assert math.isnan(row[0]) and row[1:] == (1.0, 2.0)  # NaN is a valid telemetry value
    with pytest.raises(ValueError, match="expected 3 values"):
        ring.append((1.0, 2.0))


@pytest.mark.parametrize("columns, capacity, match", [
    ((), 4, "columns"), (("a", "a"), 4, "duplicate"), (("a,b",), 4, "columns"), (("a",), 0, "capacity"),
])
def test_ring_rejects_bad_config(columns: tuple, capacity: int, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        TelemetryRing(columns, capacity)


def test_ring_append_does_not_allocate() -> None:
    ring = TelemetryRing(COLS, capacity=1024)
    row = [0.0, 0.0, 0.0]
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        for i in range(20000):
            row[0] = i * 0.005
            ring.append(row)
        grown = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    assert ring.dropped == 20000 - 1024
    assert grown < 4096, f"append kept {grown} bytes"


def test_ring_concurrent_producer_consumer_loses_nothing_silently() -> None:
    """Every row is either drained intact (never torn) or counted as dropped."""
    ring = TelemetryRing(("i", "twice", "neg"), capacity=64)
    total = 30000
    got: list[tuple[float, ...]] = []
    done = threading.Event()

    def consume() -> None:
        while not done.is_set() or len(ring):
            got.extend(ring.drain())
            time.sleep(0.0002)

    t = threading.Thread(target=consume)
    t.start()
    row = [0.0, 0.0, 0.0]
    for i in range(total):
        row[0], row[1], row[2] = i, 2.0 * i, -float(i)
        ring.append(row)
    done.set()
    t.join(timeout=10)
    assert len(got) + ring.dropped == total
    idx = [r[0] for r in got]
    assert idx == sorted(idx) and len(set(idx)) == len(idx)
    assert all(r[1] == 2 * r[0] and r[2] == -r[0] for r in got)
    assert idx[-1] == total - 1  # the newest row is never the one dropped


# ----- RotatingCsvWriter -------------------------------------------------------------------

def _read(path: Path) -> list[list[str]]:
    with open(path, newline="") as f:
        return list(csv.reader(f))


def test_rotation_bounds_count_and_size(tmp_path: Path) -> None:
    max_bytes, max_files = 400, 3
    w = RotatingCsvWriter(tmp_path, "run", COLS, max_bytes=max_bytes, max_files=max_files)
    rows = [(i * 0.005, 0.1 * i, -0.01 * i) for i in range(300)]
    longest = max(len(",".join(repr(float(v)) for v in r)) + 1 for r in rows)
    w.write_rows(rows[:150])
    w.write_rows(rows[150:])
    w.close()
    files = sorted(p.name for p in tmp_path.iterdir())
    assert files == ["run.1.csv", "run.2.csv", "run.csv"]
    assert w.rotations > max_files  # it really rotated, more than once
    chunks = []
    for name in ("run.2.csv", "run.1.csv", "run.csv"):  # oldest first
        p = tmp_path / name
        assert p.stat().st_size <= max_bytes + longest
        content = _read(p)
        assert content[0] == list(COLS)  # header on every file
        chunks.extend(tuple(float(x) for x in line) for line in content[1:])
    # The kept files hold the newest rows, contiguous and in order, ending with the last one.
    n = len(chunks)
    assert chunks == [tuple(float(x) for x in r) for r in rows[-n:]]
    assert n < 300


def test_rows_round_trip_exactly(tmp_path: Path) -> None:
    vals = [(0.1, 1e-300, -2.5e17), (float("inf"), -0.0, 1 / 3)]
    with RotatingCsvWriter(tmp_path, "x", COLS, max_bytes=1 << 20, max_files=2) as w:
        assert w.write_rows(vals) == 2
    back = [tuple(float(v) for v in line) for line in _read(tmp_path / "x.csv")[1:]]
    assert back == vals


def test_existing_file_is_rotated_at_open(tmp_path: Path) -> None:
    (tmp_path / "run.csv").write_text("old,data\n1,2\n")
    with RotatingCsvWriter(tmp_path, "run", COLS, max_bytes=1000, max_files=2) as w:
        w.write_rows([(1, 2, 3)])
    assert (tmp_path / "run.1.csv").read_text() == "old,data\n1,2\n"
    assert _read(tmp_path / "run.csv") == [list(COLS), ["1.0", "2.0", "3.0"]]


def test_single_file_limit(tmp_path: Path) -> None:
    with RotatingCsvWriter(tmp_path, "one", COLS, max_bytes=50, max_files=1) as w:
        w.write_rows([(i, i, i) for i in range(40)])
    assert [p.name for p in tmp_path.iterdir()] == ["one.csv"]
    assert _read(tmp_path / "one.csv")[-1] == ["39.0", "39.0", "39.0"]


@pytest.mark.parametrize("kwargs, field", [
    (dict(max_bytes=0), "max_bytes"), (dict(max_files=0), "max_files"),
    (dict(prefix="../x"), "prefix"), (dict(columns=("a", "b\n")), "columns"),
])
def test_writer_rejects_bad_config(tmp_path: Path, kwargs: dict, field: str) -> None:
    args = dict(prefix="p", columns=COLS, max_bytes=100, max_files=2)
    args.update(kwargs)
    with pytest.raises(ValueError, match=field):
        RotatingCsvWriter(tmp_path, **args)


def test_writer_missing_directory(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="directory"):
        RotatingCsvWriter(tmp_path / "nope", "p", COLS, 100, 2)


# ----- TelemetryLogger ---------------------------------------------------------------------

def test_logger_thread_writes_everything_by_close(tmp_path: Path) -> None:
    ring = TelemetryRing(COLS, capacity=4096)
    writer = RotatingCsvWriter(tmp_path, "tel", COLS, max_bytes=1 << 20, max_files=2)
    logger = TelemetryLogger(ring, writer, interval_s=0.02)
    for i in range(500):
        ring.append((i, i * 0.5, 1.0))
        if i == 250:
            deadline = time.monotonic() + 60.0  # the thread writes while we keep appending
            while writer.rows_written == 0 and time.monotonic() < deadline:
                time.sleep(0.005)
            assert writer.rows_written > 0
    logger.close()
    logger.close()  # idempotent
    rows = _read(tmp_path / "tel.csv")
    assert rows[0] == list(COLS)
    assert [float(r[0]) for r in rows[1:]] == [float(i) for i in range(500)]
    assert ring.dropped == 0 and logger.write_errors == 0


def test_logger_survives_write_errors(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    class FailingWriter:
        columns = COLS
        closed = False

        def write_rows(self, rows: list) -> int:
            raise OSError(28, "No space left on device")

        def close(self) -> None:
            self.closed = True

    ring = TelemetryRing(COLS, capacity=16)
    w = FailingWriter()
    with caplog.at_level(logging.WARNING, logger="ddrt.service.telemetry"):
        logger = TelemetryLogger(ring, w, interval_s=0.01)  # type: ignore[arg-type]
        ring.append((1, 2, 3))
        deadline = time.monotonic() + 60.0  # two batches: the first row's written (and failed) first
        while logger.write_errors == 0 and time.monotonic() < deadline:
            time.sleep(0.005)
        ring.append((4, 5, 6))
        logger.close()
    assert logger.write_errors == 2 and logger.rows_lost_to_errors == 2
    assert w.closed
    assert sum("No space left" in r.getMessage() for r in caplog.records) == 1  # logged once


def test_logger_rejects_mismatched_columns(tmp_path: Path) -> None:
    ring = TelemetryRing(COLS, capacity=4)
    with RotatingCsvWriter(tmp_path, "p", ("a", "b", "c"), 100, 2) as w:
        with pytest.raises(ValueError, match="columns"):
            TelemetryLogger(ring, w)


# ----- configure_logging -------------------------------------------------------------------

@pytest.fixture()
def root_logging():
    root = logging.getLogger()
    saved = (list(root.handlers), root.level)
    yield
    for h in list(root.handlers):
        if isinstance(h, DdrtLogHandler):
            root.removeHandler(h)
    root.handlers[:], root.level = saved[0], saved[1]


def _emit(handler: logging.Handler, level: int, msg: str, exc: bool = False) -> str:
    stream = io.StringIO()
    handler.setStream(stream)  # type: ignore[attr-defined]
    logger = logging.getLogger("ddrt.test")
    if exc:
        try:
            raise RuntimeError("boom")
        except RuntimeError:
            logger.log(level, msg, exc_info=True)
    else:
        logger.log(level, msg)
    return stream.getvalue()


def test_plain_format_has_level_name_no_timestamp(root_logging: None) -> None:
    h = configure_logging("info", sd_prefix=False)
    assert _emit(h, logging.WARNING, "wheel slip %d" % 3) == "WARNING ddrt.test: wheel slip 3\n"
    assert _emit(h, logging.DEBUG, "hidden") == ""  # below the level


@pytest.mark.parametrize("level, prefix", [
    (logging.DEBUG, "<7>"), (logging.INFO, "<6>"), (logging.WARNING, "<4>"),
    (logging.ERROR, "<3>"), (logging.CRITICAL, "<2>"),
])
def test_sd_prefixes(root_logging: None, level: int, prefix: str) -> None:
    h = configure_logging(logging.DEBUG, sd_prefix=True)
    assert _emit(h, level, "hello") == f"{prefix}ddrt.test: hello\n"


def test_sd_prefix_on_every_traceback_line(root_logging: None) -> None:
    h = configure_logging("DEBUG", sd_prefix=True)
    out = _emit(h, logging.ERROR, "failed", exc=True).rstrip("\n").split("\n")
    assert len(out) >= 3 and out[0] == "<3>ddrt.test: failed"
    assert all(line.startswith("<3>") for line in out)
    assert out[-1] == "<3>RuntimeError: boom"


def test_configure_twice_keeps_one_handler(root_logging: None) -> None:
    configure_logging("info", sd_prefix=False)
    configure_logging("warning", sd_prefix=False)
    root = logging.getLogger()
    assert sum(isinstance(h, DdrtLogHandler) for h in root.handlers) == 1
    assert root.level == logging.WARNING


def test_configure_rejects_bad_level(root_logging: None) -> None:
    with pytest.raises(ValueError, match="level"):
        configure_logging("loud")


def test_journal_detection(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    with open(tmp_path / "err", "w") as f:
        st = os.fstat(f.fileno())
        monkeypatch.setattr(sys, "stderr", f)
        monkeypatch.setenv("JOURNAL_STREAM", f"{st.st_dev}:{st.st_ino}")
        assert stderr_is_journal()
        monkeypatch.setenv("JOURNAL_STREAM", f"{st.st_dev}:{st.st_ino + 1}")  # stderr was redirected
        assert not stderr_is_journal()
        monkeypatch.delenv("JOURNAL_STREAM")
        assert not stderr_is_journal()


def test_formatter_is_usable_alone() -> None:
    rec = logging.LogRecord("ddrt.hal", logging.WARNING, __file__, 1, "retry %d", (2,), None)
    assert JournalFormatter(sd_prefix=True).format(rec) == "<4>ddrt.hal: retry 2"


def test_below_a_real_time_loop_the_writer_runs_just_under_it(tmp_path: Path) -> None:
    """Formatting a batch holds the GIL: with the loop at SCHED_FIFO 10 the writer runs at
    SCHED_FIFO 1, where the machine's other work cannot preempt it holding the GIL while the
    loop waits (rt.raise_gil_helper). In a subprocess: the test runner gets no real-time thread."""
    import json
    import subprocess
    import sys
    import textwrap

    code = textwrap.dedent(f"""
        import json, os, time
        from ddrt.service.telemetry import RotatingCsvWriter, TelemetryLogger, TelemetryRing
        ring = TelemetryRing(("a",), capacity=16)
        logger = TelemetryLogger(ring, RotatingCsvWriter({str(tmp_path)!r}, "t", ("a",), 1 << 20, 2), loop_priority=10)
        tid = logger._thread.native_id
        for _ in range(2000):  # until the thread has set its own policy (its first step)
            if os.sched_getscheduler(tid) != os.SCHED_OTHER:
                break
            time.sleep(0.005)
        print(json.dumps([os.sched_getscheduler(tid), os.sched_getparam(tid).sched_priority, os.SCHED_FIFO]))
        logger.close()
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                         cwd=Path(__file__).resolve().parents[1])
    assert out.returncode == 0, out.stderr
    policy, priority, fifo = json.loads(out.stdout.strip().splitlines()[-1])
    if "sched_setscheduler(SCHED_FIFO, 1)" in out.stderr:  # not permitted here
        assert priority == 0
    else:
        assert (policy, priority) == (fifo, 1), out.stderr
