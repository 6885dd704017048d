"""Recorded paths noisier than a fixed 10 mm tolerance can hold, a narrow recorded U-turn, and one
reversal rule for every kind of input; the fuzz over all of them is tests/test_recorded_fuzz.py."""

from __future__ import annotations

import math
import re
from pathlib import Path as FsPath

import numpy as np
import pytest

from ddrt.config import load_config
from ddrt.config.schema import ConfigError, build
from ddrt.config.sections import PathsConfig
from ddrt.path import PathError, load_path
from ddrt.path.report import path_report, pivot_runs
from ddrt.path.spec import speed_limits
from ddrt.simrun.runner import run_sim

ROOT = FsPath(__file__).resolve().parents[1]
CFG = load_config(ROOT / "configs" / "sim.yaml")
LIM = speed_limits(CFG)


def _arc(radius: float, length: float, spacing: float, noise: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    phi = np.linspace(0.0, length / radius, int(round(length / spacing)) + 1)
    xy = np.column_stack((radius * np.sin(phi), radius - radius * np.cos(phi)))
    return xy + rng.normal(0.0, noise, xy.shape)


def _load(xy: np.ndarray, speed: float = 1.0, tolerance: float | str | None = None):
    spec: dict = {"points": xy.tolist(), "speed": speed}
    if tolerance is not None:
        spec["tolerance"] = tolerance
    return load_path(spec, LIM, paths=CFG.paths)


def _kappa_off_pivots(path) -> np.ndarray:
    a = path.arrays()
    return np.abs(a["kappa"][:-1][~np.asarray(path.seg_pivot)])


def _turns_deg(path) -> list[float]:
    return [math.degrees(t) for *_, t in path_report(path, "path").pivots]


# --------------------------------------------------------------------------- 1. noise


def test_the_noise_is_estimated_without_the_curves_bending() -> None:
    """A planner's path at 10 cm spacing with +-4 mm of jitter (2.3 mm RMS across the curve):
    the curvature between the sparse points must not count as noise (counted, it reads as
    29-34 mm)."""
    rng = np.random.default_rng(5)
    s = np.arange(0.0, 4.0001, 0.1)
    xy = np.column_stack((s, 0.5 * np.sin(2.0 * s))) + rng.uniform(-0.004, 0.004, (len(s), 2))
    assert 1.6e-3 < _load(xy).conditioning.noise_m < 3.2e-3
    # Noise larger than the spacing is measured over a stretch where the curve shows through.
    for seed in (1, 2, 3):
        assert _load(_arc(1.0, 1.5, 0.005, 0.008, seed)).conditioning.noise_m == pytest.approx(0.008, rel=0.15)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_auto_sets_the_tolerance_from_the_noise(seed: int) -> None:
    """A GNSS/RTK-like recording (a gentle 2 m arc, 5 cm spacing, 15 mm of noise): the tolerance
    comes from the noise, not a fixed 10 mm, which can only be met by chasing the noise
    (curvature 84 /m, 14.7 s for what takes 3 s)."""
    assert PathsConfig().tolerance_m == "auto"
    path = _load(_arc(3.0, 2.0, 0.05, 0.015, seed))
    c = path.conditioning
    assert c.auto and c.tolerance_m >= 3.0 * c.noise_m and c.tolerance_m >= 0.01
    assert path.duration < 4.0
    assert _kappa_off_pivots(path).max() < 3.0 and not pivot_runs(path)
    assert "auto, from the noise" in c.summary()
    # A number stays a number; `auto` is accepted as a path's own tolerance too.
    assert _load(_arc(3.0, 2.0, 0.05, 0.015, seed), tolerance=0.05).conditioning.tolerance_m == 0.05
    assert _load(_arc(3.0, 2.0, 0.05, 0.015, seed), tolerance="auto").conditioning.auto


def test_auto_never_goes_below_its_floor_and_numbers_stay_accepted() -> None:
    exact = _load(_arc(1.0, 2.0, 0.01, 0.0, 1))
    assert exact.conditioning.tolerance_m == 0.01
    assert build(PathsConfig, {"tolerance_m": 0.02}).tolerance_m == 0.02
    assert build(PathsConfig, {"tolerance_m": "auto"}).tolerance_m == "auto"
    with pytest.raises(ConfigError, match="tolerance_m"):
        build(PathsConfig, {"tolerance_m": "loose"})


def test_a_tolerance_too_tight_for_the_noise_is_refused_with_one_that_works() -> None:
    """5 mm on 3 mm of noise can only be met by following the noise (curvature 282-1210 /m, the
    robot at 0.02 m/s), so it is refused, naming a tolerance that works; that one loads smooth."""
    xy = _arc(1.0, 2.0, 0.01, 0.003, 1)
    with pytest.raises(PathError) as exc:
        _load(xy, tolerance=0.005)
    msg = str(exc.value)
    found = re.search(r"a tolerance of ([0-9.]+) m would work", msg)
    assert found and "noise (~" in msg and "key 'points[" in msg, msg
    path = _load(xy, tolerance=float(found.group(1)))
    assert _kappa_off_pivots(path).max() < 5.0 and path.duration < 1.3 * 2.0 + 3.0


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_noisy_arc_is_never_a_reversal(seed: int) -> None:
    """8 mm of noise at 5 mm spacing: the arc must load, not be read as a reversal (`the path
    reverses here (it turns 174 degrees)`), at 0.05 m too."""
    xy = _arc(1.0, 1.5, 0.005, 0.008, seed)
    for tolerance in (None, 0.05):
        path = _load(xy, tolerance=tolerance)
        assert not pivot_runs(path)
        assert path.duration < 1.3 * 1.5 / 1.0 + 3.0


# --------------------------------------------------------------------------- 2. a narrow U-turn


def _u_turn(seed: int, gap: float = 0.02) -> np.ndarray:
    """Legs of 1 m, `gap` apart, recorded every 1 cm with 1.5 mm of noise."""
    rng = np.random.default_rng(seed)
    leg = np.arange(0.0, 1.0, 0.01)
    r = 0.5 * gap
    phi = np.linspace(-0.5 * math.pi, 0.5 * math.pi, 5)[1:-1]
    xy = np.vstack((np.column_stack((leg, np.zeros_like(leg))),
                    np.column_stack((1.0 + r * np.cos(phi), r + r * np.sin(phi))),
                    np.column_stack((leg[::-1], np.full_like(leg, gap)))))
    return xy + rng.normal(0.0, 0.0015, xy.shape)


@pytest.mark.parametrize("seed", [1, 2, 3, 4])
def test_a_narrow_recorded_u_turn_is_two_clean_legs_and_one_turn(seed: int) -> None:
    """Legs 2 cm apart: the whole half turn is turned in place (one turn, or a quarter turn onto
    the 2 cm between the legs and one off it) and each leg is straight, not 126-139 degrees
    turned in place and the rest hooked round (up to 23 /m) with the return leg keeping the
    recording's noise."""
    path = _load(_u_turn(seed), speed=0.5)
    turns = _turns_deg(path)
    assert 1 <= len(turns) <= 2 and abs(abs(sum(turns)) - 180.0) < 5.0, turns
    assert len({math.copysign(1.0, t) for t in turns}) == 1, turns
    k = _kappa_off_pivots(path)
    assert k.max() < 1.0 and float(np.sqrt(np.mean(k ** 2))) < 0.1
    legs = 2.0 * (1.0 / 0.5 + 0.5 / CFG.limits.accel)  # each leg from rest to rest at 0.5 m/s
    assert path.duration < legs + 2.0  # and the half turn


def test_a_narrow_recorded_u_turn_is_driven_in_the_time_of_its_legs_and_turn() -> None:
    path = _load(_u_turn(1), speed=0.5)
    m = run_sim(CFG, path, seed=1).metrics
    assert m["completed"] and m["sim_duration_s"] < 1.3 * 2.03 / 0.5 + 3.0


# --------------------------------------------------------------------------- 3. one reversal rule


def test_one_reversal_rule_for_waypoints_and_samples() -> None:
    """Main turned waypoints 0 -> 1 -> 0 m round in place but refused a dense 160 degree V as a
    reversal. Both are turns in place now; marked with a negative v, a cusp (test_reverse.py)."""
    wp = load_path({"points": [[0.0, 0.0], [1.0, 0.0], [0.0, 0.0]]}, LIM, paths=CFG.paths)
    assert [round(abs(t)) for t in _turns_deg(wp)] == [180]
    s = np.arange(0.0, 1.0, 0.01)
    back = np.radians(160.0)
    v = np.vstack((np.column_stack((s, 0.0 * s)), [[1.0, 0.0]],
                   np.array([1.0, 0.0]) + np.column_stack((np.cos(back) * s[1:], np.sin(back) * s[1:]))))
    path = _load(v, speed=0.5)
    assert path.conditioning.mode == "samples"
    (turn,) = _turns_deg(path)
    assert turn == pytest.approx(160.0, abs=2.0)


def test_the_command_reference_and_config_md_state_the_rule() -> None:
    commands = " ".join((ROOT / "docs" / "commands.md").read_text(encoding="utf-8").split())
    assert ("a reversal the file does not mark (the direction turns back, up to 180 degrees) is a turn in place"
            in commands)
    config = " ".join((ROOT / "docs" / "config.md").read_text(encoding="utf-8").split())
    assert "**Reversals: one rule for every input.**" in config
    assert "is a turn in place where the file does not mark it" in config
