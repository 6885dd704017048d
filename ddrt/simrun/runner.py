"""`ddrt sim`: the closed loop on the simulated robot, as fast as the CPU allows.

The same `ControlLoop.tick` as on the robot; the simulated HAL is also the clock, so
sleeping until the next deadline just advances the plant. Writes telemetry.csv (one row per
controller tick, true state beside the estimate and the reference) and metrics.json.

The rows go into a buffer of CHUNK_ROWS rows; each full buffer is appended to telemetry.csv
and folded into the metrics (running sums and maxima, ddrt/simrun/metrics.py) during the
run, so a run's memory does not grow with its length and its cost is linear in ticks. The
rows are kept in memory only when asked (`keep_rows`), or when no file is written.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import time
from array import array
from dataclasses import dataclass, field
from pathlib import Path as FsPath
from typing import Any, Callable

import numpy as np

from ddrt.config import Config
from ddrt.loop import COLUMNS, ControlLoop, LoopState
from ddrt.simrun import row_native
from ddrt.simrun.metrics import TrackingAccumulator, wrap_angles
from ddrt.path import Path
from hal.registry import open_hal

TRUTH_COLUMNS = ("x", "y", "theta", "v", "omega")
SIM_COLUMNS = ("t",) + TRUTH_COLUMNS + COLUMNS[1:]
CHUNK_ROWS = 4096  # rows per telemetry chunk: written, folded into the metrics, then reused
_COL = {name: i for i, name in enumerate(SIM_COLUMNS)}


def format_rows(arr: np.ndarray) -> str:
    """CSV lines of a (n, ncols) array: each value as f"{v:.9g}", comma-separated, CRLF-ended.

    The same text csv.writer wrote row by row. Formatted in C when row_format.c is built
    (row_native.py; DDRT_ROWFMT=python forces this Python path, the reference); here in one
    formatting call per chunk; a column that holds one value (bit for bit) over the chunk is
    formatted once."""
    text = row_native.format_rows(arr)
    if text is not None:
        return text
    return format_rows_python(arr)


def format_rows_python(arr: np.ndarray) -> str:
    """format_rows in Python: the reference the C must match, and the fallback."""
    if len(arr) == 0:
        return ""
    bits = arr.view(np.int64)
    same = (bits == bits[0]).all(axis=0)
    parts = [("%.9g" % arr[0, j]) if same[j] else "%.9g" for j in range(arr.shape[1])]
    line = ",".join(parts) + "\r\n"
    var = np.flatnonzero(~same)
    return (line * len(arr)) % tuple(arr[:, var].ravel().tolist())


class TelemetryStream:
    """A run's rows in a preallocated buffer of `chunk` rows. A full buffer (and the last,
    partial one) is appended to the CSV, folded into the run's metrics and, with `keep`,
    copied into memory; then the buffer is reused, so without `keep` memory does not grow
    with the run's length."""

    def __init__(self, path: Path, csv_path: str | FsPath | None = None, keep: bool = False,
                 chunk: int = CHUNK_ROWS, columns: tuple[str, ...] = SIM_COLUMNS,
                 sink: Callable[[np.ndarray], None] | None = None) -> None:
        self.columns = columns
        self.sink = sink  # also handed each chunk (an MCAP recording)
        self.buf = np.empty((max(1, int(chunk)), len(columns)))
        self.n = 0  # rows in the buffer
        self.tracking = TrackingAccumulator(path)
        self.ticks = 0
        self.last_t = 0.0
        self._sq_v = 0.0
        self.kept: list[np.ndarray] | None = [] if keep else None
        self.csv_path = FsPath(csv_path) if csv_path is not None else None
        self._fh = None
        if self.csv_path is not None:
            self.csv_path.parent.mkdir(parents=True, exist_ok=True)
            self._fh = open(self.csv_path, "w", newline="")
            self._fh.write(",".join(columns) + "\r\n")

    def flush(self) -> None:
        """Write, measure and (keep) store the buffered rows; empty the buffer."""
        n, self.n = self.n, 0
        if n == 0:
            return
        arr = self.buf[:n]
        if self._fh is not None:
            self._fh.write(format_rows(arr))
        if self.sink is not None:
            self.sink(arr)
        c = _COL
        self.tracking.add(arr[:, [c["x"], c["y"]]], arr[:, [c["x_est"], c["y_est"]]],
                          wrap_angles(arr[:, c["theta_ref"]] - arr[:, c["theta"]]), arr[:, c["saturated"]],
                          arr[:, c["sigma"]])
        dv = arr[:, c["v_ref"]] - arr[:, c["v"]]
        self._sq_v += float(np.dot(dv, dv))
        self.ticks += n
        self.last_t = float(arr[-1, 0])
        if self.kept is not None:
            self.kept.append(arr.copy())

    def close(self) -> None:
        """Flush what is buffered and close the CSV."""
        try:
            self.flush()
        finally:
            if self._fh is not None:
                self._fh.close()
                self._fh = None

    def table(self) -> np.ndarray | None:
        """The kept rows as one (ticks, ncols) array (None unless kept)."""
        if self.kept is None:
            return None
        if not self.kept:
            return np.zeros((0, len(self.columns)))
        return np.concatenate(self.kept) if len(self.kept) > 1 else self.kept[0]

    def metrics(self, path: Path, loop: ControlLoop) -> dict[str, Any]:
        """metrics.json's content from what has been flushed."""
        m: dict[str, Any] = self.tracking.result()
        m.update({
            "completed": loop.path_completed,
            "state": loop.state.label,
            "fault": loop.fault,
            "ticks": self.ticks,
            "sim_duration_s": self.last_t if self.ticks else 0.0,
            "path_length_m": path.length,
            "path_duration_s": path.duration,
            "rms_velocity_err_mps": math.sqrt(self._sq_v / self.ticks) if self.ticks else 0.0,
            "estimator": {"gyro_rejects": loop.estimator.health.gyro_rejects,
                          "encoder_rejects": loop.estimator.health.encoder_rejects},
        })
        return m


@dataclass
class SimResult:
    """What a run produced: metrics, the path followed, and the per-tick rows (SIM_COLUMNS).

    The rows are in memory when the run kept them (`table`), else read back on demand from
    the telemetry CSV the run streamed (9 significant digits, as written)."""

    metrics: dict[str, Any]
    path: Path
    columns: tuple[str, ...] = SIM_COLUMNS
    extra: dict[str, Any] = field(default_factory=dict)
    telemetry_csv: FsPath | None = None
    table: np.ndarray | None = field(default=None, repr=False)

    def rows_array(self) -> np.ndarray:
        """All rows, (ticks, len(columns)): the kept array, else the CSV loaded (once)."""
        if self.table is None:
            if self.telemetry_csv is None:
                raise ValueError("SimResult: the run kept no rows and wrote no telemetry "
                                 "(run_sim(..., keep_rows=True) or telemetry=FILE)")
            self.table = np.loadtxt(self.telemetry_csv, delimiter=",", skiprows=1,
                                    ndmin=2).reshape(-1, len(self.columns))
        return self.table

    @property
    def rows(self) -> np.ndarray:
        return self.rows_array()

    def column(self, name: str) -> np.ndarray:
        return self.rows_array()[:, self.columns.index(name)].copy()


def _gathered_into(gathered: array, buf: np.ndarray, n: int, t0: float) -> None:
    """Move the n rows `gathered` as (truth: TRUTH_COLUMNS, then the loop's row: COLUMNS) into
    buf[:n] in SIM_COLUMNS' order, t counted from t0; empty `gathered`."""
    width = len(TRUTH_COLUMNS) + len(COLUMNS)
    a = np.frombuffer(gathered, dtype=np.float64, count=n * width).reshape(n, width)
    k = len(TRUTH_COLUMNS)
    buf[:n, 0] = a[:, k] - t0
    buf[:n, 1:k + 1] = a[:, :k]
    buf[:n, k + 1:] = a[:, k + 1:]
    del a  # release the array's buffer before it is emptied
    del gathered[:]


def run_sim(cfg: Config, path: Path, *, duration: float | None = None, seed: int | None = None,
            start: tuple[float, float, float] | None = None,
            progress: Callable[[float, float], None] | None = None,
            telemetry: str | FsPath | None = None, keep_rows: bool | None = None,
            chunk_rows: int = CHUNK_ROWS, mcap: str | FsPath | None = None) -> SimResult:
    """Calibrate at rest, follow `path` to its end (or `duration` s), return the metrics.

    `telemetry`: a CSV file the rows are streamed to, a chunk at a time, during the run.
    `keep_rows`: keep the rows in memory too (default: only when no file is written).
    `mcap`: also record the run on the Foxglove channels (ddrt/viz/record.py; needs the extra)."""
    keep = telemetry is None if keep_rows is None else bool(keep_rows)
    pose = start or cfg.start or path.start_pose
    recording = None
    if mcap is not None:
        from ddrt.viz.record import SimRecording

        recording = SimRecording(mcap, SIM_COLUMNS, fault=lambda: loop.fault)
        recording.path(path.x, path.y)
    hal = open_hal(cfg, start=pose, seed=seed)
    try:
        robot = hal.robot  # the truth, for telemetry only
        if robot is None:
            raise ValueError(f"hal.backend: {cfg.hal.backend} has no simulated robot: run_sim needs one")
        loop = ControlLoop(cfg, hal)
        wall0 = time.perf_counter()
        stream = TelemetryStream(path, telemetry, keep, chunk_rows, sink=recording.chunk if recording else None)
        n = 0  # rows in the buffer, counted here (the hot loop) and handed to the stream
        try:
            loop.calibrate(hal.sleep_until, hal.now)
            # Stand still a little longer, as a robot does between power-on and its first
            # command: the estimator keeps refining the gyro bias at rest.
            t_idle = hal.now()
            for i in range(int(round(cfg.sim.start_delay_s / loop.period))):
                hal.sleep_until(t_idle + (i + 1) * loop.period)
                loop.tick()
            if loop.state not in (LoopState.ESTOP, LoopState.FAULT):  # a fault at rest: one tick records it, below
                loop.follow(path, pose)
            t0 = hal.now()
            # Reported as what the run is expected to take; the limit only stops a run that
            # never reaches the end.
            expected = duration if duration is not None else path.duration
            limit = duration if duration is not None else 1.5 * path.duration + 10.0
            period = loop.period
            n_ticks = int(math.ceil(limit / period))
            report_every = max(1, int(5.0 / period))
            buf = stream.buf
            size = len(buf)
            sleep_until, tick, r = hal.sleep_until, loop.tick, loop.row
            truth = robot.truth  # [x, y, theta, v, omega] in one call
            ended = (LoopState.STOPPED, LoopState.FAULT)
            # Each tick appends the truth and the loop's row to one flat array of doubles (two
            # calls, no list a row); a full chunk goes into the buffer in SIM_COLUMNS' order
            # with a few numpy assignments (_gathered_into).
            gathered = array("d")
            extend = gathered.extend
            wall_loop0 = time.perf_counter()
            for i in range(n_ticks):
                sleep_until(t0 + (i + 1) * period)
                tick()
                extend(truth())
                extend(r)
                n += 1
                if n == size:
                    _gathered_into(gathered, buf, n, t0)
                    stream.n, n = n, 0
                    stream.flush()
                if loop.state in ended:
                    break
                if progress is not None and i % report_every == 0:
                    progress(hal.now() - t0, expected)
            if n:
                _gathered_into(gathered, buf, n, t0)
            stream.n, n = n, 0
            stream.close()
            wall_loop = time.perf_counter() - wall_loop0
        finally:
            if n:  # an exception: the rows gathered so far still reach the file
                _gathered_into(gathered, buf, n, t0)
                stream.n, n = n, 0
            stream.close()
    finally:
        hal.close()
        if recording is not None:
            recording.close()
    metrics = stream.metrics(path, loop)
    metrics["wall_s"] = time.perf_counter() - wall0
    metrics["realtime_factor"] = metrics["sim_duration_s"] / wall_loop if wall_loop > 0 else float("inf")
    metrics["controller"] = cfg.controller.mode
    extra = {"metrics_fallback_points": stream.tracking.distance.fallbacks}
    return SimResult(metrics=metrics, path=path, extra=extra, telemetry_csv=stream.csv_path, table=stream.table())


def summarise(rows: Any, path: Path, loop: ControlLoop) -> dict[str, Any]:
    """metrics.json's content from per-tick rows (SIM_COLUMNS) held in memory."""
    arr = np.asarray(rows, dtype=float).reshape(-1, len(SIM_COLUMNS))
    stream = TelemetryStream(path, chunk=max(1, len(arr)))
    stream.buf[:len(arr)] = arr
    stream.n = len(arr)
    stream.close()
    return stream.metrics(path, loop)


def write_outputs(result: SimResult, out_dir: str | FsPath) -> None:
    """telemetry.csv (unless the run streamed it there) and metrics.json into `out_dir`."""
    out = FsPath(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    dest = out / "telemetry.csv"
    src = result.telemetry_csv
    if src is not None and src.exists():
        if not dest.exists() or not os.path.samefile(src, dest):
            shutil.copyfile(src, dest)
    else:
        table = result.rows_array()
        with open(dest, "w", newline="") as fh:
            fh.write(",".join(result.columns) + "\r\n")
            for i in range(0, len(table), CHUNK_ROWS):
                fh.write(format_rows(table[i:i + CHUNK_ROWS]))
    with open(out / "metrics.json", "w") as fh:
        json.dump(json_ready(result.metrics), fh, indent=2, sort_keys=True, allow_nan=False)
        fh.write("\n")


def json_ready(value: Any) -> Any:
    """`value` with every non-finite float as None (JSON's null) and numpy scalars as Python's:
    metrics.json is strict JSON, which has no NaN or Infinity."""
    if isinstance(value, dict):
        return {k: json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_ready(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def summary_text(m: dict[str, Any]) -> str:
    """One screen: what happened and how well. The real-time factor is of the following alone
    (wall_s adds the set-up: the robot opened, the gyro calibrated at rest)."""
    rtf = m["realtime_factor"]
    following = m["sim_duration_s"] / rtf if rtf and math.isfinite(rtf) else 0.0
    lines = [
        f"controller        {m['controller']}",
        f"completed         {m['completed']}  (state {m['state']}{', ' + m['fault'] if m['fault'] else ''})",
        f"simulated         {m['sim_duration_s']:.2f} s in {m['ticks']} ticks",
        f"wall time         {m['wall_s']:.2f} s in all, {following:.2f} s of it following the path "
        f"({m['realtime_factor']:.0f}x real time)",
        f"cross-track true  rms {m['rms_cross_track_m'] * 1000:.3f} mm   max {m['max_cross_track_m'] * 1000:.3f} mm",
        f"cross-track est   rms {m['rms_tracking_m'] * 1000:.3f} mm   max {m['max_tracking_m'] * 1000:.3f} mm",
        f"heading           rms {math.degrees(m['rms_heading_err_rad']):.3f} deg",
        f"final position    {m['final_pos_err_m'] * 1000:.2f} mm from the end",
        f"saturated         {m['saturated_fraction'] * 100:.1f}% of ticks",
    ]
    return "\n".join(lines)

