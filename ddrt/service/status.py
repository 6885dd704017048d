"""What the daemon reports about itself: the `status` reply, the sd_notify status line, and
`--stats-json` (timing summary, peak memory, CPU, how it ended).

Read between two ticks (status) or after the loop has ended (--stats-json): nothing here
runs on the tick.
"""

from __future__ import annotations

import json
import logging
import math
import os
import resource
import time
from pathlib import Path as FsPath
from typing import TYPE_CHECKING, Any

from ddrt.service.drivecmd import drive_status
from ddrt.service.follow import preparing
from ddrt.service.jsonlines import finite_or_null
from ddrt.loop import LoopState

if TYPE_CHECKING:
    from ddrt.service.daemon import Daemon

log = logging.getLogger("ddrt.service.daemon")


def status_line(d: Daemon) -> str:
    """One line for systemd's status (sd_notify STATUS=), once a second."""
    loop = d.loop
    s = d.stats.summary()
    state = loop.state.label if loop else "starting"
    p99 = s.get("compute_p99_us")
    if p99 is None:
        return state
    line = f"{state}; tick p99 {p99:.0f} us; missed {s['missed_ticks']}"
    if loop is not None and loop.recovery.holds:
        line += f"; holds {loop.recovery.holds}, resumed {loop.recovery.resumes}"
    return line


def recovery_report(d: Daemon) -> dict[str, Any] | None:
    """Sensor gaps, holds and resumes so far (status and --stats-json)."""
    loop = d.loop
    if loop is None:
        return None
    h = loop.estimator.health
    return {"gaps": h.gaps, "longest_gap_ms": h.longest_gap_s * 1000.0, **loop.recovery.as_dict()}


def stats_report(d: Daemon) -> dict[str, Any]:
    """--stats-json: the run's timing summary, memory, CPU, how it ended."""
    s = d.stats.summary()
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return {
        "rate_hz": 1.0 / d.period,
        "ticks": s["count"],
        "missed": s["missed_ticks"],
        "overruns": s["overruns"],
        "compute_us": {"p50": s["compute_p50_us"], "p99": s["compute_p99_us"], "max": s["compute_worst_us"]},
        "lateness_us": {"p50": s["late_p50_us"], "p99": s["late_p99_us"], "max": s["late_worst_us"]},
        "ready_s": d.ready_s,
        "maxrss_kb": peak_rss_kb(),
        "cpu_s": usage.ru_utime + usage.ru_stime,
        "wall_s": time.monotonic() - d.t_start,
        "exit_code": d.exit_code,
        "error": d.error,
        "final_duty": [d.loop.duty_l, d.loop.duty_r] if d.loop is not None else None,
        "final_state": d.loop.state.label if d.loop is not None else None,
        "reloads": dict(d.reloads),
        "recovery": recovery_report(d),
    }


def not_run_report(error: str) -> dict[str, Any]:
    """--stats-json of a daemon that never ran (a bad config): the same keys, empty, and why."""
    return {"rate_hz": None, "ticks": 0, "missed": 0, "overruns": 0,
            "compute_us": None, "lateness_us": None, "ready_s": None,
            "maxrss_kb": peak_rss_kb(),
            "cpu_s": None, "wall_s": None, "exit_code": 2, "error": error,
            "final_duty": None, "final_state": None, "reloads": None}


def daemon_status(d: Daemon) -> dict[str, Any]:
    """The `status` reply's body: state, estimate, progress, timing, faults, the socket."""
    loop = d.loop
    assert loop is not None
    est = loop.estimator
    ref = loop.reference
    progress = None
    if ref is not None and loop.path is not None and loop.state != LoopState.DRIVING:
        progress = {"sigma_m": ref.sigma, "length_m": loop.path.length,
                    "fraction": ref.sigma / loop.path.length if loop.path.length else 1.0,
                    "cross_track_m": ref.cross_track,
                    # turn (in place to the start heading), join, release, follow: ddrt/path/start.py
                    "phase": ref.phase}
    return {
        "state": loop.state.label,
        "fault": loop.fault,
        **drive_status(loop),
        "pose": {"x": est.x, "y": est.y, "theta": est.theta},
        **estimate_report(est),
        "speeds": {"v": est.v, "omega": est.omega},
        "gyro_bias_rad_s": est.bias,
        "duty": {"l": loop.duty_l, "r": loop.duty_r},
        # The supply voltage in use (measured and filtered, or the config's), the low-battery
        # stop and the hardware estop input: ddrt/loop/power.py.
        "supply": loop.power.status(),
        "progress": progress,
        "timing": d.stats.summary(),
        "faults": {**est.health.counters(), **_hal_counters(d)},
        "recovery": recovery_report(d),
        "config": d.cfg.source,
        "reloads": dict(d.reloads),
        "adaptation": loop.adapter.status() if loop.adapter is not None else None,
        "control_socket": d.server.counters() if d.server is not None else None,
        "preparing": preparing(d),
    }


def estimate_report(est: Any) -> dict[str, Any]:
    """The pose in `map`, the uncertainty of both frames, the pose fixes (docs/estimation.md) and
    the gyro FIFO's counters;
    `clock_s` is the loop's clock now, what a fix's stamp is on."""
    xm, ym, thm = est.map_pose()
    cx, cy, cth = est.frame.correction()
    track, fc = est.track, est.frame.counters
    p, q = track.p_map, track.p_odom
    return {
        "clock_s": est.t_est,
        "pose_map": {"x": xm, "y": ym, "theta": thm},
        "map_to_odom": {"x": cx, "y": cy, "theta": cth},
        "learnt": {"encoder_scale": est.frame.s, "gyro_scale": est.frame.g, "gyro_bias_rad_s": est.frame.b},
        "uncertainty": {"std_x": track.std[0], "std_y": track.std[1], "std_theta": track.std[2],
                        "std_position": math.sqrt(max(p[0] + p[7], 0.0)),
                        "cov_map": [p[0:3], p[6:9], p[12:15]], "cov_odom": [q[0:3], q[6:9], q[12:15]]},
        "pose_fixes": {"anchored": est.frame.anchored, "fused": fc.fused, "outliers": fc.outliers,
                       "reanchors": fc.reanchors,
                       "last_d2": fc.last_d2 if math.isfinite(fc.last_d2) else None,
                       "last_stamp_s": fc.last_stamp if math.isfinite(fc.last_stamp) else None},
        # Through the MPU's FIFO (sensors.gyro_fifo): the learnt sample period and the batches
        # that lost samples or were junk (ddrt/core/gyro_fifo.py); None when read at the tick.
        "gyro_fifo": est.fifo.counters() if est.fifo is not None else None,
    }


def _hal_counters(d: Daemon) -> dict[str, Any]:
    counters = d.hal.fault_counters
    return dict(counters) if counters is not None else {}


def peak_rss_kb() -> int:
    """This process's peak resident memory (kB): VmHWM, the high-water mark of its own address
    space. Not ru_maxrss: Linux carries that over from the parent across fork and exec, so a
    daemon started by a large process (a benchmark holding its results) reported the parent's
    899 MB as its own."""
    try:
        with open("/proc/self/status", "rb") as fh:
            for line in fh:
                if line.startswith(b"VmHWM:"):
                    return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        pass
    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)


def write_stats(path: str, report: dict[str, Any]) -> None:
    """--stats-json, written whole then renamed; a failure is logged, never raised."""
    try:
        target = FsPath(path)
        tmp = target.with_name(target.name + ".tmp")
        tmp.write_text(json.dumps(finite_or_null(report), indent=2, allow_nan=False) + "\n")
        os.replace(tmp, target)
    except (OSError, ValueError) as exc:
        log.error("cannot write --stats-json %s: %s", path, exc)
