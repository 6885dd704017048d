"""The journal is the audit trail. Every change of the loop's state and every
safety command gets one line with its cause and who asked over which channel (the daemon's
stderr here; the journal under systemd)."""

from __future__ import annotations

import logging
import signal
import subprocess
import time
from types import SimpleNamespace

import pytest

from ddrt.loop import LoopState
from ddrt.service import audit
from ddrt.service.audit import StateLog
from tests.support.daemon import START_TIMEOUT_S, ready_daemon, start_daemon, wait_for, write_config


def lines_with(err: str, *needles: str) -> list[str]:
    return [ln for ln in err.splitlines() if all(n in ln for n in needles)]


def test_every_command_and_loop_change_gets_one_line() -> None:
    d = start_daemon(daemon={"command_timeout_s": 0.3})
    try:
        d.wait_ready()
        st = d.status()
        x, y, th = st["pose"]["x"], st["pose"]["y"], st["pose"]["theta"]
        import math
        pts = [[round(x, 4), round(y, 4)], [round(x + 0.15 * math.cos(th), 4), round(y + 0.15 * math.sin(th), 4)]]
        # a stop while idle is still recorded, with who asked
        assert d.request({"cmd": "stop"})["ok"] is True
        # a short path to its end
        r = d.request({"cmd": "follow", "points": pts, "speed": 0.2})
        assert r["ok"] is True, r
        wait_for(lambda: d.status()["state"] == "stopped", 10.0, "the end of the path")
        # a drive, ended by its timeout
        assert d.request({"cmd": "drive", "v": 0.05, "omega": 0.0})["ok"] is True
        wait_for(lambda: d.status()["state"] == "stopped", 5.0, "the drive's timeout stop")
        assert d.request({"cmd": "estop"})["state"] == "estop"
        assert d.request({"cmd": "estop"})["state"] == "estop"  # again: no change, still a line
        assert d.request({"cmd": "reset"})["state"] == "idle"
        d.proc.send_signal(signal.SIGUSR1)
        wait_for(lambda: d.status()["state"] == "estop", 3.0, "the SIGUSR1 estop")
        d.proc.send_signal(signal.SIGTERM)
        assert d.proc.wait(timeout=10) == 0
        err = d.stderr()
    finally:
        d.close()
    sock = "over the control socket (pid "
    assert len(lines_with(err, "stop " + sock, "state stays idle")) == 1, err
    assert len(lines_with(err, "state idle -> following", "follow of", sock)) == 1, err
    assert len(lines_with(err, "state following -> stopped", "reached the end of the path")) == 1, err
    assert len(lines_with(err, "state stopped -> driving", "drive " + sock)) == 1, err
    assert len(lines_with(err, "state driving -> stopped", "drive timeout")) == 1, err
    assert len(lines_with(err, "state stopped -> estop", "estop " + sock)) == 1, err
    assert len(lines_with(err, "estop " + sock, "state stays estop")) == 1, err
    assert len(lines_with(err, "state estop -> idle", "reset " + sock)) == 1, err
    assert len(lines_with(err, "state idle -> estop", "SIGUSR1")) == 1, err
    assert len(lines_with(err, "shutdown (SIGTERM received)", "state estop -> estop", "motors zeroed")) == 1, err


def test_a_hold_and_the_fault_it_ends_in_are_logged_with_their_cause() -> None:
    d = start_daemon("--follow", sim={"sensors_freeze_after_s": 2.0})
    try:
        try:
            rc = d.proc.wait(timeout=START_TIMEOUT_S + 6)
        except subprocess.TimeoutExpired:
            pytest.fail(f"no exit after the sensors froze:\n{d.stderr()}")
        err = d.stderr()
    finally:
        d.close()
    assert rc == 1, err
    assert len(lines_with(err, "state idle -> following", "at start-up (--follow)")) == 1, err
    assert len(lines_with(err, "state following -> holding: hold:")) == 1, err
    assert len(lines_with(err, "-> fault:", "sensors stale")) == 1, err
    assert len(lines_with(err, "shutdown (after a fault)")) == 1, err


def fake_loop(state: LoopState, **kw: object) -> SimpleNamespace:
    base = dict(state=state, reference=None, fault="", holds=SimpleNamespace(active=None), path_completed=False)
    base.update(kw)
    return SimpleNamespace(**base)


def test_hold_end_and_rate_limit(caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch) -> None:
    caplog.set_level(logging.INFO, logger="ddrt.service.daemon")
    s = StateLog(LoopState.FOLLOWING)
    hold = SimpleNamespace(cause="sample gap of 80 ms")
    s.check(fake_loop(LoopState.HOLDING, holds=SimpleNamespace(active=hold)))
    s.check(fake_loop(LoopState.FOLLOWING))
    s.check(fake_loop(LoopState.HOLDING, holds=SimpleNamespace(active=hold)))
    s.check(fake_loop(LoopState.STOPPED))
    text = caplog.text
    assert "state following -> holding: hold: sample gap of 80 ms" in text
    assert "state holding -> following: the hold ended: resuming the path" in text
    assert "state holding -> stopped: the hold ended stopped" in text
    # flapping: at most BURST lines a second, then the count of those left out
    caplog.clear()
    now = [100.0]
    monkeypatch.setattr(audit.time, "monotonic", lambda: now[0])
    s = StateLog(LoopState.FOLLOWING)
    for i in range(50):
        s.check(fake_loop(LoopState.HOLDING if i % 2 == 0 else LoopState.FOLLOWING))
    assert len([r for r in caplog.records if "state " in r.getMessage()]) == audit.BURST
    now[0] += 1.5
    s.check(fake_loop(LoopState.HOLDING))
    assert f"{50 - audit.BURST} lines left out" in caplog.text


def test_no_change_costs_no_line(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG, logger="ddrt.service.daemon")
    s = StateLog(LoopState.IDLE)
    loop = fake_loop(LoopState.IDLE)
    for _ in range(100):
        s.check(loop)
    s.note("drive over Foxglove teleop", always=False)  # a drive that changed nothing
    s.check(loop)
    assert caplog.records == []
    t0 = time.perf_counter()
    for _ in range(100000):
        s.check(loop)
    assert (time.perf_counter() - t0) / 100000 < 5e-6


def test_reload_counts_applied_only_when_something_changed() -> None:
    """`applied` counts only reloads that put something new in force."""
    with ready_daemon() as d:
        write_config(d.config, d.telemetry_dir, controller={"inner": {"kp": 41.0}})
        reply = d.request({"cmd": "reload"})
        assert reply["ok"] is True and "controller.inner.kp" in reply["applied"], reply
        assert d.request({"cmd": "reload"})["applied"] == []
        assert d.status()["reloads"] == {"applied": 1, "unchanged": 1, "rejected": 0}
