"""`ddrt run`: the long-running service around one ControlLoop.

Start-up: config -> HAL -> control socket and telemetry thread -> real-time set-up -> gyro
calibration at rest -> fixed-rate loop (READY=1 after the first good tick). Each period:
sleep to an absolute deadline, tick, record timing, then (outside the timed part) serve
the control socket, ping the watchdog, apply a pending reload. Signals only set flags.

Exit codes: 0 after a requested stop (SIGTERM, SIGINT, --duration), 1 after a fault (so
systemd restarts the service), 2 for a bad config at start-up.
"""

from __future__ import annotations

import json
import logging
import math
import os
import resource
import signal
import threading
import time
from pathlib import Path as FsPath
from typing import Any

from ddrt.service import rt
from ddrt.service.clock import MonotonicClock
from ddrt.config import Config, load_config
from ddrt.config.policy import ReloadPlan, plan_reload
from ddrt.service.ctlsocket import ControlServer
from ddrt.loop import COLUMNS, ControlLoop
from ddrt.path import PathError, load_path
from ddrt.config.schema import ConfigError
from ddrt.service.sdnotify import Notifier
from ddrt.path.spec import resolve_path, speed_limits
from ddrt.service.telemetry import RotatingCsvWriter, TelemetryLogger, TelemetryRing
from ddrt.service.timing import RateScheduler, TimingStats
from hal.base import HalError
from hal.registry import open_hal

log = logging.getLogger("ddrt.service.daemon")

class _Interrupted(Exception):
    """A stop was requested before the loop started."""


COMMANDS = ("status", "follow", "stop", "estop", "reset", "gains", "reload")


class Daemon:
    """One process, one robot: the loop, its socket, its telemetry, its signals."""

    def __init__(self, config_path: str, socket_path: str | None = None, duration: float | None = None,
                 stats_json: str | None = None, follow: bool = False) -> None:
        self.t_start = time.monotonic()
        self.config_path = config_path
        self.cfg: Config = load_config(config_path)
        self._config_stat = _stat(config_path)
        # --socket wins over daemon.socket; an empty daemon.socket means no control socket.
        self.socket_path = socket_path if socket_path is not None else (self.cfg.daemon.socket or None)
        self.duration = duration
        self.stats_json = stats_json
        self.follow_at_start = follow
        self.notifier = Notifier()
        self.stop_requested = False
        self.reload_requested = False
        self.exit_code = 0
        self.ready_s: float | None = None
        self.period = 1.0 / self.cfg.controller.rate_hz
        self.stats = TimingStats(self.period)
        self.server: ControlServer | None = None
        self.telemetry: TelemetryLogger | None = None
        self.ring: TelemetryRing | None = None
        self.loop: ControlLoop | None = None
        self.hal: Any = None
        self.clock: Any = None
        self.reloads = {"applied": 0, "rejected": 0}

    # ------------------------------------------------------------------ set-up

    def _open_hal(self) -> None:
        cfg = self.cfg
        self.clock = MonotonicClock(spin_s=cfg.daemon.spin_us * 1e-6)
        start = cfg.start or (0.0, 0.0, 0.0)
        if cfg.start is None and cfg.path is not None:
            start = resolve_path(cfg).start_pose
        # Every backend takes the options it needs. One whose robot runs in simulated time
        # (Hal.owns_time) starts it at `start` and, paced, brings it up to the wall clock on
        # every read, so the loop is scheduled (and its lateness measured) on the real
        # monotonic clock; hardware times its devices on that clock.
        self.hal = open_hal(cfg, start=start, paced=True, clock=self.clock)

    def _open_telemetry(self) -> None:
        d = self.cfg.daemon
        directory = os.environ.get("LOGS_DIRECTORY") or d.telemetry_dir
        try:
            FsPath(directory).mkdir(parents=True, exist_ok=True)
            writer = RotatingCsvWriter(directory, "telemetry", COLUMNS, d.telemetry_max_bytes, d.telemetry_max_files)
        except OSError as exc:
            log.warning("telemetry disabled: cannot write to %s: %s", directory, exc)
            return
        self.ring = TelemetryRing(COLUMNS, capacity=4096)
        self.telemetry = TelemetryLogger(self.ring, writer)

    def _signals(self) -> None:
        def on_stop(signum: int, _frame: object) -> None:
            self.stop_requested = True

        def on_hup(_signum: int, _frame: object) -> None:
            self.reload_requested = True

        signal.signal(signal.SIGTERM, on_stop)
        signal.signal(signal.SIGINT, on_stop)
        signal.signal(signal.SIGHUP, on_hup)

    # ------------------------------------------------------------------ main

    def run(self) -> int:
        self._signals()
        try:
            self._open_hal()
        except (HalError, OSError, ValueError) as exc:
            log.error("cannot open the robot (hal.backend=%s): %s", self.cfg.hal.backend, exc)
            return 1
        try:
            return self._run_opened()
        finally:
            self._shutdown()

    def _run_opened(self) -> int:
        cfg = self.cfg
        # Helper threads (socket, telemetry) need little stack; with mlockall every byte of
        # the default 8 MiB per thread would be resident.
        threading.stack_size(512 * 1024)
        self.loop = loop = ControlLoop(cfg, self.hal)
        if self.socket_path:
            FsPath(self.socket_path).parent.mkdir(parents=True, exist_ok=True)
            self.server = ControlServer(self.socket_path, commands=COMMANDS)
        self._open_telemetry()
        d = cfg.daemon
        for warning in rt.apply_realtime(d.rt_priority or None, set(d.cpus) or None, d.lock_memory,
                                         d.timer_slack_ns or None, gil_switch_interval_s=0.0005):
            log.warning("real-time set-up: %s (running without it)", warning)
        clock = self.clock
        # Everything slow happens before the calibration: once it has started, the loop's
        # samples must keep coming at the rate.
        path = None
        if self.follow_at_start and cfg.path is not None:
            try:
                path = resolve_path(cfg)
            except PathError as exc:
                log.error("not following: %s", exc)
            else:
                for note in path.warnings:
                    log.warning("path: %s", note)

        def sleep_unless_stopped(deadline: float) -> float:
            if self.stop_requested:
                raise _Interrupted()
            return clock.sleep_until(deadline)

        rt.freeze_gc()
        try:
            loop.calibrate(sleep_unless_stopped, clock.now)
        except _Interrupted:
            log.info("stopped during start-up calibration")
            return 0
        except (HalError, ValueError) as exc:
            log.error("start-up calibration failed: %s", exc)
            self.exit_code = 1
            return 1
        if path is not None:
            try:
                loop.follow(path)
            except ValueError as exc:
                log.error("not following %s: %s", cfg.path, exc)
        self._fixed_rate_loop()
        return self.exit_code

    def _fixed_rate_loop(self) -> None:
        loop = self.loop
        assert loop is not None
        clock = self.clock
        stats = self.stats
        ring = self.ring
        notifier = self.notifier
        sched = RateScheduler(self.period, clock.now())
        perf = time.perf_counter
        wd_interval = notifier.watchdog_interval() or 1.0
        next_watchdog = 0.0
        next_status = 0.0
        end = sched.next_deadline() + self.duration if self.duration is not None else math.inf
        # A simulated robot integrates its physics when asked for the time: do that before
        # the timed part, so a tick's compute time is the controller's alone.
        advance_plant = self.hal.advance_to_wall_clock if self.hal.owns_time else None
        while not self.stop_requested:
            deadline = sched.next_deadline()
            woke = clock.sleep_until(deadline)
            skipped = sched.account(woke)
            if advance_plant is not None:
                advance_plant()
            t0 = perf()
            loop.tick()
            if ring is not None:
                ring.append(loop.row)
            compute = perf() - t0
            stats.record(compute, woke - deadline, skipped)
            if loop.state == "fault":
                log.error("stopping after fault: %s", loop.fault)
                self.exit_code = 1
                break
            if self.ready_s is None:
                self.ready_s = time.monotonic() - self.t_start
                notifier.ready()
                log.info("ready after %.3f s at %.0f Hz", self.ready_s, 1.0 / self.period)
            if self.server is not None:
                self.server.poll(self.handle)
            if self.reload_requested:
                self.reload_requested = False
                self.reload()
            now = woke
            if now >= next_watchdog and skipped == 0:
                notifier.watchdog()
                next_watchdog = now + wd_interval
            if now >= next_status:
                notifier.status(self.status_line())
                next_status = now + 1.0
                if self.cfg.daemon.watch_config and self._config_changed():
                    log.info("%s changed on disk (daemon.watch_config)", self.config_path)
                    self.reload()
            if woke >= end:
                break

    def _shutdown(self) -> None:
        self.notifier.stopping()
        if self.loop is not None:
            self.loop.shutdown()
            if self.ring is not None:
                self.ring.append(self.loop.row)
        elif self.hal is not None:
            try:
                self.hal.stop()
            except Exception as exc:  # noqa: BLE001 - shutting down regardless
                log.error("stop failed: %s", exc)
        if self.hal is not None:
            try:
                self.hal.close()
            except Exception as exc:  # noqa: BLE001
                log.error("close failed: %s", exc)
        if self.server is not None:
            self.server.close()
        if self.telemetry is not None:
            self.telemetry.close()
        if self.stats_json:
            FsPath(self.stats_json).write_text(json.dumps(self.stats_report(), indent=2) + "\n")
        self.notifier.close()

    # ------------------------------------------------------------------ reporting

    def status_line(self) -> str:
        loop = self.loop
        s = self.stats.summary()
        state = loop.state if loop else "starting"
        p99 = s.get("compute_p99_us")
        return f"{state}; tick p99 {p99:.0f} us; missed {s['missed_ticks']}" if p99 is not None else state

    def stats_report(self) -> dict[str, Any]:
        s = self.stats.summary()
        usage = resource.getrusage(resource.RUSAGE_SELF)
        return {
            "rate_hz": 1.0 / self.period,
            "ticks": s["count"],
            "missed": s["missed_ticks"],
            "overruns": s["overruns"],
            "compute_us": {"p50": s["compute_p50_us"], "p99": s["compute_p99_us"], "max": s["compute_worst_us"]},
            "lateness_us": {"p50": s["late_p50_us"], "p99": s["late_p99_us"], "max": s["late_worst_us"]},
            "ready_s": self.ready_s,
            "maxrss_kb": usage.ru_maxrss,
            "cpu_s": usage.ru_utime + usage.ru_stime,
            "wall_s": time.monotonic() - self.t_start,
            "exit_code": self.exit_code,
            "final_duty": [self.loop.duty_l, self.loop.duty_r] if self.loop is not None else None,
            "final_state": self.loop.state if self.loop is not None else None,
            "reloads": dict(self.reloads),
        }

    def status(self) -> dict[str, Any]:
        loop = self.loop
        assert loop is not None
        est = loop.estimator
        ref = loop.reference
        progress = None
        if ref is not None and loop.path is not None:
            progress = {"sigma_m": ref.sigma, "length_m": loop.path.length,
                        "fraction": ref.sigma / loop.path.length if loop.path.length else 1.0,
                        "cross_track_m": ref.cross_track}
        return {
            "state": loop.state,
            "fault": loop.fault,
            "pose": {"x": est.x, "y": est.y, "theta": est.theta},
            "speeds": {"v": est.v, "omega": est.omega},
            "gyro_bias_rad_s": est.bias,
            "duty": {"l": loop.duty_l, "r": loop.duty_r},
            "progress": progress,
            "timing": self.stats.summary(),
            "faults": {"gyro_rejects": est.health.gyro_rejects, "encoder_rejects": est.health.encoder_rejects,
                       "resyncs": est.health.resyncs, "stale_ticks": est.health.stale_ticks,
                       **getattr(self.hal, "fault_counters", lambda: {})()},
            "config": self.cfg.source,
            "reloads": dict(self.reloads),
            "adaptation": loop.adapter.status() if loop.adapter is not None else None,
        }

    # ------------------------------------------------------------------ commands

    def handle(self, req: dict[str, Any]) -> dict[str, Any]:
        """One control-socket request, between two ticks; never raises into the loop."""
        loop = self.loop
        assert loop is not None
        cmd = req["cmd"]
        if cmd == "status":
            return {"ok": True, "status": self.status()}
        if cmd == "gains":
            c = self.cfg.controller
            return {"ok": True, "mode": c.mode, "outer": vars_of(c.outer), "inner": vars_of(c.inner),
                    "wheel_pid": vars_of(c.wheel_pid), "heading_gain": c.heading_gain}
        if cmd == "stop":
            loop.stop()
            return {"ok": True, "state": loop.state}
        if cmd == "estop":
            loop.estop("estop requested over the control socket")
            return {"ok": True, "state": loop.state}
        if cmd == "reset":
            loop.reset()
            return {"ok": True, "state": loop.state}
        if cmd == "reload":
            return self.reload()
        if cmd == "follow":
            return self._follow(req)
        return {"ok": False, "error": f"unknown command {cmd!r}"}

    def _follow(self, req: dict[str, Any]) -> dict[str, Any]:
        loop = self.loop
        assert loop is not None
        if loop.state in ("following", "stopping"):
            return {"ok": False, "error": f"already {loop.state}: send stop first"}
        if loop.state in ("estop", "fault"):
            return {"ok": False, "error": f"in {loop.state}: send reset first"}
        source: Any
        if "path" in req:
            source = req["path"]
            if not isinstance(source, str):
                return {"ok": False, "error": "follow: path: expected a file name"}
        elif "points" in req or "shape" in req:
            # An inline spec: every key but the request's own goes to the path loader, which
            # refuses unknown ones and clamps limits above the config's (reported below).
            source = {k: v for k, v in req.items() if k not in ("cmd", "id", "pose")}
            if "points" in source:
                source.setdefault("speed", min(0.3, speed_limits(self.cfg).v_max))
        else:
            return {"ok": False, "error": "follow: give path (a file), points ([[x, y], ...]) or shape"}
        try:
            path = load_path(source, speed_limits(self.cfg), paths=self.cfg.paths, where="request")
        except (PathError, ValueError, TypeError, OSError) as exc:
            return {"ok": False, "error": f"follow: {exc}"}
        pose = req.get("pose")
        if pose is not None:
            if (not isinstance(pose, list) or len(pose) != 3
                    or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in pose)):
                return {"ok": False, "error": "follow: pose: expected [x, y, theta]"}
            pose = (float(pose[0]), float(pose[1]), float(pose[2]))
        try:
            loop.follow(path, pose)
        except ValueError as exc:
            return {"ok": False, "error": f"follow: {exc}"}
        reply = {"ok": True, "state": loop.state, "length_m": path.length, "duration_s": path.duration}
        if path.warnings:
            for note in path.warnings:
                log.warning("follow: %s", note)
            reply["warnings"] = list(path.warnings)
        return reply

    def reload(self) -> dict[str, Any]:
        """Re-read the config; put a valid one in force between ticks, bumplessly.

        The reply lists exactly what was applied (live, or from the next path) and what waits
        for a restart (ddrt.config.policy); a file that does not load, or whose mix with the
        running restart-only values breaks a rule, changes nothing.
        """
        self.notifier.reloading()
        try:
            self._config_stat = _stat(self.config_path)
            try:
                plan = plan_reload(self.cfg, load_config(self.config_path))
            except ConfigError as exc:
                return self._reject(str(exc))
            except Exception as exc:  # noqa: BLE001 - a reload must never end the loop
                log.debug("reload failed", exc_info=True)
                return self._reject(f"{self.config_path}: cannot load: {type(exc).__name__}: {exc}")
            try:
                self._apply(plan)
            except (ValueError, TypeError, ArithmeticError) as exc:
                return self._reject(f"{self.config_path}: not applied: {exc}")
            self.reloads["applied"] += 1
            if plan.restart:
                log.warning("reload: %s changed but need a restart to take effect", ", ".join(plan.restart))
            log.info("reload %s", plan.summary())
            return {"ok": True, "message": plan.summary(), **plan.report()}
        finally:
            self.notifier.ready()

    def _reject(self, why: str) -> dict[str, Any]:
        self.reloads["rejected"] += 1
        log.error("reload rejected, running config kept: %s", why)
        return {"ok": False, "error": why}

    def _apply(self, plan: ReloadPlan) -> None:
        """Hand the config in force to every part of the process that holds a copy."""
        cfg = plan.in_force
        d = cfg.daemon
        spin_s = d.spin_us * 1e-6
        if self.loop is not None:
            self.loop.reconfigure(cfg)
        if self.clock is not None and hasattr(self.clock, "spin_s"):
            self.clock.spin_s = spin_s
        if self.telemetry is not None:
            self.telemetry.writer.set_rotation(d.telemetry_max_bytes, d.telemetry_max_files)
        self.cfg = cfg

    def _config_changed(self) -> bool:
        """daemon.watch_config: has the file changed since it was last read?"""
        return _stat(self.config_path) != self._config_stat


def _stat(path: str) -> tuple[int, int, int] | None:
    """What identifies a version of a file cheaply: inode, size, modification time."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_ino, st.st_size, st.st_mtime_ns


def vars_of(obj: Any) -> dict[str, Any]:
    return {k: getattr(obj, k) for k in obj.__dataclass_fields__}


def run_daemon(config_path: str, socket_path: str | None, duration: float | None, stats_json: str | None,
               follow: bool) -> int:
    try:
        daemon = Daemon(config_path, socket_path, duration, stats_json, follow)
    except (ConfigError, PathError) as exc:
        log.error("%s", exc)
        return 2
    return daemon.run()
