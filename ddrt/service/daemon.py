"""`ddrt run`: the long-running service around one ControlLoop.

Start-up: config -> the one-daemon-per-robot lock (ddrt/service/instance.py) -> path worker
(ddrt/service/pathworker.py; it builds the config's path meanwhile) -> control socket -> HAL
-> telemetry thread -> real-time set-up -> gyro calibration at rest -> fixed-rate loop
(READY=1 after the first good tick). Nothing touches a device before the lock and the socket
are ours, so a second daemon on the same robot sends it nothing. A follow (the socket's, or
--follow's) is built by the worker while the loop ticks and starts between two ticks once
ready; its socket reply waits for that. Each period: sleep to an absolute deadline, latch a
SIGUSR1 estop, tick, record timing, then (outside the timed part) serve the control socket,
ping the watchdog, apply a pending reload. Signals only set flags.

Exit codes: 0 after a requested stop (SIGTERM, SIGINT, --duration, also while the start path
is built or the gyro calibrated), 1 after a fault or when the robot cannot be run (another daemon holds the lock,
the socket or a device cannot be opened, calibration failed: systemd restarts the service),
2 for a bad config or path file at start-up. `--stats-json` is written on every one of these
paths, after the exit code is known, and carries it.
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
from array import array
from pathlib import Path as FsPath
from typing import Any

import numpy as np

from ddrt.runtime import rt
from ddrt.runtime.clock import MonotonicClock
from ddrt.config import Config, load_config, with_overrides
from ddrt.config.policy import ReloadPlan, plan_reload
from ddrt.service.ctlsocket import ControlServer, Deferred, finite_or_null
from ddrt.service.drivecmd import drive_fields, drive_status
from ddrt.service.instance import AlreadyRunning, InstanceLock, lock_path_for
from ddrt.loop import COLUMNS, ControlLoop
from ddrt.path import PathError
from ddrt.config.schema import ConfigError
from ddrt.service.sdnotify import Notifier
from ddrt.path.spec import path_source, speed_limits
from ddrt.service.pathworker import Build, BuildJob, PathWorker, build_path, describe
from ddrt.service.commands import COMMANDS, NEVER_REFUSED, PRIORITY
from ddrt.service.telemetry import RotatingCsvWriter, TelemetryLogger, TelemetryRing
from ddrt.service.timing import RateScheduler, TimingStats, select_quantiles
from hal.base import HalError
from hal.registry import open_hal

log = logging.getLogger("ddrt.service.daemon")

class _Interrupted(Exception):
    """A stop was requested before the loop started."""


class _PendingFollow:
    """A follow whose path is being built in the worker; the loop switches to it when ready."""

    __slots__ = ("build", "pose", "reply", "what", "ticks", "late", "missed0")

    def __init__(self, build: Build, pose: tuple[float, float, float] | None, reply: Deferred | None,
                 what: str, missed0: int) -> None:
        self.build = build
        self.pose = pose
        self.reply = reply
        self.what = what
        self.ticks = 0
        self.late = array("d")  # each tick's lateness while the path is prepared (bounded)
        self.missed0 = missed0

    def report(self, missed: int) -> dict[str, Any]:
        """What preparing the path cost the loop: the ticks it ran meanwhile, how late."""
        _p50, p99, top = (select_quantiles(np.frombuffer(self.late, dtype=np.float64)) if self.late
                          else (None, None, None))
        return {"seconds": self.build.elapsed_s, "ticks": self.ticks, "missed_ticks": missed - self.missed0,
                "late_p99_us": p99 * 1e6 if p99 is not None else None,
                "late_max_us": top * 1e6 if top is not None else None}


PREPARE_SAMPLES = 1 << 14  # lateness samples kept while a path is prepared (82 s at 200 Hz)



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
        self.estop_signalled = False  # SIGUSR1: latched by the loop on its next tick
        self.exit_code = 0
        self.error: str | None = None  # why the daemon could not run or stopped on a fault
        self.lock: InstanceLock | None = None
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
        # Paths are read and built in a worker process (ddrt/service/pathworker.py), never on
        # the loop thread; at most one follow waits for its path at a time.
        self.paths: PathWorker | None = None
        self._start_build: Build | None = None
        self._pending: _PendingFollow | None = None
        self._teleop_refusal = ""  # the last teleop refusal logged
        self.viz: Any = None  # ddrt.viz.service.VizService: Foxglove and MCAP, when configured

    # ------------------------------------------------------------------ set-up

    def _open_hal(self) -> None:
        cfg = self.cfg
        self.clock = MonotonicClock(spin_s=cfg.daemon.spin_us * 1e-6)
        start = cfg.start or (0.0, 0.0, 0.0)
        if cfg.start is None and cfg.path is not None:
            start = self._wait_start_path().start_pose
        # Every backend takes the options it needs. One whose robot runs in simulated time
        # (Hal.owns_time) starts it at `start` and, paced, brings it up to the wall clock on
        # every read, so the loop is scheduled (and its lateness measured) on the real
        # monotonic clock; hardware times its devices on that clock.
        self.hal = open_hal(cfg, start=start, paced=True, clock=self.clock)

    def _open_telemetry(self) -> None:
        d = self.cfg.daemon
        directory = os.environ.get("LOGS_DIRECTORY") or d.telemetry_dir
        if d.telemetry_format == "mcap":
            return  # the Foxglove publisher writes the MCAP files (_open_viz)
        try:
            FsPath(directory).mkdir(parents=True, exist_ok=True)
            writer = RotatingCsvWriter(directory, "telemetry", COLUMNS, d.telemetry_max_bytes, d.telemetry_max_files)
        except OSError as exc:
            log.warning("telemetry disabled: cannot write to %s: %s", directory, exc)
            return
        self.ring = TelemetryRing(COLUMNS, capacity=4096)
        self.telemetry = TelemetryLogger(self.ring, writer, loop_priority=d.rt_priority)

    def _open_viz(self) -> bool:
        """Foxglove server and MCAP files (ddrt/viz/service.py); False if they cannot start."""
        from ddrt.viz.service import start_service

        try:
            self.viz = start_service(self, len(COLUMNS), self.hal)
        except Exception as exc:  # noqa: BLE001 - the SDK raises its own types (port in use, ...)
            d = self.cfg.daemon
            self._fail(f"cannot start Foxglove (daemon.foxglove {d.foxglove.host}:{d.foxglove.port}, "
                       f"daemon.telemetry_format {d.telemetry_format}): {type(exc).__name__}: {exc}")
            return False
        return True

    def apply_overrides(self, overrides: dict[str, Any], who: str,
                        planned: tuple[Config, ReloadPlan] | None = None) -> dict[str, Any]:
        """A reload of a few keys (Foxglove parameters): planned and applied as a reload is.
        `planned` is (the config it was planned over, the plan), made off the loop thread: put
        in force as it is while that config is still the running one (planning costs ~1.5 ms,
        applying ~30 us), planned again here if a reload came in between."""
        try:
            if planned is not None and planned[0] is self.cfg:
                plan = planned[1]
            else:
                plan = plan_reload(self.cfg, with_overrides(self.cfg, overrides))
            self._apply(plan)
        except (ConfigError, ValueError, TypeError, ArithmeticError) as exc:
            return self._reject(f"{who}: {exc}")
        self.reloads["applied"] += 1
        log.info("%s: %s", who, plan.summary())
        return {"ok": True, "message": plan.summary(), **plan.report()}

    def on_teleop(self, v: float, omega: float) -> None:
        """A Foxglove teleop command (between two ticks): the velocity mode, as a socket
        `drive`. A refusal is logged once until the reason changes (a panel publishing at
        20 Hz while a path runs must not flood the log)."""
        reply = self.drive(v, omega, "foxglove")
        error = "" if reply.get("ok") else str(reply.get("error", ""))
        if error and error != self._teleop_refusal:
            log.warning("foxglove teleop refused: %s", error)
        self._teleop_refusal = error

    def fault_text(self) -> str:
        return self.loop.fault if self.loop is not None else ""

    def _signals(self) -> None:
        def on_stop(signum: int, _frame: object) -> None:
            self.stop_requested = True

        def on_hup(_signum: int, _frame: object) -> None:
            self.reload_requested = True

        def on_usr1(_signum: int, _frame: object) -> None:
            self.estop_signalled = True

        signal.signal(signal.SIGTERM, on_stop)
        signal.signal(signal.SIGINT, on_stop)
        signal.signal(signal.SIGHUP, on_hup)
        signal.signal(signal.SIGUSR1, on_usr1)  # estop from a shell: kill -USR1 / systemctl kill -s USR1

    # ------------------------------------------------------------------ main

    def run(self) -> int:
        """The whole life of the daemon; returns the exit code (and writes --stats-json)."""
        code = 1
        try:
            code = self._run()
        except (ConfigError, PathError) as exc:
            self._fail(f"{exc}")
            code = 2
        except Exception as exc:  # a bug: logged with its trace, motors stopped, exit 1
            log.exception("daemon failed: %s: %s", type(exc).__name__, exc)
            self.error = self.error or f"{type(exc).__name__}: {exc}"
            code = 1
        finally:
            self.exit_code = code
            try:
                self._shutdown()
            finally:
                self._write_stats()
                if self.lock is not None:
                    self.lock.release()
        return code

    def _fail(self, message: str) -> None:
        """One clear line in the log; the reason in --stats-json."""
        log.error("%s", message)
        self.error = message

    def _run(self) -> int:
        self._signals()
        if self.cfg.daemon.foxglove.enabled or self.cfg.daemon.telemetry_format != "csv":
            from ddrt.viz.service import check_available

            check_available(self.cfg)  # a missing extra is a config error, before anything opens
        # The lock first: a second daemon on this robot must stop before it opens anything.
        d = self.cfg.daemon
        lock = InstanceLock(lock_path_for(self.socket_path,
                                          os.environ.get("LOGS_DIRECTORY") or d.telemetry_dir))
        try:
            lock.acquire()
        except AlreadyRunning as exc:
            self._fail(exc.strerror)
            return 1
        except OSError as exc:
            self._fail(f"cannot take the one-daemon-per-robot lock {lock.path}: {exc.strerror or exc}")
            return 1
        self.lock = lock
        # The path worker before any thread is pinned: its helper thread (below the loop when
        # that is real-time) and the worker processes it starts (niced) keep every CPU.
        self.paths = PathWorker(loop_priority=d.rt_priority)
        cfg = self.cfg
        if cfg.path is not None and (self.follow_at_start or cfg.start is None):
            source, kwargs = path_source(cfg)
            self._start_build = self.paths.submit(BuildJob(source, speed_limits(cfg), **kwargs))
        # Helper threads (socket, telemetry) need little stack; with mlockall every byte of
        # the default 8 MiB per thread would be resident.
        threading.stack_size(512 * 1024)
        if self.socket_path:
            try:
                FsPath(self.socket_path).parent.mkdir(parents=True, exist_ok=True)
                self.server = ControlServer(self.socket_path, commands=COMMANDS, priority=PRIORITY,
                                            never_refused=NEVER_REFUSED)
            except OSError as exc:
                self._fail(f"cannot open the control socket: {exc.strerror or exc}")
                return 1
        try:
            self._open_hal()
        except _Interrupted:
            log.info("stopped while the start path was being built")
            return 0
        except (ConfigError, PathError):
            raise
        except (HalError, OSError, ValueError) as exc:
            self._fail(f"cannot open the robot (hal.backend={self.cfg.hal.backend}): {exc}")
            return 1
        return self._run_opened()

    def _run_opened(self) -> int:
        cfg = self.cfg
        self.loop = loop = ControlLoop(cfg, self.hal)
        self._open_telemetry()
        if not self._open_viz():
            return 1
        d = cfg.daemon
        for warning in rt.apply_realtime(d.rt_priority or None, set(d.cpus) or None, d.lock_memory,
                                         d.timer_slack_ns or None, gil_switch_interval_s=0.0005):
            log.warning("real-time set-up: %s (running without it)", warning)
        clock = self.clock

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
            self._fail(f"start-up calibration failed: {exc}")
            self.exit_code = 1
            return 1
        if self.follow_at_start and self._start_build is not None:
            # Built in the worker meanwhile (or still being built): the loop switches to it
            # between two ticks once it is ready.
            self._pending = _PendingFollow(self._start_build, None, None, f"{cfg.source}: path", self.stats.missed)
            self._follow_step(0.0)  # ready already (the usual case): following from the first tick
        self._start_build = None
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
        cpu = time.thread_time
        wd_interval = notifier.watchdog_interval() or 1.0
        next_watchdog = 0.0
        next_status = 0.0
        end = sched.next_deadline() + self.duration if self.duration is not None else math.inf
        # A simulated robot integrates its physics when asked for the time: do that before
        # the timed part, so a tick's compute time is the controller's alone.
        advance_plant = self.hal.advance_to_wall_clock if self.hal.owns_time else None
        viz = self.viz
        truth = getattr(self.hal, "robot", None) if viz is not None else None
        while not self.stop_requested:
            deadline = sched.next_deadline()
            woke = clock.sleep_until(deadline)
            if self.estop_signalled:  # SIGUSR1 (any time since the last tick, or before start)
                self.estop_signalled = False
                if loop.state != "estop":
                    log.warning("estop: SIGUSR1 received; motors zeroed, latched until reset")
                    loop.estop("estop: SIGUSR1")
            # Lateness is how late the tick really starts (takes its sample), not when the
            # sleep returned: the thread can lose the CPU or the GIL after waking (a busy
            # host, a helper thread), and such a stall delays the sample as much as a late
            # wake-up does. A simulated robot's physics, run here, costs CPU time that does
            # not exist on the robot, so only its wall time beyond its own CPU time counts.
            if advance_plant is not None:
                cpu0 = cpu()
                advance_plant()
                started = clock.now() - (cpu() - cpu0)
            else:
                started = clock.now()
            if started < woke:
                started = woke
            skipped = sched.account(started)
            t0 = perf()
            loop.tick()
            if ring is not None:
                ring.append(loop.row)
            compute = perf() - t0
            stats.record(compute, started - deadline, skipped)
            if viz is not None:
                viz.put(loop.row, started - deadline, compute, started,
                        truth.pose + truth.velocity if truth is not None else None)
            if loop.state == "fault":
                self._fail(f"stopping after fault: {loop.fault}")
                self.exit_code = 1
                break
            if self.ready_s is None:
                self.ready_s = time.monotonic() - self.t_start
                notifier.ready()
                log.info("ready after %.3f s at %.0f Hz", self.ready_s, 1.0 / self.period)
            if self._pending is not None:
                self._follow_step(woke - deadline)
            if self.server is not None:
                self.server.poll(self.handle)
            if viz is not None:
                viz.between_ticks()
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
        self._cancel_follow("the daemon is stopping")
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
        if self.viz is not None:
            if self.loop is not None:
                self.viz.put(self.loop.row, 0.0, 0.0, time.monotonic(), None)
            self.viz.close()
        if self.paths is not None:
            self.paths.close()
        if self.telemetry is not None:
            self.telemetry.close()
        self.notifier.close()

    def _write_stats(self) -> None:
        if self.stats_json:
            write_stats(self.stats_json, self.stats_report())

    # ------------------------------------------------------------------ reporting

    def status_line(self) -> str:
        loop = self.loop
        s = self.stats.summary()
        state = loop.state if loop else "starting"
        p99 = s.get("compute_p99_us")
        if p99 is None:
            return state
        line = f"{state}; tick p99 {p99:.0f} us; missed {s['missed_ticks']}"
        if loop is not None and loop.recovery.holds:
            line += f"; holds {loop.recovery.holds}, resumed {loop.recovery.resumes}"
        return line

    def recovery_report(self) -> dict[str, Any] | None:
        """Sensor gaps, holds and resumes so far (status and --stats-json)."""
        loop = self.loop
        if loop is None:
            return None
        h = loop.estimator.health
        return {"gaps": h.gaps, "longest_gap_ms": h.longest_gap_s * 1000.0, **loop.recovery.as_dict()}

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
            "maxrss_kb": peak_rss_kb(),
            "cpu_s": usage.ru_utime + usage.ru_stime,
            "wall_s": time.monotonic() - self.t_start,
            "exit_code": self.exit_code,
            "error": self.error,
            "final_duty": [self.loop.duty_l, self.loop.duty_r] if self.loop is not None else None,
            "final_state": self.loop.state if self.loop is not None else None,
            "reloads": dict(self.reloads),
            "recovery": self.recovery_report(),
        }

    def status(self) -> dict[str, Any]:
        loop = self.loop
        assert loop is not None
        est = loop.estimator
        ref = loop.reference
        progress = None
        if ref is not None and loop.path is not None and loop.state != "driving":
            progress = {"sigma_m": ref.sigma, "length_m": loop.path.length,
                        "fraction": ref.sigma / loop.path.length if loop.path.length else 1.0,
                        "cross_track_m": ref.cross_track,
                        # turn (in place to the start heading), join, release, follow: ddrt/path/start.py
                        "phase": getattr(ref, "phase", "follow")}
        return {
            "state": loop.state,
            "fault": loop.fault,
            **drive_status(loop),
            "pose": {"x": est.x, "y": est.y, "theta": est.theta},
            "speeds": {"v": est.v, "omega": est.omega},
            "gyro_bias_rad_s": est.bias,
            "duty": {"l": loop.duty_l, "r": loop.duty_r},
            "progress": progress,
            "timing": self.stats.summary(),
            "faults": {**est.health.counters(), **self._hal_counters()},
            "recovery": self.recovery_report(),
            "config": self.cfg.source,
            "reloads": dict(self.reloads),
            "adaptation": loop.adapter.status() if loop.adapter is not None else None,
            "control_socket": self.server.counters() if self.server is not None else None,
            "preparing": self._preparing(),
        }

    def _hal_counters(self) -> dict[str, Any]:
        # RealHal's is a property (a dict); a backend without one has none.
        counters = getattr(self.hal, "fault_counters", None)
        if callable(counters):
            counters = counters()
        return dict(counters) if isinstance(counters, dict) else {}

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
            cancelled = self._cancel_follow("cancelled by stop")
            loop.stop()
            return {"ok": True, "state": loop.state, **cancelled}
        if cmd == "estop":
            loop.estop("estop requested over the control socket")
            cancelled = self._cancel_follow("cancelled by estop")
            return {"ok": True, "state": loop.state, **cancelled}
        if cmd == "resume":
            # After a hold ended stopped (daemon.on_recover: wait): the path from where the
            # robot stands, the schedule ramping up from rest.
            try:
                loop.resume()
            except ValueError as exc:
                return {"ok": False, "error": f"resume: {exc} (only a path interrupted by a hold, "
                                              "with daemon.on_recover: wait, is resumed)"}
            return {"ok": True, "state": loop.state}
        if cmd == "reset":
            loop.reset()
            return {"ok": True, "state": loop.state}
        if cmd == "reload":
            return self.reload()
        if cmd == "drive":
            try:
                v, omega = drive_fields(req)
            except ValueError as exc:
                return {"ok": False, "error": f"drive: {exc}"}
            return self.drive(v, omega, "control socket")
        if cmd == "follow":
            if loop.state == "stopping":
                return {"ok": False, "error": "follow: not started: the robot is still stopping on its last path; "
                                              "send follow again once status says 'stopped' "
                                              "(estop stops it at once)"}
            return self._follow(req)
        return {"ok": False, "error": f"unknown command {cmd!r}"}

    def drive(self, v: object, omega: object, source: str) -> dict[str, Any]:
        """Velocity mode (ddrt/core/drive.py): hold (v, omega) until the next drive, a stop
        or daemon.command_timeout_s without one. The one entry for every caller (the control
        socket, a teleop bridge), between two ticks; a refusal changes nothing."""
        loop = self.loop
        assert loop is not None
        if self._pending is not None:
            return {"ok": False, "error": f"drive: busy: preparing {self._pending.what} to follow: "
                                          "send stop to cancel it"}
        old = loop.path
        try:
            v_lim, w_lim, clamped = loop.drive(v, omega, source)
        except (ValueError, RuntimeError) as exc:
            return {"ok": False, "error": f"drive: {exc}"}
        if old is not None and loop.path is None and self.paths is not None:
            self.paths.dispose(old)  # the last path's samples are freed off the loop
        reply: dict[str, Any] = {"ok": True, "state": loop.state, "v": v_lim, "omega": w_lim,
                                 "timeout_s": self.cfg.daemon.command_timeout_s}
        if clamped:
            reply["clamped"] = list(clamped)
        return reply

    def _follow(self, req: dict[str, Any]) -> dict[str, Any] | Deferred:
        """Check the request, hand the path to the worker, answer when the loop has switched.

        Nothing here reads a file or builds anything: a follow costs the loop microseconds
        whatever it asks for. A follow while following (or while another one is being
        prepared) is refused, as before: send stop first.
        """
        loop = self.loop
        assert loop is not None
        if loop.state in ("following", "stopping", "driving"):
            return {"ok": False, "error": f"already {loop.state}: send stop first"}
        if loop.state in ("estop", "fault"):
            return {"ok": False, "error": f"in {loop.state}: send reset first"}
        if self._pending is not None:
            return {"ok": False, "error": f"busy: still preparing {self._pending.what} "
                                          f"({self._pending.build.elapsed_s:.1f} s): send stop to cancel it"}
        source: Any
        if "path" in req:
            source = req["path"]
            if not isinstance(source, str):
                return {"ok": False, "error": "follow: path: expected a file name"}
            if not source or "\0" in source:
                return {"ok": False, "error": f"follow: path: not a file name: {source!r}"}
        elif "points" in req or "shape" in req:
            # An inline spec: every key but the request's own goes to the path loader, which
            # refuses unknown ones and clamps limits above the config's (reported below).
            source = {k: v for k, v in req.items() if k not in ("cmd", "id", "pose")}
            if "points" in source:
                source.setdefault("speed", min(0.3, speed_limits(self.cfg).v_max))
        else:
            return {"ok": False, "error": "follow: give path (a file), points ([[x, y], ...]) or shape"}
        pose = req.get("pose")
        if pose is not None:
            if (not isinstance(pose, list) or len(pose) != 3
                    or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                               for v in pose)):
                return {"ok": False, "error": "follow: pose: expected [x, y, theta]"}
            pose = (float(pose[0]), float(pose[1]), float(pose[2]))
        job = BuildJob(source, speed_limits(self.cfg), self.cfg.paths, where="request")
        what = describe(source)
        if self.paths is None:
            # A Daemon that is not running (tests, tools): no loop to protect, build here.
            build = Build(job)
            try:
                build._finish(path=build_path(job))
            except (PathError, ValueError, TypeError, OSError) as exc:
                return {"ok": False, "error": f"follow: {exc}"}
            return self._switch(_PendingFollow(build, pose, None, what, self.stats.missed), build)
        build = self.paths.submit(job)
        reply = Deferred()
        self._pending = _PendingFollow(build, pose, reply, what, self.stats.missed)
        log.info("follow: preparing %s", what)
        return reply

    def _follow_step(self, late_s: float) -> None:
        """Between two ticks while a follow waits for its path: switch once it is ready."""
        p = self._pending
        assert p is not None
        p.ticks += 1
        if len(p.late) < PREPARE_SAMPLES:
            p.late.append(late_s)
        build = p.build
        if not build.done:
            return
        self._pending = None
        reply = self._switch(p, build) if not build.error else {"ok": False, "error": f"follow: {build.error}"}
        reply["prepared"] = p.report(self.stats.missed)
        if not reply["ok"]:
            log.error("not following %s: %s", p.what, reply["error"])
        if p.reply is not None:
            p.reply.complete(reply)
        elif build.error:
            # The start path (--follow) does not load: a bad start-up input like a bad config.
            self.error = f"{p.what}: {build.error}"
            self.exit_code = 2
            self.stop_requested = True

    def _switch(self, p: _PendingFollow, build: Build) -> dict[str, Any]:
        loop = self.loop
        assert loop is not None
        path, build.path = build.path, None
        old = getattr(loop, "path", None)
        try:
            if loop.state in ("following", "stopping", "driving"):
                raise ValueError(f"already {loop.state}")
            loop.follow(path, p.pose)
        except (ValueError, RuntimeError) as exc:
            if self.paths is not None:
                self.paths.dispose(path)
            return {"ok": False, "error": f"follow: {exc}"}
        if old is not None and old is not path and self.paths is not None:
            self.paths.dispose(old)  # the loop's last reference is gone: free it off the loop
        del old
        if self.viz is not None:
            self.viz.path_started(path)
        for note in path.warnings:
            log.warning("follow: %s", note)
        log.info("following %s: %.2f m, %.1f s (prepared in %.2f s)", p.what, path.length, path.duration,
                 build.elapsed_s)
        reply: dict[str, Any] = {
            "ok": True, "state": loop.state, "length_m": path.length, "duration_s": path.duration,
        }
        if path.warnings:
            reply["warnings"] = list(path.warnings)
        return reply

    def _cancel_follow(self, why: str) -> dict[str, Any]:
        """A stop or estop (or the daemon's exit) cancels a follow still being prepared."""
        p = self._pending
        if p is None:
            return {}
        self._pending = None
        if self.paths is not None:
            self.paths.cancel(p.build)
        log.info("follow of %s %s", p.what, why)
        if p.reply is not None:
            p.reply.complete({"ok": False, "error": f"follow: {why}"})
        return {"cancelled": f"follow of {p.what}"}

    def _preparing(self) -> dict[str, Any] | None:
        p = self._pending
        if p is None:
            return None
        return {"source": p.what, "phase": p.build.phase, "elapsed_s": p.build.elapsed_s}

    def _wait_start_path(self) -> Any:
        """The config's path, for the simulated robot's start pose: wait for the worker (no
        loop runs yet), within paths.build_timeout_s."""
        build = self._start_build
        if build is None:
            raise PathError(f"{self.cfg.source}: path: not being built")
        while not build.done:
            if self.stop_requested:
                raise _Interrupted()
            time.sleep(0.01)
        if build.error:
            raise PathError(build.error)
        return build.path

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
        if self.viz is not None:
            self.viz.set_rotation(d.telemetry_max_bytes, d.telemetry_max_files)
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


def vars_of(obj: Any) -> dict[str, Any]:
    return {k: getattr(obj, k) for k in obj.__dataclass_fields__}


def write_stats(path: str, report: dict[str, Any]) -> None:
    """--stats-json, written whole then renamed; a failure is logged, never raised."""
    try:
        target = FsPath(path)
        tmp = target.with_name(target.name + ".tmp")
        tmp.write_text(json.dumps(finite_or_null(report), indent=2, allow_nan=False) + "\n")
        os.replace(tmp, target)
    except (OSError, ValueError) as exc:
        log.error("cannot write --stats-json %s: %s", path, exc)


def run_daemon(config_path: str, socket_path: str | None, duration: float | None, stats_json: str | None,
               follow: bool) -> int:
    try:
        daemon = Daemon(config_path, socket_path, duration, stats_json, follow)
    except (ConfigError, PathError) as exc:
        log.error("%s", exc)
        if stats_json:  # nothing ran: the same keys, empty, and why
            write_stats(stats_json, {"rate_hz": None, "ticks": 0, "missed": 0, "overruns": 0,
                                     "compute_us": None, "lateness_us": None, "ready_s": None,
                                     "maxrss_kb": peak_rss_kb(),
                                     "cpu_s": None, "wall_s": None, "exit_code": 2, "error": str(exc),
                                     "final_duty": None, "final_state": None, "reloads": None})
        return 2
    return daemon.run()
