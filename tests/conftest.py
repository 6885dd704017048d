"""Fixtures every test module may use. The helpers behind them, and the ones a test imports
itself, are in tests/support/ (`from tests.support.<module> import ...`)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from ddrt.config import Config, load_config
from tests.support.daemon import DaemonProc, ready_daemon
from tests.support.repo import REPO, SIM_YAML


@pytest.fixture(scope="session")
def repo_root() -> Path:
    """The repository's root directory."""
    return REPO


@pytest.fixture(scope="session")
def sim_yaml() -> Path:
    """configs/sim.yaml: the seed report's robot on the simulated backend."""
    return SIM_YAML


@pytest.fixture(scope="session")
def sim_config() -> Config:
    """configs/sim.yaml loaded; shared, as a Config is frozen."""
    return load_config(SIM_YAML)


@pytest.fixture(scope="module")
def module_daemon(request: pytest.FixtureRequest) -> Iterator[DaemonProc]:
    """One `ddrt run` past its calibration for the whole test module, on configs/sim.yaml plus
    the module's DAEMON_SECTIONS (config sections, as `start_daemon` takes them); closed after
    the module's last test."""
    with ready_daemon(**getattr(request.module, "DAEMON_SECTIONS", {})) as d:
        yield d
