"""robot.estimate: the full parameters derived from a minimal description."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import pytest
import yaml

from ddrt.config import load_config
from ddrt.config.load import config_from_mapping
from ddrt.config.schema import ConfigError
from ddrt.params import estimate as est_mod
from ddrt.params.estimate import RobotEstimate, estimate_from_mapping
from ddrt.params.robot import RobotParams
from tests.support.repo import REPO, SIM_YAML

MINIMAL = REPO / "configs" / "sim-minimal.yaml"
ESTIMATE = {
    "mass_kg": 3.6, "track_m": 0.2156, "wheel_radius_m": 0.05,
    "encoder_wheel": {"x_m": 0.115, "radius_m": 0.052},
    "body": {"shape": "box", "length_m": 0.25, "width_m": 0.2},
}


def _derive(**over: Any) -> RobotParams:
    mapping = copy.deepcopy(ESTIMATE)
    body = over.pop("body", None)
    if body is not None:
        mapping["body"] = body
    mapping.update(over)
    return estimate_from_mapping(mapping).params()


def _data(robot: dict[str, Any], plant: dict[str, Any] | None = None) -> dict[str, Any]:
    data: dict[str, Any] = {"hal": {"backend": "sim"}, "robot": robot}
    if plant is not None:
        data["plant"] = plant
    return data


def test_total_mass_is_conserved() -> None:
    for mass in (0.5, 3.6, 40.0):
        p = _derive(mass_kg=mass)
        assert p.m_p + p.m_L + p.m_R + p.m_3 == pytest.approx(mass)
        assert min(p.m_p, p.m_L, p.m_R, p.m_3) > 0


def test_inertias_are_positive_and_follow_the_stated_formulas() -> None:
    p = _derive()
    for name in ("I_p", "I_L", "I_R", "I_3", "I_wL", "I_wR", "I_w3"):
        assert getattr(p, name) > 0
    assert p.I_p == pytest.approx(p.m_p * (0.25 ** 2 + 0.2 ** 2) / 12)  # uniform box about its centre
    cyl = _derive(body={"shape": "cylinder", "radius_m": 0.12})
    assert cyl.I_p == pytest.approx(cyl.m_p * 0.12 ** 2 / 2)  # uniform disc about its axis
    assert p.I_L == pytest.approx(p.m_L * 0.05 ** 2 / 4)
    assert p.I_w3 == pytest.approx(p.m_3 * 0.052 ** 2 / 2)


def test_box_inertia_obeys_the_parallel_axis_theorem() -> None:
    # A 0.3 x 0.2 box is two 0.15 x 0.2 halves, each at 0.075 m from the centre: about the
    # whole box's centre, each half's own inertia plus m d^2.
    whole = _derive(body={"shape": "box", "length_m": 0.3, "width_m": 0.2})
    half = _derive(body={"shape": "box", "length_m": 0.15, "width_m": 0.2})
    m_half = whole.m_p / 2
    assert half.m_p == pytest.approx(whole.m_p)
    assert whole.I_p == pytest.approx(2 * (half.I_p / 2 + m_half * 0.075 ** 2))


def test_a_centred_body_is_mirror_symmetric_and_an_offset_one_mirrors() -> None:
    p = _derive()
    assert p == p.mirrored()
    assert p.L == p.R == pytest.approx(0.2156 / 2)
    assert p.d_yc == 0.0
    left = _derive(body={**ESTIMATE["body"], "y_m": 0.01})
    right = _derive(body={**ESTIMATE["body"], "y_m": -0.01})
    assert left.mirrored() == right


def test_body_centre_defaults_to_midway_between_axle_and_encoder_wheel() -> None:
    assert _derive().d_xc == pytest.approx(0.115 / 2)
    assert _derive(body={**ESTIMATE["body"], "x_m": -0.01}).d_xc == pytest.approx(-0.01)


def test_sim_minimal_is_close_to_the_seed_robot() -> None:
    minimal, full = load_config(MINIMAL), load_config(SIM_YAML)
    assert minimal.plant == full.plant and minimal.robot_motor == full.robot_motor
    a, b = minimal.robot, full.robot
    mass = lambda p: p.m_p + p.m_L + p.m_R + p.m_3  # noqa: E731
    assert mass(a) == pytest.approx(mass(b))
    for name in ("H", "L", "R", "r_L", "r_R", "r_3"):
        assert getattr(a, name) == pytest.approx(getattr(b, name))
    assert a.d_xc == pytest.approx(b.d_xc, abs=0.005)
    for name in ("m_p", "m_L", "m_R", "m_3", "I_p", "I_L", "I_R", "I_3", "I_wL", "I_wR", "I_w3"):
        ratio = getattr(a, name) / getattr(b, name)
        assert 0.5 <= ratio <= 2.0, (name, ratio)


def test_sim_minimal_runs_in_ddrt_sim(tmp_path: Path) -> None:
    from ddrt.cli import main
    assert main(["sim", str(MINIMAL), "--out", str(tmp_path), "--quiet"]) == 0
    assert (tmp_path / "metrics.json").is_file()


def test_estimate_and_explicit_keys_are_exclusive() -> None:
    full = yaml.safe_load(SIM_YAML.read_text())["robot"]
    with pytest.raises(ConfigError) as err:
        config_from_mapping(_data({**full, "estimate": ESTIMATE}), source="my.yaml")
    text = str(err.value)
    assert text.startswith("my.yaml: robot:") and "estimate:" in text and "m_p" in text and "I_w3" in text


def test_every_bad_or_missing_estimate_key_in_one_error() -> None:
    bad = {"mass_kg": -1, "wheel_radius_m": "big", "encoder_wheel": {"x_m": 0.1},
           "body": {"shape": "box", "length_m": 0.2}, "colour": "red"}
    with pytest.raises(ConfigError) as err:
        config_from_mapping(_data({"estimate": bad}), source="my.yaml")
    text = str(err.value)
    assert text.startswith("my.yaml: ")
    for key in ("robot.estimate.mass_kg: must be > 0", "robot.estimate.wheel_radius_m", "robot.estimate.track_m: missing",
                "robot.estimate.encoder_wheel.radius_m: missing", "robot.estimate.body.width_m: missing",
                "robot.estimate.colour: unknown"):
        assert key in text, key


def test_a_body_shape_takes_only_its_own_dimensions() -> None:
    with pytest.raises(ConfigError, match=r"robot.estimate.body.shape: must be one of box, cylinder"):
        config_from_mapping(_data({"estimate": {**ESTIMATE, "body": {"shape": "sphere", "radius_m": 0.1}}}))
    with pytest.raises(ConfigError, match=r"robot.estimate.body.radius_m: not a box's dimension"):
        config_from_mapping(_data({"estimate": {**ESTIMATE, "body": {**ESTIMATE["body"], "radius_m": 0.1}}}))


def test_plant_over_an_estimated_robot() -> None:
    # Explicit plant keys override what robot:'s estimate derived; a plant estimate: merges
    # over robot:'s and replaces its explicit parameters.
    cfg = config_from_mapping(_data({"estimate": ESTIMATE}, {"m_p": 2.0}))
    assert cfg.plant.m_p == 2.0 and cfg.plant.I_p == cfg.robot.I_p
    cfg = config_from_mapping(_data({"estimate": ESTIMATE}, {"estimate": {"mass_kg": 4.0}}))
    assert cfg.plant.m_p + cfg.plant.m_L + cfg.plant.m_R + cfg.plant.m_3 == pytest.approx(4.0)
    full = yaml.safe_load(SIM_YAML.read_text())["robot"]
    cfg = config_from_mapping(_data(full, {"estimate": ESTIMATE}))
    assert cfg.plant == RobotEstimate(3.6, 0.2156, 0.05, 0.115, 0.052, "box", 0.25, 0.2).params()
    with pytest.raises(ConfigError, match=r"plant: give either estimate: or the full parameters"):
        config_from_mapping(_data(full, {"estimate": ESTIMATE, "H": 0.1}))


def test_the_assumptions_are_stated_constants() -> None:
    assert 0 < 2 * est_mod.DRIVE_WHEEL_FRACTION + est_mod.ENCODER_WHEEL_FRACTION < 1
    assert "DRIVE_WHEEL_FRACTION" in est_mod.__doc__
