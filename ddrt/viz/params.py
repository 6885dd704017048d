"""The gains as Foxglove parameters: named by their config keys, derived from the schema.

A parameter is every numeric leaf under `controller.` that the reload policy applies live
(ddrt.config.policy.leaf_modes), so a gain added to the config is a parameter without a
list to keep. Setting parameters is a reload of those keys: `plan_for` builds the config
with them and plans it exactly as a reload would (ddrt.config.policy.plan_reload), so an
invalid value, a wrong type or an unknown name refuses the whole set.
"""

from __future__ import annotations

from typing import Any, Mapping

from ddrt.config import Config, ConfigError, with_overrides
from ddrt.config.policy import ReloadPlan, leaf_modes, plan_reload, value_at
from ddrt.config.schema import LIVE

PREFIX = "controller."


def gain_keys(cfg: Config) -> tuple[str, ...]:
    """Every live, numeric controller setting (dotted config keys)."""
    return tuple(key for key, mode in leaf_modes(cfg)
                 if mode == LIVE and key.startswith(PREFIX) and _number(value_at(cfg, key)))


def _number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def values(cfg: Config, keys: tuple[str, ...]) -> dict[str, float]:
    return {k: float(value_at(cfg, k)) for k in keys}


def overrides_for(changes: Mapping[str, Any], keys: tuple[str, ...]) -> dict[str, Any]:
    """{dotted key: value} as the nested mapping a config file would have; unknown names refused."""
    nested: dict[str, Any] = {}
    for name, value in changes.items():
        if name not in keys:
            raise ConfigError(f"{name}: not a gain parameter (known: {', '.join(keys)})")
        node = nested
        parts = name.split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = value
    return nested


def plan_for(cfg: Config, changes: Mapping[str, Any], keys: tuple[str, ...]) -> ReloadPlan:
    """The reload plan that puts `changes` in force over `cfg`, or ConfigError naming the key."""
    if not changes:
        raise ConfigError("no parameters given")
    return plan_reload(cfg, with_overrides(cfg, overrides_for(changes, keys)))
