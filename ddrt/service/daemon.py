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

import logging
import math
import os
import signal
import threading
import time
from pathlib import Path as FsPath
from typing import Any, Mapping

from ddrt.errors import DdrtError
from ddrt.config import Config, load_config
from ddrt.config.policy import ReloadPlan
from ddrt.config.schema import ConfigError
from ddrt.loop import COLUMNS, ControlLoop, LoopState
from ddrt.path import PathError
from ddrt.path.spec import config_path_error, path_source, speed_limits
from ddrt.runtime import rt
from ddrt.runtime.clock import MonotonicClock, SpinClock
from ddrt.service.audit import StateLog
from ddrt.service.commands import COMMANDS, NEVER_REFUSED, PRIORITY, CommandError, Request, parse
from ddrt.service.ctlqueue import Deferred
from ddrt.service.ctlserver import ControlServer
from ddrt.service.follow import FollowSlot, PendingFollow, cancel_follow, follow_step
from ddrt.service.handlers import HANDLERS
from ddrt.service.instance import AlreadyRunning, InstanceLock, lock_path_for
from ddrt.service.pathjob import Build, BuildJob
from ddrt.service.pathworker import PathWorker
from ddrt.service.reloading import Reloader
from ddrt.service.sdnotify import Notifier
from ddrt.service.taps import start_taps
from ddrt.service.status import daemon_status, not_run_report, stats_report, status_line, write_stats
from ddrt.service.telemetry import TelemetryLogger, TelemetryRing, open_csv_telemetry
from ddrt.service.timing import RateScheduler, TimingStats
from hal.base import HalError
from hal.registry import open_hal

log = logging.getLogger("ddrt.service.daemon")


class _Interrupted(DdrtError):
    """A stop was requested before the loop started."""


class Daemon:
    """One process, one robot: the loop, its socket, its telemetry, its signals."""

    def __init__(self, config_path: str, socket_path: str | None = None, duration: float | None = None,
                 stats_json: str | None = None, follow: bool = False) -> None:
        self.t_start = time.monotonic()
        self.config_path = config_path
        self.cfg: Config = load_config(config_path)
        # --socket wins over daemon.socket; an empty daemon.socket means no control socket.
        self.socket_path = socket_path if socket_path is not None else (self.cfg.daemon.socket or None)
        self.duration = duration
        self.stats_json = stats_json
        self.follow_at_start = follow
        self.notifier = Notifier()
        self.stop_requested = False
        self.reload_requested = False
        self.estop_signalled = False  # SIGUSR1: latched by the loop on its next tick
        self.stop_signal = ""  # the signal's name (SIGTERM, SIGINT) that asked the daemon to stop
        self.audit = StateLog(LoopState.IDLE)  # the journal's line per change of state (audit.py)
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
        self.clock: SpinClock | None = None
        # Reloads are planned there and put in force by _apply, between two ticks.
        self.reloader = Reloader(config_path, self.notifier, lambda: self.cfg, self._apply,
                                 lambda: self.cfg.daemon.rt_priority or 0)
        self.reloads = self.reloader.counts
        # Paths are read and built in a worker process (ddrt/service/pathworker.py), never on
        # the loop thread; at most one follow waits for its path at a time
        # (ddrt/service/follow.py's FollowSlot).
        self.paths: PathWorker | None = None
        self._start_build: Build | None = None
        self.follows = FollowSlot()
        self._teleop_refusal = ""  # the last teleop refusal logged
        self.viz: Any = None  # Foxglove and MCAP, the state stream, the ROS 2 bridge (ddrt/service/taps.py)

    # ------------------------------------------------------------------ set-up

    def _open_hal(self) -> None:
        cfg = self.cfg
        self.clock = MonotonicClock(spin_s=cfg.daemon.spin_us * 1e-6)
        start = cfg.start or (0.0, 0.0, 0.0)
        if cfg.start is None and cfg.path is not None:
            try:
                start = self._wait_start_path().start_pose
            except PathError as exc:
                if self.follow_at_start:
                    raise  # it was to be followed: a bad start-up input, exit 2
                # Only the simulated robot's start pose came from it: not a reason to stop.
                log.warning("%s; not followed (no --follow), so the daemon goes on: the robot starts "
                            "at (0, 0, 0)", exc)
                self._start_build = None
        # Every backend takes the options it needs. One whose robot runs in simulated time
        # (Hal.owns_time) starts it at `start` and, paced, brings it up to the wall clock on
        # every read, so the loop is scheduled (and its lateness measured) on the real
        # monotonic clock; hardware times its devices on that clock.
        self.hal = open_hal(cfg, start=start, paced=True, clock=self.clock)

    def _open_viz(self) -> bool:
        """Foxglove server and MCAP files (ddrt/viz/service.py); False if they cannot start."""
        from ddrt.viz.service import start_service

        try:
            self.viz = start_taps(self, start_service(self, len(COLUMNS), self.hal))
        except Exception as exc:  # noqa: BLE001 - the SDK raises its own types (port in use, ...)
            d = self.cfg.daemon
            self._fail(f"cannot start Foxglove (daemon.foxglove {d.foxglove.host}:{d.foxglove.port}, "
                       f"daemon.telemetry_format {d.telemetry_format}): {type(exc).__name__}: {exc}")
            return False
        return True

    # ------------------------------------------------------------------ between two ticks

    def handle(self, req: Mapping[str, Any] | Request) -> dict[str, Any] | Deferred:
        """One request, between two ticks: checked against its command's declaration
        (ddrt/service/commands.py) unless it comes typed, then its handler's reply
        (ddrt/service/handlers.py). The one entry of every way in."""
        assert self.loop is not None
        if not isinstance(req, Request):
            try:
                req = parse(req)
            except CommandError as exc:
                return {"ok": False, "error": str(exc)}
        return HANDLERS[req.name](self, req)

    def status(self) -> dict[str, Any]:
        """The status reply's body (ddrt/service/status.py)."""
        return daemon_status(self)

    def reload(self) -> dict[str, Any]:
        """Re-read the config here (in-process rigs; the loop reads it off-thread: Reloader.request)."""
        return self.reloader.reload()

    def apply_overrides(self, overrides: Mapping[str, Any], who: str,
                        planned: tuple[Config, ReloadPlan] | None = None) -> dict[str, Any]:
        """A few keys from Foxglove's parameters, as a reload (Reloader.apply_overrides)."""
        return self.reloader.apply_overrides(overrides, who, planned)

    def on_teleop(self, v: float, omega: float) -> None:
        """A Foxglove teleop command (between two ticks): the velocity mode, as a socket
        `drive`. A refusal is logged once until the reason changes (a panel publishing at
        20 Hz while a path runs must not flood the log)."""
        try:
            reply = self.handle(parse({"cmd": "drive", "v": v, "omega": omega}, "foxglove", "over Foxglove teleop"))
        except CommandError as exc:
            reply = {"ok": False, "error": str(exc)}
        error = "" if reply.get("ok") else str(reply.get("error", ""))
        if error and error != self._teleop_refusal:
            log.warning("foxglove teleop refused: %s", error)
        self._teleop_refusal = error

    def fault_text(self) -> str:
        return self.loop.fault if self.loop is not None else ""

    def _signals(self) -> None:
        def on_stop(signum: int, _frame: object) -> None:
            self.stop_requested = True
            self.stop_signal = signal.Signals(signum).name

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

    def fail(self, error: str, exit_code: int) -> None:
        """Stop for `error`, exiting `exit_code`: a bad start-up input found once the loop runs
        (the --follow path that does not load)."""
        self.error = error
        self.exit_code = exit_code
        self.stop_requested = True

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
                                            never_refused=NEVER_REFUSED,
                                            max_request_bytes=request_line_limit(cfg.paths.max_file_bytes))
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
        self.audit.last = loop.state
        self.ring, self.telemetry = open_csv_telemetry(self.cfg.daemon, COLUMNS, loop_priority=self.cfg.daemon.rt_priority)
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

        rt.settle_interned()  # before the collector stops: the strings are freed at once
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
            self.follows.hold(PendingFollow(self._start_build, None, None, f"{cfg.source}: path", self.stats.missed))
            follow_step(self, 0.0)  # ready already (the usual case): following from the first tick
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
        perf, cpu = time.perf_counter, time.thread_time
        wd_interval = notifier.watchdog_interval() or 1.0
        next_watchdog = 0.0
        next_status = 0.0
        end = sched.next_deadline() + self.duration if self.duration is not None else math.inf
        # A simulated robot integrates its physics when asked for the time: do that before
        # the timed part, so a tick's compute time is the controller's alone.
        advance_plant = self.hal.advance_to_wall_clock if self.hal.owns_time else None
        viz = self.viz
        truth = self.hal.robot if viz is not None else None
        audit, sweeper = self.audit, rt.GcSweeper()  # once a second, what the stopped collector keeps
        while not self.stop_requested:
            deadline = sched.next_deadline()
            woke = clock.sleep_until(deadline)
            if self.estop_signalled:  # SIGUSR1 (any time since the last tick, or before start)
                self.estop_signalled = False
                self.audit.note("estop: SIGUSR1 received; motors zeroed, latched until reset")
                if loop.state != LoopState.ESTOP:
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
            audit.check(loop)  # one comparison unless the state changed
            if viz is not None:
                viz.put(loop.row, started - deadline, compute, started,
                        truth.pose + truth.velocity if truth is not None else None)
            if loop.state == LoopState.FAULT:
                self._fail(f"stopping after fault: {loop.fault}")
                self.exit_code = 1
                break
            if self.ready_s is None:
                self.ready_s = time.monotonic() - self.t_start
                notifier.ready()
                log.info("ready after %.3f s at %.0f Hz", self.ready_s, 1.0 / self.period)
            if self.follows.pending is not None:
                follow_step(self, woke - deadline)
            if self.server is not None:
                self.server.poll(self.handle)
            if viz is not None:
                viz.between_ticks()
            if self.reload_requested:
                self.reload_requested = False
                self.reloader.request()
            self.reloader.poll()  # a finished read put in force (one comparison when there is none)
            audit.check(loop)  # a command's change of state, with who asked
            now = woke
            if now >= next_watchdog and skipped == 0:
                notifier.watchdog()
                next_watchdog = now + wd_interval
            if now >= next_status:
                notifier.status(status_line(self))
                next_status = now + 1.0
                sweeper.maybe()
                if self.cfg.daemon.watch_config and not self.reloader.busy and self.reloader.changed_on_disk():
                    log.info("%s changed on disk (daemon.watch_config)", self.config_path)
                    self.reloader.request()
            if woke >= end:
                break

    def _shutdown(self) -> None:
        self.notifier.stopping()
        cancel_follow(self, "the daemon is stopping")
        self.reloader.cancel("the daemon is stopping")
        if self.loop is not None:
            before = self.loop.state
            self.loop.shutdown()
            why = (f"{self.stop_signal} received" if self.stop_signal
                   else "after a fault" if before == LoopState.FAULT
                   else "--duration is over" if self.exit_code == 0 and self.duration is not None
                   else f"exit code {self.exit_code}")
            log.info("shutdown (%s): state %s -> %s, motors zeroed", why, before.label, self.loop.state.label)
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
            write_stats(self.stats_json, stats_report(self))

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
            raise PathError(config_path_error(self.cfg, build.error))
        return build.path

    def _apply(self, plan: ReloadPlan) -> None:
        """Hand the config in force to every part of the process that holds a copy."""
        cfg = plan.in_force
        d = cfg.daemon
        spin_s = d.spin_us * 1e-6
        if self.loop is not None:
            self.loop.reconfigure(cfg)
        if self.clock is not None:
            self.clock.set_spin(spin_s)
        if self.telemetry is not None:
            self.telemetry.writer.set_rotation(d.telemetry_max_bytes, d.telemetry_max_files)
        if self.viz is not None:
            self.viz.set_rotation(d.telemetry_max_bytes, d.telemetry_max_files)
        self.cfg = cfg


def request_line_limit(max_file_bytes: int) -> int:
    """The socket's longest request line: a path file's content (`follow` with `content`) up to
    paths.max_file_bytes, JSON-escaped (a newline takes two bytes: +25% for lines of 8 bytes
    or more), with room for the rest; 64 KiB at least. Set at start-up."""
    return max(65536, max_file_bytes + max_file_bytes // 4 + 65536)


def run_daemon(config_path: str, socket_path: str | None, duration: float | None, stats_json: str | None,
               follow: bool) -> int:
    try:
        daemon = Daemon(config_path, socket_path, duration, stats_json, follow)
    except (ConfigError, PathError) as exc:
        log.error("%s", exc)
        if stats_json:  # nothing ran: the same keys, empty, and why
            write_stats(stats_json, not_run_report(str(exc)))
        return 2
    return daemon.run()
