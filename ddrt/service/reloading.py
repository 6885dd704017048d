"""Reloads of the running daemon's config: the whole file (SIGHUP, the `reload` command,
daemon.watch_config) or a few keys (Foxglove parameters), planned by ddrt.config.policy and
put in force by the daemon between two ticks, bumplessly.

A file that does not load, or whose mix with the running restart-only values breaks a rule,
changes nothing; the reply lists exactly what was applied (live, or from the next path) and
what waits for a restart. The tally of reloads goes to status and --stats-json: `applied`
(something new put in force), `unchanged` (valid, nothing new in force: nothing changed, or
only restart-only keys) and `rejected`.
"""

from __future__ import annotations

import logging
import os
from typing import Any, Callable, Mapping

from ddrt.config import Config, load_config, with_overrides
from ddrt.config.policy import ReloadPlan, plan_reload
from ddrt.config.schema import ConfigError
from ddrt.service.sdnotify import Notifier

log = logging.getLogger("ddrt.service.daemon")


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
                 put_in_force: Callable[[ReloadPlan], None]) -> None:
        self.config_path = config_path
        self.notifier = notifier
        self._running = running
        self._put_in_force = put_in_force
        # applied: put something new in force (live or from the next path); unchanged: valid,
        # but nothing new in force (nothing changed, or only keys that need a restart).
        self.counts = {"applied": 0, "unchanged": 0, "rejected": 0}
        self._version = file_version(config_path)

    def reload(self) -> dict[str, Any]:
        """Re-read the config; put a valid one in force (called between ticks)."""
        self.notifier.reloading()
        try:
            self._version = file_version(self.config_path)
            try:
                plan = plan_reload(self._running(), load_config(self.config_path))
            except ConfigError as exc:
                return self._reject(str(exc))
            except Exception as exc:  # noqa: BLE001 - a reload must never end the loop
                log.debug("reload failed", exc_info=True)
                return self._reject(f"{self.config_path}: cannot load: {type(exc).__name__}: {exc}")
            try:
                self._put_in_force(plan)
            except (ValueError, TypeError, ArithmeticError) as exc:
                return self._reject(f"{self.config_path}: not applied: {exc}")
            self._count(plan)
            if plan.restart:
                log.warning("reload: %s changed but need a restart to take effect", ", ".join(plan.restart))
            log.info("reload %s", plan.summary())
            return {"ok": True, "message": plan.summary(), **plan.report()}
        finally:
            self.notifier.ready()

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
