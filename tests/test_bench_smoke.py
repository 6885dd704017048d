"""A fast subset of `python -m bench.run` as a regression guard, with generous bounds.

The full run (docs/BENCHMARKS.md) is not part of CI; these check that every section still
measures something real and that the report still has every section.
"""

from __future__ import annotations

import dataclasses
from array import array

import pytest

from bench import accuracy, adaptation, grid_plans, io_bound, paths_as_given, run, tick_cost, velocity_mode
from ddrt.config import load_config
from ddrt.loop import ControlLoop
from ddrt.path.spec import resolve_path
from hal.wire import Drive, Packet, encode_frame
from hal.registry import open_hal
from lab import path_inputs
from tests.support.repo import SIM_YAML


# ------------------------------------------------------------------ tick cost


def _following_loop(seed: int) -> ControlLoop:
    cfg = load_config(SIM_YAML)
    path = resolve_path(cfg)
    hal = open_hal(cfg, start=path.start_pose, seed=seed)
    loop = ControlLoop(cfg, hal)
    loop.calibrate(hal.sleep_until, hal.now)
    loop.follow(path, path.start_pose)
    return loop


def test_stamped_tick_behaves_exactly_like_tick() -> None:
    """Twin loops on the same noise seed: timing the stages must not change what a tick does."""
    a = _following_loop(seed=7)
    b = _following_loop(seed=7)
    out = [array("q", bytes(8 * 400)) for _ in tick_cost.STAGES]
    for i in range(400):
        deadline = a.hal.now() + a.period
        a.hal.sleep_until(deadline)
        b.hal.sleep_until(deadline)
        a.tick()
        tick_cost.timed_tick(b, out, i)
        assert b.row == a.row, f"tick {i}: timed tick diverged from ControlLoop.tick"
    assert (a.ticks, a.saturated_ticks, a.state) == (b.ticks, b.saturated_ticks, b.state)
    assert a.row[10] > 0.0  # the reference speed: the twins were really moving
    assert all(max(o) > 0 for o in out)


def test_tick_cost_small_run_is_well_inside_the_period() -> None:
    tc = tick_cost.measure_tick_cost(load_config(SIM_YAML), ticks=3000, seed=3)
    assert set(tc.stages) == set(tick_cost.STAGES)
    assert tc.restarts >= 1  # 15 s of ticks on a 12.5 s path: restarted, still all "following"
    assert 0.0 < tc.tick.p50_us < 1000.0
    assert tc.fraction_of_period(tc.tick.p50_us) < 0.2
    for p in tc.stages.values():
        assert 0.0 < p.p50_us <= p.p99_us <= p.max_us <= tc.tick.max_us
    assert tc.compute.p50_us < tc.tick.p50_us
    assert tc.plant.p50_us > 0.0


# ------------------------------------------------------------------ io bound


def test_i2c_gyro_read_time() -> None:
    fast = io_bound.i2c_register_read(400_000)
    slow = io_bound.i2c_register_read(100_000)
    assert 50e-6 < fast.seconds < 150e-6
    assert slow.seconds == pytest.approx(4 * fast.seconds)
    assert fast.bits == 3 + 9 * 5  # START, Sr, STOP + addr W, reg, addr R, 2 data bytes
    with pytest.raises(ValueError, match="clock_hz"):
        io_bound.i2c_register_read(0)


def test_serial_frames_use_the_protocol_encoder() -> None:
    f = io_bound.tick_frames()
    # docs/protocol.md's example DRIVE is 12 bytes on the wire; every DRIVE has that length.
    assert f.drive_wire == len(encode_frame(Packet(1, Drive(5000, -2500, 100)))) == 12
    assert f.state_wire > f.state_raw > f.drive_raw
    assert io_bound.uart_seconds(f.drive_wire) == pytest.approx(12 * 10 / 115200)
    b = io_bound.io_bound()
    assert b.uart_both_s == pytest.approx(b.uart_drive_s + b.uart_state_s)
    assert 2e-3 < b.usb_worst_s < 2.2e-3
    assert b.usb_best_s < 100e-6


# ------------------------------------------------------------------ accuracy and the report


TINY = run.BenchOptions(seeds=(1,), lookaheads=(0.03, 0.12), scenarios=("s_curve",), workers=1, ticks=1000,
                        loop_rates=(), loop_duration_s=1.0,
                        speed_cases=(("s_curve 3 s", "configs/scenarios/s_curve.yaml", None, 3.0),), speed_repeats=1,
                        import_modules=("yaml",), import_repeats=1, sim_rss_duration_s=1.0,
                        ctl_counts=(32,), ctl_estops=5,
                        paths_cases=("figure_eight_361",), paths_long=(2000,), robots=1,
                        foxglove_duration_s=2.0, mcap_duration_s=1.0, mcap_repeats=1)


@pytest.fixture(scope="module")
def tiny_results() -> run.Results:
    return run.measure_all(TINY, "pytest tiny", say=lambda _t: None, progress=None)


@pytest.mark.slow
def test_short_scenario_both_controllers_complete(tiny_results: run.Results) -> None:
    row = tiny_results.accuracy.table["s_curve"]
    for name in ("dynamic", "kinematic"):
        cell = row[name]
        assert cell.all_completed, f"{name}: {cell.faults}"
        assert cell.stats["rms_tracking_m"].median < 5e-3
        assert cell.stats["rms_cross_track_m"].median < 5e-3
        assert cell.stats["sim_duration_s"].median < 20.0
    assert row["seed"].runs == 1


@pytest.mark.slow
def test_sweep_keeps_the_lookahead_with_the_best_worst_case(tiny_results: run.Results) -> None:
    acc = tiny_results.accuracy
    worst = {r.lookahead_m: r.worst_m for r in acc.sweep}
    assert set(worst) == {0.03, 0.12}
    assert acc.best.worst_m == min(worst.values())
    assert acc.table["s_curve"]["kinematic"].lookahead_m == acc.best.lookahead_m


def _record(scenario: str, lookahead: float, rms: float, completed: bool) -> accuracy.RunRecord:
    job = accuracy.Job(scenario, f"{scenario}.yaml", "kinematic", 1, lookahead)
    metrics = {m: rms for m in accuracy.METRICS}
    return accuracy.RunRecord(job, metrics, completed, "" if completed else "gyro saturated")


def test_a_lookahead_that_faults_early_does_not_win() -> None:
    recs = [_record("a", 0.02, 1e-5, False), _record("b", 0.02, 1e-5, True),
            _record("a", 0.05, 4e-4, True), _record("b", 0.05, 2e-4, True)]
    rows = accuracy.sweep_rows(accuracy.aggregate(recs), ["a", "b"], [0.02, 0.05])
    best = accuracy.best_lookahead(rows)
    assert best.lookahead_m == 0.05
    assert best.worst_scenario == "a" and best.worst_m == pytest.approx(4e-4)
    assert rows[0].incomplete == ("a",)


@pytest.mark.slow
def test_document_has_every_section(tiny_results: run.Results, tmp_path) -> None:
    doc = run.render_document(tiny_results)
    for title in run.SECTIONS:
        assert f"\n## {title}\n" in doc, title
    assert "| s_curve | dynamic |" in doc
    assert "### Kinematic lookahead sweep" in doc
    assert "not evaluated" in doc  # the encoder-radius pair was not in this run
    assert f"Kept: **{tiny_results.accuracy.best.lookahead_m:.2f} m**" in doc
    assert "pytest tiny" in doc
    n = min(run.OWN_COMMAND)
    assert run.OWN_COMMAND[n] in doc  # not measured in a full run: the section names its command
    kept = run.render_document(tiny_results, f"# Benchmarks\n\n{run._header(n)}\n\nmeasured by hand | 1 |\n")
    assert run.section_body(kept, n) == ["measured by hand | 1 |"]
    adapt = tiny_results.adapt
    assert set(adapt.grid) == {("s_curve", r, on) for r in adaptation.RATES_HZ for on in (False, True)}
    assert "| s_curve | " in doc and "identify on sim-offset-mass.yaml" in doc
    odo = adapt.odometry
    assert abs(odo.r_3_after - odo.r_3_true) < 0.2 * abs(odo.r_3_before - odo.r_3_true)  # calibration helps
    assert odo.circle["calibrated"].true < 0.2 * odo.circle["uncalibrated"].true
    assert tiny_results.startup.imports[0].module == "yaml" and tiny_results.startup.imports[0].median_ms > 0
    assert tiny_results.startup.sim.maxrss_kb > 10_000  # a Python with numpy is tens of MiB at least
    assert [r.name for r in tiny_results.speed] == ["s_curve 3 s"] and "| s_curve 3 s | 3.0 s |" in doc
    assert all(r.command_cpu_x > 1.0 and r.loop_x > 1.0 for r in tiny_results.speed)  # faster than real time
    assert tiny_results.startup.loop_loads == {"yaml": True}
    assert "| 32 | idle | 5/5 |" in doc and "| 32 | dribbling | 5/5 |" in doc  # every estop answered
    assert "| figure_eight_361 |" in doc and "| 2000 |" in doc  # paths as given
    robots = tiny_results.robots
    assert robots is not None and len(robots.robots) == 1 and len(robots.runs) == 6
    assert "| dynamic | " in doc and "| kinematic | " in doc and "bench/population.py" in doc
    assert "### The velocity mode" in doc and "| drive | " in doc
    assert doc.count("| yes | completed |") == 5  # every wiring fault fixed, its figure-eight completed
    assert "### Harsh population, commissioned" in doc and "| commissioned (" in doc
    assert ("| missed ticks (in" in doc) == (tiny_results.live.foxglove is not None)
    assert "| lane change 5 m, 0.9 m/s | 9.3 V, measured | " in doc  # section 12, the supply voltage
    out = tmp_path / "BENCHMARKS.md"
    out.write_text(doc)
    assert out.read_text().count("\n## ") == len(run.SECTIONS)


def test_quick_preset_is_smaller_than_full() -> None:
    assert len(run.QUICK.seeds) == 1 and len(run.FULL.seeds) == 3
    assert run.FULL.ticks >= 100_000 > run.QUICK.ticks
    assert run.FULL.loop_duration_s == 30.0 and run.QUICK.loop_duration_s == 5.0
    assert tuple(run.FULL.loop_rates) == (100, 200, 500, 1000)
    assert run.FULL.workers == 2


def test_population_robots_are_physically_consistent() -> None:
    """bench/population.py: a fixed seed gives the same robots; each is a valid config within the
    stated ranges, its belief and truth a few percent apart."""
    from bench import population
    from ddrt.path.spec import speed_limits

    a, b = population.population(40), population.population(40)
    assert [r.sections for r in a] == [r.sections for r in b]
    for r in a:
        assert 1.0 <= r.mass <= 19.0 and 6.0 <= r.supply_v <= 24.0
        cfg = population.config_of(r, "figure8", "dynamic")
        robot, plant = cfg.robot, cfg.plant
        total = robot.m_p + robot.m_L + robot.m_R + robot.m_3
        assert total == pytest.approx(r.mass)
        for name in ("m_p", "I_p", "L", "r_L", "H"):
            assert abs(getattr(plant, name) / getattr(robot, name) - 1.0) <= 0.05 + 1e-12, (r.name, name)
        assert abs(plant.r_3 / robot.r_3 - 1.0) <= 1e-3 + 1e-12
        assert cfg.sim.command_latency_s > 0.0 and cfg.sim.sensor_latency_s > 0.0
        assert cfg.limits.v_max is None and cfg.limits.accel is None  # every other key at default
        assert 0.3 < speed_limits(cfg).v_max < 2.5


def test_the_population_campaign_gives_each_robot_its_described_config() -> None:
    """bench/population.py's campaign, expanded as `ddrt sweep` expands it, gives each robot the
    config its config_of() describes."""
    from bench import population
    from ddrt.sweep.cases import expand

    plan = expand(population.campaign(2))
    robots = population.population(2)
    assert len(plan.cases) > 0
    for case in plan.cases:
        r = robots[int(str(case.params["robot"])[1:])]
        assert case.config.raw == population.config_of(r, case.params["path"], case.params["variant"]).raw


# ------------------------------------------------------------------ section 9: paths as given


@pytest.mark.slow
@pytest.mark.parametrize("name", ["circle_1cm", "teach_repeat"])
def test_recordings_closed_loop_meet_the_targets(name) -> None:
    row = paths_as_given.measure_case(path_inputs.CASES[name](), seed=1, exact=False)
    r = row.run
    assert r.completed
    assert r.time_s <= row.target_s
    assert r.true_rms_m < path_inputs.TARGET_TRUE_RMS_M
    assert r.domega_rms < path_inputs.TARGET_DOMEGA_RMS
    assert r.saturated <= path_inputs.TARGET_SATURATION


# ------------------------------------------------------------------ section 11: Foxglove, MCAP, velocity mode


def test_velocity_mode_tick_cost_and_stop_within_the_bound() -> None:
    r = velocity_mode.measure(load_config(SIM_YAML), ticks=2000)
    assert 0.0 < r.drive.p50_us < 1000.0 and 0.0 < r.follow.p50_us < 1000.0
    assert [s.jerk_max for s in r.stops] == [load_config(SIM_YAML).drive.jerk_max, None]
    for s in r.stops:
        assert s.still_s <= s.bound_s + 0.05 and s.travel_m <= s.bound_m + 0.01, s
        assert s.travel_m > s.bound_m - 0.05  # it drove on through the timeout
    text = "\n".join(velocity_mode.render(r))
    assert "| drive | " in text and "| follow | " in text and "| none | " in text


@pytest.mark.slow
@pytest.mark.skipif(bool(run.foxglove_missing()), reason=run.foxglove_missing() or "available")
def test_foxglove_section_quick_measures_both_runs_and_the_recording() -> None:
    live = run.measure_live(dataclasses.replace(run.QUICK, ticks=2000))
    fx = live.foxglove
    assert fx is not None
    for name in ("off", "on"):
        assert fx[name]["exit_code"] == 0 and fx[name]["runs"] == fx["pairs"] >= 2
        assert fx[name]["first_ticks"] > 0.5 * 200 * run.QUICK.foxglove_duration_s
    client = fx["on"]["client"]
    assert client["counts"].get("/state", 0) > 0.5 * fx["on"]["first_ticks"]  # the client saw the ticks
    assert len(fx["pair_p99_deltas_us"]) == fx["pairs"]
    assert 0.0 < client["age_ms"]["p50"] < 1000.0
    m = fx["mcap"]
    assert m["mcap"]["mcap_mb"] > 0.0 and m["csv"]["mcap_mb"] is None and m["csv"]["ticks"] == m["mcap"]["ticks"]
    text = "\n".join(run.render_live(live))
    for row in ("| tick compute p99 (us), on + VizRing.put |", "| missed ticks (in how many late wake-ups) |",
                "| peak RSS (MB) |",
                "| with --mcap |", "### The velocity mode"):
        assert row in text, row


def test_only_splices_one_section_and_keeps_every_other_line() -> None:
    h = run._header
    doc = "\n".join(["# Benchmarks", "", "intro", "", h(9), "", "nine", "| a |", "", h(10), "", "ten", ""])
    inserted = run.splice_section(doc, 11, ["eleven"])
    assert inserted == doc + "\n" + h(11) + "\n\neleven\n"
    replaced = run.splice_section(inserted, 11, ["eleven again", "", "more"])
    assert replaced == doc + "\n" + h(11) + "\n\neleven again\n\nmore\n"
    middle = run.splice_section(doc, 9, ["new nine"])  # a section followed by another
    assert middle == doc.replace("nine\n| a |\n", "new nine\n")
    no_ten = "\n".join(["# Benchmarks", "", h(9), "", "nine", "", h(11), "", "old", ""])
    assert run.splice_section(no_ten, 10, ["ten"]) == no_ten.replace(h(11), h(10) + "\n\nten\n\n" + h(11))
    with pytest.raises(SystemExit):
        run.main(["--only", "3", "--out", "/nonexistent/x.md"])  # only the sections in run.ONLY


def test_suite_under_load_runs_pytest_beside_hogs_and_stops_at_a_failure(tmp_path, capsys) -> None:
    from bench import suite_under_load as sul

    ok = sul.main(["--runs", "2", "--hogs", "1", "--log-dir", str(tmp_path), "--",
                   "tests/test_layout.py::test_hal_never_imports_sim_hal"])
    out = capsys.readouterr().out
    assert ok == 0 and out.count("1 passed") == 2 and "all runs passed" in out
    bad = sul.main(["--runs", "3", "--hogs", "0", "--log-dir", str(tmp_path), "--", "tests/no_such_test.py"])
    out = capsys.readouterr().out
    assert bad == 1 and "run 2/3" not in out and "stopped at run 1" in out
    hogs = sul.start_hogs(2)
    sul.stop_hogs(hogs)
    assert all(p.poll() is not None for p in hogs)
    assert sul.closing_line("x\n===== 3 passed, 1 failed in 2.0s =====\n") == "3 passed, 1 failed in 2.0s"


def test_a_full_run_keeps_the_sections_measured_by_their_own_commands() -> None:
    h = run._header
    own = sorted(run.OWN_COMMAND)
    old = "\n".join(["# Benchmarks", "", h(13), "", "old thirteen", "", h(own[0]), "", "kept text", "| a | b |", "",
                     h(own[1]), "", "", "second kept", "", ""])
    assert run.section_body(old, own[0]) == ["kept text", "| a | b |"]
    assert run.section_body(old, own[1]) == ["second kept"]
    assert run.section_body(old, own[2]) is None
    assert run.section_body("", own[0]) is None
    with pytest.raises(SystemExit):
        run.main(["--only", str(own[0]), "--out", "/nonexistent/x.md"])  # measured by its own command


def test_capabilities_hold_every_section_once_and_headlines_survive_a_splice() -> None:
    grouped = [n for _, group in run.CAPABILITIES for n in group]
    assert sorted(grouped) == list(range(1, len(run.SECTIONS))) and run.DOC_ORDER == (0, *grouped)
    assert not any("issue" in title.lower() for title in run.SECTIONS)
    h = run._header
    doc = "\n".join(["# Benchmarks", "", h(10), "", "**Headline:** 80 of 80.", "", "old table", "",
                     "# Timing and load", "", h(2), "", "two", ""])
    assert run.headline(doc, 10) == ["**Headline:** 80 of 80.", ""] and run.headline(doc, 2) == []
    spliced = run.splice_section(doc, 10, run.headline(doc, 10) + ["new table"])
    assert spliced == doc.replace("old table", "new table")  # the group heading ends the section
    assert run.section_body(spliced, 10) == ["**Headline:** 80 of 80.", "", "new table"]


@pytest.mark.parametrize("steps, turns", [
    ([(1, 0)] * 10 + [(0, 1)] * 10, 1),  # a 90 degree corner
    ([(1, 0), (0, 1)] * 10, 0),  # a staircase is its line
    ([(1, 0)] * 8 + [(1, 1)] * 8 + [(1, 0)] * 8, 2),  # two 45 degree turns
    ([(1, 0)] * 6 + [(1, 1), (1, 0)] * 5, 0),  # a 27 degree one, below 40
])
def test_grid_plans_counts_the_turns_the_cells_force(steps, turns) -> None:
    import numpy as np

    xy = 0.03 * (np.cumsum([(0, 0)] + steps, axis=0) + 0.5)
    assert grid_plans.forced_turns(xy, 0.03) == turns


def test_grid_plans_counts_both_lengths_and_drives_plans_in_closed_loop(capsys) -> None:
    assert grid_plans.main(["--seeds", "11", "--count", "4", "--closed-loop", "1"]) == 0
    out = capsys.readouterr().out
    assert "seed 11: " in out and "of 4 within" in out
    assert "against the path's length (a turn in place counting its wheels' travel): " in out
    assert "closed loop, 1 plans: 1 completed" in out
    rs = grid_plans.measure(11, 4)
    assert all(r.plan_length_m > 0.0 and r.blended_turns >= 0 for r in rs)
    assert sum(r.turns_in_place + r.blended_turns for r in rs) > 0  # the fuzz's plans turn
