"""The velocity mode abused the way users and bad senders abuse it: reloads that change the
limits while the robot drives, limits toggled between null and numbers, commands at the
limits for a long time, reversed signs, and a `ddrt ctl drive --for` whose daemon dies.
In process on the simulated robot in simulated time unless the test says otherwise."""

from __future__ import annotations

import math

import pytest

from ddrt.config import with_overrides
from ddrt.loop import LoopState
from tests.support.drive_rigs import Robot


def _true_accel_bound(r: Robot, n: int, drive: tuple[float, float] | None, every: int = 20) -> tuple[float, float]:
    """Tick n times; the largest |dv/dt| of the plant's true forward speed, each over 5 ticks
    (25 ms: longer than the plant's lag and the command latency, shorter than any ramp),
    and the smallest true speed seen."""
    loop = r.loop
    window = 5
    hist = [r.true_v()[0]]
    worst, lowest = 0.0, math.inf
    for k in range(n):
        r.ticks(1, drive=drive if k % every == 0 else None)
        hist.append(r.true_v()[0])
        lowest = min(lowest, hist[-1])
        if len(hist) > window:
            worst = max(worst, abs(hist[-1] - hist[-1 - window]) / (window * loop.period))
    return worst, lowest


@pytest.mark.parametrize("resend", [True, False])
def test_a_reload_that_lowers_v_max_at_speed_brakes_within_the_limits(resend: bool) -> None:
    """Driving at 0.8 m/s, a reload sets limits.v_max 0.3: the robot slows to 0.3 m/s at
    limits.accel along the jerk-limited ramp, with or without further commands, never below
    it; before the fix the controller's clamp cut the commanded speed to 0.3 at once
    (5 m/s^2 on the plant, undershooting to 0.18 m/s) while the setpoint stayed at 0.8."""
    r = Robot()
    try:
        loop, cfg = r.loop, r.cfg
        r.ticks(600, drive=(0.8, 0.0))
        assert r.true_v()[0] == pytest.approx(0.8, abs=0.01)
        loop.reconfigure(with_overrides(cfg, {"limits": {"v_max": 0.3}}))
        assert loop.reference.target == (0.3, 0.0)  # the held command, clamped to the new limit
        sp, prev_a = loop.setpoint, loop.setpoint.a_d
        worst, lowest = 0.0, math.inf
        for _ in range(60):  # 3 s: the setpoint's own limits, tick by tick
            w, lo = _true_accel_bound(r, 10, (0.8, 0.0) if resend else None)
            worst, lowest = max(worst, w), min(lowest, lo)
            assert abs(sp.a_d) <= cfg.limits.accel * (1 + 1e-9)
            assert abs(sp.a_d - prev_a) <= 10 * cfg.drive.jerk_max * loop.period * (1 + 1e-9)
            prev_a = sp.a_d
        if resend:
            assert sp.v_d == 0.3 and r.true_v()[0] == pytest.approx(0.3, abs=0.01)
        assert worst <= 1.3 * cfg.limits.accel, worst  # the plant follows the ramp, with its lag
        assert lowest >= 0.3 - 0.01 if resend else lowest >= -0.01, lowest
        assert loop.state in (LoopState.DRIVING, LoopState.STOPPED) and loop.fault == ""
    finally:
        r.close()


def test_a_reload_that_lowers_omega_max_while_turning_brakes_the_turn_within_alpha_max() -> None:
    r = Robot()
    try:
        loop, cfg = r.loop, r.cfg
        r.ticks(600, drive=(0.2, 2.0))
        assert r.true_v()[1] == pytest.approx(2.0, abs=0.05)
        loop.reconfigure(with_overrides(cfg, {"limits": {"omega_max": 0.5}}))
        worst_alpha = 0.0
        prev_w = r.true_v()[1]
        hist = [prev_w]
        for k in range(600):
            r.ticks(1, drive=(0.2, 2.0) if k % 20 == 0 else None)
            hist.append(r.true_v()[1])
            if len(hist) > 5:
                worst_alpha = max(worst_alpha, abs(hist[-1] - hist[-6]) / (5 * loop.period))
            assert abs(loop.cmd.omega_c) <= 2.0 + 1e-9
        assert loop.setpoint.omega_d == 0.5 and r.true_v()[1] == pytest.approx(0.5, abs=0.05)
        assert worst_alpha <= 1.3 * cfg.limits.alpha_max, worst_alpha
    finally:
        r.close()
