"""`resume` over the control socket: a path a hold left stopped (daemon.on_recover: wait)
continues from where the robot stands; anything else is refused and changes nothing."""

from __future__ import annotations

import os
import signal
import time

import pytest

from tests.support.daemon import STATE_TIMEOUT_S, start_daemon, wait_for

LINE = {"shape": "line", "length": 2.0, "speed": 0.3, "pose": [0.0, 0.0, 0.0]}
STALL_S = 0.15  # the daemon SIGSTOPped: longer than estimator.max_gap_s and 10 ticks, so a hold


@pytest.mark.slow
def test_resume_continues_a_path_a_waiting_hold_stopped() -> None:
    """The hold is made by the test (the daemon stopped for 150 ms once the robot is under
    way), not by a sensor freeze at a fixed time, which a slow start could have let pass
    before the path began. A loaded host may add holds of its own (a stalled loop): each
    one also ends stopped, and is resumed the same way."""
    d = start_daemon(daemon={"on_recover": "wait"})
    try:
        d.wait_ready()
        nothing = d.request({"cmd": "resume"})
        assert nothing["ok"] is False and "resume refused in idle: nothing to resume" in nothing["error"]
        assert d.status()["state"] == "idle"
        started = d.request({"cmd": "follow", **LINE})
        assert started["ok"] is True, started
        wait_for(lambda: d.status()["progress"]["sigma_m"] > 0.1, STATE_TIMEOUT_S, "the robot under way")
        os.kill(d.proc.pid, signal.SIGSTOP)
        time.sleep(STALL_S)
        os.kill(d.proc.pid, signal.SIGCONT)
        resumed = 0
        while True:
            st = wait_for(lambda: (lambda s: s if s["state"] == "stopped" else None)(d.status()),
                          STATE_TIMEOUT_S, "the robot to stop")
            assert st["fault"] in ("", None), st
            rec = st["recovery"]
            assert rec["resumes"] == 0, rec  # every hold ended waiting, none resumed by itself
            if st["progress"]["sigma_m"] > LINE["length"] - 0.01:
                assert rec["waits"] == resumed, rec
                break
            assert rec["waits"] == resumed + 1, rec
            assert st["progress"]["sigma_m"] > 0.1, st["progress"]  # stopped part way
            reply = d.request({"cmd": "resume"})
            assert reply == {"ok": True, "state": "following"}, reply
            resumed += 1
        assert resumed >= 1  # the test's own hold, at least
        end = d.status()
        assert end["progress"]["sigma_m"] == pytest.approx(LINE["length"], abs=0.01)
        again = d.request({"cmd": "resume"})
        assert again["ok"] is False and "nothing to resume" in again["error"]
    finally:
        d.close()
