"""Reloads of the running daemon's config: the whole file (SIGHUP, the `reload` command,
daemon.watch_config) or a few keys (Foxglove parameters), planned by ddrt.config.policy and
put in force by the daemon between two ticks, bumplessly.

The file is read off the loop thread: reading and validating it (YAML, `extends:`, every
section) costs 5-15 ms of CPU here, one to three periods at 200 Hz (0.4 s for a 250 KB file
with a recorded path pasted in), and on the loop thread that was a stall of the motor command
(4.2 periods once, CI). A helper thread reads it (`request`) while the loop runs on: the GIL's
0.5 ms switch interval bounds what its Python can delay a tick; what it cannot bound are the
single calls that hold the GIL throughout (libyaml composing the document, freeing its node
tree), under a millisecond for a config of a few KB, 15-30 ms for 250 KB (bench/reload_stall.py; a
pure-Python parse was measured and is worse: more objects to free in one go). Between two
ticks `poll` plans the loaded file over the config then in force (~0.3 ms) and puts it in force. Requests that come while a read is under way are answered by
the next read, which starts when that one is done: the file may have changed after the first
read opened it.

A read that has not returned after READ_DEADLINE_S (the path is now a FIFO nobody writes, a
network file system stopped answering) is given up: its waiters get an error that says so, the
requests queued behind it are answered, and while that thread is still stuck each new request
is refused at once, naming it. Reloads are never locked out by one read, and at most one
reader thread is ever stuck.

A file that does not load, or whose mix with the running restart-only values breaks a rule,
changes nothing; the reply lists exactly what was applied (live, or from the next path) and
what waits for a restart. The tally of reloads goes to status and --stats-json: `applied`
(something new put in force), `unchanged` (valid, nothing new in force: nothing changed, or
only restart-only keys) and `rejected`.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

from ddrt.config import Config, load_config, with_overrides
from ddrt.config.policy import ReloadPlan, plan_reload
from ddrt.config.schema import ConfigError
from ddrt.runtime.rt import raise_gil_helper
from ddrt.service.sdnotify import Notifier

log = logging.getLogger("ddrt.service.daemon")

Waiter = Callable[[dict[str, Any]], None]  # takes a reload's reply (a socket request's Deferred.complete)
# A config is read in milliseconds (0.4 s for a 250 KB file); this is for reads that never end,
# and under `ddrt ctl reload`'s 60 s wait, so its caller hears why.
READ_DEADLINE_S = 30.0
_STUCK_WHY = "(is the file a FIFO, or on a file system that does not answer?)"


@dataclass(eq=False)
class _Read:
    """One read of the config file in a helper thread, and who waits for its outcome. The
    thread sets `version` and `loaded` or `error`, then `done` last."""

    waiters: list[Waiter]
    started: float = 0.0  # time.monotonic() when the thread was started
    version: tuple[int, int, int] | None = None
    loaded: Config | None = None
    error: str = ""
    done: bool = False
    thread: threading.Thread | None = field(default=None, repr=False)


def file_version(path: str) -> tuple[int, int, int] | None:
    """What identifies a version of a file cheaply: inode, size, modification time."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_ino, st.st_size, st.st_mtime_ns


class Reloader:
    """Plans reloads of `config_path` over the running config and keeps their tally
    (`counts`); `put_in_force(plan)` is the daemon's, which hands the new config to every
    part of the process that holds a copy."""

    def __init__(self, config_path: str, notifier: Notifier, running: Callable[[], Config],
                 put_in_force: Callable[[ReloadPlan], None], loop_priority: Callable[[], int] = lambda: 0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.config_path = config_path
        self._clock = clock
        self._loop_priority = loop_priority  # the loop's SCHED_FIFO priority (0: not real-time)
        self.notifier = notifier
        self._running = running
        self._put_in_force = put_in_force
        # applied: put something new in force (live or from the next path); unchanged: valid,
        # but nothing new in force (nothing changed, or only keys that need a restart).
        self.counts = {"applied": 0, "unchanged": 0, "rejected": 0}
        self._version = file_version(config_path)
        self._reading: _Read | None = None  # the read under way
        self._queued: list[Waiter] | None = None  # requests for the read after it
        self._stuck: _Read | None = None  # a read given up at its deadline, until its thread returns

    @property
    def busy(self) -> bool:
        """A read is under way or queued (poll has something to do)."""
        return self._reading is not None

    def request(self, waiter: Waiter | None = None) -> None:
        """Ask for a reload (loop thread): the file is read in a helper thread; `poll` puts it
        in force and hands the reply to `waiter`. Never blocks."""
        waiters = [waiter] if waiter is not None else []
        if self._reading is None:
            self._begin(waiters)
        elif self._queued is None:
            self._queued = waiters
        else:
            self._queued.extend(waiters)

    def poll(self) -> None:
        """Between two ticks: put a finished read in force, answer its waiters, start the next."""
        read = self._reading
        if read is None:
            return
        if not read.done:
            if self._clock() - read.started < READ_DEADLINE_S:
                return
            self._stuck = read  # given up: its thread may return one day, its outcome is not used
            read = _Read(read.waiters, version=self._version, done=True,
                         error=f"{self.config_path}: not read: no answer within {READ_DEADLINE_S:.0f} s {_STUCK_WHY}")
        self._reading = None
        self._version = read.version
        try:
            reply = self._finish(read.loaded, read.error)
        finally:
            self.notifier.ready()
        for waiter in read.waiters:
            waiter(reply)
        queued, self._queued = self._queued, None
        if queued is not None:
            self._begin(queued)

    def _begin(self, waiters: list[Waiter]) -> None:
        """Start a read for `waiters`, or refuse it at once while a given-up read is still stuck
        (another would most likely be stuck the same way)."""
        if not self._still_stuck():
            self._start(waiters)
            return
        stuck = self._stuck
        assert stuck is not None
        self.notifier.reloading()
        try:
            reply = self._reject(f"{self.config_path}: not read: the read started {self._clock() - stuck.started:.0f} s "
                                 f"ago has not returned {_STUCK_WHY}")
        finally:
            self.notifier.ready()
        for waiter in waiters:
            waiter(reply)

    def _still_stuck(self) -> bool:
        """A read given up at its deadline whose thread has not returned yet."""
        stuck = self._stuck
        if stuck is None:
            return False
        if stuck.done or stuck.thread is None or not stuck.thread.is_alive():
            self._stuck = None
            return False
        return True

    def cancel(self, why: str) -> None:
        """The daemon is stopping: answer everyone still waiting (the read itself is let be)."""
        waiters = (self._reading.waiters if self._reading is not None else []) + (self._queued or [])
        self._reading, self._queued = None, None
        for waiter in waiters:
            waiter({"ok": False, "error": f"reload: {why}"})

    def reload(self) -> dict[str, Any]:
        """Re-read the config on the calling thread and put a valid one in force (the in-process
        rigs; the daemon's loop uses request/poll)."""
        self.notifier.reloading()
        try:
            read = _Read([])
            self._read(read)
            self._version = read.version
            return self._finish(read.loaded, read.error)
        finally:
            self.notifier.ready()

    def _start(self, waiters: list[Waiter]) -> None:
        self.notifier.reloading()
        read = _Read(waiters, started=self._clock())
        read.thread = threading.Thread(target=self._read_beside, args=(read, self._loop_priority()),
                                       name="ddrt-reload", daemon=True)
        self._reading = read
        try:
            read.thread.start()
        except RuntimeError as exc:  # no thread to be had (a process at its limit): say so, go on
            read.error = f"{self.config_path}: not read: cannot start a thread: {exc}"
            read.done = True
            self.poll()

    def _read_beside(self, read: _Read, loop_priority: int) -> None:
        """The helper thread: below a real-time loop (it inherited the loop's SCHED_FIFO
        priority, at which the loop could not preempt it: rt.raise_gil_helper), then the read."""
        warning = raise_gil_helper(loop_priority)
        if warning:
            log.debug("reload thread: %s", warning)
        self._read(read)

    def _read(self, read: _Read) -> None:
        """Load the file (any thread): what the loop thread needs to plan it, or why not."""
        try:
            read.version = file_version(self.config_path)
            read.loaded = load_config(self.config_path)
        except ConfigError as exc:
            read.error = str(exc)
        except Exception as exc:  # noqa: BLE001 - a reload must never end the loop
            log.debug("reload failed", exc_info=True)
            read.error = f"{self.config_path}: cannot load: {type(exc).__name__}: {exc}"
        finally:
            read.done = True

    def _finish(self, loaded: Config | None, error: str) -> dict[str, Any]:
        """Plan a loaded file over the config in force and put it in force (loop thread)."""
        if loaded is None:
            return self._reject(error or f"{self.config_path}: cannot load")
        try:
            plan = plan_reload(self._running(), loaded)
        except ConfigError as exc:
            return self._reject(str(exc))
        except Exception as exc:  # noqa: BLE001 - a reload must never end the loop
            log.debug("reload failed", exc_info=True)
            return self._reject(f"{self.config_path}: cannot plan: {type(exc).__name__}: {exc}")
        try:
            self._put_in_force(plan)
        except (ValueError, TypeError, ArithmeticError) as exc:
            return self._reject(f"{self.config_path}: not applied: {exc}")
        self._count(plan)
        if plan.restart:
            log.warning("reload: %s changed but need a restart to take effect", ", ".join(plan.restart))
        log.info("reload %s", plan.summary())
        return {"ok": True, "message": plan.summary(), **plan.report()}

    def apply_overrides(self, overrides: Mapping[str, Any], who: str,
                        planned: tuple[Config, ReloadPlan] | None = None) -> dict[str, Any]:
        """A reload of a few keys (Foxglove parameters): planned and applied as a reload is.
        `planned` is (the config it was planned over, the plan), made off the loop thread: put
        in force as it is while that config is still the running one (planning costs ~1.5 ms,
        applying ~30 us), planned again here if a reload came in between."""
        try:
            running = self._running()
            if planned is not None and planned[0] is running:
                plan = planned[1]
            else:
                plan = plan_reload(running, with_overrides(running, overrides))
            self._put_in_force(plan)
        except (ConfigError, ValueError, TypeError, ArithmeticError) as exc:
            return self._reject(f"{who}: {exc}")
        self._count(plan)
        log.info("%s: %s", who, plan.summary())
        return {"ok": True, "message": plan.summary(), **plan.report()}

    def _count(self, plan: ReloadPlan) -> None:
        self.counts["applied" if plan.live or plan.next_path else "unchanged"] += 1

    def changed_on_disk(self) -> bool:
        """daemon.watch_config: has the file changed since it was last read?"""
        return file_version(self.config_path) != self._version

    def _reject(self, why: str) -> dict[str, Any]:
        self.counts["rejected"] += 1
        log.error("reload rejected, running config kept: %s", why)
        return {"ok": False, "error": why}
