"""The measured supply voltage and the hardware estop in the loop (ddrt/loop/power.py): the
filter, the motor model, the limits and the profile that follow it, the low-battery stop, the
estop input; checked on the simulated robot, whose supply the test sets or scripts."""

from __future__ import annotations

import logging
import math
from dataclasses import replace
from typing import Any, Callable

import pytest

from ddrt.config import ConfigError, load_config
from ddrt.config.policy import plan_reload
from ddrt.core.envelope import resolve_limits
from ddrt.core.motor import Motor
from ddrt.loop import COLUMNS, ControlLoop, LoopState
from ddrt.loop.power import HW_ESTOP_REASON, HYSTERESIS, TAU_MODEL_S, TAU_SLOW_S
from ddrt.path.spec import load_path, speed_limits
from ddrt.simrun.runner import run_sim
from hal.registry import open_hal
from tests.support.repo import SIM_YAML

BATTERY_V, HW_ESTOP = COLUMNS.index("battery_v"), COLUMNS.index("hw_estop")  # telemetry row indices

FROM_MOTORS = {"v_max": None, "accel": None, "torque_max_nm": None}
S_CURVE = {"shape": "s_curve", "length": 5.0, "offset": 0.8, "speed": 0.9}
CIRCLE = {"shape": "circle", "radius": 0.5, "speed": 0.3}


def _config(plant_v: float = 12.0, measured: bool = True, **sections: Any):
    over: dict[str, Any] = {"estimator": {"calibration_s": 0.2}, "plant": {"motor": {"supply_v": plant_v}},
                            "sim": {"battery_measured": measured}}
    for key, value in sections.items():
        over[key] = {**over.get(key, {}), **value}
    return load_config(SIM_YAML, over)


class Rig:
    """A loop on the simulated robot; `volts(t)`, when given, replaces the measured supply."""

    def __init__(self, cfg, spec: dict | None = CIRCLE, volts: Callable[[float], float] | None = None) -> None:
        self.cfg = cfg
        self.path = load_path(spec, speed_limits(cfg), paths=cfg.paths) if spec is not None else None
        self.hal = open_hal(cfg, start=self.path.start_pose if self.path else (0.0, 0.0, 0.0), seed=1)
        if volts is not None:
            read = self.hal.read

            def scripted():
                s = read()
                s.battery_v = volts(s.t)
                return s

            self.hal.read = scripted  # type: ignore[method-assign]
        self.loop = ControlLoop(cfg, self.hal)
        self.loop.calibrate(self.hal.sleep_until, self.hal.now)  # type: ignore[attr-defined]
        self.t = self.hal.now()  # type: ignore[attr-defined]

    def run(self, seconds: float, until: Callable[[ControlLoop], bool] | None = None) -> None:
        for _ in range(int(round(seconds / self.loop.period))):
            self.t += self.loop.period
            self.hal.sleep_until(self.t)  # type: ignore[attr-defined]
            self.loop.tick()
            if until is not None and until(self.loop):
                return

    def follow(self) -> None:
        assert self.path is not None
        self.loop.follow(self.path, self.path.start_pose)


@pytest.fixture
def rigs() -> list[Rig]:
    made: list[Rig] = []
    yield made
    for rig in made:
        rig.hal.close()


def test_the_duty_for_a_torque_scales_with_the_measured_supply(rigs: list[Rig]) -> None:
    rig = Rig(_config(plant_v=9.3), spec=None)
    rigs.append(rig)
    rig.run(0.1)
    loop = rig.loop
    # One motor model, shared: the controller's inverse, the estimator's prediction.
    assert loop.controller.motor is loop.motor and loop.estimator.motor is loop.motor
    assert loop.motor.supply_v == 9.3 == loop.power.v
    believed = Motor(rig.cfg.robot_motor)  # what the loop used before: the config's 12 V
    for tau, w in ((0.3, 0.0), (-0.2, 8.0), (0.5, -12.0)):
        d12, _ = believed.duty_for_torque(tau, w)
        d93, _ = loop.motor.duty_for_torque(tau, w)
        assert d93 / d12 == pytest.approx(12.0 / 9.3, rel=1e-12)
        # ... and at that duty a 9.3 V motor gives the torque asked (the forward model, anew).
        m = rig.cfg.robot_motor
        wheel = m.k_nm_per_a * (d93 * 9.3 - m.k_nm_per_a * w) / m.resistance_ohm
        wheel -= m.viscous_nms * w + m.coulomb_nm * math.tanh(w / m.coulomb_smoothing_rad_s)
        assert wheel == pytest.approx(tau, abs=1e-12)


def test_without_a_measurement_the_config_supply_is_used(rigs: list[Rig]) -> None:
    rig = Rig(_config(plant_v=9.3, measured=False, limits={"battery_min_v": 11.0}), spec=None)
    rigs.append(rig)
    assert not rig.hal.info.battery_measured
    rig.run(0.1)
    assert rig.loop.sample is not None and math.isnan(rig.loop.sample.battery_v)
    assert rig.loop.motor.supply_v == 12.0 and rig.loop.row[BATTERY_V] == 12.0
    st = rig.loop.power.status()
    assert st["measured"] is False and st["min_v"] is None and not st["low"]  # nothing to compare with


def test_the_filter_its_time_constant_gaps_and_implausible_readings(rigs: list[Rig]) -> None:
    step_at = [math.inf]
    bad: dict[float, float] = {}

    def volts(t: float) -> float:
        return bad.get(round(t, 6), 12.0 if t < step_at[0] else 9.0)

    rig = Rig(_config(), spec=None, volts=volts)
    rigs.append(rig)
    loop, p = rig.loop, rig.loop.power
    rig.run(0.05)
    assert p.v == p.v_slow == 12.0
    step_at[0] = rig.t + 0.5 * loop.period  # the next sample reads 9 V
    n = 12
    rig.run(n * loop.period)
    # A first-order low-pass sampled every period: 9 + 3 exp(-n T / tau), at both time constants.
    assert p.v - 9.0 == pytest.approx(3.0 * math.exp(-n * loop.period / TAU_MODEL_S), rel=1e-9)
    assert p.v_slow - 9.0 == pytest.approx(3.0 * math.exp(-n * loop.period / TAU_SLOW_S), rel=1e-9)
    assert loop.motor.supply_v == p.v
    v, slow = p.v, p.v_slow
    for k, reading in enumerate((math.nan, 0.5, 100.0, -9.0)):  # none, then three implausible
        bad[round(rig.t + (k + 1) * loop.period, 6)] = reading
    rig.run(4 * loop.period)
    assert (p.v, p.v_slow) == (v, slow)  # the last good value kept
    assert p.rejected == 3 and p.last_rejected == -9.0
    rig.run(loop.period)
    assert p.v < v  # and followed again


def test_the_limits_and_a_starting_path_follow_the_measured_supply(rigs: list[Rig]) -> None:
    cfg = _config(plant_v=9.3, limits=FROM_MOTORS)
    rig = Rig(cfg, spec=S_CURVE)
    rigs.append(rig)
    loop = rig.loop
    at = {v: resolve_limits(cfg.limits, cfg.robot, replace(cfg.robot_motor, supply_v=v)) for v in (9.3, 12.0)}
    assert loop.limits.limits == at[9.3].limits and loop.controller.limits == at[9.3].limits
    assert at[9.3].limits.v_max < at[12.0].limits.v_max and at[9.3].limits.torque_max_nm < at[12.0].limits.torque_max_nm
    assert loop.drive_limits().v_max == at[9.3].profile_v_max
    # The path was profiled for the config's 12 V; it asks more than the motors give at 9.3 V.
    path = rig.path
    assert path is not None
    env93 = replace(path.limits.envelope, motor=replace(path.limits.envelope.motor, supply_v=9.3))
    assert path.envelope_excess(env93) > 0.01
    rig.follow()
    assert loop.path is not path and loop.path.duration > path.duration * 1.02
    assert loop.path.envelope_excess(env93) <= 1e-6
    assert "9.30 V" in loop.reprofiled
    rig.run(30.0, until=lambda lp: lp.state == LoopState.STOPPED)
    assert loop.path_completed


def test_a_path_the_measured_supply_can_drive_is_left_as_it_is(rigs: list[Rig]) -> None:
    rig = Rig(_config(plant_v=12.0, limits=FROM_MOTORS), spec=S_CURVE)
    rigs.append(rig)
    rig.follow()
    assert rig.loop.path is rig.path and rig.loop.reprofiled == ""


def test_a_reload_keeps_the_measured_supply_in_the_new_motor_model(rigs: list[Rig]) -> None:
    cfg = _config(plant_v=9.3, limits=FROM_MOTORS)
    rig = Rig(cfg, spec=None)
    rigs.append(rig)
    rig.run(0.1)
    new = load_config(SIM_YAML, {"estimator": {"calibration_s": 0.2}, "plant": {"motor": {"supply_v": 9.3}},
                                 "limits": FROM_MOTORS, "robot": {"motor": {"resistance_ohm": 4.0}}})
    old_motor = rig.loop.motor
    rig.loop.reconfigure(plan_reload(rig.loop.cfg, new).in_force)
    loop = rig.loop
    assert loop.motor is not old_motor and loop.motor.supply_v == 9.3
    assert loop.estimator.motor is loop.motor and loop.controller.motor is loop.motor
    assert loop.limits.limits == resolve_limits(new.limits, new.robot, replace(new.robot_motor, supply_v=9.3)).limits


def test_a_low_battery_stops_along_the_path_and_waits_for_the_voltage_and_a_resume(
        rigs: list[Rig], caplog: pytest.LogCaptureFixture) -> None:
    level = [12.0]
    rig = Rig(_config(limits={"battery_min_v": 10.0}), volts=lambda t: level[0])
    rigs.append(rig)
    loop, p = rig.loop, rig.loop.power
    rig.follow()
    rig.run(1.0)
    assert loop.state == LoopState.FOLLOWING
    caplog.set_level(logging.WARNING, logger="ddrt.loop")
    level[0] = 10.3  # within 5 % above the minimum: a warning, once, and on it goes
    rig.run(3.0)
    assert loop.state == LoopState.FOLLOWING
    assert sum("within 5 % of limits.battery_min_v" in r.getMessage() for r in caplog.records) == 1
    level[0] = 9.6
    rig.run(5.0, until=lambda lp: lp.state != LoopState.FOLLOWING)
    assert loop.state == LoopState.STOPPING  # the path's controlled stop, not estop
    assert p.v_slow < 10.0 and "battery low" in p.reason and "limits.battery_min_v = 10 V" in p.reason
    sigma = loop.reference.sigma
    rig.run(5.0, until=lambda lp: lp.state == LoopState.STOPPED)
    assert loop.state == LoopState.STOPPED and loop.at_rest and not loop.path_completed
    assert loop.reference.sigma > sigma  # it braked along the path
    assert p.status()["low"] and p.status()["low_stops"] == 1
    for start in (loop.resume, lambda: loop.follow(rig.path), lambda: loop.drive(0.1, 0.0)):
        with pytest.raises(ValueError, match="battery low"):
            start()
    level[0] = 10.0 * (1.0 + 0.5 * HYSTERESIS)  # above the minimum, within the hysteresis
    rig.run(6.0)
    with pytest.raises(ValueError, match="battery low"):
        loop.resume()
    level[0] = 10.5
    rig.run(4.0)
    assert loop.state == LoopState.STOPPED and not p.low  # recovered, and still where it stopped
    loop.resume()
    assert loop.state == LoopState.FOLLOWING
    rig.run(30.0, until=lambda lp: lp.state == LoopState.STOPPED)
    assert loop.path_completed


def test_the_hardware_estop_input_latches_estop_until_closed_and_reset(rigs: list[Rig]) -> None:
    rig = Rig(_config())
    rigs.append(rig)
    loop, hal = rig.loop, rig.hal
    assert hal.info.hw_estop_wired
    rig.follow()
    rig.run(1.0)
    assert loop.state == LoopState.FOLLOWING and hal.robot.applied_duty != (0.0, 0.0)
    hal.estop_input_open = True  # type: ignore[attr-defined]
    rig.run(loop.period)
    assert loop.state == LoopState.ESTOP and loop.fault == HW_ESTOP_REASON
    assert (loop.duty_l, loop.duty_r) == (0.0, 0.0) and loop.row[HW_ESTOP] == 1.0
    with pytest.raises(ValueError, match="hardware emergency-stop input open"):
        loop.reset()
    hal.estop_input_open = False  # type: ignore[attr-defined]
    rig.run(0.5)
    assert loop.state == LoopState.ESTOP and loop.row[HW_ESTOP] == 0.0  # latched: closing it is not a reset
    assert hal.robot.applied_duty == (0.0, 0.0)
    loop.reset()
    assert loop.state == LoopState.IDLE


def test_battery_min_v_is_validated_and_reloads_live() -> None:
    with pytest.raises(ConfigError, match="limits.battery_min_v"):
        load_config(SIM_YAML, {"limits": {"battery_min_v": -1.0}})
    with pytest.raises(ConfigError, match="sim.battery_measured"):
        load_config(SIM_YAML, {"sim": {"battery_measured": 1}})
    cfg = load_config(SIM_YAML)
    assert cfg.limits.battery_min_v is None and cfg.sim.battery_measured
    plan = plan_reload(cfg, load_config(SIM_YAML, {"limits": {"battery_min_v": 10.5}}))
    assert plan.in_force.limits.battery_min_v == 10.5 and "limits.battery_min_v" in plan.live


def test_telemetry_and_foxglove_carry_the_voltage() -> None:
    from ddrt.loop import COLUMNS
    from ddrt.viz.channels import STATE_FIELDS

    at = COLUMNS.index("battery_v")
    assert COLUMNS[at:at + 2] == ("battery_v", "hw_estop") and {"battery_v", "hw_estop"} <= set(STATE_FIELDS)


def _end_error_mm(result) -> float:
    a, c = result.rows_array(), result.columns
    last = a[-1]
    return 1e3 * math.hypot(last[c.index("x_est")] - last[c.index("x")], last[c.index("y_est")] - last[c.index("y")])


def test_the_measured_supply_makes_estimate_and_tracking_truer_on_a_low_battery() -> None:
    """The plant's supply at 9.3 V, the config's 12 V: the same run without and with the
    measurement. Without it, the model overestimates every torque by 12/9.3, which the
    estimator's speed prediction and the controller's feed-forward both carry."""
    runs = {}
    for measured in (False, True):
        cfg = _config(plant_v=9.3, measured=measured, limits=FROM_MOTORS)
        runs[measured] = run_sim(cfg, load_path(S_CURVE, speed_limits(cfg), paths=cfg.paths), keep_rows=True)
    off, on = runs[False], runs[True]
    assert off.metrics["completed"] and on.metrics["completed"]
    assert on.metrics["rms_cross_track_m"] < 0.85 * off.metrics["rms_cross_track_m"]
    assert _end_error_mm(on) < 0.5 * _end_error_mm(off)
    assert on.metrics["rms_tracking_m"] < 0.5 * off.metrics["rms_tracking_m"]
    assert on.column("battery_v")[-1] == 9.3 and off.column("battery_v")[-1] == 12.0
