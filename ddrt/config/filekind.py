"""Which of ddrt's YAML files a mapping is (a config, a path file, a sweep campaign, a
commissioning answers file), told from its top-level keys, so that a file given to the
wrong command is named as what it is, with the command that takes it, rather than
refused key by key.

The kinds' keys are listed here, not imported: the config package sits below the path
loader, the sweep and the commissioning (tests/test_file_kind.py holds the lists equal to
those modules' own).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

__all__ = ["FileKind", "CONFIG", "PATH", "CAMPAIGN", "ANSWERS", "kind_of", "not_a"]


@dataclass(frozen=True)
class FileKind:
    """A kind of file: what to call it, and how it is used (`FILE` stands for its name)."""

    name: str
    usage: str

    def sentence(self, fname: str, what: str) -> str:
        """"FILE: this is a path file, not a config: give it with ..." """
        return f"{fname}: this is {self.name}, not {what}: {self.usage.replace('FILE', fname)}"


CONFIG = FileKind("a config", "run it with `ddrt sim FILE` (or `ddrt run FILE`), or name it in a campaign's base:")
PATH = FileKind("a path file", "give it with `ddrt sim CONFIG --path FILE`, look at it with `ddrt path FILE`, "
                               "follow it with `ddrt ctl follow FILE`, or name it in a config's path:")
CAMPAIGN = FileKind("a sweep campaign", "run it with `ddrt sweep FILE --out DIR`")
ANSWERS = FileKind("a commissioning answers file", "give it with `ddrt commission CONFIG --answers FILE`")

# A path spec names exactly one of these (ddrt/path/spec.py).
PATH_KEYS = frozenset({"shape", "points", "file"})
# A campaign's keys (ddrt/sweep/campaign.py KEYS); `name`, `description` and `paths` are a config's too.
CAMPAIGN_KEYS = frozenset({"name", "description", "base", "overrides", "variants", "population", "paths", "axes",
                           "seeds", "run", "metrics", "pass", "summary"})
# An answers file's sections (ddrt/commission/answers.py KEYS).
ANSWER_SECTIONS = frozenset({"wiring", "battery", "odometry", "check"})
# A config's sections that no other kind of file has (ddrt/config/load.py TOP_KEYS).
CONFIG_SECTIONS = frozenset({"extends", "robot", "plant", "sim", "sensors", "hal", "controller", "estimator",
                             "pursuit", "limits", "daemon", "drive"})


def kind_of(data: Any) -> FileKind | None:
    """The kind of file whose top level `data` is, or None when it looks like none of them."""
    if not isinstance(data, Mapping) or not data:
        return None
    keys = {k for k in data if isinstance(k, str)}
    campaign_only = keys & (CAMPAIGN_KEYS - {"name", "description", "paths"})
    if keys & CONFIG_SECTIONS and not campaign_only:
        return CONFIG
    if keys & PATH_KEYS:
        return PATH
    if keys and keys <= ANSWER_SECTIONS:
        return ANSWERS
    if campaign_only:
        return CAMPAIGN
    return None


def not_a(data: Any, expected: FileKind, fname: str, what: str) -> str | None:
    """The message for a file given where `expected` was, when it is plainly another kind;
    `what` is how the command calls what it wanted ("a config", "a path file")."""
    kind = kind_of(data)
    if kind is None or kind == expected:
        return None
    return kind.sentence(fname, what)
