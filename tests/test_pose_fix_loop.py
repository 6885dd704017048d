"""Pose fixes in the closed loop on the simulated robot (ddrt/core/pose_fix.py, ddrt/path/frame.py):
a path in `map` does not step the motor command at a fix, and with a fix every second a 2 %
gyro scale error stops moving the robot off its path (the target, on the plain and
the realistic plant), once the first fixes have taught the map the scale."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ddrt.path.frame import MapReference
from tests.support.fix_runs import cross_track, run_with_fixes

GYRO_2PC = {"sim": {"gyro": {"scale_error": 0.02}}}
CIRCLE = {"shape": "circle", "radius": 0.5, "laps": 2, "speed": 0.3}


def _steps(run, fix_ticks):  # type: ignore[no-untyped-def]
    """|duty change| between consecutive ticks: at the fixes (into the tick a fix was fused
    before, and into the next), and the largest elsewhere once moving (after 2 s)."""
    duty = np.array(run.duty)
    d = np.abs(np.diff(duty, axis=0)).max(axis=1)
    near = [j for i in fix_ticks for j in (i - 1, i) if 0 <= j < len(d)]
    at = d[near]
    mask = np.ones(len(d), bool)
    mask[near] = False
    mask[:400] = False
    return at, d[mask]


def test_a_fix_does_not_step_the_motor_command_of_a_path_in_map() -> None:
    # Fixes that disagree with the odometry by 8 mm sideways: each one moves the map pose.
    run = run_with_fixes(CIRCLE, 8.0, GYRO_2PC, offset=(0.0, 0.008, 0.0))
    assert run.state == "following"
    assert all(r["fused"] for r in run.replies) and len(run.replies) >= 6
    assert max(math.hypot(*r["correction"][:2]) for r in run.replies) > 0.002  # the fixes did move it
    at, steady = _steps(run, run.fix_ticks)
    assert at.max() <= steady.max(), (at.max(), steady.max())
    # The same fixes applied at once (map_blend_s 0) do step it: the check above can fail.
    jumpy = run_with_fixes(CIRCLE, 8.0, {**GYRO_2PC, "estimator": {"calibration_s": 0.2, "map_blend_s": 0.0}},
                           offset=(0.0, 0.008, 0.0))
    at0, steady0 = _steps(jumpy, jumpy.fix_ticks)
    assert at0.max() > 1.5 * steady0.max(), (at0.max(), steady0.max())


class _Frame:
    """What MapReference asks of the estimator's MapFrame: its correction and jump count."""

    def __init__(self) -> None:
        self.jumps = 0
        self.corr = (0.0, 0.0, 0.0)

    def correction(self) -> tuple[float, float, float]:
        return self.corr

    def fix(self, corr: tuple[float, float, float]) -> None:
        self.corr = corr
        self.jumps += 1


def _offsets(ref: MapReference, frame: _Frame, ticks: int, dt: float = 0.005,
             fixes: dict[int, tuple[float, float, float]] | None = None) -> np.ndarray:
    out = []
    for k in range(ticks):
        if fixes and k in fixes:
            frame.fix(fixes[k])
        out.append(ref._blend(dt))
    return np.array(out)


def test_the_blend_takes_a_fix_in_without_a_step_in_position_or_in_speed() -> None:
    """A fix of 10 mm: the reference's offset moves continuously and starts from the speed it
    had (an exponential blend would move 1/100 of the jump in the first 5 ms tick; this one
    about 1/5000), takes 59 % of it in map_blend_s and 91 % in twice that; a second fix while
    blending does not step the speed; without a blend the jump is taken at once."""
    frame = _Frame()
    ref = MapReference(None, (0.0, 0.0, 0.0), frame, 0.5, 0.005)  # type: ignore[arg-type]
    d = _offsets(ref, frame, 401, fixes={1: (0.010, 0.0, 0.0)})[:, 0]
    assert d[0] == 0.0 and abs(d[1]) < 0.010 / 2000  # continuous, and slow to start
    assert d[2] - d[1] > d[1]  # then gathering speed
    assert d[101] / 0.010 == pytest.approx(1.0 - 3.0 * math.exp(-2.0), abs=0.01)  # 59 % in 0.5 s
    assert d[201] / 0.010 == pytest.approx(1.0 - 5.0 * math.exp(-4.0), abs=0.01)  # 91 % in 1 s
    frame2 = _Frame()
    ref2 = MapReference(None, (0.0, 0.0, 0.0), frame2, 0.5, 0.005)  # type: ignore[arg-type]
    d2 = _offsets(ref2, frame2, 120, fixes={1: (0.010, 0.0, 0.0), 60: (0.0, 0.0, 0.0)})[:, 0]
    speed = np.diff(d2)
    assert abs(speed[59] - speed[58]) < 0.1 * abs(speed[58])  # the second fix does not step the speed
    frame3 = _Frame()
    ref3 = MapReference(None, (0.0, 0.0, 0.0), frame3, 0.0, 0.005)  # type: ignore[arg-type]
    assert _offsets(ref3, frame3, 3, fixes={1: (0.010, 0.0, 0.0)})[1, 0] == pytest.approx(0.010)


def test_without_fixes_map_is_odom_and_a_path_in_map_is_followed_as_in_odom() -> None:
    run = run_with_fixes(CIRCLE, 3.0, fixes=False)
    assert run.state == "following" and not run.replies
    # No fix: the map pose is the odometry's own, so the path is followed as ever (sub-mm).
    ct = cross_track(run.path, np.array(run.true_xy))
    assert ct.max() < 0.002


# The realistic plant of configs/scenarios/realistic/figure8_cheap_sensors.yaml with the 2 %
# scale error: a bias drifting 0.01 deg/s per second, the register held, the MCU's clock off,
# a slipping omni wheel. The estimator keeps its defaults: its error model's bias walk
# (estimator.uncertainty_bias_walk) allows for such a drift.
REALISTIC_PLANT = {"gyro": {"scale_error": 0.02, "drift_dps_per_s": 0.01, "register_hold": True, "clock_ppm": 5000.0},
                   "encoder": {"slip": {"mean": -0.003, "sigma": 0.001, "tau_s": 20.0}}}
REALISTIC = {"sim": REALISTIC_PLANT}
BIG_CIRCLE = {"shape": "circle", "radius": 1.0, "laps": 4, "speed": 0.4}


@pytest.mark.slow
@pytest.mark.parametrize("plant", [GYRO_2PC, REALISTIC], ids=["plain", "realistic"])
@pytest.mark.parametrize("seed", [1, 2])
def test_fixes_every_second_hold_a_robot_with_a_2pc_gyro_scale_error_on_its_path(plant: dict, seed: int) -> None:
    """The target's case: a fix every second (5 mm, 1 degree, 0.1 s late), 60 s on a 1 m circle
    at 0.4 m/s with an uncalibrated 2 % gyro scale error, default estimator settings."""
    free = run_with_fixes(BIG_CIRCLE, 60.0, plant, fixes=False, seed=seed)
    fixed = run_with_fixes(BIG_CIRCLE, 60.0, plant, seed=seed)
    ct_free = cross_track(free.path, np.array(free.true_xy))
    ct = cross_track(fixed.path, np.array(fixed.true_xy))
    assert len(ct) > 11000 and len(ct_free) > 11000  # a minute of driving, both
    assert ct_free.max() > 0.030
    # Every fix is taken, the realistic plant's drifting bias included (the error model allows
    # for it; with estimator.uncertainty_bias_walk 0 a sixth of them were outliers).
    assert all(r["fused"] for r in fixed.replies) and len(fixed.replies) >= 59
    # From 6 s on the robot stays within 10 mm of the path. The first seconds are the scale
    # being learnt from 5 mm / 1 degree fixes (16 to 23 mm at 3.3 s on these two seeds, as a
    # gyro with no scale error at all does on some: docs/BENCHMARKS.md section 15); even then
    # the robot is never as far off as it drifts without fixes.
    assert ct[1200:].max() < 0.010, ct[1200:].max()
    assert ct.max() < 0.030, ct.max()
    learnt = fixed.replies[-1]["learnt"]["gyro_scale"]
    assert learnt == pytest.approx(1.0 / 1.02 - 1.0, abs=0.003)


@pytest.mark.slow
def test_a_bias_drift_the_error_model_does_not_allow_for_turns_fixes_into_outliers() -> None:
    """The realistic plant's drifting bias with the bias walk of the bias filters alone (1e-5
    rad/s per sqrt(s), estimator.uncertainty_bias_walk at 0): the map grows
    sure of a heading that is drifting away, and fixes are refused."""
    told_nothing = {"sim": REALISTIC_PLANT, "estimator": {"calibration_s": 0.2, "uncertainty_bias_walk": 0.0}}
    run = run_with_fixes(BIG_CIRCLE, 30.0, told_nothing)
    assert sum(1 for r in run.replies if r.get("outlier")) >= 2


def test_the_first_seconds_peak_is_fix_noise_read_as_a_scale_error() -> None:
    """Why the first seconds peak: with a gyro that has no scale error at all, a model that does
    not know its scale (the default 1.73 %) reads a 3-sigma sideways error of the second fix as
    one and the robot leaves the path by more than 10 mm; told the scale is known (0.3 %, a
    calibrated gyro), the same fixes move it by less."""
    exact = {"sim": {"gyro": {"scale_error": 0.0}}}
    unknown = run_with_fixes(BIG_CIRCLE, 6.0, exact, seed=2)
    known = run_with_fixes(BIG_CIRCLE, 6.0, {**exact, "estimator": {"calibration_s": 0.2, "gyro_scale_std": 0.003}},
                           seed=2)
    assert unknown.replies[1]["learnt"]["gyro_scale"] > 0.01  # the second fix taught a 1 %+ scale error
    assert cross_track(unknown.path, np.array(unknown.true_xy)).max() > 0.010
    assert cross_track(known.path, np.array(known.true_xy)).max() < 0.008


def test_a_reload_of_the_uncertainty_figures_rescales_without_a_jump() -> None:
    """estimator.* applies live: a new encoder_scale_std rescales its row of every covariance
    (so they stay positive definite), a new fix_history_s starts a fresh history at the
    present pose; the map pose does not move and fixes keep working."""
    from ddrt.config import load_config
    from ddrt.core.pose_fix import PoseFix
    from ddrt.loop import ControlLoop
    from ddrt.path import load_path
    from ddrt.path.spec import speed_limits
    from hal.registry import open_hal
    from tests.support.repo import SIM_YAML

    cfg = load_config(SIM_YAML, {"estimator": {"calibration_s": 0.2}})
    path = load_path(CIRCLE, speed_limits(cfg), paths=cfg.paths)
    hal = open_hal(cfg, start=path.start_pose, seed=1)
    try:
        loop = ControlLoop(cfg, hal)
        loop.calibrate(hal.sleep_until, hal.now)  # type: ignore[attr-defined]
        loop.follow(path, path.start_pose)
        t0 = hal.now()  # type: ignore[attr-defined]
        for i in range(400):
            hal.sleep_until(t0 + (i + 1) * loop.period)  # type: ignore[attr-defined]
            loop.tick()
        est = loop.estimator
        p_ss = est.track.p_map[3 * 6 + 3]
        pose = est.map_pose()
        cfg2 = load_config(SIM_YAML, {"estimator": {"calibration_s": 0.2, "encoder_scale_std": 0.02,
                                                    "fix_history_s": 1.0}})
        loop.reconfigure(cfg2)
        assert est.map_pose() == pose
        assert est.track.p_map[3 * 6 + 3] == pytest.approx(4.0 * p_ss)
        assert np.all(np.linalg.eigvalsh(np.array(est.track.p_map).reshape(6, 6)) > -1e-12)
        assert est.track.hist.cap == int(math.ceil(1.0 / loop.period)) + 2
        fix = None
        for i in range(400, 500):
            hal.sleep_until(t0 + (i + 1) * loop.period)  # type: ignore[attr-defined]
            loop.tick()
            if i == 460:  # the true pose now, fused 0.2 s later
                fix = PoseFix(*hal.robot.pose, (1e-4, 0, 0, 0, 1e-4, 0, 0, 0, 3e-4), est.t_est)  # type: ignore[union-attr]
        assert fix is not None
        reply = est.fuse_fix(fix)
        assert reply["fused"] and reply["d2"] < 3.0, reply
    finally:
        hal.close()
