"""The telemetry row (ddrt/loop/record.py) and the loop's states (ddrt/loop/states.py): the CSV
header and the state codes are an interface (telemetry files, Foxglove, scripts that read
them), so they are pinned here, and every column is checked against its source."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from ddrt.config import load_config
from ddrt.loop import COLUMNS, ControlLoop, LoopState, state_label
from ddrt.loop.record import ADAPTER_COLUMNS, LATER_COLUMNS, TICK_COLUMNS, fill_row_source
from ddrt.path.spec import load_path, speed_limits
from hal.registry import open_hal

REPO = Path(__file__).resolve().parents[1]
SIM_YAML = REPO / "configs" / "sim.yaml"
ADAPTIVE_YAML = REPO / "configs" / "adaptive" / "figure8_fast_offset_mass_adaptive.yaml"

# telemetry.csv's header as it has always been: a column is only ever added at the end.
HEADER = (
    "t", "x_est", "y_est", "theta_est", "v_est", "omega_est", "gyro_bias",
    "x_ref", "y_ref", "theta_ref", "v_ref", "omega_ref", "v_cmd", "omega_cmd",
    "tau_l", "tau_r", "duty_l", "duty_r", "sigma", "cross_track_est", "saturated", "state",
    "fresh", "hal_fault_ticks",
    "ad_m_k", "ad_mbar", "ad_I", "ad_m_x", "ad_fric_l", "ad_fric_r", "ad_active",
    "battery_v", "hw_estop",
    "x_map", "y_map", "theta_map", "std_x", "std_y", "std_theta", "cov_xy", "fixes",
    "wheel_slip",
)
# The state column's codes as they have always been.
CODES = ("idle", "following", "stopping", "stopped", "estop", "fault", "holding", "driving")


def test_the_header_is_the_declared_columns_in_order_and_unchanged() -> None:
    assert COLUMNS == HEADER
    assert tuple(c.name for c in TICK_COLUMNS + ADAPTER_COLUMNS + LATER_COLUMNS) == COLUMNS
    assert len(set(COLUMNS)) == len(COLUMNS)


def test_the_generated_row_writes_each_column_at_its_own_index_once() -> None:
    src = fill_row_source()
    for i, name in enumerate(COLUMNS):
        assert src.count(f"  # {name}\n") == 1 and f"r[{i}] = " in src.split(f"  # {name}\n")[0].splitlines()[-1]


def test_state_codes_are_the_enum_values_and_labels_the_names() -> None:
    assert [s.label for s in LoopState] == list(CODES)
    assert [int(s) for s in LoopState] == list(range(len(CODES)))
    assert f"{LoopState.HOLDING}" == str(LoopState.HOLDING) == "holding"
    assert state_label(6) == "holding" and state_label(42) == "42" and state_label(-1) == "-1"


def _moving_loop(cfg_path: Path, ticks: int) -> ControlLoop:
    cfg = load_config(cfg_path, {"estimator": {"calibration_s": 0.2}})
    path = load_path({"shape": "circle", "radius": 0.5, "speed": 0.3}, speed_limits(cfg), paths=cfg.paths)
    hal = open_hal(cfg, start=path.start_pose, seed=1)
    loop = ControlLoop(cfg, hal)
    loop.calibrate(hal.sleep_until, hal.now)  # type: ignore[attr-defined]
    loop.follow(path, path.start_pose)
    t0 = hal.now()  # type: ignore[attr-defined]
    for i in range(ticks):
        hal.sleep_until(t0 + (i + 1) * loop.period)  # type: ignore[attr-defined]
        loop.tick()
    hal.close()
    return loop


@pytest.mark.parametrize("cfg_path", [SIM_YAML, ADAPTIVE_YAML], ids=["sim", "adaptive"])
def test_every_column_holds_its_source(cfg_path: Path) -> None:
    loop = _moving_loop(cfg_path, 300)
    row = dict(zip(COLUMNS, loop.row))
    est, sp, cmd, ref, sample = loop.estimator, loop.setpoint, loop.cmd, loop.reference, loop.sample
    assert loop.state == LoopState.FOLLOWING and ref is not None and sample is not None
    expected = {
        "t": sample.t, "x_est": est.x, "y_est": est.y, "theta_est": est.theta, "v_est": est.v,
        "omega_est": est.yaw.w, "gyro_bias": est.yaw.b, "x_ref": sp.x_d, "y_ref": sp.y_d,
        "theta_ref": sp.theta_d, "v_ref": sp.v_d, "omega_ref": sp.omega_d, "v_cmd": cmd.v_c,
        "omega_cmd": cmd.omega_c, "tau_l": cmd.tau_l, "tau_r": cmd.tau_r, "duty_l": loop.duty_l,
        "duty_r": loop.duty_r, "sigma": ref.sigma, "cross_track_est": ref.cross_track,
        "saturated": float(cmd.saturated), "state": 1.0, "fresh": 1.0, "hal_fault_ticks": 0.0,
        "battery_v": loop.power.v, "hw_estop": 0.0,
    }
    ad = loop.adapter
    if ad is None:
        expected.update({name: 0.0 for name in HEADER[24:31]})  # no adapter: the columns keep their zeros
    else:
        expected.update(dict(zip(HEADER[24:30], ad.theta)))
        expected["ad_active"] = float(loop.adapt_active)
        assert any(v != 0.0 for v in ad.theta)
    xm, ym, thm = est.map_pose()
    p = est.track.p_map
    expected.update({"x_map": xm, "y_map": ym, "theta_map": thm, "std_x": math.sqrt(p[0]), "std_y": math.sqrt(p[7]),
                     "std_theta": math.sqrt(p[14]), "cov_xy": p[1], "fixes": 0.0,
                     "wheel_slip": 0.0})
    assert set(expected) == set(COLUMNS)
    for name in COLUMNS:
        assert row[name] == expected[name] and isinstance(row[name], float), name
    assert row["std_x"] > 0.0 and row["std_theta"] > 0.0  # moving: the uncertainty has grown
    assert row["sigma"] > 0.01 and row["v_ref"] > 0.0 and math.isfinite(row["v_cmd"])  # really moving
    assert row["battery_v"] == 12.0 == loop.motor.supply_v  # the simulated supply, measured
