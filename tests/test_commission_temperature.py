"""`ddrt commission`'s rest step and the gyro's temperature: the die temperature read beside
the bias, the bias's slope measured from two rests far enough apart (and written), or left for
the stops to learn with the reason said."""

from __future__ import annotations

import io
import math
import random
from pathlib import Path
from typing import Any

import pytest
import yaml

from ddrt.commission import commission, session_for
from ddrt.commission.rest import MAX_SLOPE_DPS_PER_C, MIN_SPAN_C, temperature_slope
from ddrt.commission.session import Options
from tests.support.repo import REPO

SIM = REPO / "configs" / "sim.yaml"
START_C = 31.0
SLOPE = 0.1  # deg/s per degC, the plant's


def _session(tmp_path: Path, **over: Any) -> Any:
    src = tmp_path / "robot.yaml"
    data = {"extends": str(SIM), "sim": {"gyro": {"temp_start_c": START_C, "bias_per_c_dps": SLOPE}}}
    data.update(over)
    src.write_text(yaml.safe_dump(data))
    return session_for(src, Options(out=tmp_path / "out.yaml", from_sim_truth=True, figures=False), None,
                       yes=True, out=io.StringIO())


EMULATED = {"hal": {"backend": "real", "imu": {"bus": "sim"}, "bridge": {"url": "ddrtsim://robot"}}}


@pytest.mark.parametrize("over", [{"sensors": {"gyro_temp_hz": 5}}, EMULATED], ids=["sim", "real-driver-defaults"])
def test_the_rest_reads_the_die_and_leaves_the_slope_to_the_stops_at_one_temperature(
        tmp_path: Path, over: dict[str, Any]) -> None:
    s = _session(tmp_path, **over)
    commission(s, step="link")
    commission(s, step="rest")
    r = s.state.get("rest")
    assert r["temperature_c"] == pytest.approx(START_C, abs=0.01)  # TEMP_OUT's LSB is 1/340 degC
    assert "left for the stops" in r["temperature"] and "config" not in r
    assert r["pairs"] == [[pytest.approx(START_C, abs=0.01), pytest.approx(r["bias_dps"])]]


def test_a_second_rest_two_degrees_away_measures_the_slope_and_writes_it(tmp_path: Path) -> None:
    s = _session(tmp_path, sensors={"gyro_temp_hz": 5})
    commission(s, step="link")
    commission(s, step="rest")
    first = s.state.get("rest")
    # The rest before, as if taken with the die 3 degC colder: the plant's bias then was 0.3 deg/s lower.
    s.state.put("rest", dict(first, pairs=[[START_C - 3.0, first["bias_dps"] - 3.0 * SLOPE]]))
    commission(s, step="rest")
    r = s.state.get("rest")
    assert r["bias_per_c_dps"] == pytest.approx(SLOPE, abs=0.005)  # two 3 s rests' bias noise over 3 degC
    assert r["config"] == {"estimator": {"gyro_bias_per_c_dps": pytest.approx(SLOPE, abs=0.005)}}
    assert s.config("dynamics").estimator.gyro_bias_per_c_dps == pytest.approx(r["bias_per_c_dps"], abs=1e-5)
    commission(s, step="rest")  # a third rest at the same temperature as the second keeps the slope
    again = s.state.get("rest")
    assert again["bias_per_c_dps"] == pytest.approx(r["bias_per_c_dps"], abs=0.005) and again["config"]
    assert len(again["pairs"]) == 3


def test_without_temperature_reads_the_report_says_so(tmp_path: Path) -> None:
    s = _session(tmp_path)  # the simulated backend's default: TEMP_OUT not read
    commission(s, step="link")
    commission(s, step="rest")
    r = s.state.get("rest")
    assert r["temperature_c"] is None and "sensors.gyro_temp_hz is 0" in r["temperature"]
    assert "config" not in r and r["pairs"] == []


def test_the_slope_rule_over_random_rests() -> None:
    rng = random.Random(7)
    for _ in range(500):
        n = rng.randrange(0, 4)
        pairs = [[rng.uniform(20, 60), rng.uniform(-5, 5)] for _ in range(n)]
        temp, bias = rng.uniform(20, 60), rng.uniform(-5, 5)
        out = temperature_slope(pairs, bias, temp, 5.0)
        far = max(pairs, key=lambda p: abs(temp - p[0])) if pairs else None
        if far is None or abs(temp - far[0]) < MIN_SPAN_C:
            assert "config" not in out and "left for the stops" in out["temperature"]
            continue
        slope = (bias - far[1]) / (temp - far[0])
        if abs(slope) > MAX_SLOPE_DPS_PER_C:
            assert "config" not in out and "not written" in out["temperature"]
        else:
            assert out["bias_per_c_dps"] == pytest.approx(slope)
            assert out["config"]["estimator"]["gyro_bias_per_c_dps"] == pytest.approx(slope, abs=1e-5)
    assert "TEMP_OUT gave no reading" in temperature_slope([], 0.0, math.nan, 5.0)["temperature"]
