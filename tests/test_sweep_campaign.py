"""`ddrt sweep` without a cluster: campaign files, their cases, malformed campaigns refused
before anything runs, pass criteria, the journal, the table, the summary and the figures.
(tests/test_sweep_cluster.py runs campaigns on real Dask clusters.)"""

from __future__ import annotations

import io
import json
import math
import os
import threading
from pathlib import Path

import pytest

from ddrt import cli
from ddrt.sweep import run as sweep_run
from ddrt.sweep.campaign import CampaignError, campaign_from_mapping, load_campaign
from ddrt.sweep.cases import expand
from ddrt.sweep.columns import KNOWN_METRICS, NUMERIC_METRICS, TEXT_METRICS, flatten
from ddrt.sweep.criteria import parse_criterion, passes
from ddrt.sweep.driver import run_plan, write_results
from ddrt.sweep.journal import ROWS, Journal, read_rows
from ddrt.sweep.progress import Progress
from ddrt.sweep.summary import summary_text
from ddrt.sweep.table import arrow_table, read_table, without_wall_time

REPO = Path(__file__).resolve().parents[1]
S_CURVE = REPO / "configs" / "scenarios" / "s_curve.yaml"
SHORT = {"duration_s": 0.5}  # after the 1 s calibration at rest: a fraction of a second of wall time
QUICK_START = {"sim": {"start_delay_s": 0.0}}


def write_campaign(tmp_path: Path, text: str, name: str = "campaign.yaml") -> Path:
    p = tmp_path / name
    p.write_text(text.replace("BASE", str(S_CURVE)))
    return p


def mapping(**keys) -> dict:
    return dict({"base": str(S_CURVE), "overrides": QUICK_START, "run": SHORT}, **keys)


# ------------------------------------------------------------------ the campaign file


def test_ranges_lists_and_the_product_of_axes() -> None:
    camp = campaign_from_mapping(mapping(
        axes={"controller.outer.k_y": {"start": 100, "stop": 400, "step": 100},
              "controller.outer.k_theta": {"start": 10, "stop": 40, "num": 3, "scale": "log"},
              "pursuit.lookahead_m": {"start": 0.1, "stop": 0.3, "step": 0.1},
              "sim.slip.probability": [0.0, 0.25]},
        seeds=2))
    k_y, k_th, la, slip = (a.values for a in camp.axes)
    assert k_y == (100, 200, 300, 400) and all(type(v) is int for v in k_y)
    assert k_th == (10.0, 20.0, 40.0)
    assert la == (0.1, 0.2, 0.3)  # 0.1 + 2 * 0.1 without its 0.30000000000000004
    assert slip == (0.0, 0.25) and camp.seeds == (1, 2)
    plan = expand(camp)
    assert len(plan.cases) == 4 * 3 * 3 * 2 * 2
    assert plan.columns == ("controller.outer.k_y", "controller.outer.k_theta", "pursuit.lookahead_m",
                            "sim.slip.probability", "seed")
    last = plan.cases[-1]
    assert last.params == {"controller.outer.k_y": 400, "controller.outer.k_theta": 40.0,
                           "pursuit.lookahead_m": 0.3, "sim.slip.probability": 0.25, "seed": 2}
    assert last.config.controller.outer.k_y == 400 and last.config.pursuit.lookahead_m == 0.3
    assert last.config.sim.slip.probability == 0.25 and last.seed == 2
    assert len({c.case_id for c in plan.cases}) == len(plan.cases)
    assert len(plan.paths) == 1  # one path, built once for 144 cases
    assert expand(camp).fingerprint == plan.fingerprint


def test_population_paths_variants_and_path_speed() -> None:
    """The robots of ddrt/sweep/population.py, each on its own speed; a path file's speed as an axis."""
    from ddrt.sweep.population import population

    camp = campaign_from_mapping({
        "population": {"robots": 3, "seed": 7},
        "paths": {"eight": {"shape": "figure_eight", "width": 1.2, "height": 0.6},
                  "circle": str(REPO / "configs" / "paths" / "circle_1m.yaml")},
        "variants": {"dyn": {"controller": {"mode": "dynamic"}}, "kin": {"controller": {"mode": "kinematic"}}},
        "overrides": {"daemon": {"socket": None}},
    })
    plan = expand(camp)
    assert plan.columns == ("variant", "robot", "path", "seed")
    assert len(plan.cases) == 2 * 3 * 2
    robots = population(3, 7)
    for case in plan.cases:
        robot = robots[int(str(case.params["robot"])[1:])]
        assert case.config.robot.m_p == robot.sections["robot"]["m_p"]
        assert case.params["seed"] == robot.sections["sim"]["seed"]  # no seeds: the config's own
        path = plan.paths[case.path_key]
        assert case.config.path["speed"] == robot.path_speed  # a YAML path file, inlined to set its speed
        assert path.duration > 0


def test_what_the_criteria_and_the_summary_read_is_kept_whatever_metrics_lists() -> None:
    """metrics: [ticks] with the default summary metric gave a summary of dashes: it was not kept."""
    camp = campaign_from_mapping(mapping(metrics=["ticks"], **{"pass": ["max_cross_track_m < 0.05",
                                                                         "max_cross_track_m < 0.06"]}))
    assert camp.run.metrics == ("ticks", "max_cross_track_m") and camp.summary_metrics == ("max_cross_track_m",)
    camp = campaign_from_mapping(mapping(metrics=["ticks"], summary={"metrics": ["rms_cross_track_m"]}))
    assert camp.run.metrics == ("ticks", "rms_cross_track_m")
    assert campaign_from_mapping(mapping(metrics=["ticks"])).run.metrics == ("ticks", "rms_cross_track_m")


def test_axes_on_a_path_file_set_keys_of_the_path() -> None:
    plan = expand(campaign_from_mapping(mapping(axes={"path.speed": [0.2, 0.4]})))
    speeds = [max(plan.paths[c.path_key].v) for c in plan.cases]
    assert speeds[0] == pytest.approx(0.2, rel=1e-6) and speeds[1] == pytest.approx(0.4, rel=1e-6)


BAD = [
    # (campaign text, what the one-line error must name)
    ("bse: BASE\n", ["campaign.yaml: bse: unknown key"]),
    ("", ["campaign.yaml: the campaign is empty"]),
    ("- BASE\n", ["campaign.yaml: the top level must be a mapping"]),
    ("name: x\n", ["campaign.yaml: base: missing"]),
    ("base: nowhere.yaml\n", ["campaign.yaml: base: no such file 'nowhere.yaml'"]),
    ("base: BASE\npaths: [nope.yaml]\n", ["campaign.yaml: paths[0]: no such file 'nope.yaml'"]),
    ("base: BASE\npaths: {p: missing/path.csv}\n", ["paths.p: no such file"]),
    ("base: BASE\naxes: {controller.outer.k_y: {start: 10, stop: 1, step: 1}}\n",
     ["axes.controller.outer.k_y: the range has no values"]),
    ("base: BASE\naxes: {controller.outer.k_y: {start: 1, stop: 10, num: 0}}\n",
     ["axes.controller.outer.k_y.num: must be >= 1 (and <= 100000), got 0"]),
    ("base: BASE\naxes: {controller.outer.k_y: []}\n", ["axes.controller.outer.k_y: the list of values is empty"]),
    ("base: BASE\naxes: {}\n", ["campaign.yaml: axes: empty"]),
    ("base: BASE\naxes: []\n", ["campaign.yaml: axes: expected a mapping"]),
    ("base: BASE\naxes: {controller.outer.k_y: 400}\n", ["axes.controller.outer.k_y: expected a list of values or a range"]),
    ("base: BASE\naxes: {controller.outer.k_y: {start: a, stop: 3, step: 1}}\n",
     ["axes.controller.outer.k_y.start: expected a number, got 'a'"]),
    ("base: BASE\naxes: {controller.outer.k_y: {start: 1, stop: 3, step: 1, num: 3}}\n",
     ["exactly one of step and num"]),
    ("base: BASE\naxes: {controller.outer.k_y: {from: 1}}\n", ["axes.controller.outer.k_y.from: unknown key (known: num, scale, start, step, stop)"]),
    ("base: BASE\naxes: {controller.outer.k_y: [1, 2, 1]}\n", ["is listed twice"]),
    ("base: BASE\nseeds: three\n", ["campaign.yaml: seeds: expected a whole number, got 'three'"]),
    ("base: BASE\nseeds: [1, x]\n", ["campaign.yaml: seeds[1]: expected a whole number"]),
    ("base: BASE\nseeds: 0\n", ["campaign.yaml: seeds: a count of seeds is 1 to 1000000", "got 0"]),
    ("base: BASE\nrun: {duration_s: long}\n", ["campaign.yaml: run.duration_s: expected a number, got 'long'"]),
    ("base: BASE\nrun: {laps: 2}\n", ["campaign.yaml: run.laps: unknown key"]),
    ("base: BASE\npopulation: {robots: 2.5}\n", ["population.robots: expected a whole number"]),
    ("base: BASE\nmetrics: [rms_cross_track_m, nope]\n", ["metrics[1]: expected a metric of metrics.json: rms_cross_track_m, ", "got 'nope'"]),
    ("base: BASE\npass: 'rms < 3'\n", ["campaign.yaml: pass: unknown metric 'rms'"]),
    ("base: BASE\npass: ['completed == 1']\n", ["pass[0]: completed is true or false"]),
    ("base: BASE\npass: ['rms_cross_track_m is small']\n", ["pass[0]: expected METRIC OP VALUE"]),
    ("base: BASE\nvariants: {fast: 3}\n", ["campaign.yaml: variants.fast: expected a mapping"]),
    # Axis values that make a config invalid: the case is named by its axis values, then the key.
    ("base: BASE\naxes: {plant.m_p: [0.8, -1.0]}\n",
     ["campaign.yaml: case 1 (plant.m_p=-1.0): plant.m_p: must be > 0"]),
    ("base: BASE\naxes: {controller.outer.k_yy: [1]}\nseeds: [4]\n",
     ["case 0 (controller.outer.k_yy=1, seed=4): controller.outer.k_yy: unknown key"]),
    ("base: BASE\naxes: {controller.mode: [dynamic, flying]}\n",
     ["case 1 (controller.mode=flying): controller.mode: must be one of"]),
    ("base: BASE\naxes: {controller.outer: [1]}\n", ["case 0 (controller.outer=1): controller.outer"]),
    ("base: BASE\npaths: {p: {shape: circle, radius: -1}}\n", ["case 0 (path=p): path: key 'radius': must be >= 0.001 m"]),
    ("base: BASE\nvariants: {a: {controller: {mode: kinematic}}, b: {controller: {mode: kinematic}}}\n",
     ["case 1 (variant=b): the same run as case 0"]),
    ("base: BASE\noverrides: {hal: {backend: real, imu: {bus: 1}, bridge: {url: /dev/ttyACM0}}}\n",
     ["case 0: hal.backend: real"]),
    ("base: BASE\naxes: {path: [a.yaml]}\n", ["axes.path: not a config key to sweep"]),
    # Numbers beyond what a float or the table holds: refused by key, never an OverflowError
    # or a MemoryError (seeds: 10**10 would build a tuple of 10**10 first). A range's numbers are
    # held to the walker's range for every number, as a config's are.
    ("base: BASE\naxes: {controller.outer.k_y: {start: -1e308, stop: 1e308, step: 1}}\n",
     ["axes.controller.outer.k_y.start: out of range, got -1e+308"]),
    ("base: BASE\naxes: {controller.outer.k_y: {start: 0, stop: 1, step: 1e-300}}\n",
     ["axes.controller.outer.k_y.step: out of range, got 1e-300"]),
    ("base: BASE\naxes: {controller.outer.k_y: {start: -1e12, stop: 1e12, step: 1}}\n",
     ["axes.controller.outer.k_y: more than 100000 values (from -1e+12 to 1e+12 by 1"]),
    ("base: BASE\naxes: {controller.outer.k_y: {start: 0, stop: 1, step: 1e-12}}\n",
     ["axes.controller.outer.k_y: more than 100000 values (from 0"]),
    ("base: BASE\naxes: {controller.outer.k_y: {start: 1" + "0" * 330 + ", stop: 1, step: -1}}\n",
     ["axes.controller.outer.k_y.start: too large for a number, got a 331-digit integer"]),
    ("base: BASE\nrun: {duration_s: 1" + "0" * 330 + "}\n", ["run.duration_s: too large for a number"]),
    ("base: BASE\nseeds: 10000000000\n", ["campaign.yaml: seeds: a count of seeds is 1 to 1000000 (more cases: split the campaign), got 10000000000"]),
    ("base: BASE\nseeds: [1, 18446744073709551616]\n", ["campaign.yaml: seeds[1]: out of range"]),
    # extends: names the file a config is read over; laid over a case it would silently do nothing.
    ("base: BASE\noverrides: {extends: BASE}\n", ["campaign.yaml: overrides.extends: a case's config is read from base:"]),
    ("base: BASE\nvariants: {a: {}, b: {extends: BASE}}\n", ["campaign.yaml: variants.b.extends:"]),
    ("base: BASE\nseeds: 2\naxes: {sim.seed: [5, 6]}\n", ["campaign.yaml: axes.sim.seed: seeds: sets every case's"]),
]


@pytest.mark.parametrize("text, expected", BAD, ids=[f"bad{i}" for i in range(len(BAD))])
def test_malformed_campaigns_are_refused_before_anything_runs(tmp_path: Path, text: str, expected: list[str],
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    camp = write_campaign(tmp_path, text)
    out = tmp_path / "out"
    assert cli.main(["sweep", str(camp), "--out", str(out), "--workers", "1"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("ddrt: error: ") and "Traceback" not in err
    for fragment in expected:
        assert fragment in err, err
    assert not out.exists()  # nothing ran, nothing was written


def test_the_metric_lists_are_those_of_metrics_json() -> None:
    """columns.py lists metrics.json's figures so campaigns are checked before running: a real
    run's metrics must be exactly these (wall_s is the row's own column)."""
    from ddrt.config import load_config
    from ddrt.path.spec import resolve_path
    from ddrt.simrun.runner import run_sim

    cfg = load_config(S_CURVE, QUICK_START)
    m = flatten(run_sim(cfg, resolve_path(cfg), duration=0.1).metrics)
    assert set(m) - {"wall_s", "controller"} == set(KNOWN_METRICS)
    assert all(isinstance(m[k], (int, float)) for k in NUMERIC_METRICS)
    assert all(isinstance(m[k], str) for k in TEXT_METRICS)


# ------------------------------------------------------------------ criteria


def test_criteria() -> None:
    small = parse_criterion("rms_cross_track_m < 0.005", "pass")
    done = parse_criterion("completed == true", "pass")
    clean = parse_criterion("fault == ''", "pass")
    row = {"status": "ok", "rms_cross_track_m": 0.001, "completed": True, "fault": ""}
    assert small.holds(row) and done.holds(row) and clean.holds(row) and passes(row, (small, done, clean))
    assert not small.holds(dict(row, rms_cross_track_m=0.01))
    assert not small.holds(dict(row, rms_cross_track_m=None))  # no value fails
    assert not clean.holds(dict(row, fault="gyro saturated"))
    assert not passes(dict(row, status="timeout"), (small,))  # a run that did not end never passes
    assert parse_criterion("saturated_fraction<=0.02", "x").text == "saturated_fraction<=0.02"
    with pytest.raises(ValueError, match="needs a number"):
        parse_criterion("completed < true", "pass")
    with pytest.raises(ValueError, match="is a number"):
        parse_criterion("rms_cross_track_m < true", "pass")
    with pytest.raises(ValueError, match="is text"):
        parse_criterion("fault == 3", "pass")


def test_default_criteria_follow_ddrt_sims_exit_status() -> None:
    assert [c.text for c in campaign_from_mapping({"base": str(S_CURVE)}).run.criteria] == ["completed == true"]
    assert [c.text for c in campaign_from_mapping(mapping()).run.criteria] == ["fault == ''"]


# ------------------------------------------------------------------ running in this process


@pytest.fixture(scope="module")
def small_plan():
    return expand(campaign_from_mapping(mapping(axes={"controller.outer.k_y": [100, 400],
                                                      "controller.outer.k_theta": [20, 40]},
                                                **{"pass": ["rms_cross_track_m < 1e-4", "fault == ''"]})))


@pytest.fixture(scope="module")
def small_rows(small_plan):
    return run_plan(small_plan, workers=1)


def test_rows_are_deterministic_and_typed(small_plan, small_rows) -> None:
    assert [r["case"] for r in small_rows] == [0, 1, 2, 3]
    again = run_plan(small_plan, workers=1)
    t1, t2 = arrow_table(small_plan, small_rows), arrow_table(small_plan, list(reversed(again)))
    assert without_wall_time(t1).equals(without_wall_time(t2))
    assert not t1.equals(t2.set_column(t2.schema.get_field_index("rms_cross_track_m"), "rms_cross_track_m",
                                       t2.column("rms_tracking_m")))  # the comparison does see the numbers
    for r in small_rows:
        assert r["status"] == "ok" and r["error"] == "" and r["sim_duration_s"] == pytest.approx(0.5)
        assert r["pass"] == (r["rms_cross_track_m"] < 1e-4 and r["fault"] == "")
    assert str(t1.schema.field("controller.outer.k_y").type) == "int64"
    assert str(t1.schema.field("rms_cross_track_m").type) == "double"
    assert str(t1.schema.field("completed").type) == "bool"


def test_a_failed_or_timed_out_run_is_a_row_with_its_error(small_plan, monkeypatch: pytest.MonkeyPatch) -> None:
    case = small_plan.cases[0]
    path = small_plan.paths[case.path_key]
    slow = small_plan.campaign.run.__class__(**{**small_plan.campaign.run.__dict__, "timeout_s": 1e-9})
    row = sweep_run.run_case(case, path, slow)
    assert row["status"] == "timeout" and "run.timeout_s" in row["error"] and row["pass"] is False
    assert row["rms_cross_track_m"] is None and row["case_id"] == case.case_id

    def broken(*args, **kwargs):
        raise RuntimeError("the plant\nexploded")

    monkeypatch.setattr(sweep_run, "run_sim", broken)
    row = sweep_run.run_case(case, path, small_plan.campaign.run)
    assert row["status"] == "failed" and row["error"] == "RuntimeError: the plant exploded"
    table = arrow_table(small_plan, [row])  # a table of failures only keeps its column types
    assert str(table.schema.field("rms_cross_track_m").type) == "double"


def test_outputs_summary_and_figures(tmp_path: Path, small_plan, small_rows) -> None:
    figures = write_results(small_plan, small_rows, tmp_path)
    table = read_table(tmp_path / "results.parquet")
    assert table.num_rows == 4 and table.column("case").to_pylist() == [0, 1, 2, 3]
    csv_lines = (tmp_path / "results.csv").read_text().splitlines()
    assert len(csv_lines) == 5 and csv_lines[0].startswith('"case","case_id","controller.outer.k_y"')
    text = (tmp_path / "summary.md").read_text()
    assert "## By controller.outer.k_y" in text and "## By controller.outer.k_theta" in text
    assert "| 400 | 2 | 2 |" in text and "rms_cross_track_m p50" in text
    assert not any("p90" in ln or "p99" in ln for ln in text.splitlines() if ln.startswith("|"))  # 4 runs
    names = sorted(p.name for p in (tmp_path / "figures").glob("*.png"))
    assert figures == 3 and "pass_rate_controller.outer.k_y_x_controller.outer.k_theta.png" in names


def test_percentiles_are_given_only_over_enough_runs() -> None:
    from ddrt.sweep.summary import MIN_RUNS, _table, group

    rows = [{"status": "ok", "m": float(v)} for v in range(12)]
    table = _table("x", [group(rows, "many", ["m"]), group(rows[:3], "few", ["m"])], ["m"])
    assert table[0] == "| x | runs | ok | pass | m p50 | m p90 | m max |"  # no group has 100 runs: no p99
    many, few = table[2].split(" | "), table[3].split(" | ")
    assert many[5] == "9.9" and few[5] == "-" and few[4] == "1" and few[6] == "2 |"
    assert MIN_RUNS[90] == 10 and _table("x", [group(rows[:9], "nine", ["m"])], ["m"])[0].count("p90") == 0


def test_the_sweep_says_one_figure_and_draws_lengths_in_mm(tmp_path: Path, small_plan, small_rows,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    from matplotlib.figure import Figure

    from ddrt.sweep.driver import SweepReport
    from ddrt.sweep.figures import box_plot

    assert SweepReport(small_plan, tmp_path, figures=1).text().splitlines()[1].endswith(" and 1 figure")
    assert SweepReport(small_plan, tmp_path, figures=3).text().splitlines()[1].endswith(" and 3 figures")
    saved: list[Figure] = []
    monkeypatch.setattr(Figure, "savefig", lambda fig, *a, **k: saved.append(fig))
    box_plot(small_plan, small_rows, "controller.outer.k_y", "rms_cross_track_m", tmp_path / "b.png")
    ax = saved[0].axes[0]
    assert ax.get_ylabel() == "rms_cross_track_m (mm)"
    drawn = sorted(v for ln in ax.get_lines() for v in ln.get_ydata() if math.isfinite(v))
    assert max(drawn) == pytest.approx(1000.0 * max(r["rms_cross_track_m"] for r in small_rows), rel=1e-12)
    saved[0].canvas.draw()
    assert ax.yaxis.get_major_formatter().get_offset() == ""  # no "1e-5" over the axis


def test_a_value_with_a_bar_or_a_newline_stays_one_table_cell() -> None:
    """A variant may be named anything: its `|` and line breaks must not split summary.md's rows."""
    plan = expand(campaign_from_mapping(mapping(variants={"fast|light\nv2": {}, "kin": {"controller": {"mode": "kinematic"}}})))
    rows = [{"case": c.index, "case_id": c.case_id, "status": "ok", "pass": True, "rms_cross_track_m": 0.001,
             **c.params} for c in plan.cases]
    table = [line for line in summary_text(plan, rows).splitlines() if line.startswith("| fast")]
    assert len(table) == 1 and table[0].startswith("| fast\\|light v2 | 1 | 1 |")
    head = [line for line in summary_text(plan, rows).splitlines() if line.startswith("| variant")][0]
    cells = lambda line: len(line.replace("\\|", "").split("|"))  # noqa: E731
    assert cells(table[0]) == cells(head)


def test_summary_lists_runs_that_did_not_end(small_plan, small_rows) -> None:
    rows = [dict(small_rows[0], status="failed", error="KilledWorker: gone", rms_cross_track_m=None, **{"pass": False})]
    text = summary_text(small_plan, rows + small_rows[1:])
    assert "3 ok, 1 failed, 0 timed out" in text and "KilledWorker: gone" in text


# ------------------------------------------------------------------ the journal and resuming


def test_the_journal_keeps_whole_rows_and_refuses_another_campaign(tmp_path: Path, small_plan, small_rows) -> None:
    j = Journal(tmp_path, small_plan, resume=False)
    for r in small_rows[:2]:
        j.append(r)
    j.close()
    with open(tmp_path / ROWS, "a") as fh:
        fh.write('{"case": 2, "case_id": "cut sho')  # a kill in the middle of a line
    rows, _ = read_rows(tmp_path / ROWS)
    assert [r["case"] for r in rows] == [0, 1]
    with pytest.raises(CampaignError, match="already holds 2 rows"):
        Journal(tmp_path, small_plan, resume=False)
    j = Journal(tmp_path, small_plan, resume=True)
    assert j.resumed == 2
    j.append(small_rows[2])
    j.close()
    assert [r["case"] for r in read_rows(tmp_path / ROWS)[0]] == [0, 1, 2]  # the cut line is gone
    other = expand(campaign_from_mapping(mapping(axes={"controller.outer.k_y": [100, 200]})))
    with pytest.raises(CampaignError, match="rows are of another campaign"):
        Journal(tmp_path, other, resume=True)


def test_resume_and_limit_through_the_command(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """--limit runs some, --resume the rest (the cases run in this process: see run_in_process)."""
    import ddrt.sweep.driver as driver

    asked: list[int | None] = []  # the local cluster's size each run asked for
    monkeypatch.setattr(driver, "DaskCluster", lambda workers, scheduler: asked.append(workers) or driver.InProcess())
    camp = write_campaign(tmp_path, "base: BASE\noverrides: {sim: {start_delay_s: 0}}\nrun: {duration_s: 0.3}\n"
                                    "axes: {controller.outer.k_y: [100, 200, 400]}\n")
    out = tmp_path / "out"
    assert cli.main(["sweep", str(camp), "--out", str(out), "--limit", "1", "--workers", "8", "--quiet"]) == 0
    assert asked == [1]  # never more worker processes than runs to do
    assert "1 of 3 cases have rows (1 run now, 0 kept" in capsys.readouterr().out
    assert cli.main(["sweep", str(camp), "--out", str(out), "--quiet"]) == 2
    assert "--resume continues it" in capsys.readouterr().err
    assert cli.main(["sweep", str(camp), "--out", str(out), "--resume", "--quiet"]) == 0
    assert "3 of 3 cases have rows (2 run now, 1 kept from before)" in capsys.readouterr().out
    assert asked == [1, min(2, driver.machine_workers())]  # the default: a worker per core, at most the runs
    assert read_table(out / "results.parquet").column("controller.outer.k_y").to_pylist() == [100, 200, 400]
    assert len((out / ROWS).read_text().splitlines()) == 3


def test_progress_bar_shows_rate_and_eta() -> None:
    now = [0.0]
    stream = io.StringIO()
    bar = Progress(4, stream=stream, clock=lambda: now[0])
    now[0] = 2.0
    bar.update(True)
    assert "sweep 1/4 [######" in stream.getvalue() and "0.50 runs/s ETA 0:00:06" in stream.getvalue()
    now[0] = 8.0
    for ok in (False, True, True):
        bar.update(ok)
    assert stream.getvalue().splitlines()[-1].endswith("took 0:00:08, 1 failed")


def test_ddrt_sim_never_imports_dask(tmp_path: Path) -> None:
    """The sweep extra stays optional: `ddrt sim` loads neither dask, pyarrow nor ddrt.sweep."""
    import subprocess
    import sys

    code = (f"import json, sys\nfrom ddrt import cli\n"
            f"cli.main(['sim', {str(S_CURVE)!r}, '--duration', '0.2', '--quiet', '--out', {str(tmp_path)!r}])\n"
            "print(json.dumps(sorted(m for m in sys.modules if m.split('.')[0] in ('dask', 'distributed', 'pyarrow')"
            " or m.startswith('ddrt.sweep'))))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=REPO)
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout.splitlines()[-1]) == []


def test_load_campaign_names_relative_files_from_its_folder(tmp_path: Path) -> None:
    (tmp_path / "sub").mkdir()
    camp = write_campaign(tmp_path / "sub", "base: ../base.yaml\npaths: [../p.yaml]\n")
    (tmp_path / "base.yaml").write_text(f"extends: {S_CURVE}\n")
    (tmp_path / "p.yaml").write_text("shape: circle\nradius: 0.5\nspeed: 0.2\n")
    c = load_campaign(camp)
    assert c.bases == ((tmp_path / "base.yaml").resolve(),) and c.paths == {"p": str((tmp_path / "p.yaml").resolve())}
    assert math.isclose(expand(c).cases[0].expected_s, expand(c).paths[expand(c).cases[0].path_key].duration)


def test_only_the_command_imports_the_sweep_package_and_only_when_it_runs() -> None:
    """docs/design.md: ddrt.sweep is a leaf of the command (and of the reference's generator);
    dask and pyarrow stay optional."""
    import ast

    found = []
    for folder in ("ddrt", "hal", "sim_hal"):
        for f in sorted((REPO / folder).rglob("*.py")):
            if (REPO / "ddrt" / "sweep") in f.parents:
                continue
            tree = ast.parse(f.read_text(encoding="utf-8"))
            top_level = {id(node) for node in tree.body}
            for node in ast.walk(tree):
                names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                         [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
                for name in names:
                    if name.split(".")[:2] == ["ddrt", "sweep"] or name.split(".")[0] in ("dask", "distributed",
                                                                                          "pyarrow"):
                        found.append((f.relative_to(REPO).as_posix(), id(node) in top_level, name))
    # ddrt.docgen writes the campaign reference from ddrt/sweep/reference.py, importing it when it does.
    assert found and all(path in ("ddrt/cli.py", "ddrt/docgen.py") and not top for path, top, _ in found), found
    assert {name for path, _, name in found if path == "ddrt/docgen.py"} == {"ddrt.sweep.reference"}


def test_the_example_campaign_and_the_documented_keys() -> None:
    """configs/campaigns/ expands as written, and docs/sweep.md shows it as it is; the reference
    it links to has every campaign key."""
    from ddrt.sweep.campaign import KEYS

    gains = REPO / "configs" / "campaigns" / "gains.yaml"
    plan = expand(load_campaign(gains))
    assert plan.columns == ("variant", "controller.outer.k_y", "controller.outer.k_theta", "seed")
    assert len(plan.cases) == 2 * 5 * 3 * 3
    doc = (REPO / "docs" / "sweep.md").read_text(encoding="utf-8")
    shown = doc.split("```yaml\n", 1)[1].split("```", 1)[0]
    written = [line for line in gains.read_text(encoding="utf-8").splitlines() if not line.startswith("#")]
    assert [line.split("  #")[0].rstrip() for line in shown.splitlines()] == \
        [line.split("  #")[0].rstrip() for line in written]
    assert "(reference/campaign.md)" in doc
    page = (REPO / "docs" / "reference" / "campaign.md").read_text(encoding="utf-8")
    assert [k for k in KEYS if f"| `{k}` |" not in page] == []


def test_leaving_on_ctrl_c_silences_the_loggers_that_print_a_cancelled_callbacks_traceback() -> None:
    import logging

    from ddrt.sweep.execute import silence_shutdown_logs

    names = ("tornado", "tornado.application", "asyncio", "distributed.client")
    saved = {n: logging.getLogger(n).level for n in names}
    try:
        logging.getLogger("tornado.application").setLevel(logging.ERROR)  # Dask's config does this
        assert logging.getLogger("tornado.application").isEnabledFor(logging.ERROR)
        silence_shutdown_logs()
        for n in names:
            assert not logging.getLogger(n).isEnabledFor(logging.ERROR), n
            assert logging.getLogger(n).isEnabledFor(logging.CRITICAL), n
        assert logging.getLogger("ddrt").isEnabledFor(logging.ERROR)  # ours are untouched
    finally:
        for n, level in saved.items():
            logging.getLogger(n).setLevel(level)


def test_a_whole_number_beyond_int64_in_a_parameter_column_is_kept_as_text() -> None:
    """description: takes any value, so an axis over it may hold 2**64: the table is written
    (the value as its text), instead of failing after every run has finished."""
    plan = expand(campaign_from_mapping(mapping(axes={"description": [2**64, 1]})))
    rows = [sweep_run.blank_row(c, plan.campaign.run, "failed", "not run") for c in plan.cases]
    table = arrow_table(plan, rows)
    assert str(table.schema.field("description").type) == "string"
    assert table.column("description").to_pylist() == [str(2**64), "1"]


def _refused_in_time(tmp_path: Path, text: str, capsys: pytest.CaptureFixture[str], camp: Path | None = None) -> str:
    """The one-line error of `ddrt sweep` on a campaign, which must come within 10 s (a FIFO
    that is opened blocks until someone writes it)."""
    camp = camp or write_campaign(tmp_path, text)
    out = tmp_path / "out"
    status: list[int] = []
    t = threading.Thread(target=lambda: status.append(cli.main(["sweep", str(camp), "--out", str(out),
                                                                "--workers", "1"])), daemon=True)
    t.start()
    t.join(10.0)
    assert status == [2], "ddrt sweep blocked on a FIFO" if t.is_alive() else status
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("ddrt: error: ") and "Traceback" not in err
    assert not out.exists()
    return err


def test_fifos_directories_and_devices_are_refused_by_their_type(tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """Never opened: a campaign, a base config, a path file (named by paths:, by the base's path:,
    or as a CSV by an inline file:) that is a FIFO; a directory or a device is named as one,
    not as a missing file."""
    for name in ("fifo.yaml", "fifo.csv", "camp.yaml"):
        os.mkfifo(tmp_path / name)
    err = _refused_in_time(tmp_path, "", capsys, camp=tmp_path / "camp.yaml")
    assert "camp.yaml: a FIFO, not a campaign file" in err
    assert "campaign.yaml: base: 'fifo.yaml' is a FIFO, not a file" in _refused_in_time(
        tmp_path, "base: fifo.yaml\n", capsys)
    assert "campaign.yaml: paths.p: 'fifo.yaml' is a FIFO, not a file" in _refused_in_time(
        tmp_path, "base: BASE\npaths: {p: fifo.yaml}\n", capsys)
    assert "case 0 (path=p): path: key 'file': " in _refused_in_time(
        tmp_path, "base: BASE\npaths: {p: {file: fifo.csv, speed: 0.2}}\n", capsys)
    base = tmp_path / "base.yaml"
    base.write_text(f"extends: {S_CURVE}\npath: fifo.yaml\n")
    err = _refused_in_time(tmp_path, f"base: {base}\n", capsys)
    assert "case 0: path: " in err and "fifo.yaml: is a FIFO" in err
    err = _refused_in_time(tmp_path, f"base: {base}\naxes: {{path.speed: [0.2]}}\n", capsys)  # read to set a key
    assert "case 0 (path.speed=0.2): path: " in err and "fifo.yaml: is a FIFO" in err
    assert "base: '/tmp' is a directory, not a file" in _refused_in_time(tmp_path, "base: /tmp\n", capsys)
    assert "base: '/dev/null' is a device, not a file" in _refused_in_time(tmp_path, "base: /dev/null\n", capsys)
    assert "base: 'a\\x00b' is unreadable" in _refused_in_time(tmp_path, 'base: "a\\0b"\n', capsys)


def test_what_a_path_lacks_is_said_of_the_campaign(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A population with no path anywhere is "path: missing" (not a complaint about a shape
    nobody wrote, from the speed set on nothing); a path file that is not a mapping says so
    when an axis sets one of its keys (not that the mapping {speed} lacks a shape)."""
    err = _refused_in_time(tmp_path, "population: {robots: 1}\n", capsys)
    assert "case 0 (robot=r00): path: missing: give the campaign paths:, or the base config a path:" in err
    (tmp_path / "list.yaml").write_text("- 1\n")
    err = _refused_in_time(tmp_path, "base: BASE\npaths: [list.yaml]\naxes: {path.speed: [0.2]}\n", capsys)
    assert "list.yaml: expected a mapping at the top level, got list" in err


def test_a_journal_line_that_is_not_a_row_of_the_campaign_is_run_again(tmp_path: Path, small_plan,
                                                                        small_rows) -> None:
    """A line edited by hand (JSON but not a row, a row without its case, with a value of the
    wrong type, with another case's parameters) is not kept: its case runs again, and the table
    is written, where these failed with a traceback (before anything ran, or after everything had)."""
    j = Journal(tmp_path, small_plan, resume=False)
    j.append(small_rows[0])
    j.close()
    r1, r2, r3 = small_rows[1], small_rows[2], small_rows[3]
    junk = ["[1]", "17", json.dumps({k: v for k, v in r1.items() if k != "case"}),
            json.dumps(dict(r2, ticks="many")), json.dumps(dict(r3, case=0)),
            json.dumps(dict(r3, **{"controller.outer.k_y": 100}))]
    with open(tmp_path / ROWS, "a") as fh:
        fh.write("\n".join(junk) + "\n")
    j = Journal(tmp_path, small_plan, resume=True)
    assert j.resumed == 1 and list(j.rows) == [small_rows[0]["case_id"]]
    for r in small_rows[1:]:
        j.append(r)
    j.close()
    again = Journal(tmp_path, small_plan, resume=True)  # the rows appended after the junk are the ones kept
    again.close()
    assert sorted(r["case"] for r in again.rows.values()) == [0, 1, 2, 3]
    table = arrow_table(small_plan, list(again.rows.values()))
    assert table.column("ticks").to_pylist() == [r["ticks"] for r in small_rows]


def test_an_out_that_is_not_a_folder_is_refused_by_name(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    camp = write_campaign(tmp_path, "base: BASE\nrun: {duration_s: 0.3}\n")
    a_file = tmp_path / "table.csv"
    a_file.write_text("keep me\n")
    fifo_out = tmp_path / "fifo_out"
    fifo_out.mkdir()
    os.mkfifo(fifo_out / ROWS)
    for out, expected in ((a_file, f"--out {a_file}: a file, not a folder"), ("", "--out: expected a folder, got ''"),
                          (fifo_out, f"--out {fifo_out}: rows.jsonl is a FIFO, not the file a campaign writes")):
        assert cli.main(["sweep", str(camp), "--out", str(out), "--workers", "1", "--resume"]) == 2
        err = capsys.readouterr().err
        assert err == f"ddrt: error: {expected}\n"
    assert a_file.read_text() == "keep me\n" and not (Path.cwd() / ROWS).exists()


def test_an_address_that_is_not_a_dask_scheduler_fails_in_bounded_time(tmp_path: Path,
                                                                        capsys: pytest.CaptureFixture[str],
                                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """A server that accepts and says nothing (Client(timeout=) bounds the connect, not the
    handshake: this hung for ever), one that answers with other bytes (a MemoryError from a
    frame length read from text), and tls:// without a context (a TypeError): each is one line
    naming the address, exit 1, within the connect timeout and its margin."""
    import socket

    import ddrt.sweep.execute as execute

    monkeypatch.setattr(execute, "CONNECT_TIMEOUT_S", 1.0)
    camp = write_campaign(tmp_path, "base: BASE\nrun: {duration_s: 0.3}\n")
    servers = []
    for reply in (b"", b"HTTP/1.0 400 Bad Request\r\n\r\n" + b"\xff" * 64):
        srv = socket.socket()
        srv.bind(("127.0.0.1", 0))
        srv.listen(4)
        servers.append(srv)

        def serve(srv: socket.socket = srv, reply: bytes = reply) -> None:
            held = []
            while True:
                try:
                    conn, _ = srv.accept()
                except OSError:
                    return
                conn.sendall(reply)
                held.append(conn)  # kept open, saying nothing more

        threading.Thread(target=serve, daemon=True).start()
    try:
        for address in [f"tcp://127.0.0.1:{s.getsockname()[1]}" for s in servers] + ["tls://127.0.0.1:1"]:
            status: list[int] = []
            t = threading.Thread(target=lambda: status.append(cli.main(
                ["sweep", str(camp), "--out", str(tmp_path / "out"), "--scheduler", address, "--quiet"])), daemon=True)
            t.start()
            t.join(20.0)
            assert status == [1], f"--scheduler {address} still waiting after 20 s" if t.is_alive() else status
            err = capsys.readouterr().err
            assert err.startswith(f"ddrt: error: cannot reach the Dask scheduler at {address}: ")
            assert err.count("\n") == 1 and "Traceback" not in err, err
    finally:
        for s in servers:
            s.close()
