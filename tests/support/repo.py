"""Where the repository is, for tests that read its configs, docs and sources, or run a child
process in it; and configs/sim.yaml, the config nearly every test starts from."""

from __future__ import annotations

from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
SIM_YAML = REPO / "configs" / "sim.yaml"
