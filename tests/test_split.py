"""ddrt/core/split.py: an identified lumped model split into the platform's parameters, held
physical when the exact split is not."""

from __future__ import annotations

import dataclasses
import math
import random

import numpy as np
import pytest

from ddrt import calibrate as cal
from ddrt.config import load_config
from ddrt.core.model import Dynamics
from ddrt.params.robot import RobotParams
from ddrt.core.split import LUMPED, bounds, lumped_of, physical_split
from tests.support.repo import REPO

COULOMB = 0.03


def _robot() -> RobotParams:
    return load_config(REPO / "configs" / "sim.yaml").robot


def _regression(theta: np.ndarray, seed: int = 1, rows: int = 400, noise: float = 0.01) -> cal.IdentifyResult:
    """An identification's fit of rows drawn around the model `theta` (LUMPED order)."""
    rng = np.random.default_rng(seed)
    scale = np.array([1.0, 1.0, 10.0, 1.0, 20.0, 20.0])  # regressors of different sizes, as a run gives
    phi = rng.normal(size=(rows, 6)) * scale
    y = phi @ theta + rng.normal(scale=noise, size=rows)
    return cal.fit([(list(r), float(v)) for r, v in zip(phi, y)], 30.0, (2.0, 1.5))


def _cost(p: RobotParams, res: cal.IdentifyResult, q: np.ndarray) -> float:
    e = lumped_of(p, q) - np.array([res.values[k] for k in LUMPED])
    return float(e @ res.normal @ e)


def _inside(p: RobotParams, q: np.ndarray) -> bool:
    b = bounds(p, COULOMB)
    names = ("m_p", "d_xc", "d_yc", "I_p", "fric_l", "fric_r")
    return all(b.lower[k] <= v <= b.upper[k] for k, v in zip(names, q))


def _true_theta(p: RobotParams, **platform: float) -> np.ndarray:
    q = dict(m_p=p.m_p, d_xc=p.d_xc, d_yc=p.d_yc, I_p=p.I_p, fric_l=0.002, fric_r=-0.001)
    q.update(platform)
    return lumped_of(p, [q[k] for k in ("m_p", "d_xc", "d_yc", "I_p", "fric_l", "fric_r")])


def _q(split) -> np.ndarray:
    return np.array([*split.platform.values(), *split.friction.values()])


def test_a_feasible_split_is_the_exact_one_unchanged() -> None:
    p = _robot()
    res = _regression(_true_theta(p, m_p=0.9, d_xc=0.03, I_p=0.008))
    split = physical_split(p, COULOMB, res.values, res.normal, res.std_err)
    assert split.held == []
    assert split.lumped == {k: res.values[k] for k in LUMPED}  # the fit itself, not a refit
    dyn = Dynamics.from_params(dataclasses.replace(p, **split.platform))
    for k in ("m_k", "mbar", "I", "m_x"):
        assert getattr(dyn, k) == pytest.approx(res.values[k], rel=1e-12, abs=1e-15), k
    assert split.platform["m_p"] == pytest.approx(0.9, rel=0.01)


def test_no_platform_inertia_is_held_physical_and_named() -> None:
    """The wheels configured three times as heavy in yaw as the run says: I_p < 0 unconstrained."""
    p = _robot()
    heavy = dataclasses.replace(p, I_L=3 * p.I_L + 0.004, I_R=3 * p.I_R + 0.004)
    res = _regression(_true_theta(p))
    assert res.values["I"] < Dynamics.from_params(dataclasses.replace(heavy, I_p=1e-9, d_xc=0.0, d_yc=0.0)).I
    split = physical_split(heavy, COULOMB, res.values, res.normal, res.std_err)
    assert [h.name for h in split.held] == ["I_p"]
    assert split.held[0].unconstrained is not None and split.held[0].unconstrained < 0.0
    assert split.platform["I_p"] > 0.0 and split.platform["m_p"] > 0.0
    RobotParams(**dict(dataclasses.asdict(heavy), **split.platform))  # validates
    # the mass the run separates well is kept; the yaw inertia is the least the configured wheels allow
    assert split.lumped["m_k"] == pytest.approx(res.values["m_k"], rel=1e-3)
    assert split.platform["I_p"] == pytest.approx(bounds(heavy, COULOMB).lower["I_p"])
    assert split.lumped["I"] > res.values["I"]
    assert "I_p" in "\n".join(cal.held_lines(split))


@pytest.mark.parametrize("what, name", [("mass", "m_p"), ("centre", "d_xc"), ("side", "d_yc"),
                                        ("friction", "fric_l")])
def test_each_impossible_split_names_its_parameter(what: str, name: str) -> None:
    p = _robot()
    theta = _true_theta(p)
    if what == "mass":  # the wheels configured heavier than the whole robot weighs
        p = dataclasses.replace(p, m_L=p.m_L + 0.6, m_R=p.m_R + 0.6)
    elif what == "centre":  # the platform's moment far beyond the front wheel
        theta[3] += 2.0 * p.m_p * p.H
    elif what == "side":
        theta[1] -= 2.0 * p.m_p * p.L
    else:
        theta[4] = -3.0 * COULOMB
    res = _regression(theta)
    split = physical_split(p, COULOMB, res.values, res.normal, res.std_err)
    assert name in [h.name for h in split.held]
    assert _inside(p, _q(split)) and split.platform["m_p"] > 0.0 and split.platform["I_p"] > 0.0


@pytest.mark.parametrize("seed", range(40))
def test_fuzz_the_split_is_physical_and_no_physical_split_fits_better(seed: int) -> None:
    """Random robots and random models, physical or not: the split stays inside the bounds, gives
    the model it says it gives, and fits the run at least as well as any physical point drawn."""
    rng = random.Random(seed)
    p = _robot()
    p = dataclasses.replace(p, **{k: getattr(p, k) * rng.uniform(0.5, 2.0)
                                  for k in ("m_p", "m_L", "m_R", "m_3", "I_p", "I_L", "I_R", "I_3")})
    theta = _true_theta(_robot(), m_p=rng.uniform(-0.5, 2.0), d_xc=rng.uniform(-0.3, 0.3),
                        d_yc=rng.uniform(-0.2, 0.2), I_p=rng.uniform(-0.01, 0.02),
                        fric_l=rng.uniform(-0.06, 0.03), fric_r=rng.uniform(-0.06, 0.03))
    res = _regression(theta, seed=seed, noise=rng.choice((0.001, 0.05)))
    split = physical_split(p, COULOMB, res.values, res.normal, res.std_err)
    q = _q(split)
    assert _inside(p, q) and all(math.isfinite(v) for v in q)
    assert np.allclose(lumped_of(p, q), [split.lumped[k] for k in LUMPED])
    if not split.held:
        assert split.lumped == {k: res.values[k] for k in LUMPED}
        return
    best = _cost(p, res, q)
    b = bounds(p, COULOMB)
    names = ("m_p", "d_xc", "d_yc", "I_p", "fric_l", "fric_r")
    for _ in range(300):  # random physical points, and points near the one found
        near = rng.random() < 0.5
        trial = np.array([(min(max(v * rng.uniform(0.9, 1.1) + rng.gauss(0, 1e-4), b.lower[k]), b.upper[k])
                           if near else rng.uniform(b.lower[k], min(b.upper[k], b.lower[k] + 3.0 * abs(v) + 0.05)))
                          for k, v in zip(names, q)])
        assert _cost(p, res, trial) >= best * (1 - 1e-9) - 1e-12


def test_without_a_normal_matrix_the_standard_errors_weigh() -> None:
    p = _robot()
    heavy = dataclasses.replace(p, I_L=3 * p.I_L + 0.004, I_R=3 * p.I_R + 0.004)
    res = _regression(_true_theta(p))
    split = physical_split(heavy, COULOMB, res.values, None, res.std_err)
    assert [h.name for h in split.held] == ["I_p"] and split.platform["I_p"] > 0.0


def test_a_non_finite_fit_is_a_clear_error() -> None:
    p = _robot()
    values = dict(zip(LUMPED, [float("nan")] + [0.0] * 5))
    with pytest.raises(ValueError, match="not finite"):
        physical_split(p, COULOMB, values, None, None)


def test_identify_fragment_says_what_it_held(tmp_path) -> None:
    p = _robot()
    res = _regression(_true_theta(p))
    cfg = load_config(REPO / "configs" / "sim.yaml")
    heavy = dataclasses.replace(cfg, robot=dataclasses.replace(cfg.robot, I_L=3 * p.I_L + 0.004,
                                                               I_R=3 * p.I_R + 0.004))
    text = cal.identify_fragment(heavy, res)
    assert "physically impossible" in text and "I_p" in text.split("physically impossible")[1]
    import yaml

    frag = yaml.safe_load(text)["robot"]
    assert frag["I_p"] > 0.0 and frag["motor"]["coulomb_nm"] >= 0.0
