"""A file given to the command that does not take it is named as what it is (a path file, a
campaign, a commissioning answers file, a config), with the command that takes it."""

from __future__ import annotations

import pytest

from ddrt.cli import main
from ddrt.commission.answers import KEYS as ANSWER_KEYS, AnswersError, load_answers
from ddrt.config import ConfigError, load_config
from ddrt.config import filekind
from ddrt.config.load import TOP_KEYS
from ddrt.path import PathError, load_path
from ddrt.sweep.campaign import KEYS as CAMPAIGN_KEYS, CampaignError, load_campaign
from tests.support.repo import REPO, SIM_YAML

CONFIGS = REPO / "configs"
PATH_FILES = sorted((CONFIGS / "paths").glob("*.*")) + sorted((CONFIGS / "scenarios" / "realistic").glob("*.csv"))
CAMPAIGNS = sorted((CONFIGS / "campaigns").glob("*.yaml"))
CONFIG_FILES = [p for p in sorted(CONFIGS.rglob("*.yaml")) if p.parent.name not in ("paths", "campaigns")]


def _answers(tmp_path):
    f = tmp_path / "answers.yaml"
    f.write_text("odometry: {distance_m: 1.002, turn_offset_deg: -3}\ncheck: {end_offset_mm: 4}\n")
    return f


def test_the_kinds_key_lists_are_those_of_their_loaders() -> None:
    assert filekind.CAMPAIGN_KEYS == set(CAMPAIGN_KEYS)
    assert filekind.ANSWER_SECTIONS == {k.split(".")[0] for k in ANSWER_KEYS}
    assert filekind.CONFIG_SECTIONS <= set(TOP_KEYS)
    # What a config shares with the other kinds is all that is left out of its own sections.
    assert set(TOP_KEYS) - filekind.CONFIG_SECTIONS == {"paths", "path", "start", "name", "description"}


@pytest.mark.parametrize("f", CONFIG_FILES, ids=lambda p: str(p.relative_to(CONFIGS)))
def test_every_config_in_the_repository_is_seen_as_a_config(f) -> None:
    import yaml

    assert filekind.kind_of(yaml.safe_load(f.read_text())) is filekind.CONFIG


@pytest.mark.parametrize("f", PATH_FILES, ids=lambda p: p.name)
def test_a_path_file_given_as_the_config_is_named_with_the_commands_that_take_it(f) -> None:
    with pytest.raises(ConfigError) as exc:
        load_config(f)
    text = str(exc.value)
    assert text.startswith(f"{f}: this is a path file, not a config")
    assert f"ddrt sim CONFIG --path {f}" in text and f"ddrt path {f}" in text


@pytest.mark.parametrize("f", CAMPAIGNS, ids=lambda p: p.name)
def test_a_campaign_given_as_a_config_or_a_path_names_ddrt_sweep(f) -> None:
    with pytest.raises(ConfigError, match=f"this is a sweep campaign, not a config: run it with `ddrt sweep {f} --out DIR`"):
        load_config(f)
    with pytest.raises(PathError, match="this is a sweep campaign, not a path file"):
        load_path(f)


def test_an_answers_file_given_as_a_config_names_ddrt_commission(tmp_path) -> None:
    f = _answers(tmp_path)
    assert load_answers(f)["odometry.distance_m"] == 1.002
    with pytest.raises(ConfigError, match=f"this is a commissioning answers file, not a config: give it with "
                                          f"`ddrt commission CONFIG --answers {f}`"):
        load_config(f)


def test_a_config_given_where_another_file_belongs_is_named_as_a_config(tmp_path) -> None:
    for load, error, what in ((load_path, PathError, "a path file"), (load_answers, AnswersError, "an answers file"),
                              (load_campaign, CampaignError, "a campaign")):
        with pytest.raises(error, match=f"this is a config, not {what}: run it with `ddrt sim {SIM_YAML}`"):
            load(SIM_YAML)
    with pytest.raises(AnswersError, match="this is a path file, not an answers file"):
        load_answers(CONFIGS / "paths" / "rectangle.yaml")
    with pytest.raises(CampaignError, match="this is a path file, not a campaign"):
        load_campaign(CONFIGS / "paths" / "rectangle.yaml")


def test_a_file_of_no_known_kind_keeps_the_key_by_key_error(tmp_path) -> None:
    f = tmp_path / "odd.yaml"
    f.write_text("robt: {H: 0.1}\n")
    with pytest.raises(ConfigError, match="robt: unknown section"):
        load_config(f)
    f.write_text("shap: circle\nradius: 1\n")
    with pytest.raises(PathError, match="exactly one of keys 'shape', 'points', 'file' is required"):
        load_path(f)


def test_ddrt_sim_given_a_path_file_says_use_path(capsys) -> None:
    f = CONFIGS / "paths" / "figure8_slow.yaml"
    assert main(["sim", str(f), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "this is a path file, not a config" in err and "--path" in err
