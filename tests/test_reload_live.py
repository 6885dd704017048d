"""A reload over every key, in process: the reply's lists match what the running objects show.

The daemon is built as `ddrt run` builds it (its own HAL, loop and telemetry), follows a path
on the simulated robot, and is reloaded once per setting with a file that changes only that
setting. For a live key the part that uses it must show the new value; for a next-path key
the path being followed keeps its profile and the next one gets the value; for a restart key
nothing running changes. After every reload the robot is still following.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import pytest

from ddrt.config.policy import leaf_modes, value_at
from ddrt.config.schema import LIVE, NEXT_PATH, RESTART
from ddrt.core.model import Dynamics
from ddrt.loop import ControlLoop, LoopState
from ddrt.path import load_path
from ddrt.path.spec import speed_limits
from ddrt.runtime.clock import MonotonicClock
from ddrt.service.daemon import Daemon
from hal.registry import open_hal
from tests.support.reload_rig import Rig, write_config
from tests.support.repo import SIM_YAML


def _nested(key: str, value: Any) -> dict[str, Any]:
    out: Any = value
    for part in reversed(key.split(".")):
        out = {part: out}
    return out


def _changed(key: str, value: Any) -> Any:
    """A valid value different from `value` for the setting `key`."""
    if isinstance(value, bool):
        return not value
    if key == "sensors.gyro_range_dps":
        return 500
    if key.endswith("_sign"):
        return -value
    if key == "estimator.gyro_delay_s":
        return 0.002
    if key.endswith(("forgetting",)):
        return 0.99
    if key.endswith(("probability", "scale_error", "duty_max")):
        return 0.5 * value if value else 0.1
    if key in ("daemon.rt_priority", "daemon.spin_us"):
        return 7
    if key == "controller.rate_hz":
        return 100.0
    if isinstance(value, int):
        return value + 1
    if isinstance(value, float):
        return value * 1.02 + 1e-6
    return None


# What the running objects use, read from the objects themselves (not from the config).
def _probe(rig: Rig, key: str) -> Any:
    d, loop = rig.d, rig.d.loop
    section, _, name = key.partition(".")
    if key.startswith("controller.inner."):
        pid = loop.controller.pid_v
        return {"kp": pid.kp, "ki": pid.ki, "kd": pid.kd, "integrator_limit": pid.limit}[name.split(".")[1]]
    if key.startswith("controller.outer."):
        return getattr(loop.controller.outer, key.rsplit(".", 1)[1])
    if key == "controller.heading_gain":
        return loop.controller.heading_gain
    if key == "controller.rate_hz":
        return 1.0 / loop.period
    if key.startswith("robot.motor."):
        assert loop.estimator.motor is loop.controller.motor
        return getattr(loop.controller.motor.params, key.rsplit(".", 1)[1])
    if section == "robot":
        return loop.controller.dyn, loop.estimator.dyn, loop.estimator.metres_per_count
    if section == "estimator":
        return getattr(loop.estimator.cfg, name)
    if section == "limits" and name in ("duty_max", "torque_max_nm", "max_path_error_m", "v_max", "omega_max"):
        return getattr(loop.controller.limits, name) if name != "max_path_error_m" else loop.cfg.limits.max_path_error_m
    if key == "daemon.spin_us":
        return round(d.clock.spin_s * 1e6)
    if key in ("daemon.telemetry_max_files", "daemon.telemetry_max_bytes"):
        w = d.telemetry.writer
        w.write_rows([])  # the writing thread takes new bounds before its next rows
        return w.max_files if key.endswith("files") else w.max_bytes
    if key == "daemon.socket":
        return d.socket_path
    return None


def _expected_probe(rig: Rig, key: str, cfg: Any) -> Any:
    """What _probe must show when `cfg` is in force."""
    section, _, name = key.partition(".")
    if section == "robot" and not key.startswith("robot.motor."):
        dyn = Dynamics.from_params(cfg.robot)
        info = rig.d.hal.info
        return dyn, dyn, 2.0 * math.pi * cfg.robot.r_3 / info.encoder_counts_per_rev
    if key == "controller.rate_hz":
        return cfg.controller.rate_hz
    if key == "daemon.socket":
        return cfg.daemon.socket or None
    return value_at(cfg, key)


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> Rig:
    r = Rig(tmp_path_factory.mktemp("reload"))
    yield r
    r.close()


def _cases() -> list[tuple[str, str]]:
    from ddrt.config import load_config

    cfg = load_config(SIM_YAML)
    return [(k, m) for k, m in leaf_modes(cfg) if _changed(k, value_at(cfg, k)) is not None
            and not k.startswith(("plant.motor_l", "plant.motor_r"))]


CASES = _cases()


def test_the_cases_cover_every_kind_and_most_keys() -> None:
    modes = {m for _, m in CASES}
    assert modes == {LIVE, NEXT_PATH, RESTART}
    assert len(CASES) > 90


@pytest.mark.parametrize(("key", "mode"), CASES, ids=[k for k, _ in CASES])
def test_reload_one_key(rig: Rig, key: str, mode: str) -> None:
    d = rig.d
    before_cfg = d.cfg
    old = value_at(before_cfg, key)
    new = _changed(key, old)
    probe_before = _probe(rig, key)
    reference_before = d.loop.reference
    profile_before = d.loop.path.limits if d.loop.path is not None else None
    assert d.loop.state == LoopState.FOLLOWING
    reply = rig.reload(_nested(key, new))
    try:
        assert reply["ok"], reply
        lists = {LIVE: reply["applied"], NEXT_PATH: reply["next_path"], RESTART: reply["restart"]}
        # The simulated robot (plant:) defaults to robot: key by key, so a robot key the plant
        # does not set changes the plant's too: that part waits for a restart.
        inherited = _inherited_by_plant(key)
        assert [k for k in lists[mode] if k not in inherited] == [key], reply
        others = [k for m, keys in lists.items() for k in keys if k != key]
        assert all(k in inherited for k in others), reply
        in_force = value_at(d.cfg, key)
        assert in_force == (old if mode == RESTART else new)
        assert value_at(d.loop.cfg, key) == in_force
        probe = _probe(rig, key)
        if probe is not None:
            assert probe == _expected_probe(rig, key, d.cfg), f"{key}: the running part does not show it"
            if mode == RESTART:
                assert probe == probe_before
        if mode == NEXT_PATH:
            # The path being followed keeps its profile and its reference stage ...
            assert d.loop.reference is reference_before
            assert d.loop.path.limits == profile_before
            # ... and the next one is built with the new value.
            if section_of(key) == "limits" and key.rsplit(".", 1)[1] in dataclasses.asdict(profile_before):
                assert getattr(speed_limits(d.cfg), key.rsplit(".", 1)[1]) == new
        rig.ticks(5)
        assert d.loop.state == LoopState.FOLLOWING, d.loop.fault
    finally:
        back = rig.reload({})
        assert back["ok"], back
        rig.ticks(2)
    assert value_at(d.cfg, key) == old


def _inherited_by_plant(key: str) -> set[str]:
    if key.startswith("robot.motor."):
        name = key.rsplit(".", 1)[1]
        return {f"plant.motor_l.{name}", f"plant.motor_r.{name}"}
    if key.startswith("robot."):
        return {"plant." + key.partition(".")[2]}
    return set()


def section_of(key: str) -> str:
    return key.partition(".")[0]


def test_calibrated_encoder_radius_takes_effect_on_reload(tmp_path: Path) -> None:
    """An uncalibrated r_3 (4% small) under-reads the distance; reloading the calibrated one
    changes the metres per count at once without a jump in the estimated position, and the
    estimate then follows the true travel."""
    file = tmp_path / "ddrt.yaml"
    write_config(file, tmp_path, {"robot": {"r_3": 0.050}})
    d = Daemon(str(file))
    d.hal = open_hal(d.cfg, start=(0.0, 0.0, 0.0))
    d.clock = MonotonicClock()
    d.loop = loop = ControlLoop(d.cfg, d.hal)
    loop.calibrate(d.hal.sleep_until, d.hal.now)
    path = load_path({"shape": "line", "length": 2.0, "speed": 0.3}, speed_limits(d.cfg))
    loop.follow(path)
    robot = d.hal.robot

    def run(n: int) -> None:
        for _ in range(n):
            d.hal.sleep_until(d.hal.now() + loop.period)
            loop.tick()

    run(400)  # 2 s
    x_true0 = robot.pose[0]
    x_est0 = loop.estimator.x
    assert x_est0 < 0.97 * x_true0  # the small radius under-reads by 4%
    write_config(file, tmp_path, {"robot": {"r_3": 0.052}})
    reply = d.reload()
    assert reply["ok"] and reply["applied"] == ["robot.r_3"], reply
    assert loop.estimator.metres_per_count == pytest.approx(2 * math.pi * 0.052 / 8192)
    run(1)
    assert abs(loop.estimator.x - x_est0) < 0.005  # no jump
    run(400)
    travelled_true = robot.pose[0] - x_true0
    travelled_est = loop.estimator.x - x_est0
    assert travelled_est == pytest.approx(travelled_true, rel=0.01)
    assert loop.state in (LoopState.FOLLOWING, LoopState.STOPPED)
    d.hal.close()
