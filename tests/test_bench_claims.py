"""Claims BENCHMARKS.md makes, rerun small with the benchmark's own scenario code: a payload put
on mid-run is learnt (bench/adaptation.py), a gyro bias step is learnt on the move
(bench/wheel_encoders.py), and a warm-up's drift is followed through TEMP_OUT
(bench/gyro_warmup.py). A tests/test_bench_*.py module tests bench/ and may import it; no other
test module does (tests/test_layout.py)."""

from __future__ import annotations

import dataclasses as dc

import pytest

from bench.adaptation import measure_events
from bench.gyro_warmup import SLOPE_DPS_PER_C, one_run
from bench.wheel_encoders import BIAS_STEP_AT_S, bias_step
from ddrt.config import load_config
from ddrt.path.spec import resolve_path
from ddrt.simrun.runner import run_sim


@pytest.mark.slow
def test_a_payload_put_on_mid_run_is_learnt() -> None:
    """Where adaptation is for: 1 kg put on at 8 s and a draggy floor patch on the 0.8 m/s
    figure-eight; from the payload on, the estimated pose tracks at least 1.5x better with
    adaptation (measured 2.5x, BENCHMARKS.md section 19)."""
    name = "realistic/payload_floor_fast.yaml"
    cells = measure_events((1,), 1, (name,))
    off, on = cells[(name, False)], cells[(name, True)]
    assert on[2] * 1.5 < off[2]
    assert on[0] < off[0]


@pytest.mark.slow
def test_bias_step_is_learnt_on_the_move_with_all_three_sensors() -> None:
    """A 0.5 deg/s bias step mid-run on the rectangle (no stop) is learnt within 10 s, and the
    true path is better than with the front encoder and gyro alone (generous bounds; the
    figures are in BENCHMARKS.md, bench/wheel_encoders.py)."""
    got = bias_step(8192)
    assert got["completed"] and got["first_stop_s"] > 10.0
    assert got["learnt_s"] <= 10.0 and abs(got["end_err_dps"]) < 0.1
    cfg = load_config("configs/scenarios/rectangle.yaml")
    cfg = dc.replace(cfg, sim=dc.replace(cfg.sim, gyro=dc.replace(cfg.sim.gyro, bias_step_dps=0.5,
                                                                  bias_step_at_s=BIAS_STEP_AT_S)))
    front_only = run_sim(cfg, resolve_path(cfg)).metrics["rms_cross_track_m"]
    assert got["true_rms"] < 0.7 * front_only


def test_through_the_loop_a_warm_up_leaves_the_heading_true() -> None:
    """ControlLoop on the realistic plant (bench/gyro_warmup.py's warm-up: 1 deg/s over 5 min),
    two 28 s drives with a stop after each: with TEMP_OUT read the heading ends within a few
    tenths of a degree, and the slope is learnt within 5 %; without it, degrees off."""
    with_temp = one_run(5.0, None, 1, drive_s=50.0)
    without = one_run(0.0, None, 1, drive_s=50.0)
    assert with_temp.stops == without.stops == 2 and not with_temp.fault
    assert abs(with_temp.heading_end_deg) < 0.3
    assert abs(without.heading_end_deg) > 3.0
    assert with_temp.slope_dps_per_c == pytest.approx(SLOPE_DPS_PER_C, rel=0.05)
