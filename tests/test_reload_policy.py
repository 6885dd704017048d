"""The reload policy is derived from the fields' declarations: what it reports as applied is in
the config it puts in force, what it reports as waiting for a restart is not."""

from __future__ import annotations

import copy
from typing import Any

import pytest
import yaml

from ddrt.config import ConfigError, config_from_mapping, load_config, with_overrides
from ddrt.config.policy import leaf_modes, value_at, plan_reload
from ddrt.config.schema import APPLY_MODES, LIVE, NEXT_PATH, RESTART
from tests.support.repo import REPO, SIM_YAML


def test_gain_change_is_live() -> None:
    old = load_config(SIM_YAML)
    new = with_overrides(old, {"controller": {"inner": {"kp": 33.0}}})
    plan = plan_reload(old, new)
    assert plan.live == ("controller.inner.kp",)
    assert plan.restart == () and plan.next_path == ()
    assert plan.in_force.controller.inner.kp == 33.0


def test_rate_change_waits_for_a_restart_and_the_rest_applies() -> None:
    old = load_config(SIM_YAML)
    new = with_overrides(old, {"controller": {"rate_hz": 100.0, "heading_gain": 4.0}})
    plan = plan_reload(old, new)
    assert plan.restart == ("controller.rate_hz",)
    assert plan.live == ("controller.heading_gain",)
    assert plan.in_force.controller.rate_hz == old.controller.rate_hz
    assert plan.in_force.controller.heading_gain == 4.0


def test_values_equal_to_the_running_ones_are_no_change() -> None:
    old = load_config(SIM_YAML)
    same = with_overrides(old, {"controller": {"rate_hz": old.controller.rate_hz,
                                               "inner": {"kp": old.controller.inner.kp}}})
    assert plan_reload(old, same).report() == {"applied": [], "next_path": [], "restart": []}
    assert plan_reload(old, old).summary() == "applied: nothing changed"


@pytest.mark.parametrize(("key", "mode"), [
    ("controller.rate_hz", RESTART), ("controller.mode", RESTART), ("controller.inner.kp", LIVE),
    ("controller.outer.k_y", LIVE), ("controller.adaptation.enabled", RESTART),
    ("controller.adaptation.forgetting", RESTART), ("hal.backend", RESTART),
    ("sensors.gyro_range_dps", RESTART), ("sim.seed", RESTART), ("sim.slip.probability", RESTART),
    ("plant.m_p", RESTART), ("plant.motor_l.resistance_ohm", RESTART), ("robot.m_p", LIVE),
    ("robot.r_3", LIVE), ("robot.motor.k_nm_per_a", LIVE), ("estimator.gyro_scale", LIVE),
    ("estimator.accel_noise", LIVE), ("estimator.calibration_s", RESTART), ("daemon.socket", RESTART),
    ("daemon.cpus", RESTART), ("daemon.spin_us", LIVE), ("daemon.telemetry_max_files", LIVE),
    ("daemon.telemetry_dir", RESTART), ("daemon.stop_decel", LIVE), ("daemon.watch_config", LIVE),
    ("daemon.command_timeout_s", LIVE), ("drive.jerk_max", LIVE), ("drive.angular_jerk_max", LIVE),
    ("limits.v_max", NEXT_PATH), ("limits.duty_max", LIVE), ("limits.max_path_error_m", LIVE),
    ("pursuit.lookahead_m", NEXT_PATH), ("path", RESTART), ("start", RESTART),
])
def test_declared_mode(key: str, mode: str) -> None:
    modes = dict(leaf_modes(load_config(SIM_YAML)))
    assert modes[key] == mode


def test_every_leaf_has_one_known_mode_and_a_key_that_reads_back() -> None:
    cfg = load_config(SIM_YAML)
    leaves = list(leaf_modes(cfg))
    keys = [k for k, _ in leaves]
    assert len(keys) == len(set(keys)) > 100
    for key, mode in leaves:
        assert mode in APPLY_MODES, key
        value_at(cfg, key)  # every reported key names a real field
    assert not any(k.startswith(("source", "base_dir", "raw")) for k in keys)


@pytest.mark.parametrize("direction", ["added", "removed"])
def test_rate_change_in_an_added_or_removed_section_waits_for_a_restart(direction: str) -> None:
    base = {"robot": copy.deepcopy(yaml.safe_load(SIM_YAML.read_text())["robot"])}
    with_rate = copy.deepcopy(base)
    with_rate["controller"] = {"rate_hz": 100.0}
    a, b = config_from_mapping(base), config_from_mapping(with_rate)
    old, new = (a, b) if direction == "added" else (b, a)
    plan = plan_reload(old, new)
    assert plan.restart == ("controller.rate_hz",)
    assert plan.in_force.controller.rate_hz == old.controller.rate_hz


def test_a_mix_of_running_and_new_values_is_validated_whole() -> None:
    """Raising the gyro range (restart) and omega_max (next path) in one reload must not put
    the new omega_max in force against the old range."""
    old = load_config(SIM_YAML)
    new = with_overrides(old, {"sensors": {"gyro_range_dps": 500}, "limits": {"omega_max": 6.0}})
    with pytest.raises(ConfigError, match="limits.omega_max.*restart"):
        plan_reload(old, new)


def test_every_changed_leaf_is_reported_once_and_put_in_force_by_its_mode() -> None:
    """Change every numeric leaf at once; each key appears in exactly the list of its mode,
    and the config in force shows the new value exactly for the applied ones."""
    old = load_config(SIM_YAML)
    raw = yaml.safe_load(SIM_YAML.read_text())
    overrides: dict[str, Any] = {}
    changed: list[str] = []
    for key, _mode in leaf_modes(old):
        value = value_at(old, key)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            continue
        if key in ("limits.omega_max", "controller.rate_hz", "sim.step_hz"):
            new_value = value * 0.5 if isinstance(value, float) else value  # keep cross-rules valid
        elif key.endswith(("forgetting",)):
            new_value = 0.95
        elif key.endswith(("probability", "scale_error", "duty_max")):
            new_value = value * 0.5 if value else 0.1
        elif key == "sensors.gyro_range_dps":
            new_value = 500
        elif key.endswith("_sign"):
            new_value = -value
        elif key == "estimator.gyro_delay_s":
            new_value = 0.001
        elif key in ("daemon.rt_priority", "daemon.spin_us"):
            new_value = 5
        elif isinstance(value, int):
            new_value = value + 1
        else:
            new_value = value * 1.01 + 1e-6
        if new_value == value:
            continue
        node = overrides
        parts = key.split(".")
        if parts[0] == "plant" and len(parts) == 2 and parts[1].startswith("motor"):
            continue
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = new_value
        changed.append(key)
    assert len(changed) > 60
    new = config_from_mapping(_deep_merge(raw, overrides), source="new.yaml")
    plan = plan_reload(old, new)
    reported = plan.live + plan.next_path + plan.restart
    assert sorted(reported) == sorted(set(reported))
    modes = dict(leaf_modes(old))
    for key in changed:
        assert key in reported, key
        lists = {LIVE: plan.live, NEXT_PATH: plan.next_path, RESTART: plan.restart}
        assert key in lists[modes[key]], key
        shown = value_at(plan.in_force, key)
        if modes[key] == RESTART:
            assert shown == value_at(old, key), key
        else:
            assert shown == value_at(new, key), key


def _deep_merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = copy.deepcopy(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _deep_merge(out[k], v)
        else:
            out[k] = v
    return out


def _documented_modes() -> dict[str, str]:
    """The reload column of docs/reference/config.md, by key."""
    text = (REPO / "docs" / "reference" / "config.md").read_text(encoding="utf-8")
    rows: dict[str, str] = {}
    for line in text.splitlines():
        parts = [p.strip() for p in line.strip().strip("|").split("|")]
        if len(parts) >= 7 and parts[0].startswith("`") and parts[5] != "-":
            rows[parts[0].strip("`")] = parts[5].replace(" ", "_")
    return rows


def test_the_reference_states_the_declared_mode_of_every_setting() -> None:
    """Every leaf's mode is its own row's, or, under a section that takes another's keys
    (plant: takes robot:'s), that section's row's."""
    rows = _documented_modes()
    assert set(rows.values()) == set(APPLY_MODES)
    for key, mode in leaf_modes(load_config(SIM_YAML)):
        candidates = [k for k in rows if k == key or key.startswith(k + ".")]
        assert candidates, f"docs/reference/config.md does not say how {key} applies"
        best = max(candidates, key=len)
        assert rows[best] == mode, f"docs/reference/config.md says {best}: {rows[best]}, {key} is declared {mode}"


def test_backend_change_waits_for_a_restart() -> None:
    old = load_config(SIM_YAML)
    # The real backend needs its devices named (hal.imu.bus, hal.bridge.url) to validate.
    new = with_overrides(old, {"hal": {"backend": "real", "imu": {"bus": 1}, "bridge": {"url": "/dev/ttyACM0"}}})
    plan = plan_reload(old, new)
    # A real MPU's defaults (TEMP_OUT read, the FIFO on) come with the backend, at the restart too.
    assert sorted(plan.restart) == sorted(("hal.backend", "hal.imu.bus", "hal.bridge.url",
                                           "sensors.gyro_temp_hz", "sensors.gyro_fifo"))
    assert new.sensors.gyro_temp_hz > 0 and new.sensors.gyro_fifo
    assert plan.in_force.hal == old.hal and plan.in_force.sensors == old.sensors
