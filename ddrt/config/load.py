"""The config: one path from YAML file to a validated, typed, frozen `Config`.

Load -> merge (`extends:` a base file, then `plant:` over `robot:`) -> validate whole. A bad
file raises ConfigError with the file name and the dotted key.
"""

from __future__ import annotations

import copy
import os
from pathlib import Path as FsPath
from typing import Any, Callable, Mapping

from ddrt.config.filekind import CONFIG, PATH, not_a
from ddrt.config.schema import RESTART, ConfigError, Decl, build, convert, field_items
from ddrt.config.sections import (
    Config, ControllerConfig, DaemonConfig, DriveConfig, EstimatorConfig, HalConfig, LimitsConfig, PathsConfig,
    PursuitConfig, SensorsConfig, SimConfig,
)
from ddrt.config.yamlio import read_yaml, shorten
from ddrt.params.estimate import estimate_from_mapping
from ddrt.params.robot import RobotParams
from ddrt.params.motor import MotorParams

# --------------------------------------------------------------------------- loading

# The file's own keys, beside Config's sections: how it is read and what it is called.
OWN_KEYS = {
    "extends": Decl(unit="file name", doc="Base file this one is deep-merged over, relative to this file's folder "
                                          "([config.md](config.md#how-a-file-is-read)).", reload=RESTART),
    "name": Decl(doc="Short label of the config; not interpreted.", reload=RESTART),
    "description": Decl(doc="Free text; not interpreted.", reload=RESTART),
}
# The keys a config file may hold at its top level (docs/reference/config.md documents each).
TOP_KEYS = ("extends", "robot", "plant", "sim", "sensors", "hal", "controller", "estimator",
             "pursuit", "limits", "daemon", "drive", "paths", "path", "start", "name", "description")


def _section(data: Mapping[str, Any], key: str) -> Any:
    """A section's mapping; absent or empty (None) is {}, anything else is validated as is."""
    value = data.get(key)
    return {} if value is None else value


def merge_mappings(base: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """Deep merge: mappings merge key by key, anything else in `over` replaces (`extends:`,
    `plant:` over `robot:`, and a campaign's cases over their base)."""
    out = copy.deepcopy(dict(base))
    for key, value in over.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = merge_mappings(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


# Every key of a config that names a file or a folder. One rule for all of them: a relative
# name is taken from the folder of the config file that names it (also when that file is the
# base of another through extends:), never from the working directory, so a config and the
# files beside it can be copied anywhere together. `hal.url` is a serial URL, not a file.
FILE_KEYS: tuple[tuple[str, ...], ...] = (
    ("path",), ("path", "file"), ("daemon", "socket"), ("daemon", "telemetry_dir"), ("hal", "pwm_sysfs", "root"),
)


def _file_names(data: dict[str, Any], change: Callable[[str], str]) -> dict[str, Any]:
    """`data` (changed in place) with `change` applied to every non-empty name under FILE_KEYS;
    anything else there (absent, null, not text) is left for validation to judge."""
    for keys in FILE_KEYS:
        parent: Any = data
        for key in keys[:-1]:
            parent = parent.get(key) if isinstance(parent, Mapping) else None
        if not isinstance(parent, dict):
            continue  # a section that is not a mapping (or a path given as a file name) has no such key
        value = parent.get(keys[-1])
        if isinstance(value, str) and value:
            parent[keys[-1]] = change(value)
    return data


def _anchored(data: dict[str, Any], folder: FsPath) -> dict[str, Any]:
    """`data` with every relative file name made absolute against `folder`."""
    return _file_names(data, lambda name: name if FsPath(name).is_absolute() else str(folder / name))


def files_relative_to(data: Mapping[str, Any], folder: FsPath, given_in: FsPath) -> dict[str, Any]:
    """A copy of a loaded config's mapping for a config written into `folder` (the commissioned
    config): the names the file in `given_in` gave relative (loading joined them to that
    folder) become relative to `folder`, so that both name the same files and move with
    them; absolute names (/run/ddrt/ddrt.sock) stay as they were given."""
    prefix = str(given_in).rstrip(os.sep) + os.sep
    out = copy.deepcopy(dict(data))
    return _file_names(out, lambda name: os.path.relpath(name, folder) if name.startswith(prefix) else name)


def _read_yaml(path: FsPath, chain: tuple[str, ...] = ()) -> dict[str, Any]:
    if str(path) in chain:
        raise ConfigError(f"{path}: extends itself through {' -> '.join(chain)}")
    data = read_yaml(path, ConfigError)
    if data is None:
        data = {}
    if not isinstance(data, Mapping):
        raise ConfigError(f"{path}: the top level must be a mapping of sections")
    data = _anchored(dict(data), path.parent)
    parent = data.get("extends")
    if parent is not None:
        if not isinstance(parent, str):
            raise ConfigError(f"{path}: extends: expected a file name, got {shorten(parent)}")
        base_path = (path.parent / parent).resolve()
        if not base_path.is_file():
            raise ConfigError(f"{path}: extends: no such file {shorten(parent)} (looked for {base_path})")
        base = _read_yaml(base_path, chain + (str(path),))
        data = merge_mappings(base, {k: v for k, v in data.items() if k != "extends"})
    return dict(data)


def _explicit(section: Any, where: str) -> Any:
    """robot: or plant: with its `estimate:` (if any) replaced by the parameters derived from it."""
    if not isinstance(section, Mapping) or "estimate" not in section:
        return section
    both = [key for key in RobotParams.names() if key in section]
    if both:
        raise ConfigError(f"{where}: give either estimate: or the full parameters, not both "
                          f"(remove estimate:, or {', '.join(both)})")
    try:
        derived = estimate_from_mapping(section["estimate"], f"{where}.estimate").params()
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    out = {k: v for k, v in section.items() if k != "estimate"}
    out.update({f.name: value for f, value in field_items(derived)})
    return out


def _plant_section(robot_section: Any, plant_over: Mapping[str, Any]) -> Any:
    """plant: over robot:, key by key. A plant estimate: replaces robot:'s parameters (and
    merges over its estimate:); explicit plant keys override those robot:'s estimate derived."""
    if "estimate" in plant_over:
        base = {k: v for k, v in robot_section.items() if k not in RobotParams.names()}
        return _explicit(merge_mappings(base, plant_over), "plant")
    return merge_mappings(_explicit(robot_section, "robot"), plant_over)


def _params(section: Any, where: str, extras: tuple[str, ...] = ("motor",)) -> tuple[RobotParams, dict[str, Any]]:
    """robot: or plant: as RobotParams (the walker checks every parameter) and its motor mapping."""
    params = build(RobotParams, section, where, ignore=extras)
    # The motor keys are merged (plant.motor_l over plant.motor over robot.motor) before the
    # walker builds them, so here they need only be mappings.
    for key in extras:
        if section.get(key) is not None and not isinstance(section[key], Mapping):
            raise ConfigError(f"{where}.{key}: expected a mapping of motor constants, got {shorten(section[key])}")
    motor = section.get("motor")
    return params, {} if motor is None else motor


def _motor(mapping: Any, where: str) -> MotorParams:
    return build(MotorParams, mapping, where)


def config_from_mapping(data: Mapping[str, Any], source: str = "<memory>", base_dir: str = ".") -> Config:
    """Validate a whole merged mapping into a Config; errors name `source` and the key."""
    try:
        return _config_from_mapping(data, source, base_dir)
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None


def _config_from_mapping(data: Mapping[str, Any], source: str, base_dir: str) -> Config:
    # The top level is not one dataclass (plant: merges over robot:, extends: and name: are
    # the file's own), so its keys are checked here; every section below goes to the walker.
    unknown = sorted(k if isinstance(k, str) else shorten(k) for k in data if k not in TOP_KEYS)
    if unknown:
        raise ConfigError(f"{unknown[0]}: unknown section (known: {', '.join(TOP_KEYS)})")
    if "robot" not in data:
        raise ConfigError("robot: missing (required): the controller's robot parameters")
    robot_section = data["robot"]
    robot, robot_motor_map = _params(_explicit(robot_section, "robot"), "robot")
    robot_motor = _motor(robot_motor_map, "robot.motor")

    plant_over = _section(data, "plant")
    if not isinstance(plant_over, Mapping):
        raise ConfigError("plant: expected a mapping of robot parameters")
    plant_section = _plant_section(robot_section, plant_over)
    plant, plant_motor_map = _params(plant_section, "plant", ("motor", "motor_l", "motor_r"))
    # A plant may give one motor for both wheels (motor:) or each its own (motor_l:, motor_r:).
    plant_motor_l = _motor(merge_mappings(plant_motor_map, plant_section.get("motor_l") or {}), "plant.motor_l")
    plant_motor_r = _motor(merge_mappings(plant_motor_map, plant_section.get("motor_r") or {}), "plant.motor_r")

    start = data.get("start")
    if start is not None:
        try:
            start = convert(tuple[float, float, float], start, "start")
        except ConfigError as exc:
            raise ConfigError(f"{exc} (expected [x, y, theta] in metres and radians)") from None
    paths = build(PathsConfig, _section(data, "paths"), "paths")
    path = data.get("path")
    if path is not None and not isinstance(path, (str, Mapping)):
        raise ConfigError(f"path: expected a path file name or a path mapping, got {shorten(path)}")
    if start is not None:
        paths.check_pose(start, "start")

    limits = build(LimitsConfig, _section(data, "limits"), "limits")
    hal = build(HalConfig, _section(data, "hal"), "hal")
    # The gyro's keys default per backend (SensorsConfig.for_backend): a real MPU reads TEMP_OUT and its FIFO.
    sensors = build(SensorsConfig, _section(data, "sensors"), "sensors", base=SensorsConfig.for_backend(hal.backend))

    cfg = Config(
        robot=robot,
        robot_motor=robot_motor,
        plant=plant,
        plant_motor_l=plant_motor_l,
        plant_motor_r=plant_motor_r,
        sim=build(SimConfig, _section(data, "sim"), "sim"),
        sensors=sensors,
        hal=hal,
        controller=build(ControllerConfig, _section(data, "controller"), "controller"),
        estimator=build(EstimatorConfig, _section(data, "estimator"), "estimator"),
        pursuit=build(PursuitConfig, _section(data, "pursuit"), "pursuit"),
        limits=limits,
        daemon=build(DaemonConfig, _section(data, "daemon"), "daemon"),
        drive=build(DriveConfig, _section(data, "drive"), "drive"),
        paths=paths,
        path=path,
        start=start,
        source=source,
        base_dir=base_dir,
        raw=copy.deepcopy(dict(data)),
    )
    cfg.validate()
    return cfg


def daemon_socket_of(path: str | FsPath, error: Exception) -> str | None:
    """`daemon.socket` as the file (with its `extends:`) gives it, the rest not validated, for
    `ddrt ctl --config` while the file is being edited: a typo elsewhere must not keep the
    operator from the daemon's socket (estop, stop, the reload that reports the typo).
    Raises `error`, the file's own load error, when the YAML or that key is wrong too."""
    try:
        daemon = _read_yaml(FsPath(path).resolve()).get("daemon", {})
    except ConfigError:
        raise error from None
    socket = daemon.get("socket", DaemonConfig().socket) if isinstance(daemon, Mapping) else 0
    if socket is not None and not isinstance(socket, str):
        raise error from None
    return socket


def load_config(path: str | FsPath, overrides: Mapping[str, Any] | None = None) -> Config:
    """Read, merge and validate a YAML config file (plus optional in-memory overrides)."""
    p = FsPath(path)
    if p.suffix.lower() == ".csv":
        raise ConfigError(PATH.sentence(str(p), "a config"))
    try:
        data = _read_yaml(p.resolve())
    except ConfigError as exc:
        raise ConfigError(str(exc).replace(str(p.resolve()), str(p), 1)) from None
    other = not_a(data, CONFIG, str(p), "a config")
    if other is not None:
        raise ConfigError(other)
    if overrides:
        data = merge_mappings(data, overrides)
    return config_from_mapping(data, source=str(p), base_dir=str(p.resolve().parent))


def with_overrides(cfg: Config, overrides: Mapping[str, Any]) -> Config:
    """The same config with some keys replaced (for sweeps and benchmarks)."""
    return config_from_mapping(merge_mappings(cfg.raw, overrides), source=cfg.source, base_dir=cfg.base_dir)
