"""A campaign file: what to vary, how to run each case, what to keep and what passes.

The file is read strictly, as configs are: an unknown key, a wrong type, a range with no
values or an empty axis is a CampaignError naming the file and the key, before any case is
built. The keys (docs/sweep.md has them all):

    name, description      text
    base                   a config file, or a list of them (then an axis `base`)
    overrides              a mapping merged over every case's config
    variants               name -> a mapping merged over the config (an axis `variant`)
    population             {robots, seed, path_speed}: random robots (an axis `robot`)
    paths                  name -> a path file or an inline spec, or a list of files (an axis `path`)
    axes                   dotted config key -> a list of values or a range
    seeds                  N (seeds 1..N) or a list (an axis `seed`)
    run                    {duration_s, timeout_s}
    metrics                the metrics.json figures to keep (default: every one)
    pass                   criteria, e.g. "rms_cross_track_m < 0.005"
    summary                {metrics}: the figures the summary's percentiles are of
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path as FsPath
from typing import Any, Mapping, TypeVar

from ddrt.config.filekind import CAMPAIGN, not_a
from ddrt.errors import DdrtError
from ddrt.config.schema import INT_LIMIT, ConfigError, Section, build, setting
from ddrt.config.yamlio import read_yaml, shorten
from ddrt.config.textfile import mode_kind
from ddrt.sweep.columns import KNOWN_METRICS, NUMERIC_METRICS, TEXT_METRICS
from ddrt.sweep.criteria import Criterion, parse_criterion
from ddrt.sweep.ranges import axis_values

T = TypeVar("T")

KEYS = ("name", "description", "base", "overrides", "variants", "population", "paths", "axes", "seeds", "run",
        "metrics", "pass", "summary")
# Names the campaign gives its own axes; a config key cannot be one of them.
BUILTIN_AXES = ("base", "variant", "robot", "path", "seed")
MAX_CASES = 1_000_000
DEFAULT_TIMEOUT_S = 600.0
DEFAULT_SUMMARY_METRIC = "rms_cross_track_m"


class CampaignError(DdrtError, ValueError):
    """A campaign is malformed or one of its cases is invalid; the message names the file,
    the case where there is one, and the key."""


@dataclass(frozen=True)
class Axis:
    """One swept config key (dotted) and its values, in the file's order."""

    key: str
    values: tuple[Any, ...]


@dataclass(frozen=True)
class PopulationSpec(Section):
    """`population:`: `robots` robots drawn from `seed` by ddrt/sweep/population.py."""

    robots: int = setting(ge=1, doc="How many robots are drawn (an axis `robot`).")
    seed: int = setting(20261201, doc="The seed they are drawn from: the same seed, the same robots.")
    path_speed: bool = setting(True, doc="Each robot follows its path at its own drawn speed.")


@dataclass(frozen=True)
class RunSpec(Section):
    """`run:`: how long each case may run."""

    duration_s: float | None = setting(
        None, unit="s", gt=0, doc="Simulated time each case runs, as `ddrt sim --duration`; null: to the path's end.")
    timeout_s: float | None = setting(
        DEFAULT_TIMEOUT_S, unit="s", gt=0, doc="Wall time after which a case is stopped (status `timeout`); null: none.")


@dataclass(frozen=True)
class RunSettings:
    """How every case runs and what its row keeps."""

    duration_s: float | None = None  # as `ddrt sim --duration`; None: the path's end
    timeout_s: float | None = DEFAULT_TIMEOUT_S  # wall seconds; None: no limit
    metrics: tuple[str, ...] = NUMERIC_METRICS  # TEXT_METRICS are always kept
    criteria: tuple[Criterion, ...] = ()


@dataclass(frozen=True)
class Campaign:
    """A campaign file, checked: everything needed to expand its cases."""

    source: str  # the file, as named, for messages
    folder: FsPath  # where its relative file names start
    name: str = ""
    bases: tuple[FsPath, ...] = ()  # absolute
    base_labels: tuple[str, ...] = ()  # as written
    base_axis: bool = False  # given as a list: the axis (and column) `base`
    overrides: dict[str, Any] = field(default_factory=dict)
    variants: dict[str, dict[str, Any]] = field(default_factory=dict)
    population: PopulationSpec | None = None
    paths: dict[str, str | dict[str, Any]] = field(default_factory=dict)  # name -> absolute file or spec
    axes: tuple[Axis, ...] = ()
    seeds: tuple[int, ...] | None = None  # None: each config's own sim.seed
    run: RunSettings = RunSettings()
    summary_metrics: tuple[str, ...] = (DEFAULT_SUMMARY_METRIC,)


def load_campaign(path: str | FsPath) -> Campaign:
    """Read and check a campaign file."""
    p = FsPath(path)
    kind = file_kind(p)
    if kind not in ("a file", "missing"):  # a missing file: read_yaml's "cannot read" says so
        raise CampaignError(f"{p}: {kind}, not a campaign file")
    data = read_yaml(p, CampaignError)
    return campaign_from_mapping(data, source=str(p), folder=p.resolve().parent)


def campaign_from_mapping(data: Any, source: str = "<campaign>", folder: str | FsPath = ".") -> Campaign:
    """Check a campaign given as a mapping (a parsed file, or built in code by a benchmark)."""
    return _Reader(source, FsPath(folder).resolve()).campaign(data)


def file_kind(p: FsPath) -> str:
    """"a file" for a regular file, else what `p` is ("missing", "a directory", "a FIFO", ...),
    found by stat alone: opening a FIFO that nobody writes would block for ever."""
    try:
        mode = os.stat(p).st_mode
    except FileNotFoundError:
        return "missing"
    except (OSError, ValueError) as exc:  # ValueError: a name with a NUL byte
        why = (exc.strerror if isinstance(exc, OSError) else None) or exc
        return f"unreadable ({' '.join(str(why).split())})"
    return mode_kind(mode)


class _Reader:
    """Checks one campaign mapping key by key; every error names the source and the key."""

    def __init__(self, source: str, folder: FsPath) -> None:
        self.source = source
        self.folder = folder

    def fail(self, key: str, problem: str) -> CampaignError:
        return CampaignError(f"{self.source}: {key}: {problem}")

    def campaign(self, data: Any) -> Campaign:
        if data is None:
            raise CampaignError(f"{self.source}: the campaign is empty")
        if not isinstance(data, Mapping):
            raise CampaignError(f"{self.source}: the top level must be a mapping of campaign keys")
        other = not_a(data, CAMPAIGN, self.source, "a campaign")
        if other is not None:
            raise CampaignError(other)
        for key in data:
            if key not in KEYS:
                raise self.fail(str(key), f"unknown key (known: {', '.join(KEYS)})")
        bases, labels = self.bases(data.get("base"))
        population = self.population(data.get("population"))
        if not bases and population is None:
            raise self.fail("base", "missing: a config file (or a population: of robots) is required")
        axes = self.axes(data.get("axes"))
        metrics = self.metrics(data.get("metrics"))
        criteria = self.criteria(data.get("pass"))
        summary_metrics = self.summary(data.get("summary"), criteria)
        # What the criteria and the summary read is kept even when metrics: leaves it out.
        wanted = [c.metric for c in criteria] + list(summary_metrics)
        kept = metrics + tuple(dict.fromkeys(m for m in wanted if m not in metrics + TEXT_METRICS))
        camp = Campaign(
            source=self.source, folder=self.folder,
            name=self.text(data.get("name"), "name"),
            bases=bases, base_labels=labels, base_axis=isinstance(data.get("base"), list),
            overrides=self.config_keys(data.get("overrides"), "overrides"),
            variants=self.variants(data.get("variants")),
            population=population,
            paths=self.paths(data.get("paths")),
            axes=axes,
            seeds=self.seeds(data.get("seeds")),
            run=self.run(data.get("run"), kept, criteria),
            summary_metrics=summary_metrics,
        )
        self.text(data.get("description"), "description")
        if camp.seeds and any(axis.key == "sim.seed" for axis in camp.axes):
            raise self.fail("axes.sim.seed", "seeds: sets every case's sim.seed: sweep the seed with one or the other")
        self.count(camp)
        return camp

    # ----------------------------------------------------------------- single keys

    def text(self, value: Any, key: str) -> str:
        if value is None:
            return ""
        if not isinstance(value, str):
            raise self.fail(key, f"expected text, got {shorten(value)}")
        return value

    def mapping(self, value: Any, key: str) -> dict[str, Any]:
        if value is None:
            return {}
        if not isinstance(value, Mapping):
            raise self.fail(key, f"expected a mapping, got {shorten(value)}")
        return dict(value)

    def config_keys(self, value: Any, key: str) -> dict[str, Any]:
        """A mapping laid over a case's config. `extends:` names the file a config is read over,
        which is resolved before any of this is laid on: here it would do nothing, silently."""
        m = self.mapping(value, key)
        if "extends" in m:
            raise self.fail(f"{key}.extends", "a case's config is read from base: (a list of files makes "
                                              "them an axis); extends: here would be ignored")
        return m

    def file(self, value: Any, key: str) -> FsPath:
        if not isinstance(value, str) or not value:
            raise self.fail(key, f"expected a file name, got {shorten(value)}")
        p = self.folder / value
        kind = file_kind(p)
        if kind == "missing":
            raise self.fail(key, f"no such file {shorten(value)} (looked for {os.path.normpath(p)})")
        if kind != "a file":
            raise self.fail(key, f"{shorten(value)} is {kind}, not a file")
        return p.resolve()

    def bases(self, value: Any) -> tuple[tuple[FsPath, ...], tuple[str, ...]]:
        if value is None:
            return (), ()
        items = value if isinstance(value, list) else [value]
        if not items:
            raise self.fail("base", "the list of config files is empty")
        if isinstance(value, list) and len(set(map(str, items))) != len(items):
            raise self.fail("base", "a config file is listed twice")
        files = tuple(self.file(v, f"base[{i}]" if isinstance(value, list) else "base") for i, v in enumerate(items))
        return files, tuple(str(v) for v in items)

    def population(self, value: Any) -> PopulationSpec | None:
        if value is None:
            return None
        return self.section(PopulationSpec, value, "population")

    def section(self, cls: type[T], value: Any, key: str) -> T:
        """A section of the campaign read by the config's walker: its fields' declarations check it."""
        try:
            return build(cls, value, key)
        except ConfigError as exc:
            raise CampaignError(f"{self.source}: {exc}") from None

    def variants(self, value: Any) -> dict[str, dict[str, Any]]:
        m = self.mapping(value, "variants")
        if value is not None and not m:
            raise self.fail("variants", "empty: name at least one variant, or leave the key out")
        out = {}
        for name, over in m.items():
            if not isinstance(over, Mapping):
                raise self.fail(f"variants.{name}", f"expected a mapping of config keys, got {shorten(over)}")
            out[str(name)] = self.config_keys(over, f"variants.{name}")
        return out

    def paths(self, value: Any) -> dict[str, str | dict[str, Any]]:
        if value is None:
            return {}
        if isinstance(value, list):
            named = {}
            for i, item in enumerate(value):
                f = self.file(item, f"paths[{i}]")
                if f.stem in named:
                    raise self.fail(f"paths[{i}]", f"two paths named {f.stem!r}: give them names (a mapping)")
                named[f.stem] = str(f)
            if not named:
                raise self.fail("paths", "the list of paths is empty")
            return named
        m = self.mapping(value, "paths")
        if not m:
            raise self.fail("paths", "empty: name at least one path, or leave the key out")
        out: dict[str, str | dict[str, Any]] = {}
        for name, spec in m.items():
            if isinstance(spec, Mapping):
                spec = dict(spec)
                if isinstance(spec.get("file"), str):  # a CSV named by an inline spec: from this file's folder
                    spec["file"] = str(self.folder / spec["file"])
                out[str(name)] = spec
            else:
                out[str(name)] = str(self.file(spec, f"paths.{name}"))
        return out

    def seeds(self, value: Any) -> tuple[int, ...] | None:
        if value is None:
            return None
        if isinstance(value, int) and not isinstance(value, bool):
            if value < 1:
                raise self.fail("seeds", f"expected a count >= 1 (seeds 1..N) or a list of seeds, got {value}")
            if value > MAX_CASES:  # before the tuple is built: seeds: 10000000000 would exhaust the memory
                raise self.fail("seeds", f"{shorten(value)} seeds, more cases than {MAX_CASES}: split the campaign")
            return tuple(range(1, value + 1))
        if not isinstance(value, list) or not value:
            raise self.fail("seeds", f"expected a count (seeds 1..N) or a non-empty list of seeds, got {shorten(value)}")
        for i, s in enumerate(value):
            if isinstance(s, bool) or not isinstance(s, int):
                raise self.fail(f"seeds[{i}]", f"expected a whole number, got {shorten(s)}")
            if abs(s) > INT_LIMIT:  # the range of a config's sim.seed, and of the table's int64 column
                raise self.fail(f"seeds[{i}]", f"out of range (at most {INT_LIMIT} either way), got {shorten(s)}")
        if len(set(value)) != len(value):
            raise self.fail("seeds", "a seed is listed twice")
        return tuple(value)

    def run(self, value: Any, metrics: tuple[str, ...], criteria: tuple[Criterion, ...]) -> RunSettings:
        times = self.section(RunSpec, {} if value is None else value, "run")
        duration, timeout = times.duration_s, times.timeout_s
        if not criteria:  # as `ddrt sim`'s exit status: the path completed, or ran its duration without a fault
            criteria = (parse_criterion("fault == ''" if duration else "completed == true", "pass"),)
        return RunSettings(duration, timeout, metrics, criteria)

    def names(self, value: Any, key: str) -> tuple[str, ...]:
        if not isinstance(value, list) or not value:
            raise self.fail(key, f"expected a non-empty list of metric names, got {shorten(value)}")
        for i, name in enumerate(value):
            if name not in KNOWN_METRICS:
                raise self.fail(f"{key}[{i}]", f"unknown metric {shorten(name)} (known: {', '.join(KNOWN_METRICS)})")
        return tuple(dict.fromkeys(value))

    def metrics(self, value: Any) -> tuple[str, ...]:
        if value is None:
            return NUMERIC_METRICS
        return tuple(m for m in self.names(value, "metrics") if m not in TEXT_METRICS)

    def criteria(self, value: Any) -> tuple[Criterion, ...]:
        if value is None:
            return ()
        items = value if isinstance(value, list) else [value]
        if not items:
            raise self.fail("pass", "the list of criteria is empty: leave the key out for the default")
        try:
            return tuple(parse_criterion(c, f"pass[{i}]" if isinstance(value, list) else "pass")
                         for i, c in enumerate(items))
        except ValueError as exc:
            raise CampaignError(f"{self.source}: {exc}") from None

    def summary(self, value: Any, criteria: tuple[Criterion, ...]) -> tuple[str, ...]:
        m = self.mapping(value, "summary")
        for key in m:
            if key != "metrics":
                raise self.fail(f"summary.{key}", "unknown key (known: metrics)")
        if "metrics" in m:
            names = self.names(m["metrics"], "summary.metrics")
            bad = [n for n in names if n not in NUMERIC_METRICS or n == "completed"]
            if bad:
                raise self.fail("summary.metrics", f"{bad[0]} is not a number to take percentiles of")
            return names
        numbers = [c.metric for c in criteria if c.metric in NUMERIC_METRICS and c.metric != "completed"]
        return tuple(dict.fromkeys(numbers)) or (DEFAULT_SUMMARY_METRIC,)

    # ----------------------------------------------------------------- axes

    def axes(self, value: Any) -> tuple[Axis, ...]:
        m = self.mapping(value, "axes")
        if value is not None and not m:
            raise self.fail("axes", "empty: give at least one config key to sweep, or leave the key out")
        out = []
        for key, spec in m.items():
            where = f"axes.{key}"
            if not isinstance(key, str) or not key or any(not part for part in key.split(".")):
                raise self.fail(where, "expected a dotted config key, e.g. controller.outer.k_y")
            if key in BUILTIN_AXES or key.split(".")[0] in ("extends",):
                raise self.fail(where, f"not a config key to sweep: {key} has its own campaign key"
                                       + (" (paths:)" if key == "path" else " (base:)" if key == "extends" else ""))
            out.append(Axis(key, axis_values(spec, where, self.fail)))
        return tuple(out)

    def count(self, camp: Campaign) -> None:
        n = max(1, len(camp.bases)) * max(1, len(camp.variants)) * (camp.population.robots if camp.population else 1)
        n *= max(1, len(camp.paths)) * len(camp.seeds or (0,))
        for axis in camp.axes:
            n *= len(axis.values)
        if n > MAX_CASES:
            raise self.fail("axes", f"{n} cases, more than {MAX_CASES}: split the campaign")
