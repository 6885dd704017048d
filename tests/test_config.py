"""ddrt.config: the seed configs, plant defaults, error messages, the generated reference's coverage,
and which changes need a restart."""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import re
import types
import typing
from pathlib import Path
from typing import Any, Callable

import pytest
import yaml

from ddrt.config import load as config_mod
from ddrt.config import (
    AdaptationConfig, BridgeConfig, Config, ControllerConfig, DaemonConfig, EstimatorConfig, GyroTruth,
    HalConfig, ImuConfig, LimitsConfig, OuterGains, PathsConfig, PursuitConfig, PwmSysfsConfig,
    SensorsConfig, SimConfig, SlipConfig, config_from_mapping, load_config,
    with_overrides,
)
from ddrt.config.sections import INNER_PID, WHEEL_PID, InnerPid, WheelPid
from ddrt.config.sim_truth import FloorPatch, PayloadEvent
from ddrt.params.decl import decl_of
from ddrt.params.robot import RobotParams
from ddrt.params.motor import MotorParams
from ddrt.config.schema import ConfigError
from tests.support.repo import REPO, SIM_YAML

OFFSET = REPO / "configs" / "sim-offset-mass.yaml"
DOC = REPO / "docs" / "config.md"
REFERENCE = REPO / "docs" / "reference" / "config.md"
REAL_HAL = REPO / "hal" / "real.py"

# The seed's Table 5.1 "estimate" column in SI (mm -> m, kg mm^2 -> 1e-6 kg m^2). r_3 is left
# out: configs/sim.yaml holds a calibrated encoder-wheel radius instead of the seed's.
TABLE_5_1 = {
    "H": 0.115, "L": 0.1078, "R": 0.1078, "r_L": 0.050, "r_R": 0.050,
    "d_xc": 0.02579, "d_yc": 0.0, "m_p": 0.75, "m_L": 1.15, "m_R": 1.15, "m_3": 0.55,
    "I_p": 6.42868e-3, "I_L": 3.51882e-4, "I_R": 3.51882e-4, "I_3": 6.53657e-4,
    "I_wL": 6.28378e-4, "I_wR": 6.28378e-4, "I_w3": 6.28378e-4,
}


def _sim_mapping() -> dict[str, Any]:
    """configs/sim.yaml as a plain mapping, without its path (tests need no path file)."""
    data = yaml.safe_load(SIM_YAML.read_text(encoding="utf-8"))
    data.pop("path", None)
    return data


def _minimal() -> dict[str, Any]:
    """The smallest valid config: the seed robot and nothing else."""
    return {"robot": copy.deepcopy(_sim_mapping()["robot"])}


def _write(tmp_path: Path, name: str, data: Any) -> Path:
    p = tmp_path / name
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(data if isinstance(data, str) else yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return p


# --------------------------------------------------------------------------- seed configs


def test_sim_config_holds_table_5_1_in_si() -> None:
    cfg = load_config(SIM_YAML)
    for name, value in TABLE_5_1.items():
        assert getattr(cfg.robot, name) == pytest.approx(value, rel=1e-12, abs=1e-15), name
    assert cfg.robot.r_3 == pytest.approx(0.052)
    # the plant is the "actual" column: close to the belief, but not equal
    assert cfg.plant.m_p == pytest.approx(0.8)
    assert cfg.plant.r_L == pytest.approx(0.049) and cfg.plant.r_R == pytest.approx(0.051)
    assert cfg.plant != cfg.robot
    # per-wheel motors merge over robot.motor: supply_v is inherited, the rest overridden
    assert cfg.plant_motor_l.resistance_ohm == pytest.approx(3.95)
    assert cfg.plant_motor_r.k_nm_per_a == pytest.approx(0.390)
    assert cfg.plant_motor_l.supply_v == cfg.plant_motor_r.supply_v == cfg.robot_motor.supply_v == 12.0
    assert cfg.plant_motor_l.coulomb_smoothing_rad_s == cfg.robot_motor.coulomb_smoothing_rad_s
    assert cfg.hal.backend == "sim"
    assert cfg.controller.mode == "dynamic" and cfg.controller.rate_hz == 200.0
    assert cfg.sim.slip.probability == 0.25


def test_offset_mass_config_holds_table_5_2() -> None:
    base = load_config(SIM_YAML)
    cfg = load_config(OFFSET)
    assert cfg.plant.m_p == 2.8
    assert cfg.plant.m_p - base.plant.m_p == pytest.approx(2.0)  # the added 2 kg
    assert cfg.plant.d_xc == pytest.approx(0.056) and cfg.plant.d_yc == pytest.approx(0.010)
    assert cfg.robot == base.robot  # the controller is not told
    assert cfg.robot.I_p == 6.42868e-3
    # everything not overridden comes from the base file through extends:
    assert cfg.plant.L == base.plant.L == pytest.approx(0.108)
    assert cfg.plant_motor_l == base.plant_motor_l
    assert cfg.controller == base.controller and cfg.sim == base.sim
    assert cfg.raw["name"] != base.raw["name"]
    assert "extends" not in cfg.raw


@pytest.mark.parametrize("path", [SIM_YAML, OFFSET], ids=lambda p: p.name)
def test_seed_configs_name_an_existing_path_file(path: Path) -> None:
    cfg = load_config(path)
    assert isinstance(cfg.path, str)
    assert (Path(cfg.base_dir) / cfg.path).is_file()
    assert cfg.source == str(path)


# --------------------------------------------------------------------------- plant defaults


def test_plant_keys_default_to_robot_key_by_key(tmp_path: Path) -> None:
    data = _minimal()
    data["plant"] = {"m_p": 3.0, "d_yc": 0.02, "motor_l": {"resistance_ohm": 5.0}}
    cfg = load_config(_write(tmp_path, "partial.yaml", data))
    assert cfg.plant.m_p == 3.0 and cfg.plant.d_yc == 0.02
    for name in RobotParams.names():
        if name not in ("m_p", "d_yc"):
            assert getattr(cfg.plant, name) == getattr(cfg.robot, name), name
    assert cfg.plant_motor_l.resistance_ohm == 5.0
    for f in dataclasses.fields(MotorParams):
        if f.name != "resistance_ohm":
            assert getattr(cfg.plant_motor_l, f.name) == getattr(cfg.robot_motor, f.name), f.name
    assert cfg.plant_motor_r == cfg.robot_motor
    assert cfg.robot.m_p == 0.75  # robot: itself is untouched


def test_plant_motor_applies_to_both_wheels_and_is_deep_merged(tmp_path: Path) -> None:
    data = _minimal()
    data["plant"] = {"motor": {"supply_v": 24.0}, "motor_r": {"supply_v": 18.0}}
    cfg = load_config(_write(tmp_path, "motors.yaml", data))
    assert cfg.robot_motor.supply_v == 12.0
    assert cfg.plant_motor_l.supply_v == 24.0
    assert cfg.plant_motor_r.supply_v == 18.0
    assert cfg.plant_motor_l.k_nm_per_a == cfg.robot_motor.k_nm_per_a


def test_no_plant_section_means_the_plant_is_the_robot(tmp_path: Path) -> None:
    cfg = load_config(_write(tmp_path, "noplant.yaml", _minimal()))
    assert cfg.plant == cfg.robot
    assert cfg.plant_motor_l == cfg.plant_motor_r == cfg.robot_motor
    assert cfg.controller == ControllerConfig() and cfg.daemon == DaemonConfig()


def test_extends_is_relative_to_the_extending_file_and_deep_merges(tmp_path: Path) -> None:
    base = _minimal()
    base["daemon"] = {"cpus": [0, 1], "stop_decel": 0.7}
    base["limits"] = {"v_max": 0.5}
    _write(tmp_path, "base.yaml", base)
    child = _write(tmp_path / "sub", "child.yaml",
                   {"extends": "../base.yaml", "daemon": {"cpus": [2]}, "limits": {"accel": 0.3}})
    cfg = load_config(child)
    assert cfg.daemon.cpus == (2,)  # lists replace
    assert cfg.daemon.stop_decel == 0.7  # mappings merge key by key
    assert cfg.limits.v_max == 0.5 and cfg.limits.accel == 0.3
    assert cfg.robot.I_p == 6.42868e-3


# --------------------------------------------------------------------------- bad files


def _set(path: str, value: Any) -> Callable[[dict[str, Any]], None]:
    def mutate(data: dict[str, Any]) -> None:
        node = data
        *parents, last = path.split(".")
        for part in parents:
            node = node.setdefault(part, {})
        node[last] = value
    return mutate


def _delete(path: str) -> Callable[[dict[str, Any]], None]:
    def mutate(data: dict[str, Any]) -> None:
        node = data
        *parents, last = path.split(".")
        for part in parents:
            node = node[part]
        del node[last]
    return mutate



# (id, mutation of the seed mapping, dotted key the message must name)
BAD_VALUES = [
    ("unknown_section", _set("controler", {"rate_hz": 100}), "controler"),
    ("unknown_inner_key", _set("controller.inner.kp_", 1.0), "controller.inner.kp_"),
    ("string_for_number", _set("controller.inner.kp", "abc"), "controller.inner.kp"),
    ("bool_for_number", _set("controller.rate_hz", True), "controller.rate_hz"),
    ("negative_mass", _set("robot.m_p", -0.75), "robot.m_p"),
    ("zero_radius", _set("robot.r_L", 0), "robot.r_L"),
    ("nan_robot", _set("robot.I_p", float("nan")), "robot.I_p"),
    ("inf_limit", _set("limits.v_max", float("inf")), "limits.v_max"),
    ("nan_gain", _set("controller.inner.ki", float("nan")), "controller.inner.ki"),
    ("minus_inf_nested", _set("sim.gyro.bias_dps", float("-inf")), "sim.gyro.bias_dps"),
    ("bad_mode", _set("controller.mode", "fast"), "controller.mode"),
    ("duty_above_one", _set("limits.duty_max", 1.5), "limits.duty_max"),
    ("missing_robot", _delete("robot"), "robot"),
    ("missing_robot_key", _delete("robot.I_w3"), "robot.I_w3"),
    ("unknown_robot_key", _set("robot.mass", 3.0), "robot.mass"),
    ("negative_plant_mass", _set("plant.m_p", -2.0), "plant.m_p"),
    ("unknown_motor_key", _set("plant.motor_l.ohms", 3.0), "plant.motor_l.ohms"),
    ("nan_motor", _set("robot.motor.coulomb_nm", float("nan")), "robot.motor.coulomb_nm"),
    ("start_two_values", _set("start", [0.0, 1.0]), "start"),
    ("start_not_numbers", _set("start", [0.0, "x", 0.0]), "start"),
    ("gyro_range", _set("sensors.gyro_range_dps", 300), "sensors.gyro_range_dps"),
    ("backend", _set("hal.backend", "usb"), "hal.backend"),
    ("rt_priority", _set("daemon.rt_priority", 100), "daemon.rt_priority"),
    ("cpu_not_int", _set("daemon.cpus", [0, "one"]), "daemon.cpus"),
    ("slip_probability", _set("sim.slip.probability", 1.5), "sim.slip.probability"),
    ("forgetting", _set("controller.adaptation.forgetting", 0.5), "controller.adaptation.forgetting"),
    ("section_not_mapping", _set("limits", 3), "limits"),
    ("extends_not_text", _set("extends", ["sim.yaml"]), "extends"),
    ("negative_motor", _set("robot.motor.supply_v", -12.0), "robot.motor.supply_v"),
    ("motor_l_not_mapping", _set("plant.motor_l", 5), "plant.motor_l"),
    ("plant_motor_not_mapping", _set("plant.motor", [1]), "plant.motor"),
    ("section_empty_list", _set("sim", []), "sim"),
]


@pytest.mark.parametrize(("case", "mutate", "key"), BAD_VALUES, ids=[
    c.values[0] if hasattr(c, "values") else c[0] for c in BAD_VALUES])
def test_bad_value_names_file_and_key(tmp_path: Path, case: str, mutate: Callable[[dict[str, Any]], None],
                                      key: str) -> None:
    data = _sim_mapping()
    mutate(data)
    path = _write(tmp_path, f"bad_{case}.yaml", data)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    msg = str(info.value)
    assert path.name in msg
    assert re.search(rf"(^|[\s:]){re.escape(key)}([\s:\[]|$)", msg), msg


@pytest.mark.parametrize(("text", "line"), [
    ("robot:\n  H: 0.1\n   L: 2\n", 3),
    ("name: x\n\nsim:\n\tstep_hz: 1\n", 4),
])
def test_invalid_yaml_names_file_and_line(tmp_path: Path, text: str, line: int) -> None:
    path = _write(tmp_path, "syntax.yaml", text)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    msg = str(info.value)
    assert "syntax.yaml" in msg
    assert f"line {line}" in msg


def test_empty_file_reports_missing_robot(tmp_path: Path) -> None:
    path = _write(tmp_path, "empty.yaml", "")
    with pytest.raises(ConfigError, match=r"empty\.yaml: robot: missing"):
        load_config(path)


def test_top_level_not_a_mapping(tmp_path: Path) -> None:
    path = _write(tmp_path, "list.yaml", "- robot\n- plant\n")
    with pytest.raises(ConfigError, match=r"list\.yaml"):
        load_config(path)


def test_extends_a_missing_file_names_the_missing_file(tmp_path: Path) -> None:
    path = _write(tmp_path, "child.yaml", "extends: nowhere.yaml\n")
    with pytest.raises(ConfigError, match=r"nowhere\.yaml"):
        load_config(path)


def test_extends_a_missing_file_names_the_extending_file_and_key(tmp_path: Path) -> None:
    path = _write(tmp_path, "child.yaml", "extends: nowhere.yaml\n")
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert "child.yaml" in str(info.value) and "extends" in str(info.value)


@pytest.mark.parametrize("files", [
    {"a.yaml": "extends: b.yaml\n", "b.yaml": "extends: a.yaml\n"},
    {"a.yaml": "extends: a.yaml\n"},
    {"a.yaml": "extends: b.yaml\n", "b.yaml": "extends: c.yaml\n", "c.yaml": "extends: b.yaml\n"},
], ids=["two", "self", "three"])
def test_extends_cycle_is_an_error(tmp_path: Path, files: dict[str, str]) -> None:
    for name, text in files.items():
        _write(tmp_path, name, text)
    with pytest.raises(ConfigError) as info:
        load_config(tmp_path / "a.yaml")
    msg = str(info.value)
    assert "a.yaml" in msg and "extends" in msg


def test_config_error_is_a_value_error() -> None:
    assert issubclass(ConfigError, ValueError)


def test_overrides_are_validated_with_the_file_name() -> None:
    cfg = load_config(SIM_YAML)
    with pytest.raises(ConfigError, match=r"sim\.yaml: limits\.duty_max"):
        with_overrides(cfg, {"limits": {"duty_max": 2.0}})
    assert with_overrides(cfg, {"limits": {"duty_max": 0.8}}).limits.duty_max == 0.8
    assert cfg.limits.duty_max == 1.0  # the original is untouched


# --------------------------------------------------------------------------- the generated reference

_ROW = re.compile(r"^\|\s*`([^`]+)`\s*\|" + r"([^|]*)\|" * 5 + r"(.*)\|\s*$")
_KEYS_AS = re.compile(r"\(keys as `([^`]+)`\)")

# Config fields whose keys live elsewhere in the file: plant: takes robot:'s keys.
_CONFIG_FIELD_KEY = {"robot_motor": "robot.motor", "plant": "plant", "plant_motor_l": "plant.motor_l",
                     "plant_motor_r": "plant.motor_r"}
# The real backend's device sub-sections.
_BACKEND_SECTIONS = ("hal.imu.", "hal.bridge.", "hal.pwm_sysfs.")


class _Row(typing.NamedTuple):
    type: str
    unit: str
    bounds: str
    default: str
    reload: str
    meaning: str


def _reference_rows() -> dict[str, _Row]:
    """docs/reference/config.md's rows by key (each key once: a repeat fails here)."""
    rows: dict[str, _Row] = {}
    for line in REFERENCE.read_text(encoding="utf-8").splitlines():
        m = _ROW.match(line)
        if m:
            key, *cells = (s.strip() for s in m.groups())
            assert key not in rows, f"documented more than once: {key}"
            rows[key] = _Row(*cells)
    return rows


def _dataclass_in(tp: Any) -> tuple[type | None, str]:
    """The dataclass a field's type holds (directly, as Optional, or as each item of a list:
    then the key's suffix is '[]'), else None."""
    if dataclasses.is_dataclass(tp):
        return tp, ""
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        for arg in typing.get_args(tp):
            if dataclasses.is_dataclass(arg):
                return arg, ""
    args = typing.get_args(tp)
    if typing.get_origin(tp) is tuple and len(args) == 2 and args[1] is Ellipsis and dataclasses.is_dataclass(args[0]):
        return args[0], "[]"
    return None, ""


def _walk(cls: type, prefix: str, out: dict[str, tuple[type, dataclasses.Field]]) -> None:
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        key = f"{prefix}.{f.name}"
        out[key] = (cls, f)
        sub, suffix = _dataclass_in(hints[f.name])
        if sub is not None:
            _walk(sub, key + suffix, out)


def _schema_keys() -> dict[str, tuple[type, dataclasses.Field]]:
    """Every dotted key the config's dataclasses define, found from Config's own fields (a walk
    of this test's own, so that it checks ddrt/config/keys.py's too)."""
    out: dict[str, tuple[type, dataclasses.Field]] = {}
    hints = typing.get_type_hints(Config)
    for f in dataclasses.fields(Config):
        if not f.compare:
            continue
        key = _CONFIG_FIELD_KEY.get(f.name, f.name)
        out[key] = (Config, f)
        cls, _ = _dataclass_in(hints[f.name])
        if cls is not None:
            _walk(cls, key, out)
    return out


def _row_of(rows: dict[str, _Row], key: str) -> _Row:
    """The row that documents `key`: its own, or the same key of the section whose keys a
    section takes (plant.m_p is robot.m_p's row; sim.wheels.scale.mean sim.encoder.slip.mean's)."""
    if key in rows:
        return rows[key]
    for head, row in sorted(rows.items(), key=lambda kv: -len(kv[0])):
        m = _KEYS_AS.search(row.type)
        if m and key.startswith(head + "."):
            return _row_of(rows, m.group(1) + key[len(head):])
    raise KeyError(key)


def test_schema_walk_reaches_every_section_class() -> None:
    reached = {cls for cls, _ in _schema_keys().values()}
    for cls in (SimConfig, SlipConfig, GyroTruth, SensorsConfig, HalConfig, ImuConfig, BridgeConfig,
                PwmSysfsConfig, ControllerConfig, OuterGains, InnerPid, WheelPid, AdaptationConfig,
                EstimatorConfig, PursuitConfig, LimitsConfig, DaemonConfig, PathsConfig, RobotParams,
                MotorParams, PayloadEvent, FloorPatch):
        assert cls in reached, cls.__name__


def test_every_config_key_declares_a_description() -> None:
    """A field without a declaration, or with an empty description, fails here (and the
    reference could not be written)."""
    lacking = [key for key, (_cls, f) in _schema_keys().items()
               if decl_of(f) is None or len(decl_of(f).doc.strip()) < 10]  # type: ignore[union-attr]
    assert not lacking, f"no description: {lacking}"


def test_the_reference_documents_every_config_field() -> None:
    rows = _reference_rows()
    assert len(rows) > 250
    missing = []
    for key in _schema_keys():
        try:
            _row_of(rows, key)
        except KeyError:
            missing.append(key)
    assert not missing, f"docs/reference/config.md lacks: {missing}"


def test_the_reference_documents_every_top_level_key() -> None:
    rows = _reference_rows()
    missing = [k for k in config_mod.TOP_KEYS if k not in rows]
    assert not missing, f"docs/reference/config.md lacks: {missing}"


def _estimate_keys() -> set[str]:
    """robot.estimate's keys, as ddrt/params/estimate.py reads them (not a dataclass section)."""
    from ddrt.params import estimate
    out = {f"robot.estimate.{k}" for k in estimate.KEYS}
    out |= {f"robot.estimate.encoder_wheel.{k}" for k in estimate.ENCODER_KEYS}
    return out | {f"robot.estimate.body.{k}" for k in estimate.BODY_KEYS}


def test_the_reference_documents_no_key_that_does_not_exist() -> None:
    known = set(_schema_keys()) | set(config_mod.TOP_KEYS)
    stale = [k for k in _reference_rows() if k not in known]
    assert not stale, f"docs/reference/config.md documents unknown keys: {stale}"


def test_config_md_documents_the_estimate_keys() -> None:
    """robot.estimate: is read by ddrt/params/estimate.py, not the walker: its table stays in
    docs/config.md, with the explanation of its assumptions, and names each of its keys."""
    text = DOC.read_text(encoding="utf-8")
    documented = set()
    for m in re.finditer(r"^\| `(robot\.estimate\.[^`]+)`(?:, `([^`]+)`)?", text, re.M):
        documented.add(m.group(1))
        if m.group(2):
            documented.add(m.group(1).rpartition(".")[0] + "." + m.group(2))
    groups = {"robot.estimate.encoder_wheel", "robot.estimate.body"}  # documented by their keys
    assert documented == _estimate_keys() - groups


def test_every_row_has_a_type_default_reload_and_meaning() -> None:
    for key, row in _reference_rows().items():
        assert row.type and len(row.meaning) > 10, key
        assert row.reload in ("live", "next path", "restart", "-"), key
        assert row.default or row.type.startswith("section"), key


def _key_default(keys: dict[str, tuple[type, dataclasses.Field]], key: str) -> Any:
    """The default a key takes, as the walker gives it: the value in its enclosing section's
    default, else its field's own; MISSING if it has none."""
    f = keys[key][1]
    parent = key.rpartition(".")[0]
    if parent in keys:
        section = _key_default(keys, parent)
        if dataclasses.is_dataclass(section):
            return getattr(section, f.name)
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return dataclasses.MISSING


def _documented_value(text: str) -> Any:
    """A default as the reference writes it: `0.3`, `true`, `null`, `"MPU-6050"`, `[]`."""
    return json.loads(text.strip().strip("`"))


def test_the_references_defaults_are_the_schemas() -> None:
    """The default column says what the walker gives a missing key (a default changed in code
    and not in the reference fails here, through tests/test_docgen.py's equality too)."""
    rows = _reference_rows()
    keys = _schema_keys()
    checked, wrong = 0, []
    for key in keys:
        if key not in rows:
            continue  # a key of a section that takes another's keys: that row is checked
        value = _key_default(keys, key)
        cell = rows[key].default
        if value is dataclasses.MISSING:
            if cell not in ("required", "") and not cell.endswith("'s"):
                wrong.append(f"{key}: no default, the reference says {cell}")
            continue
        if dataclasses.is_dataclass(value):
            continue  # a sub-section: its own keys carry the defaults
        doc = _documented_value(cell)
        value = list(value) if isinstance(value, tuple) else value
        numbers = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (value, doc))
        if not (math.isclose(value, doc, rel_tol=1e-12) if numbers else value == doc and type(value) is type(doc)):
            wrong.append(f"{key}: the reference says {cell}, the schema {value!r}")
        checked += 1
    assert checked > 200 and not wrong, wrong


def test_every_default_is_within_its_declared_bounds() -> None:
    keys = _schema_keys()
    wrong = []
    for key, (_cls, f) in keys.items():
        value, decl = _key_default(keys, key), decl_of(f)
        if decl is None or value is dataclasses.MISSING or value is None or dataclasses.is_dataclass(value):
            continue
        problem = decl.check(value, key)
        if problem is not None:
            wrong.append(problem)
    assert not wrong, wrong


def test_a_pid_section_missing_keys_take_that_sections_defaults() -> None:
    """controller.inner and controller.wheel_pid are two sections of one PID (InnerPid, WheelPid)
    with two default sets: a key one of them leaves out takes its own section's default."""
    data = _minimal()
    data["controller"] = {"inner": {"kp": 30.0}, "wheel_pid": {"kp": 0.2}}
    c = config_from_mapping(data).controller
    assert c.inner == dataclasses.replace(INNER_PID, kp=30.0)
    assert c.wheel_pid == dataclasses.replace(WHEEL_PID, kp=0.2)
    assert config_from_mapping(_minimal()).controller.wheel_pid == WHEEL_PID
    data["controller"] = {"wheel_pid": {"integrator_limit": 0.0}}
    with pytest.raises(ConfigError, match=r"controller\.wheel_pid\.integrator_limit: must be > 0"):
        config_from_mapping(data)


def test_the_reference_covers_the_real_backends_keys() -> None:
    """hal.imu/bridge/pwm_sysfs are typed sections: the real backend reads nothing else
    (no raw mapping, no reader of its own), and every one of their keys is documented."""
    source = REAL_HAL.read_text(encoding="utf-8")
    assert "_ConfigReader" not in source and ".raw" not in source
    keys = {k for k in _schema_keys() if k.startswith(_BACKEND_SECTIONS)}
    assert {"hal.imu.bus", "hal.bridge.url", "hal.pwm_sysfs.root", "hal.pwm_sysfs.direction_gpios"} <= keys
    assert "hal.imu.gyro_range_dps" not in keys  # one gyro range: sensors.gyro_range_dps
    documented = {k for k in _reference_rows() if k.startswith(_BACKEND_SECTIONS)}
    assert keys == documented
