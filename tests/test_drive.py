"""The velocity mode (`drive`), in process on the simulated robot (configs/sim.yaml), in
simulated time: the ramp's limits, the timeout's stop measured on the plant's true state,
switching between drive, follow, stop, estop and faults, refusals, and a fuzz of the
request against a running loop.
"""

from __future__ import annotations

import math
import random
from pathlib import Path
from typing import Any

import pytest

from ddrt.config import with_overrides
from ddrt.config.sections import LimitsConfig
from ddrt.core.drive import REFUSE_FACTOR, check_command
from ddrt.core.ramp import Ramp
from ddrt.loop import LoopState
from ddrt.path import load_path
from ddrt.path.spec import speed_limits
from ddrt.service.drivecmd import drive_for
from ddrt.service.follow import PendingFollow as _PendingFollow
from ddrt.service.pathjob import Build, BuildJob
from tests.support.drive_rigs import DaemonRig, Robot

LINE = {"shape": "line", "length": 2.0, "speed": 0.3}


# ---------------------------------------------------------------- the ramp, alone


@pytest.mark.parametrize("jerk", [10.0, 2.0, None])
def test_the_ramp_never_exceeds_its_limits_and_lands_on_the_target(jerk: float | None) -> None:
    rng = random.Random(7)
    accel, dt = 1.0, 0.005
    r = Ramp(accel, jerk)
    prev_rate = 0.0
    target = 0.0
    for k in range(20_000):
        if k % 400 == 0 or rng.random() < 0.002:
            target = rng.uniform(-1.0, 1.0)
        r.step(target, dt)
        assert abs(r.rate) <= accel * (1 + 1e-9)
        if jerk is not None:
            assert abs(r.rate - prev_rate) <= jerk * dt * (1 + 1e-9)
        prev_rate = r.rate
    # From rest to a step target: exactly on it, no overshoot, in the time-optimal time.
    r.reset()
    values = []
    while not (r.value == 0.8 and r.rate == 0.0):
        values.append(r.step(0.8, dt))
        assert len(values) < 2000
    assert max(values) == 0.8
    optimal = 0.8 / accel + (accel / jerk if jerk else 0.0)
    assert len(values) * dt == pytest.approx(optimal, abs=2 * dt)


def test_a_smaller_decel_is_honoured_and_a_larger_one_is_not() -> None:
    r = Ramp(1.0, None)
    r.reset(1.0)
    r.step(0.0, 0.01, accel=0.5)
    assert r.value == pytest.approx(0.995)
    r.step(0.0, 0.01, accel=5.0)
    assert r.value == pytest.approx(0.985)


# ---------------------------------------------------------------- the command's values

# The seed robot's explicit limits (null ones are derived from the motors by the loop).
SEED_LIMITS = LimitsConfig(v_max=1.0, accel=1.0, torque_max_nm=1.0)


@pytest.mark.parametrize(("v", "omega", "field", "why"), [
    ("1", 0.0, "v", "expected a number"), (True, 0.0, "v", "expected a number"), (0.0, False, "omega", "number"),
    (None, 0.0, "v", "expected a number"), ([1.0], 0.0, "v", "number"), ({"x": 1}, 0.0, "v", "number"),
    (math.nan, 0.0, "v", "finite"), (0.0, -math.inf, "omega", "finite"), (1e300, 0.0, "v", "unit error"),
    (0.0, 31.0, "omega", "limits.omega_max"), (10**400, 0.0, "v", "too large"), (-10.5, 0.0, "v", "limits.v_max"),
])
def test_garbage_values_are_refused_naming_the_field(v: Any, omega: Any, field: str, why: str) -> None:
    with pytest.raises(ValueError, match=rf"^{field}: .*{why}"):
        check_command(v, omega, SEED_LIMITS)


def test_values_beyond_the_limits_are_clamped_and_said_so() -> None:
    lim = SEED_LIMITS
    assert check_command(0.3, -1, lim) == (0.3, -1.0, ())
    assert check_command(-2.5, 7.0, lim) == (-lim.v_max, lim.omega_max, ("v", "omega"))
    assert check_command(REFUSE_FACTOR * lim.v_max, 0, lim)[0] == lim.v_max  # the bound itself is clamped


# ---------------------------------------------------------------- the loop on the simulated robot


@pytest.fixture()
def robot() -> Robot:
    r = Robot()
    yield r
    r.close()


def test_the_setpoint_keeps_the_limits_and_the_robot_reaches_the_command(robot: Robot) -> None:
    loop, cfg = robot.loop, robot.cfg
    lim, drv = cfg.limits, cfg.drive
    dt = loop.period
    sp = loop.setpoint
    prev = (0.0, 0.0)
    commands = [(0.6, 1.5), (0.6, 1.5), (-0.4, -2.5), (0.0, 3.0), (0.8, 0.0)]
    for v, w in commands:
        for k in range(300):
            if k % 20 == 0:
                loop.drive(v, w)
            robot.ticks(1)
            assert loop.state == LoopState.DRIVING, loop.fault
            assert abs(sp.v_d) <= lim.v_max and abs(sp.omega_d) <= lim.omega_max
            assert abs(sp.a_d) <= lim.accel * (1 + 1e-9) and abs(sp.alpha_d) <= lim.alpha_max * (1 + 1e-9)
            assert abs(sp.a_d - prev[0]) <= drv.jerk_max * dt * (1 + 1e-9)
            assert abs(sp.alpha_d - prev[1]) <= drv.angular_jerk_max * dt * (1 + 1e-9)
            prev = (sp.a_d, sp.alpha_d)
        assert (sp.v_d, sp.omega_d) == (v, w)  # 1.5 s is enough for every step above
        tv, tw = robot.true_v()
        assert tv == pytest.approx(v, abs=0.01) and tw == pytest.approx(w, abs=0.05)
    assert loop.row[21] == LoopState.DRIVING


def test_the_kinematic_baseline_drives_too_and_the_seeds_method_is_refused() -> None:
    r = Robot(controller={"mode": "kinematic"})
    try:
        for cmd in ((0.3, 1.0), (0.0, 1.5), (-0.2, 0.0)):  # a turn in place among them
            r.ticks(400, drive=cmd)
            assert r.true_v() == pytest.approx(cmd, abs=0.01)
    finally:
        r.close()
    r = Robot(controller={"mode": "seed"})
    try:
        with pytest.raises(ValueError, match="seed"):
            r.loop.drive(0.3, 0.0)
        assert r.loop.state == LoopState.IDLE and r.loop.reference is None
    finally:
        r.close()


@pytest.mark.parametrize("jerk", [10.0, None])
def test_after_the_last_command_at_1_m_s_the_robot_stands_still_in_time_and_distance(jerk: float | None) -> None:
    """The issue's requirement, on the plant's true state: still within the timeout plus the
    braking time at limits.accel (with the jerk ramps in and out), no farther than that.
    Measured: jerk 10 m/s^3, still 1.565 s after the last command, 1.050 m (bounds 1.6 s, 1.05 m);
    no jerk limit, 1.495 s and 1.000 m (bounds 1.5 s, 1.0 m)."""
    r = Robot(drive={"jerk_max": jerk})
    try:
        loop, cfg = r.loop, r.cfg
        r.ticks(500, drive=(1.0, 0.0))  # 2.5 s at 10 Hz: up to speed
        assert r.true_v()[0] == pytest.approx(1.0, abs=0.01)
        loop.drive(1.0, 0.0)  # the last command
        t0, (x0, y0, _) = r.hal.now(), r.plant.pose
        timeout, a = cfg.daemon.command_timeout_s, cfg.limits.accel
        ramps = a / jerk if jerk else 0.0
        braking_s = 1.0 / a + ramps
        allowed_m = 1.0 * timeout + 1.0 / (2 * a) + 1.0 * ramps / 2
        still_t = None
        travel = 0.0
        while r.hal.now() - t0 < timeout + braking_s + 1.0:
            r.ticks(1)
            x, y, _ = r.plant.pose
            travel = math.hypot(x - x0, y - y0)
            v, w = r.true_v()
            moving = abs(v) > 0.005 or abs(w) > 0.01
            if moving:
                still_t = None
            elif still_t is None:
                still_t = r.hal.now() - t0
        assert loop.state == LoopState.STOPPED and loop.duty_l == loop.duty_r == 0.0
        assert r.plant.applied_duty == (0.0, 0.0)
        assert still_t is not None and still_t <= timeout + braking_s + 0.05, still_t  # 10 ticks of lag
        assert travel <= allowed_m + 0.01, (travel, allowed_m)  # the plant lags the setpoint by ~1 cm
        assert travel > allowed_m - 0.05  # and it did drive on through the timeout
        assert loop.reference.timeouts == 1
    finally:
        r.close()


def test_commands_within_the_timeout_keep_it_driving_and_a_late_one_resumes(robot: Robot) -> None:
    loop = robot.loop
    robot.ticks(810, drive=(0.3, 0.0), every=90)  # every 0.45 s: inside the 0.5 s timeout
    assert loop.state == LoopState.DRIVING and loop.reference.timeouts == 0 and loop.reference.braking == ""
    robot.ticks(30)  # 0.6 s of silence since the last: braking (for 0.4 s from 0.3 m/s)
    assert loop.reference.braking == "timeout" and loop.state == LoopState.DRIVING
    loop.drive(0.3, 0.0)  # the joystick's next message: on again
    robot.ticks(200, drive=(0.3, 0.0))
    assert loop.reference.braking == "" and loop.setpoint.v_d == 0.3


def test_stop_during_drive_brakes_to_rest_then_the_motors_are_zero(robot: Robot) -> None:
    loop, cfg = robot.loop, robot.cfg
    robot.ticks(400, drive=(0.8, 1.0))
    loop.stop()
    assert loop.state == LoopState.DRIVING and loop.reference.braking == "stop"
    took = robot.until(lambda: loop.state == LoopState.STOPPED, 3.0)
    braking = 0.8 / cfg.limits.accel + cfg.limits.accel / cfg.drive.jerk_max
    assert braking - 2 * loop.period <= took <= braking + 0.3
    assert loop.duty_l == loop.duty_r == 0.0
    v, w = robot.true_v()
    assert abs(v) < 0.005 and abs(w) < 0.02


def test_estop_during_drive_zeroes_the_motors_at_once_and_drive_is_refused_until_reset(robot: Robot) -> None:
    loop = robot.loop
    robot.ticks(300, drive=(0.5, 0.0))
    loop.estop("test")
    assert loop.duty_l == loop.duty_r == 0.0 and loop.state == LoopState.ESTOP
    robot.hal.sleep_until(robot.hal.now() + 0.005)  # the command latency
    assert robot.plant.applied_duty == (0.0, 0.0)
    with pytest.raises(RuntimeError, match="reset first"):
        loop.drive(0.5, 0.0)
    robot.ticks(10)
    assert loop.state == LoopState.ESTOP and loop.duty_l == 0.0
    loop.reset()
    robot.until(lambda: abs(robot.true_v()[0]) < 0.002, 3.0)
    loop.drive(0.2, 0.0)
    assert loop.state == LoopState.DRIVING


def test_drive_while_faulted_is_refused_and_changes_nothing(robot: Robot) -> None:
    loop = robot.loop
    loop.enter_fault("test")
    with pytest.raises(RuntimeError, match="fault"):
        loop.drive(0.1, 0.0)
    assert loop.state == LoopState.FAULT and loop.reference is None


def test_drive_does_not_take_over_a_path_and_follow_does_not_take_over_a_drive(robot: Robot) -> None:
    loop = robot.loop
    path = load_path(LINE, speed_limits(robot.cfg))
    loop.follow(path)
    robot.ticks(50)
    ref = loop.reference
    for state in (LoopState.FOLLOWING, LoopState.STOPPING):
        with pytest.raises(ValueError, match="does not take over a path"):
            loop.drive(0.2, 0.0)
        assert loop.state == state and loop.reference is ref
        loop.stop()
    robot.until(lambda: loop.state == LoopState.STOPPED, 5.0)
    loop.drive(0.2, 0.0)  # once stopped
    assert loop.state == LoopState.DRIVING
    with pytest.raises(ValueError, match="driving: send stop first"):
        loop.follow(path)
    assert loop.state == LoopState.DRIVING


def test_a_sensor_gap_while_driving_holds_brakes_and_ends_stopped_refusing_drive_meanwhile(robot: Robot) -> None:
    loop, hal = robot.loop, robot.hal
    robot.ticks(300, drive=(0.5, 0.0))
    hal.freeze(hal.now() + 0.001, 0.06)
    robot.ticks(14)
    assert loop.state == LoopState.HOLDING
    with pytest.raises(ValueError, match="holding"):
        loop.drive(0.5, 0.0)
    robot.until(lambda: loop.state != LoopState.HOLDING, 3.0)
    assert loop.state == LoopState.STOPPED and loop.recovery.waits == 1  # a drive is not resumed
    assert abs(robot.true_v()[0]) < 0.005


def test_a_reload_of_the_jerk_limit_applies_to_the_drive_at_once(robot: Robot) -> None:
    loop = robot.loop
    robot.ticks(10, drive=(0.0, 0.0))
    loop.reconfigure(with_overrides(robot.cfg, {"drive": {"jerk_max": 1.0}}))
    loop.drive(1.0, 0.0)
    robot.ticks(20)
    assert loop.setpoint.a_d == pytest.approx(20 * loop.period * 1.0, rel=1e-6)  # 1 m/s^3 for 0.1 s


# ---------------------------------------------------------------- the daemon's entry, status and fuzz


@pytest.fixture()
def rig(tmp_path: Path) -> DaemonRig:
    r = DaemonRig(tmp_path)
    yield r
    r.d.hal.close()


def test_status_shows_the_mode_and_the_commanded_and_limited_velocities(rig: DaemonRig) -> None:
    d = rig.d
    assert d.status()["mode"] == "none" and d.status()["drive"] is None
    reply = d.handle({"cmd": "drive", "v": 2.0, "omega": -0.5, "id": 3})
    assert reply == {"ok": True, "state": "driving", "v": 1.0, "omega": -0.5, "timeout_s": 0.5, "clamped": ["v"]}
    rig.ticks(40)
    s = d.status()
    assert s["mode"] == "drive" and s["state"] == "driving" and s["progress"] is None
    drv = s["drive"]
    assert drv["commanded"] == {"v": 2.0, "omega": -0.5} and drv["limited"] == {"v": 1.0, "omega": -0.5}
    assert 0.0 < drv["setpoint"]["v"] < 1.0 and drv["phase"] == "driving"
    assert drv["since_command_s"] == pytest.approx(0.2) and drv["source"] == "control socket"
    assert d.handle({"cmd": "stop"})["state"] == "driving"
    assert d.status()["drive"]["phase"] == "braking"


@pytest.mark.parametrize(("req", "error"), [
    ({"cmd": "drive", "v": 0.1}, "drive: omega: missing (yaw rate, rad/s)"),
    ({"cmd": "drive", "omega": 0.1}, "drive: v: missing (forward speed, m/s)"),
    ({"cmd": "drive", "v": 0.1, "omega": 0, "speed": 1}, "drive: speed: unknown field (drive takes v, omega)"),
    ({"cmd": "drive", "v": "0.1", "omega": 0}, "drive: v: expected a number in m/s, got str"),
    ({"cmd": "drive", "v": 0.1, "omega": True}, "drive: omega: expected a number in rad/s, got bool"),
    ({"cmd": "drive", "v": 1e300, "omega": 0}, "drive: v: 1e+300 m/s is more than 10 x limits.v_max"),
])
def test_bad_requests_are_refused_with_the_field_and_change_nothing(rig: DaemonRig, req: dict, error: str) -> None:
    before = rig.snapshot()
    reply = rig.d.handle(req)
    assert reply["ok"] is False and reply["error"].startswith(error), reply
    assert rig.snapshot() == before


def test_drive_while_a_follow_is_prepared_is_refused(rig: DaemonRig) -> None:
    d = rig.d
    d.follows.hold(_PendingFollow(Build(BuildJob(LINE, speed_limits(d.cfg), d.cfg.paths)), None, None, "shape line", 0))
    reply = d.handle({"cmd": "drive", "v": 0.1, "omega": 0.0})
    assert reply["ok"] is False and "preparing shape line" in reply["error"] and d.loop.state == LoopState.IDLE


def test_follow_while_driving_is_refused_over_handle(rig: DaemonRig) -> None:
    d = rig.d
    assert d.handle({"cmd": "drive", "v": 0.1, "omega": 0.0})["ok"]
    reply = d.handle({"cmd": "follow", **LINE})
    assert reply == {"ok": False, "error": "follow refused in driving: send stop first, and follow once status says 'stopped'"}


_JUNK: list[Any] = [None, True, False, 0, -1, 1, 0.5, -0.5, 3, 1e300, -1e300, 10**30, 2**63, "1", "", "nan",
                    [], [0.1], {}, {"v": 1}, 9.99, 10.01, 30.0, -30.1, 1e-320, -0.0]


def test_a_few_thousand_random_requests_never_crash_the_loop_and_refusals_change_nothing(rig: DaemonRig) -> None:
    rng = random.Random(15)
    d = rig.d
    keys = ["v", "omega", "id", "speed", "V", "cmd2", ""]
    refused = accepted = 0
    for i in range(3000):
        def value() -> Any:
            return rng.choice(_JUNK) if rng.random() < 0.3 else rng.uniform(-12.0, 12.0)

        req: dict[str, Any] = {"cmd": "drive"}
        if rng.random() < 0.5:
            req.update(v=value(), omega=value())
        else:
            for key in rng.sample(keys, rng.randint(0, 4)):
                req[key] = value()
        if rng.random() < 0.03:
            req = {"cmd": rng.choice(["stop", "estop", "reset", "reset", "status"])}
        before = rig.snapshot()
        reply = d.handle(req)
        assert isinstance(reply, dict) and isinstance(reply.get("ok"), bool)
        if reply["ok"] is False:
            refused += 1
            assert reply["error"].startswith(("drive: ", "cannot")) or "reset first" in reply["error"], reply
            assert rig.snapshot() == before, req
        elif req["cmd"] == "drive":
            accepted += 1
            lim = d.cfg.limits
            assert abs(reply["v"]) <= lim.v_max and abs(reply["omega"]) <= lim.omega_max
        if i % 5 == 0:
            rig.ticks(1)
        assert d.loop.state != LoopState.FAULT, d.loop.fault
        assert all(math.isfinite(x) for x in (d.loop.duty_l, d.loop.duty_r, d.loop.setpoint.v_d))
    assert refused > 1000 and accepted > 50, (refused, accepted)


def test_ctl_drive_for_resends_at_10_hz_then_stops() -> None:
    sent: list[dict[str, Any]] = []
    now = [0.0]

    def send(payload: dict[str, Any]) -> dict[str, Any]:
        sent.append(payload)
        return {"ok": True, "state": "driving"}

    out = drive_for(send, 0.3, 0.1, 1.0, clock=lambda: now[0], sleep=lambda s: now.__setitem__(0, now[0] + s))
    drives = [p for p in sent if p["cmd"] == "drive"]
    assert len(drives) == 10 and sent[-1] == {"cmd": "stop"} and out["ok"] and out["seconds"] == pytest.approx(1.0)
    refused: list[dict[str, Any]] = []
    out = drive_for(lambda p: refused.append(p) or {"ok": False, "error": "x"}, 0.3, 0.0, 1.0,
                    clock=lambda: 0.0, sleep=lambda s: None)
    assert refused == [{"cmd": "drive", "v": 0.3, "omega": 0.0}] and out["ok"] is False  # no stop sent


def test_with_limits_left_to_the_motors_drive_keeps_to_what_they_give_with_headroom() -> None:
    """limits.v_max and accel null: the velocity mode takes the numbers from the motors (the
    profile's top speed, inside limits.feedback_headroom), clamps a faster command to it and
    the robot gets there unsaturated."""
    r = Robot(limits={"v_max": None, "accel": None, "torque_max_nm": None})
    try:
        loop = r.loop
        top = loop.limits.profile_v_max
        assert math.isfinite(top) and 0.3 < top < loop.limits.limits.v_max
        v, w, clamped = loop.drive(1.5 * top, 0.0)
        assert (v, clamped) == (top, ("v",))
        r.ticks(int(6.0 / loop.period), drive=(1.5 * top, 0.0))
        assert r.true_v()[0] == pytest.approx(top, rel=0.03)
        assert abs(loop.duty_l) < loop.cfg.limits.duty_max and abs(loop.duty_r) < loop.cfg.limits.duty_max
    finally:
        r.close()
