"""The commissioning run's memory: each finished step's result in one JSON file, so a run
stopped part way (Ctrl-C, a wrong measurement, a flat battery) resumes where it stopped,
and `--step NAME` re-runs one step over the others' results."""

from __future__ import annotations

import json
import math
import os
import time
from pathlib import Path
from typing import Any

from ddrt.config.textfile import read_state_text
from ddrt.errors import DdrtError


class StateError(DdrtError, ValueError):
    """The state file cannot be read as a commissioning state."""


def _finite(value: Any) -> Any:
    """JSON has no NaN: non-finite floats are stored as null."""
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


class State:
    """Step name -> its result (a JSON mapping with the time it finished)."""

    def __init__(self, path: Path, config: str, digest: str = "") -> None:
        self.path = path
        self.config = config
        self.digest = digest  # of the input config's content: a stored step of another content is stale
        self.stored_digest = digest
        self.steps: dict[str, dict[str, Any]] = {}
        if path.exists():
            try:
                data = json.loads(read_state_text(path, ValueError))
            except (OSError, ValueError) as exc:
                raise StateError(f"{path}: not a commissioning state ({exc}); remove it to start over") from None
            if not isinstance(data, dict) or not isinstance(data.get("steps"), dict):
                raise StateError(f"{path}: not a commissioning state (no steps:); remove it to start over")
            if data.get("config") != config:
                raise StateError(f"{path}: belongs to the commissioning of {data.get('config')!r}, not {config!r}; "
                                 "give another --out or remove it")
            self.steps = data["steps"]
            self.stored_digest = str(data.get("digest", ""))

    def done(self, step: str) -> bool:
        return step in self.steps

    def get(self, step: str) -> dict[str, Any] | None:
        return self.steps.get(step)

    def put(self, step: str, result: dict[str, Any]) -> None:
        """Store a finished step's result and write the file (atomically: a crash keeps the old)."""
        self.steps[step] = dict(_finite(result), finished=time.strftime("%Y-%m-%d %H:%M:%S %Z"))
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_suffix(".tmp")
        tmp.write_text(json.dumps({"config": self.config, "digest": self.digest, "steps": self.steps}, indent=2, sort_keys=True) + "\n",
                       encoding="utf-8")
        os.replace(tmp, self.path)

    @property
    def stale(self) -> bool:
        """The input config changed since the stored steps ran."""
        return bool(self.steps) and self.stored_digest != self.digest
