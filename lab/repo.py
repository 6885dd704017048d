"""Where the repository is, for inputs that read its configs; and configs/sim.yaml."""

from __future__ import annotations

from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SIM_YAML = REPO / "configs" / "sim.yaml"
