"""The daemon's reloads read the config file off the loop thread (ddrt/service/reloading.py):
`request` returns at once while a helper thread reads, `poll` puts the result in force between
two ticks and answers who asked, requests during a read get the next read, and a stop answers
everyone still waiting. Driven with a read that is held open, so nothing here depends on how
long a read takes."""

from __future__ import annotations

import os
import threading
from pathlib import Path
from typing import Any

import pytest

import ddrt.service.reloading as reloading
from ddrt.config import Config, load_config
from ddrt.config.policy import ReloadPlan
from ddrt.service.reloading import Reloader
from tests.support.reload_rig import write_config


class Brackets:
    """A Notifier that records the reload brackets it sends."""

    def __init__(self) -> None:
        self.sent: list[str] = []

    def reloading(self) -> bool:
        self.sent.append("RELOADING")
        return True

    def ready(self) -> bool:
        self.sent.append("READY")
        return True


class Held:
    """load_config that waits for `go` before reading: a read under way for as long as a test needs."""

    def __init__(self) -> None:
        self.go = threading.Event()
        self.started = threading.Semaphore(0)
        self.reads = 0

    def __call__(self, path: Any) -> Config:
        self.reads += 1
        self.started.release()
        assert self.go.wait(30.0), "the test never let the read go on"
        return load_config(path)


class Host:
    """What a daemon gives its Reloader: the config in force and a way to put a plan in force."""

    def __init__(self, file: Path, loop_priority: int = 0) -> None:
        self.cfg = load_config(file)
        self.applied: list[ReloadPlan] = []
        self.notifier = Brackets()
        self.now = 1000.0  # the reloader's clock (s), moved by the tests that need its deadline
        self.reloader = Reloader(str(file), self.notifier, lambda: self.cfg, self.put,  # type: ignore[arg-type]
                                 lambda: loop_priority, clock=lambda: self.now)

    def put(self, plan: ReloadPlan) -> None:
        self.applied.append(plan)
        self.cfg = plan.in_force


def _finish(host: Host, held: Held) -> None:
    """Let the read under way end, and poll: it is put in force (a read that poll starts next
    is held again)."""
    held.go.set()
    reading = host.reloader._reading
    assert reading is not None and reading.thread is not None
    reading.thread.join(30.0)
    held.go.clear()
    host.reloader.poll()


def _host(tmp: Path, loop_priority: int = 0) -> Host:
    file = tmp / "ddrt.yaml"
    write_config(file, tmp, {})
    return Host(file, loop_priority)


def _reload_to_the_end(host: Host) -> list[dict[str, Any]]:
    """Request a reload, wait for its read, poll: the replies."""
    replies: list[dict[str, Any]] = []
    host.reloader.request(replies.append)
    reading = host.reloader._reading
    assert reading is not None and reading.thread is not None
    reading.thread.join(30.0)
    host.reloader.poll()
    return replies


@pytest.fixture()
def held(monkeypatch: pytest.MonkeyPatch) -> Held:
    h = Held()
    monkeypatch.setattr(reloading, "load_config", h)
    return h


def test_request_returns_while_the_file_is_read_and_poll_puts_it_in_force(tmp_path: Path, held: Held) -> None:
    file = tmp_path / "ddrt.yaml"
    write_config(file, tmp_path, {})
    host = Host(file)
    write_config(file, tmp_path, {"controller": {"inner": {"kp": 61.0}}})
    replies: list[dict[str, Any]] = []
    host.reloader.request(replies.append)
    assert held.started.acquire(timeout=30.0)  # the read has begun, and is held open
    assert host.reloader.busy and host.notifier.sent == ["RELOADING"]
    host.reloader.poll()  # between two ticks: nothing to do yet, nothing blocks
    assert replies == [] and host.applied == [] and host.cfg.controller.inner.kp != 61.0
    _finish(host, held)
    assert host.cfg.controller.inner.kp == 61.0
    assert len(replies) == 1 and replies[0]["ok"] is True and "controller.inner.kp" in replies[0]["applied"]
    assert host.notifier.sent == ["RELOADING", "READY"]
    assert not host.reloader.busy and host.reloader.counts == {"applied": 1, "unchanged": 0, "rejected": 0}
    assert not host.reloader.changed_on_disk()  # the version read is the one on disk


def test_requests_during_a_read_get_the_next_read(tmp_path: Path, held: Held) -> None:
    """The file may change after a read opened it: who asks during a read is answered by a
    read that starts after that one, and several such requests share it."""
    file = tmp_path / "ddrt.yaml"
    write_config(file, tmp_path, {})
    host = Host(file)
    first: list[dict[str, Any]] = []
    later: list[dict[str, Any]] = []
    write_config(file, tmp_path, {"controller": {"inner": {"kp": 61.0}}})
    host.reloader.request(first.append)
    assert held.started.acquire(timeout=30.0)
    host.reloader.request(later.append)
    host.reloader.request()  # SIGHUP: nobody waits for the reply
    host.reloader.request(later.append)
    assert held.reads == 1
    _finish(host, held)
    assert [r["ok"] for r in first] == [True] and later == []
    assert host.reloader.busy and held.started.acquire(timeout=30.0)  # the next read began at once
    write_config(file, tmp_path, {"controller": {"inner": {"kp": 62.0}}})  # while it is held open
    _finish(host, held)
    assert held.reads == 2 and host.cfg.controller.inner.kp == 62.0
    assert len(later) == 2 and all(r["ok"] and "controller.inner.kp" in r["applied"] for r in later)
    assert not host.reloader.busy and host.notifier.sent == ["RELOADING", "READY"] * 2


def test_a_bad_file_read_off_the_loop_is_rejected_by_name(tmp_path: Path, held: Held) -> None:
    file = tmp_path / "ddrt.yaml"
    write_config(file, tmp_path, {})
    host = Host(file)
    before = host.cfg
    write_config(file, tmp_path, {"controller": {"inner": {"kp": "abc"}}})
    replies: list[dict[str, Any]] = []
    host.reloader.request(replies.append)
    _finish(host, held)
    assert replies[0]["ok"] is False and "controller.inner.kp" in replies[0]["error"]
    assert host.cfg is before and host.applied == []
    assert host.reloader.counts["rejected"] == 1 and host.notifier.sent == ["RELOADING", "READY"]


def test_a_read_that_raises_anything_is_a_rejection(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    host = _host(tmp_path)

    def broken(path: Any) -> Config:
        raise MemoryError("no room")

    monkeypatch.setattr(reloading, "load_config", broken)
    replies = _reload_to_the_end(host)
    assert replies[0]["ok"] is False and "MemoryError" in replies[0]["error"]
    assert host.reloader.config_path in replies[0]["error"]


def test_a_stop_answers_everyone_still_waiting(tmp_path: Path, held: Held) -> None:
    host = _host(tmp_path)
    replies: list[dict[str, Any]] = []
    host.reloader.request(replies.append)
    assert held.started.acquire(timeout=30.0)
    host.reloader.request(replies.append)
    host.reloader.cancel("the daemon is stopping")
    assert [r["ok"] for r in replies] == [False, False] and "stopping" in replies[0]["error"]
    held.go.set()
    host.reloader.poll()  # the abandoned read ends unseen
    assert len(replies) == 2 and host.applied == [] and not host.reloader.busy


def test_the_reader_thread_goes_below_a_real_time_loop(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A thread inherits its creator's SCHED_FIFO priority: at the loop's own, the loop could not
    preempt it on a shared CPU. The reader asks to go below the loop's priority, on its own
    thread, before it reads; a synchronous reload leaves the calling thread's alone."""
    host = _host(tmp_path, loop_priority=40)
    asked: list[tuple[int, str]] = []
    monkeypatch.setattr(reloading, "raise_gil_helper",
                        lambda p: asked.append((p, threading.current_thread().name)) or None)
    replies = _reload_to_the_end(host)
    assert asked == [(40, "ddrt-reload")] and replies[0]["ok"] is True
    host.reloader.reload()
    assert len(asked) == 1


def test_no_thread_to_be_had_is_a_rejection_not_a_crash(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    host = _host(tmp_path)

    def refuse(self: threading.Thread) -> None:
        raise RuntimeError("can't start new thread")

    monkeypatch.setattr(threading.Thread, "start", refuse)
    replies: list[dict[str, Any]] = []
    host.reloader.request(replies.append)  # on the loop thread: must not raise
    assert replies and replies[0]["ok"] is False and "cannot start a thread" in replies[0]["error"]
    assert not host.reloader.busy and host.notifier.sent == ["RELOADING", "READY"]
    assert host.reloader.counts["rejected"] == 1


def test_a_read_that_never_returns_is_given_up_and_reloads_go_on(tmp_path: Path, held: Held) -> None:
    """A read that does not return (a FIFO, a file system that stopped answering) must not lock
    reloads out: at its deadline its waiters and those queued behind it are answered; while
    its thread is still stuck a request is refused at once, naming the file; once it returns,
    reads work again. At most one reader is ever stuck."""
    host = _host(tmp_path)
    first: list[dict[str, Any]] = []
    queued: list[dict[str, Any]] = []
    host.reloader.request(first.append)
    assert held.started.acquire(timeout=30.0)
    host.reloader.request(queued.append)
    host.now += reloading.READ_DEADLINE_S - 1.0
    host.reloader.poll()
    assert first == [] and host.reloader.busy  # slow, but not yet given up
    host.now += 2.0
    host.reloader.poll()
    assert len(first) == 1 and first[0]["ok"] is False and "no answer within 30 s" in first[0]["error"]
    assert host.reloader.config_path in first[0]["error"]
    assert len(queued) == 1 and queued[0]["ok"] is False and "has not returned" in queued[0]["error"]
    assert not host.reloader.busy and held.reads == 1  # no second reader started behind the stuck one
    later: list[dict[str, Any]] = []
    host.reloader.request(later.append)  # answered at once, on the calling thread
    assert len(later) == 1 and later[0]["ok"] is False and host.reloader.config_path in later[0]["error"]
    assert host.reloader.counts["rejected"] == 3 and host.applied == []
    assert host.notifier.sent == ["RELOADING", "READY"] * 3
    stuck = host.reloader._stuck
    assert stuck is not None and stuck.thread is not None
    held.go.set()  # the stuck read returns at last; its outcome is not used
    stuck.thread.join(30.0)
    write_config(Path(host.reloader.config_path), tmp_path,
                 {"controller": {"inner": {"kp": 63.0}}})
    replies = _reload_to_the_end(host)
    assert replies[0]["ok"] is True and host.cfg.controller.inner.kp == 63.0 and held.reads == 2


def test_a_config_path_turned_into_a_fifo_does_not_lock_reloads_out(tmp_path: Path) -> None:
    """The real thing: opening a FIFO nobody writes blocks the reader; the loop's side goes on."""
    host = _host(tmp_path)
    path = Path(host.reloader.config_path)
    saved = path.read_text()
    path.unlink()
    os.mkfifo(path)
    replies: list[dict[str, Any]] = []
    host.reloader.request(replies.append)
    reading = host.reloader._reading
    assert reading is not None and reading.thread is not None
    reading.thread.join(0.2)
    assert reading.thread.is_alive()  # blocked in open()
    host.now += reloading.READ_DEADLINE_S + 1.0
    host.reloader.poll()
    assert replies[0]["ok"] is False and str(path) in replies[0]["error"] and "FIFO" in replies[0]["error"]
    fd = os.open(path, os.O_WRONLY | os.O_NONBLOCK)  # a writer that closes at once: the reader sees an empty file
    os.close(fd)
    reading.thread.join(30.0)
    assert not reading.thread.is_alive()
    path.unlink()
    path.write_text(saved)
    assert _reload_to_the_end(host)[0]["ok"] is True
