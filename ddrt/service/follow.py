"""A `follow` from request to the loop's switch: the path is read and built in the worker
process (ddrt/service/pathworker.py), the loop keeps ticking, and between two ticks, once
the path is ready, the loop switches to it and the request's `Deferred` reply is sent.

At most one follow waits for its path at a time: the daemon's `FollowSlot`. Nothing here reads
a file or builds anything on the loop thread: a follow costs the loop microseconds whatever
it asks for. A stop, an estop or the daemon's exit cancels a follow still being prepared.
"""

from __future__ import annotations

import logging
from array import array
from typing import TYPE_CHECKING, Any

import numpy as np

from ddrt.path import PathError
from ddrt.path.frame import inverse
from ddrt.path.spec import config_path_error, speed_limits
from ddrt.service.audit import peer_text
from ddrt.service.commands import Request
from ddrt.service.ctlqueue import Deferred
from ddrt.service.pathjob import Build, BuildJob, build_path, content_source, describe
from ddrt.service.timing import select_quantiles
from ddrt.loop import Event, ModeRefused, StartTooFar
from ddrt.loop.modes import refused_in

if TYPE_CHECKING:
    from ddrt.service.daemon import Daemon

log = logging.getLogger("ddrt.service.daemon")

PREPARE_SAMPLES = 1 << 14  # lateness samples kept while a path is prepared (82 s at 200 Hz)


class PendingFollow:
    """A follow whose path is being built in the worker; the loop switches to it when ready."""

    __slots__ = ("build", "pose", "reply", "what", "ticks", "late", "missed0", "who", "built")

    def __init__(self, build: Build, pose: tuple[float, float, float] | None, reply: Deferred | None,
                 what: str, missed0: int, who: str = "", built: tuple[float, float, float] | None = None) -> None:
        self.who = who  # who asked, over which channel (the log's audit line)
        self.build = build
        self.pose = pose
        self.reply = reply
        self.what = what
        self.ticks = 0
        self.late = array("d")  # each tick's lateness while the path is prepared (bounded)
        self.missed0 = missed0
        self.built = built  # frame map: the correction the path was built at

    def report(self, missed: int) -> dict[str, Any]:
        """What preparing the path cost the loop: the ticks it ran meanwhile, how late."""
        _p50, p99, top = (select_quantiles(np.frombuffer(self.late, dtype=np.float64)) if self.late
                          else (None, None, None))
        return {"seconds": self.build.elapsed_s, "ticks": self.ticks, "missed_ticks": missed - self.missed0,
                "late_p99_us": p99 * 1e6 if p99 is not None else None,
                "late_max_us": top * 1e6 if top is not None else None}


class FollowSlot:
    """The one follow that may wait for its path at a time, owned by the daemon; the socket's
    handlers ask it, and only this module's steps fill and empty it."""

    def __init__(self) -> None:
        self._pending: PendingFollow | None = None

    @property
    def pending(self) -> PendingFollow | None:
        return self._pending

    def hold(self, pending: PendingFollow) -> None:
        if self._pending is not None:
            raise RuntimeError(f"a follow of {self._pending.what} is already being prepared")
        self._pending = pending

    def release(self) -> PendingFollow | None:
        """The follow that was waiting (None if none was), and the slot empty."""
        pending, self._pending = self._pending, None
        return pending

    def busy_text(self) -> str:
        """'' when free, else what is being prepared, for a refusal."""
        return "" if self._pending is None else self._pending.what


def start_follow(d: Daemon, req: Request) -> dict[str, Any] | Deferred:
    """Check the request, hand the path to the worker, answer when the loop has switched.

    A follow the loop's mode machine refuses in its state (ddrt/loop/modes.py) is refused before
    its path is built (its guard, a low battery, when the loop takes it), and so is one while another is being prepared (send stop to cancel that).
    """
    loop = d.loop
    assert loop is not None
    if why := refused_in(Event.FOLLOW, loop.state):
        return {"ok": False, "error": why}
    waiting = d.follows.pending
    if waiting is not None:
        return {"ok": False, "error": f"busy: still preparing {waiting.what} "
                                      f"({waiting.build.elapsed_s:.1f} s): send stop to cancel it"}
    source: Any
    args = req.args
    if "path" in args:
        source = args["path"]
        if req.extra:
            return {"ok": False, "error": f"follow: {sorted(req.extra)[0]!s:.40}: not with path (the keys of a "
                                          "path spec belong in the file it names)"}
    elif "content" in args:
        # A path file's content (ddrt ctl follow FILE): read as that file would be.
        try:
            source = content_source({**args, **req.extra}, d.cfg.paths.max_file_bytes)
        except ValueError as exc:
            return {"ok": False, "error": f"follow: {exc}"}
    elif "points" in req.extra or "shape" in req.extra:
        # An inline spec: every key but the request's own goes to the path loader, which
        # refuses unknown ones and clamps limits above the config's (reported below).
        source = dict(req.extra)
        if "points" in source:
            source.setdefault("speed", min(0.3, speed_limits(d.cfg).v_max))
    else:
        return {"ok": False, "error": "follow: give path (a file the daemon reads), content (a file's text, "
                                      "with format csv or yaml), points ([[x, y], ...]) or shape"}
    pose = tuple(args["pose"]) if "pose" in args else None
    here = args["here"]
    if here and pose is not None:
        return {"ok": False, "error": "follow: here and pose: give one (here places the path at the robot's "
                                      "pose; pose says where the robot is)"}
    frame = args["frame"]
    built = None
    if frame == "map":
        if pose is not None:
            return {"ok": False, "error": "follow: pose and frame map: give one (set the pose first with the pose "
                                          "command, then follow in map)"}
        # Built in odom as the fixes' correction stands now (ddrt/path/frame.py follows it from there).
        built = loop.estimator.frame.correction()
    # here: the path is moved (in the worker) so that it starts at the robot's pose and heading
    place_at = (loop.estimator.map_pose() if frame == "map" else loop.estimator_pose()) if here else None
    job = BuildJob(source, speed_limits(d.cfg), d.cfg.paths, where="request", place_at=place_at,
                   to_odom=inverse(built) if built is not None else None)
    who = peer_text(d.server.peer if d.server is not None else "")
    what = describe(source)
    if d.paths is None:
        # A Daemon that is not running (tests, tools): no loop to protect, build here.
        build = Build(job)
        try:
            build.finish(path=build_path(job))
        except (PathError, ValueError, TypeError, OSError) as exc:
            return {"ok": False, "error": f"follow: {exc}"}
        return switch(d, PendingFollow(build, pose, None, what, d.stats.missed, who, built), build)
    build = d.paths.submit(job)
    reply = Deferred()
    d.follows.hold(PendingFollow(build, pose, reply, what, d.stats.missed, who, built))
    log.info("follow: preparing %s", what)
    return reply


def follow_step(d: Daemon, late_s: float) -> None:
    """Between two ticks while a follow waits for its path: switch once it is ready."""
    p = d.follows.pending
    assert p is not None
    p.ticks += 1
    if len(p.late) < PREPARE_SAMPLES:
        p.late.append(late_s)
    build = p.build
    if not build.done:
        return
    d.follows.release()
    reply = switch(d, p, build) if not build.error else {"ok": False, "error": f"follow: {build.error}"}
    reply["prepared"] = p.report(d.stats.missed)
    if not reply["ok"]:
        log.error("not following %s: %s", p.what, reply["error"])
    if p.reply is not None:
        p.reply.complete(reply)
    elif build.error:
        # The start path (--follow) does not load: a bad start-up input like a bad config.
        d.fail(config_path_error(d.cfg, build.error), 2)  # names the config file and `path:`


def switch(d: Daemon, p: PendingFollow, build: Build) -> dict[str, Any]:
    """The loop takes the built path (between two ticks); the last one is freed off the loop."""
    loop = d.loop
    assert loop is not None
    path = build.take()
    old = loop.path
    try:
        d.audit.note(f"follow of {p.what} {p.who or 'at start-up (--follow)'}", always=False)
        loop.follow(path, p.pose, p.built)  # built: a path in map, steered in odom (ddrt/path/frame.py)
    except (ValueError, RuntimeError) as exc:  # ModeRefused among them: its message says it all
        if d.paths is not None:
            d.paths.dispose(path)
        if isinstance(exc, ModeRefused):
            return {"ok": False, "error": str(exc)}
        # --here moves the path to start at the robot: the other way out of a far start.
        here = (", or follow it from where the robot stands: `ddrt ctl follow FILE --here`"
                if isinstance(exc, StartTooFar) else "")
        return {"ok": False, "error": f"follow: {exc}{here}"}
    if old is not None and old is not path and d.paths is not None:
        d.paths.dispose(old)  # the loop's last reference is gone: free it off the loop
    del old
    if d.viz is not None:
        d.viz.path_started(path)
    for note in path.notes:
        log.info("follow: %s", note)
    for warning in path.warnings:
        log.warning("follow: %s", warning)
    log.info("following %s: %.2f m, %.1f s (prepared in %.2f s)", p.what, path.length, path.duration,
             build.elapsed_s)
    reply: dict[str, Any] = {
        "ok": True, "state": loop.state.label, "length_m": path.length, "duration_s": path.duration,
    }
    if path.warnings:
        reply["warnings"] = list(path.warnings)
    if path.notes:
        reply["notes"] = list(path.notes)
    return reply


def cancel_follow(d: Daemon, why: str) -> dict[str, Any]:
    """A stop or estop (or the daemon's exit) cancels a follow still being prepared."""
    p = d.follows.release()
    if p is None:
        return {}
    if d.paths is not None:
        d.paths.cancel(p.build)
    log.info("follow of %s %s", p.what, why)
    if p.reply is not None:
        p.reply.complete({"ok": False, "error": f"follow: {why}"})
    return {"cancelled": f"follow of {p.what}"}


def preparing(d: Daemon) -> dict[str, Any] | None:
    """The follow being prepared, for status (None when there is none)."""
    p = d.follows.pending
    if p is None:
        return None
    return {"source": p.what, "phase": p.build.phase, "elapsed_s": p.build.elapsed_s}
