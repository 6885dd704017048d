"""`resume` over the control socket: a path a hold left stopped (daemon.on_recover: wait)
continues from where the robot stands; anything else is refused and changes nothing."""

from __future__ import annotations

import pytest

from tests.support.daemon import start_daemon, wait_for

LINE = {"shape": "line", "length": 1.2, "speed": 0.3, "pose": [0.0, 0.0, 0.0]}


@pytest.mark.slow
def test_resume_continues_a_path_a_waiting_hold_stopped() -> None:
    d = start_daemon(daemon={"on_recover": "wait"},
                     sim={"sensors_freeze_after_s": 3.0, "sensors_freeze_for_s": 0.15})
    try:
        d.wait_ready()
        nothing = d.request({"cmd": "resume"})
        assert nothing["ok"] is False and "nothing to resume in state idle" in nothing["error"]
        assert d.status()["state"] == "idle"
        started = d.request({"cmd": "follow", **LINE}, timeout=60.0)
        assert started["ok"] is True, started
        st = wait_for(lambda: (lambda s: s if s["state"] == "stopped" else None)(d.status()), 30.0,
                      "the hold to end stopped")
        assert st["recovery"]["waits"] == 1 and st["recovery"]["resumes"] == 0, st["recovery"]
        sigma_stopped = st["progress"]["sigma_m"]
        assert 0.1 < sigma_stopped < LINE["length"] - 0.1, st["progress"]  # stopped part way
        reply = d.request({"cmd": "resume"})
        assert reply == {"ok": True, "state": "following"}, reply
        wait_for(lambda: d.status()["state"] == "stopped", 30.0, "the path to end")
        end = d.status()
        assert end["fault"] in ("", None) and end["recovery"]["waits"] == 1, end
        assert end["progress"]["sigma_m"] == pytest.approx(LINE["length"], abs=0.01)
        again = d.request({"cmd": "resume"})
        assert again["ok"] is False and "nothing to resume" in again["error"]
    finally:
        d.close()
