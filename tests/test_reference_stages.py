"""Every reference stage is a ddrt.core.reference.Reference: the loop calls the same members on
each, so none may be missing, and only a path's own reference resumes after a hold."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from ddrt.calibrate import SpinReference
from ddrt.config import load_config
from ddrt.core.drive import DriveReference
from ddrt.core.reference import Reference
from ddrt.core.types import Setpoint
from ddrt.path.reference import PathReference
from ddrt.path.spec import load_path, speed_limits
from ddrt.path.start import StartReference

SIM_YAML = Path(__file__).resolve().parents[1] / "configs" / "sim.yaml"
PERIOD = 0.005


def _stages() -> dict[str, Reference]:
    cfg = load_config(SIM_YAML)
    path = load_path({"shape": "line", "length": 1.0, "speed": 0.3}, speed_limits(cfg), paths=cfg.paths)
    on_path = PathReference(path, 0.05, 0.5, PERIOD)
    timed = PathReference(path, 0.05, 0.5, PERIOD, time_indexed=True)
    start = StartReference(PathReference(path, 0.05, 0.5, PERIOD), (0.0, 0.1, math.pi / 2), path.limits, PERIOD,
                           turn=True, join=True, y_cap=0.02)
    drive = DriveReference(cfg.limits, cfg.drive, 0.5, PERIOD)
    spin = SpinReference((0.0, 0.0, 0.0), math.pi, 1.0, 3.0, PERIOD)
    return {"path": on_path, "time-indexed": timed, "start": start, "drive": drive, "spin": spin}


STAGES = _stages()


@pytest.mark.parametrize("name", sorted(STAGES))
def test_each_stage_has_every_member_the_loop_uses(name: str) -> None:
    ref = STAGES[name]
    assert isinstance(ref, Reference)
    sp = Setpoint()
    ref.update(0.0, 0.0, 0.0, sp, PERIOD)
    assert sp.active
    for value in (ref.sigma, ref.cross_track):
        assert isinstance(value, float) and math.isfinite(value)
    assert isinstance(ref.done, bool) and ref.stopping is False
    assert ref.phase == {"path": "follow", "time-indexed": "follow", "start": "turn", "drive": "drive",
                         "spin": "turn"}[name]


@pytest.mark.parametrize("name", sorted(STAGES))
def test_a_paths_reference_and_its_start_resume_the_others_do_not(name: str) -> None:
    ref = _stages()[name]
    if name in ("path", "time-indexed", "start"):
        assert ref.resumable
        ref.request_stop(1.0)
        assert ref.stopping
        ref.resume(0.0, 0.0, 0.0)
        assert not ref.stopping and not ref.done
    else:
        assert not ref.resumable
        with pytest.raises(ValueError, match="not resumed"):
            ref.resume(0.0, 0.0, 0.0)
