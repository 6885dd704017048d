"""Telemetry: a fixed-size ring the loop appends to, a thread that writes it out as CSV.

The loop must never wait on a disk (an SD card can stall for hundreds of milliseconds), so
the hot path only copies a row of floats into a preallocated ring. A background thread
drains the ring every ~0.2 s and writes batches to size-bounded rotating CSV files. If the
writer falls behind, the ring overwrites the OLDEST unwritten rows and counts them: the
robot keeps running and the log says how much is missing.

Also `configure_logging`: stderr without timestamps (journald stamps every line) and, when
asked, sd-daemon "<N>" priority prefixes so `journalctl -p warning` works.
"""

from __future__ import annotations

import logging
import os
import sys
import threading
from array import array
from pathlib import Path
from typing import TYPE_CHECKING, Iterable, Sequence

from ddrt.runtime.rotation import FileRotation, positive_int

if TYPE_CHECKING:
    from ddrt.config.sections import DaemonConfig

log = logging.getLogger(__name__)


def _check_columns(owner: str, columns: Sequence[str]) -> tuple[str, ...]:
    cols = tuple(columns)
    if not cols:
        raise ValueError(f"{owner}.columns: need at least one column")
    for c in cols:
        if not isinstance(c, str) or not c or any(ch in c for ch in ',"\r\n'):
            raise ValueError(f"{owner}.columns: {c!r} is not a plain CSV column name")
    if len(set(cols)) != len(cols):
        raise ValueError(f"{owner}.columns: duplicate names in {cols!r}")
    return cols


class TelemetryRing:
    """`capacity` rows of `len(columns)` floats in one preallocated array.

    One producer (the loop) and one consumer (the writer thread). The lock is held for a few
    float stores or one slice copy, so the loop never waits long on it.
    """

    __slots__ = ("columns", "width", "capacity", "_buf", "_head", "_tail", "dropped", "_lock")

    def __init__(self, columns: tuple[str, ...], capacity: int) -> None:
        self.columns = _check_columns("TelemetryRing", columns)
        self.width = len(self.columns)
        self.capacity = positive_int("TelemetryRing.capacity", capacity)
        self._buf = array("d", bytes(8 * self.capacity * self.width))
        self._head = 0  # rows ever appended
        self._tail = 0  # rows ever consumed (drained or overwritten)
        self.dropped = 0  # rows overwritten before the writer got them
        self._lock = threading.Lock()

    def __len__(self) -> int:
        """Rows waiting to be drained."""
        return self._head - self._tail

    @property
    def appended(self) -> int:
        return self._head

    def append(self, values: Sequence[float]) -> None:
        """Copy one row in, O(1); when full, the oldest unwritten row is overwritten."""
        width = self.width
        if len(values) != width:
            raise ValueError(f"TelemetryRing.append: expected {width} values {self.columns}, got {len(values)}")
        buf = self._buf
        with self._lock:
            head = self._head
            j = (head % self.capacity) * width
            for v in values:
                buf[j] = v
                j += 1
            self._head = head + 1
            if head + 1 - self._tail > self.capacity:
                self._tail += 1
                self.dropped += 1

    def drain(self, max_rows: int | None = None) -> list[tuple[float, ...]]:
        """Take the unwritten rows, oldest first (at most `max_rows`)."""
        width, cap = self.width, self.capacity
        with self._lock:
            tail, head = self._tail, self._head
            n = head - tail if max_rows is None else min(head - tail, max_rows)
            if n <= 0:
                return []
            start = (tail % cap) * width
            end = start + n * width
            if end <= cap * width:
                flat = self._buf[start:end]
            else:
                flat = self._buf[start:] + self._buf[: end - cap * width]
            self._tail = tail + n
        # Building tuples happens outside the lock.
        return [tuple(flat[i : i + width]) for i in range(0, n * width, width)]


def _format_row(row: Sequence[float]) -> str:
    return ",".join([repr(float(v)) for v in row]) + "\n"


class RotatingCsvWriter(FileRotation):
    """CSV files `prefix.csv`, `prefix.1.csv` ... `prefix.<max_files-1>.csv` (oldest last).

    Each file starts with the header row. A file is rotated once it has reached `max_bytes`,
    so no file exceeds `max_bytes` by more than one row. An existing `prefix.csv` from an
    earlier run is rotated away at open, so every run starts a fresh file.
    """

    def __init__(self, directory: str | os.PathLike[str], prefix: str, columns: Sequence[str],
                 max_bytes: int, max_files: int) -> None:
        self.columns = _check_columns("RotatingCsvWriter", columns)
        super().__init__(directory, prefix, ".csv", max_bytes, max_files, owner="RotatingCsvWriter")
        self._header = ",".join(self.columns) + "\n"
        self.rows_written = 0
        self.rotate_stale()
        self._open_new()

    def _open_new(self) -> None:
        self._file = open(self.path(0), "w", encoding="ascii", newline="")
        self._file.write(self._header)
        self._size = len(self._header)

    def write_rows(self, rows: Iterable[Sequence[float]]) -> int:
        """Append rows, rotating as needed; flushed to the OS before returning."""
        if self._pending_rotation is not None:
            self._take_rotation()
        n = 0
        width = len(self.columns)
        for row in rows:
            if len(row) != width:
                raise ValueError(f"RotatingCsvWriter.write_rows: expected {width} values, got {len(row)}")
            if self._size >= self.max_bytes:
                self._file.close()
                self._rotate()
                self._open_new()
            line = _format_row(row)
            self._file.write(line)
            self._size += len(line)
            n += 1
        self._file.flush()
        self.rows_written += n
        return n

    def close(self) -> None:
        if not self._file.closed:
            self._file.close()

    def __enter__(self) -> "RotatingCsvWriter":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class TelemetryLogger:
    """Background thread: every `interval_s`, drain the ring and write the batch.

    A write error (disk full, card removed) is logged once and counted; the rows of that
    batch are lost but the thread keeps going, because telemetry must never stop the robot.
    `close()` writes whatever is still in the ring, then closes the writer.
    """

    def __init__(self, ring: TelemetryRing, writer: RotatingCsvWriter, interval_s: float = 0.2,
                 loop_priority: int = 0) -> None:
        if tuple(writer.columns) != ring.columns:
            raise ValueError(f"TelemetryLogger: writer columns {writer.columns} != ring columns {ring.columns}")
        if not (isinstance(interval_s, (int, float)) and 0 < interval_s < 60):
            raise ValueError(f"TelemetryLogger.interval_s: expected seconds in (0, 60), got {interval_s!r}")
        self.ring = ring
        self.writer = writer
        self.interval_s = float(interval_s)
        self.loop_priority = loop_priority  # the loop's SCHED_FIFO priority: the writer runs below it
        self.write_errors = 0
        self.rows_lost_to_errors = 0
        self._stop = threading.Event()
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="ddrt-telemetry", daemon=True)
        self._thread.start()

    def _flush_once(self) -> None:
        rows = self.ring.drain()
        if not rows:
            return
        try:
            self.writer.write_rows(rows)
        except Exception as exc:  # noqa: BLE001 - a dead writer thread would lose rows silently
            self.write_errors += 1
            self.rows_lost_to_errors += len(rows)
            if self.write_errors == 1:
                log.warning("telemetry write failed, dropping rows: %s: %s", type(exc).__name__, exc)

    def _run(self) -> None:
        from ddrt.runtime.rt import raise_gil_helper

        # Formatting a batch holds the GIL: just below a real-time loop, not among the
        # machine's other work, which could preempt it holding the GIL (rt.raise_gil_helper).
        why = raise_gil_helper(self.loop_priority)
        if why:
            log.warning("telemetry writer: %s (at normal priority)", why)
        while not self._stop.wait(self.interval_s):
            self._flush_once()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        self._thread.join()
        self._flush_once()
        self.writer.close()

    def __enter__(self) -> "TelemetryLogger":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class JournalFormatter(logging.Formatter):
    """`LEVEL name: message`, or `<N>name: message` on every line when `sd_prefix` is set.

    journald takes a leading <N> as the syslog priority of that line; tracebacks are split
    into lines by journald, so every line gets the prefix.
    """

    def __init__(self, sd_prefix: bool) -> None:
        super().__init__()
        self.sd_prefix = sd_prefix

    def format(self, record: logging.LogRecord) -> str:
        text = f"{record.name}: {record.getMessage()}"
        if record.exc_info:
            text += "\n" + self.formatException(record.exc_info)
        if record.stack_info:
            text += "\n" + self.formatStack(record.stack_info)
        if not self.sd_prefix:
            return f"{record.levelname} {text}"
        level = record.levelno
        prio = 7 if level < logging.INFO else 6 if level < logging.WARNING else 4 if level < logging.ERROR \
            else 3 if level < logging.CRITICAL else 2
        prefix = f"<{prio}>"
        return "\n".join(prefix + line for line in text.split("\n"))


def stderr_is_journal() -> bool:
    """True when stderr is connected to journald ($JOURNAL_STREAM names its device:inode)."""
    value = os.environ.get("JOURNAL_STREAM", "")
    try:
        dev, ino = (int(x) for x in value.split(":"))
        st = os.fstat(sys.stderr.fileno())
    except (ValueError, OSError, AttributeError):
        return False
    return st.st_dev == dev and st.st_ino == ino


class DdrtLogHandler(logging.StreamHandler):  # type: ignore[type-arg]
    """ddrt's handler on the root logger: the one configure_logging replaces."""


def configure_logging(level: int | str = "INFO", sd_prefix: bool | None = None) -> logging.Handler:
    """Send log records to stderr with no timestamps; sd_prefix=None means "if journald".

    Replaces a handler installed by an earlier call (so reloads can change the level).
    """
    if isinstance(level, str):
        number = logging.getLevelName(level.upper())
        if not isinstance(number, int):
            raise ValueError(f"log level: expected one of debug/info/warning/error/critical, got {level!r}")
        level = number
    elif isinstance(level, bool) or not isinstance(level, int):
        raise ValueError(f"log level: expected a name or a number, got {level!r}")
    if sd_prefix is None:
        sd_prefix = stderr_is_journal()
    root = logging.getLogger()
    for h in list(root.handlers):
        if isinstance(h, DdrtLogHandler):
            root.removeHandler(h)
    handler = DdrtLogHandler(sys.stderr)
    handler.setFormatter(JournalFormatter(sd_prefix))
    root.addHandler(handler)
    root.setLevel(level)
    return handler


def open_csv_telemetry(d: "DaemonConfig", columns: Sequence[str],
                       loop_priority: int = 0) -> tuple[TelemetryRing | None, TelemetryLogger | None]:
    """The daemon's CSV telemetry (ring and writer thread), or (None, None) when the format is
    MCAP only (the Foxglove publisher writes those) or the directory cannot be written: the
    robot runs on without telemetry, and the log says why. $LOGS_DIRECTORY (systemd's
    LogsDirectory=) wins over daemon.telemetry_dir."""
    directory = os.environ.get("LOGS_DIRECTORY") or d.telemetry_dir
    if d.telemetry_format == "mcap":
        return None, None
    try:
        Path(directory).mkdir(parents=True, exist_ok=True)
        writer = RotatingCsvWriter(directory, "telemetry", columns, d.telemetry_max_bytes, d.telemetry_max_files)
    except OSError as exc:
        log.warning("telemetry disabled: cannot write to %s: %s", directory, exc)
        return None, None
    ring = TelemetryRing(columns, capacity=4096)
    return ring, TelemetryLogger(ring, writer, loop_priority=loop_priority)
