"""A campaign's cases: every combination of its axes, each built into a validated Config and
a resolved Path before anything runs.

A case's config is layered: the base file (after `extends:`), a drawn robot's sections,
`overrides:`, the variant, the path, then the axes' keys. It is validated whole by the
config's own loader, and its path is built with the same limits `ddrt sim` would use, so a
bad axis value is refused here, naming the campaign, the case (its axis values) and the key.
Identical configs and paths are built once: a seed axis costs nothing to check.
"""

from __future__ import annotations

import copy
import hashlib
import itertools
import json
from dataclasses import dataclass
from pathlib import Path as FsPath
from typing import Any, Iterable, Mapping

from ddrt.config import Config, ConfigError, config_from_mapping, load_config
from ddrt.config.yamlio import MAX_BYTES, read_yaml
from ddrt.path import Path
from ddrt.path.spec import PathError, config_path_error, path_source, speed_limits
from ddrt.service.pathjob import BuildJob, build_path, check_path_file
from ddrt.sweep.campaign import Campaign, CampaignError
from ddrt.sweep.population import Robot, population
from ddrt.config.load import merge_mappings


@dataclass(frozen=True)
class Case:
    """One run of a campaign: its axis values, its config, which path, which noise seed."""

    index: int
    case_id: str  # a digest of what the run depends on: the same case, the same id
    params: dict[str, Any]  # column -> value, in the campaign's axis order
    config: Config
    path_key: str  # into Plan.paths
    seed: int | None  # for run_sim; None: the config's sim.seed
    expected_s: float  # the path's duration, so the longest runs can start first

    @property
    def label(self) -> str:
        return ", ".join(f"{k}={_show(v)}" for k, v in self.params.items())


@dataclass(frozen=True)
class Plan:
    """Every case of a campaign, checked, and the paths they drive."""

    campaign: Campaign
    cases: tuple[Case, ...]
    paths: dict[str, Path]
    columns: tuple[str, ...]  # the parameter columns, in order
    fingerprint: str  # changes when any case or what a row keeps changes


@dataclass(frozen=True)
class _Choice:
    """One value of one dimension: what the table shows and what it does to the config."""

    shown: Any
    layer: dict[str, Any]  # merged over the config (a `path` entry is merged over the path)
    folder: str | None = None  # a base's: where its config's relative names start
    robot: Robot | None = None
    path: str | dict[str, Any] | None = None
    seed: int | None = None


def _show(v: Any) -> str:
    return json.dumps(v) if isinstance(v, (list, dict)) else str(v)


def _digest(value: Any, n: int = 16) -> str:
    text = json.dumps(value, sort_keys=True, separators=(",", ":"), default=repr)
    return hashlib.sha256(text.encode()).hexdigest()[:n]


def nested(key: str, value: Any) -> dict[str, Any]:
    """{"a": {"b": value}} from "a.b"."""
    for part in reversed(key.split(".")):
        value = {part: value}
    return value


def inline_path(source: Any) -> Any:
    """A path file as the mapping it stands for, so keys (its speed) can be set on it: a
    YAML spec read (its CSV named absolutely), a CSV as {file: NAME}. Mappings pass through."""
    if not isinstance(source, str):
        return source
    p = FsPath(source)
    if p.suffix.lower() == ".csv":
        return {"file": str(p)}
    check_path_file(str(p), MAX_BYTES, PathError)  # a FIFO is refused, not read (that would block)
    data = read_yaml(p, PathError)
    if not isinstance(data, Mapping):  # else the keys set on it would replace it and hide this
        raise PathError(f"{p}: expected a mapping at the top level, got {type(data).__name__}")
    if isinstance(data.get("file"), str):
        data = dict(data, file=str(p.parent / data["file"]))
    return data


def _apply(data: dict[str, Any], layer: Mapping[str, Any]) -> dict[str, Any]:
    """`layer` over the config mapping; its path keys over the path, inlined if it was a file."""
    path_over = layer.get("path")
    if isinstance(path_over, Mapping) and "path" in data:
        data = dict(data, path=inline_path(data["path"]))
    return merge_mappings(data, layer)


class _Builder:
    """Expands a campaign; holds the caches that make identical configs and paths cheap."""

    def __init__(self, camp: Campaign) -> None:
        self.camp = camp
        self.configs: dict[str, Config] = {}
        self.paths: dict[str, Path] = {}

    def dimensions(self) -> list[tuple[str, list[_Choice]]]:
        camp = self.camp
        dims: list[tuple[str, list[_Choice]]] = []
        bases = []
        for label, f in zip(camp.base_labels, camp.bases):
            try:
                raw = load_config(f).raw
            except (ConfigError, PathError) as exc:
                raise CampaignError(f"{camp.source}: base: {exc}") from None
            bases.append(_Choice(label, raw, folder=str(f.parent)))
        if camp.base_axis:
            dims.append(("base", bases))
        elif bases:
            dims.append(("", bases))  # one base file: not a column
        else:
            dims.append(("", [_Choice(None, {}, folder=str(camp.folder))]))  # no base: every key at default
        if camp.variants:
            dims.append(("variant", [_Choice(name, over) for name, over in camp.variants.items()]))
        if camp.population is not None:
            robots = population(camp.population.robots, camp.population.seed)
            dims.append(("robot", [_Choice(r.name, {}, robot=r) for r in robots]))
        if camp.paths:
            dims.append(("path", [_Choice(name, {}, path=src) for name, src in camp.paths.items()]))
        for axis in camp.axes:
            dims.append((axis.key, [_Choice(v, nested(axis.key, v)) for v in axis.values]))
        if camp.seeds is not None:
            dims.append(("seed", [_Choice(s, {}, seed=s) for s in camp.seeds]))
        return dims

    def mapping(self, choices: Iterable[_Choice]) -> tuple[dict[str, Any], str, int | None]:
        """The case's merged config mapping, the folder its names start from, its seed.

        Layers, each over the last: the base; the robot's sections (its robot: and plant:
        replace the base's, its sim: merges); the path chosen; the robot's speed on it;
        overrides:; then the variant and the axes in the campaign's order."""
        first, *rest = list(choices)
        data = copy.deepcopy(first.layer)
        folder = str(first.folder)
        robot = next((c.robot for c in rest if c.robot is not None), None)
        path = next((c.path for c in rest if c.path is not None), None)
        seed = next((c.seed for c in rest if c.seed is not None), None)
        if robot is not None:
            data = dict(data, robot=copy.deepcopy(robot.sections["robot"]),
                        plant=copy.deepcopy(robot.sections["plant"]))
            data = merge_mappings(data, {"sim": robot.sections["sim"]})
        if path is not None:
            data = dict(data, path=copy.deepcopy(path))
        population = self.camp.population
        if robot is not None and population is not None and population.path_speed and data.get("path") is not None:
            data = _apply(data, {"path": {"speed": robot.path_speed}})
        data = _apply(data, self.camp.overrides)
        for c in rest:
            if c.layer:
                data = _apply(data, c.layer)
        return data, folder, seed

    def config(self, data: dict[str, Any], folder: str, where: str) -> Config:
        key = _digest([data, folder], 32)
        cfg = self.configs.get(key)
        if cfg is None:
            try:
                cfg = config_from_mapping(data, source=where, base_dir=folder)
            except (ConfigError, PathError) as exc:
                raise CampaignError(str(exc)) from None
            if cfg.hal.backend == "real" and cfg.hal.imu.bus != "sim":
                raise CampaignError(f"{where}: hal.backend: real with hal.imu.bus: {cfg.hal.imu.bus} drives a robot "
                                    "itself; a campaign runs on the simulated robot (hal.backend: sim)")
            self.configs[key] = cfg
        return cfg

    def path(self, cfg: Config) -> str:
        """The case's path, built as the daemon builds one: its files checked first (a FIFO,
        a device or a directory is refused instead of blocking the read), then loaded."""
        if cfg.path is None:
            raise CampaignError(f"{cfg.source}: path: missing: give the campaign paths:, or the base config a path:")
        key = _digest([cfg.path, cfg.base_dir, repr(speed_limits(cfg)), repr(cfg.paths)], 12)
        if key not in self.paths:
            try:
                source, kwargs = path_source(cfg)
                self.paths[key] = build_path(BuildJob(source, speed_limits(cfg), **kwargs))
            except PathError as exc:
                raise CampaignError(" ".join(config_path_error(cfg, str(exc)).split())) from None
            except (ConfigError, OSError) as exc:
                raise CampaignError(" ".join(str(exc).split())) from None
        return key


def expand(camp: Campaign) -> Plan:
    """Every case of `camp`, each config validated and each path built; the first bad case is
    a CampaignError naming it."""
    builder = _Builder(camp)
    dims = builder.dimensions()
    columns = tuple(name for name, _ in dims if name)
    cases: list[Case] = []
    seen: dict[str, int] = {}
    settings = camp.run
    for index, combo in enumerate(itertools.product(*(choices for _, choices in dims))):
        params = {name: c.shown for (name, _), c in zip(dims, combo) if name}
        label = ", ".join(f"{k}={_show(v)}" for k, v in params.items())
        where = f"{camp.source}: case {index}" + (f" ({label})" if label else "")
        try:
            data, folder, seed = builder.mapping(combo)
        except (ConfigError, PathError, OSError) as exc:
            raise CampaignError(f"{where}: path: {' '.join(str(exc).split())}") from None
        cfg = builder.config(data, folder, where)
        path_key = builder.path(cfg)
        if "seed" not in params:
            params["seed"] = cfg.sim.seed
        case_id = _digest({"config": data, "seed": seed, "duration_s": settings.duration_s})
        if case_id in seen:
            raise CampaignError(f"{where}: the same run as case {seen[case_id]} (two values that make the same config)")
        seen[case_id] = index
        cases.append(Case(index, case_id, params, cfg, path_key, seed, builder.paths[path_key].duration))
    if "seed" not in columns:
        columns += ("seed",)
    fingerprint = _digest({"cases": [c.case_id for c in cases], "duration_s": settings.duration_s,
                           "metrics": settings.metrics, "pass": [c.text for c in settings.criteria]}, 32)
    return Plan(camp, tuple(cases), builder.paths, columns, fingerprint)
