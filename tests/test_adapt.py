"""ddrt.core.adapt: the RLS estimate on synthetic motion, its gates, bounds and fallback, and the
closed loop with the 2 kg offset mass the controller is not told about."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from ddrt.core.adapt import NAMES, AdaptedDynamics, DynamicsAdapter
from ddrt.config import AdaptationConfig, ConfigError, load_config, with_overrides
from ddrt.loop import COLUMNS
from ddrt.core.model import Dynamics
from ddrt.core.motor import Motor
from ddrt.params.motor import MotorParams
from ddrt.path.spec import resolve_path
from ddrt.simrun.runner import run_sim
from tests.support.repo import REPO, SIM_YAML

NOMINAL = Dynamics(m_k=4.3, mbar=0.0, I=0.048, m_x=0.083, L=0.108, R=0.108, r_L=0.05, r_R=0.05)
TRUE = AdaptedDynamics(m_k=6.5, mbar=-0.03, I=0.059, m_x=0.226, L=0.108, R=0.108, r_L=0.05, r_R=0.05,
                       fric_l=0.012, fric_r=-0.006)
MOTOR = Motor(MotorParams())
DT = 0.005


def _simulate(adapter: DynamicsAdapter, true: Dynamics, seconds: float, duties,
              state: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0),
              dt: float = DT) -> tuple[float, float, float, float]:
    """Integrate `true` driven by duties(t) through the motor model; feed the adapter.

    `state` (v, omega, duty_l, duty_r) continues a previous run; the final one is returned.
    """
    v, w, dl, dr = state
    sub = 10
    for k in range(int(round(seconds / dt))):
        adapter.update(v, w, dl, dr)
        dl, dr = duties(k * dt)
        for _ in range(sub):
            wl = (v - true.L * w) / true.r_L
            wr = (v + true.R * w) / true.r_R
            tl = MOTOR.electromagnetic_torque(dl, wl) - MOTOR.friction(wl)
            tr = MOTOR.electromagnetic_torque(dr, wr) - MOTOR.friction(wr)
            a, alpha = true.forward(v, w, tl, tr)
            v += a * dt / sub
            w += alpha * dt / sub
    return v, w, dl, dr


def _rich(t: float) -> tuple[float, float]:
    """Sum of sines on both wheels, both always driving forward (wheels well away from 0)."""
    base = 0.45 + 0.12 * math.sin(1.3 * t) + 0.06 * math.sin(3.1 * t + 0.4)
    turn = 0.12 * math.sin(0.9 * t + 1.0) + 0.05 * math.sin(2.3 * t)
    return base - turn, base + turn


def _adapter(**over) -> DynamicsAdapter:
    return DynamicsAdapter(NOMINAL, MOTOR, AdaptationConfig(**over), DT)


def test_converges_to_the_true_parameters_on_exact_model_data() -> None:
    # Exact-model data carries no residual: a light prior (noise_accel) lets the data decide.
    ad = _adapter(forgetting=1.0, noise_accel=0.03)
    _simulate(ad, TRUE, 30.0, _rich)
    est = dict(zip(NAMES, ad.theta))
    truth = {"m_k": TRUE.m_k, "mbar": TRUE.mbar, "I": TRUE.I, "m_x": TRUE.m_x, "fric_l": TRUE.fric_l,
             "fric_r": TRUE.fric_r}
    assert est["m_k"] == pytest.approx(truth["m_k"], rel=0.03)
    assert est["I"] == pytest.approx(truth["I"], rel=0.03)
    assert est["m_x"] == pytest.approx(truth["m_x"], rel=0.05)
    assert est["mbar"] == pytest.approx(truth["mbar"], abs=0.01)
    assert est["fric_l"] == pytest.approx(truth["fric_l"], abs=0.004)
    assert est["fric_r"] == pytest.approx(truth["fric_r"], abs=0.004)
    assert ad.trusted
    assert ad.res_adapt < ad.res_nominal


def test_no_update_without_excitation() -> None:
    """Straight at constant speed: no acceleration, so the estimate must not drift."""
    ad = _adapter()
    state = _simulate(ad, TRUE, 20.0, lambda t: (0.5, 0.5))
    late_updates = ad.updates
    before = list(ad.theta)
    _simulate(ad, TRUE, 10.0, lambda t: (0.5, 0.5), state)
    # After the start-up transient has died out, no further update happens.
    assert ad.updates == late_updates
    assert all(abs(a - b) <= 1e-6 * max(1.0, abs(b)) for a, b in zip(ad.theta, before))


def test_no_update_near_zero_wheel_speed() -> None:
    """Slow motion (friction-dominated) is gated out even when it accelerates."""
    ad = _adapter()
    _simulate(ad, TRUE, 10.0, lambda t: (0.03 + 0.03 * math.sin(2 * t), 0.03 + 0.03 * math.sin(2 * t)))
    assert ad.updates == 0
    assert ad.theta == ad.theta0
    assert not ad.trusted


def test_estimates_stay_within_bounds_and_h_positive_definite() -> None:
    """Data from a robot far outside the bounds: clamped, never outside, never singular."""
    ad = _adapter()
    huge = AdaptedDynamics(m_k=40.0, mbar=0.5, I=0.6, m_x=2.0, L=0.108, R=0.108, r_L=0.05, r_R=0.05)
    _simulate(ad, huge, 15.0, _rich)
    assert ad.updates > 100
    for x, lo, hi in zip(ad.theta, ad.lo, ad.hi):
        assert lo <= x <= hi
    assert ad.theta[0] == pytest.approx(ad.hi[0])  # the mass hit its bound
    m_k, mbar, inertia = ad.theta[0], ad.theta[1], ad.theta[2]
    assert m_k * inertia - mbar * mbar > 0.0


def test_fallback_on_non_finite_input_and_blend_towards_target() -> None:
    ad = _adapter(min_updates=50)
    _simulate(ad, TRUE, 8.0, _rich)
    assert ad.trusted
    d1 = ad.blend(0.5)
    assert NOMINAL.m_k < d1.m_k < ad.theta[0]  # part of the way, not a jump
    for _ in range(100):
        d2 = ad.blend(0.5)
    assert d2.m_k == pytest.approx(ad.theta[0], rel=1e-6)
    ad.update(float("nan"), 0.0, 0.5, 0.5)
    assert ad.fallbacks == 1
    assert ad.theta == ad.theta0 and not ad.trusted
    assert ad.blend(100.0).m_k == pytest.approx(NOMINAL.m_k)


def test_not_trusted_before_min_updates() -> None:
    ad = _adapter(min_updates=10_000)
    _simulate(ad, TRUE, 5.0, _rich)
    assert 0 < ad.updates < 10_000
    assert not ad.trusted
    assert ad.target() == ad.theta0


def test_adapted_dynamics_inverse_undoes_forward_with_friction() -> None:
    tl, tr = TRUE.inverse(0.4, 0.7, 0.3, -1.2)
    a, alpha = TRUE.forward(0.4, 0.7, tl, tr)
    assert a == pytest.approx(0.3, abs=1e-9)
    assert alpha == pytest.approx(-1.2, abs=1e-9)
    plain_l, _ = Dynamics.inverse(TRUE, 0.4, 0.7, 0.3, -1.2)
    assert tl - plain_l == pytest.approx(TRUE.fric_l * math.tanh((0.4 - 0.108 * 0.7) / (0.05 * 0.2)))


def test_update_cost_is_small() -> None:
    ad = _adapter()
    n = 4000
    t0 = time.thread_time()  # the CPU it takes, which a loaded host does not inflate
    for i in range(n):
        ad.update(0.5 + 0.2 * math.sin(i * 0.01), math.sin(i * 0.013), 0.5, 0.4)
    per_tick = (time.thread_time() - t0) / n
    assert ad.updates > n // 2
    assert per_tick < 300e-6  # measured ~25 us; a 200 Hz tick has 5000 us


def test_the_prior_weighs_the_same_in_seconds_at_any_rate() -> None:
    """The rows of successive ticks are nearly the same sample: the same seconds of motion move
    the estimate as far at 1 kHz as at 200 Hz (counted per tick, 1 kHz would move it ~5x
    faster towards the data), and a heavier prior (noise_accel) moves it less."""
    moved = {}
    for dt in (0.005, 0.001):
        ad = DynamicsAdapter(NOMINAL, MOTOR, AdaptationConfig(forgetting=1.0), dt)
        _simulate(ad, TRUE, 3.0, _rich, dt=dt)
        moved[dt] = (ad.theta[0] - NOMINAL.m_k) / (TRUE.m_k - NOMINAL.m_k)
    assert 0.05 < moved[0.005] < 1.0
    assert moved[0.001] == pytest.approx(moved[0.005], rel=0.25)
    heavy = _adapter(forgetting=1.0, noise_accel=3.0)
    _simulate(heavy, TRUE, 3.0, _rich)
    assert 0.0 < (heavy.theta[0] - NOMINAL.m_k) / (TRUE.m_k - NOMINAL.m_k) < 0.7 * moved[0.005]


def test_estimate_is_used_only_when_clearly_better_than_the_configured_model() -> None:
    """min_improvement changes nothing the adapter learns, only when its estimate is used: from
    the same data, an estimate whose RMS residual is a fraction q of the configured model's is
    used under min_improvement < 1 - q and not above it."""
    probe = _adapter(min_updates=50, min_improvement=0.0)
    _simulate(probe, TRUE, 8.0, _rich)
    q = math.sqrt(probe.res_adapt / probe.res_nominal)
    assert probe.trusted and q < 0.9
    for margin, used in ((-0.05, True), (0.05, False)):
        ad = _adapter(min_updates=50, min_improvement=1.0 - q + margin)
        _simulate(ad, TRUE, 8.0, _rich)
        assert ad.theta == probe.theta
        assert ad.trusted is used
        assert ad.target() == (ad.theta if used else ad.theta0)


def test_learnt_friction_fades_out_below_min_wheel_speed() -> None:
    """The friction is learnt only with both wheels faster than min_wheel_speed: below it the
    compensator's share fades linearly to zero instead of switching sign at a reversal."""
    d = AdaptedDynamics(m_k=4.3, mbar=0.0, I=0.048, m_x=0.0, L=0.1, R=0.1, r_L=0.05, r_R=0.05,
                        fric_l=0.02, fric_r=0.02, fric_full_speed=1.0)
    full = d._wheel(2.0, 0.02)
    assert full == pytest.approx(0.02 * math.tanh(2.0 / 0.2))
    assert d._wheel(0.5, 0.02) == pytest.approx(0.5 * 0.02 * math.tanh(0.5 / 0.2))
    assert d._wheel(0.0, 0.02) == 0.0
    assert d._wheel(-0.5, 0.02) == pytest.approx(-d._wheel(0.5, 0.02))
    ad = _adapter()
    assert ad.estimate().fric_full_speed == ad.cfg.min_wheel_speed == ad.blend(0.1).fric_full_speed


@pytest.mark.parametrize("key,value", [("bound_ratio", 1.0), ("filter_hz", 0.0), ("blend_s", -1.0),
                                       ("min_wheel_speed", -0.5), ("forgetting", 0.5), ("noise_accel", 0.0),
                                       ("min_improvement", 1.0), ("min_improvement", -0.1)])
def test_bad_config_names_the_key(key: str, value: float) -> None:
    with pytest.raises(ConfigError, match=f"controller.adaptation.{key}"):
        load_config(SIM_YAML, {"controller": {"adaptation": {key: value}}})


# --------------------------------------------------------------------------- closed loop


def _run(scenario: str, enabled: bool, rate_hz: float = 200.0, **over):
    cfg = load_config(REPO / "configs/scenarios" / scenario)
    cfg = with_overrides(cfg, {"controller": {"rate_hz": rate_hz, "adaptation": {"enabled": enabled, **over}}})
    return cfg, run_sim(cfg, resolve_path(cfg))


def _laps(result, laps: int = 5) -> list[float]:
    """Estimated-pose RMS cross-track of each lap (by progress along the path)."""
    from ddrt.path.sampled import distances_to_polyline
    from ddrt.simrun.metrics import path_polyline
    d = distances_to_polyline(path_polyline(result.path), np.c_[result.column("x_est"), result.column("y_est")])
    lap = result.path.length / laps
    k = np.minimum((result.column("sigma") / lap).astype(int), laps - 1)
    return [float(np.sqrt(np.mean(d[k == i] ** 2))) for i in range(laps)]


@pytest.mark.slow
def test_offset_mass_figure8_fast_is_identified_and_tracks_as_the_nominal_robot() -> None:
    """The 2 kg offset mass at 1 kHz, where the model is what limits the tracking error: five laps
    of the 0.8 m/s figure-eight, the first being the adapter's learning lap."""
    five = str(REPO / "configs/paths/figure8_fast_5laps.yaml")

    def run(scenario: str, enabled: bool):
        cfg = load_config(REPO / "configs/scenarios" / scenario,
                          {"controller": {"rate_hz": 1000.0, "adaptation": {"enabled": enabled}}})
        return cfg, run_sim(cfg, resolve_path(cfg, five))

    cfg, off = run("figure8_fast_offset_mass.yaml", False)
    _, on = run("figure8_fast_offset_mass.yaml", True)
    _, nominal = run("figure8_fast.yaml", False)
    assert on.metrics["completed"]
    truth = Dynamics.from_params(cfg.plant)
    assert on.column("ad_m_k")[-1] == pytest.approx(truth.m_k, rel=0.03)
    assert on.column("ad_I")[-1] == pytest.approx(truth.I, rel=0.03)
    assert on.column("ad_m_x")[-1] == pytest.approx(truth.m_x, rel=0.03)
    assert on.column("ad_active")[-1] == 1.0
    # Whole run: at least 2x better (measured 0.209 -> 0.037 mm). After the learning lap:
    # within 1.2x of the nominal robot without adaptation (measured 0.020 vs 0.043 mm).
    assert on.metrics["rms_tracking_m"] < 0.5 * off.metrics["rms_tracking_m"]
    assert max(_laps(on)[1:]) < 1.2 * max(_laps(nominal)[1:])
    # The true pose is mostly the odometry's business. Measured +15% (0.27 -> 0.31 mm) although
    # the estimated pose tracks 5x tighter: the 10% target of docs/adaptation.md is not met here (BENCHMARKS.md
    # section 7); this bound only guards against it getting worse.
    assert on.metrics["rms_cross_track_m"] < 1.3 * off.metrics["rms_cross_track_m"]


def test_offset_mass_at_200_hz_still_gains() -> None:
    """At the default rate the loop's own floor dominates, but the model still helps."""
    _, off = _run("figure8_fast_offset_mass.yaml", False)
    _, on = _run("figure8_fast_offset_mass.yaml", True)
    assert on.column("ad_active")[-1] == 1.0
    assert on.metrics["rms_tracking_m"] < 0.85 * off.metrics["rms_tracking_m"]  # measured 0.188 -> 0.099 mm


@pytest.mark.parametrize("rate_hz, bound", [pytest.param(1000.0, 1.1, marks=pytest.mark.slow), (200.0, 1.3)])
def test_no_harm_on_the_nominal_slow_figure8(rate_hz: float, bound: float) -> None:
    """0.3 m/s, nominal robot. At 1 kHz: within the 10% target of docs/adaptation.md on both poses. At 200 Hz
    adaptation is not proven harmless (measured +11% est, +8% true; why it stays off by
    default); the looser bound only guards against that getting worse."""
    _, off = _run("figure8_slow.yaml", False, rate_hz)
    _, on = _run("figure8_slow.yaml", True, rate_hz)
    assert on.column("ad_active").max() == 1.0  # it did adapt
    assert on.metrics["rms_tracking_m"] < bound * off.metrics["rms_tracking_m"]
    assert on.metrics["rms_cross_track_m"] < bound * off.metrics["rms_cross_track_m"]


@pytest.mark.slow
def test_slow_offset_mass_at_1_khz_is_helped() -> None:
    """0.3 m/s with the hidden mass, 1 kHz: measured 0.137 -> 0.036 mm."""
    _, off = _run("figure8_slow_offset_mass.yaml", False, 1000.0)
    _, on = _run("figure8_slow_offset_mass.yaml", True, 1000.0)
    assert on.metrics["rms_tracking_m"] < 0.6 * off.metrics["rms_tracking_m"]


@pytest.mark.slow
def test_slow_seed_circle_is_untouched() -> None:
    """31 mm/s: wheels below min_wheel_speed, so the adapter never updates and nothing changes."""
    _, off = _run("seed_circle_offset_mass.yaml", False)
    _, on = _run("seed_circle_offset_mass.yaml", True)
    assert on.column("ad_active").max() == 0.0
    assert on.metrics["rms_tracking_m"] == pytest.approx(off.metrics["rms_tracking_m"], rel=1e-9)


def test_telemetry_columns_appended_at_the_end() -> None:
    i = COLUMNS.index("ad_m_k")  # after the tick's columns, before any added since (battery_v, ...)
    assert COLUMNS[i:i + 7] == ("ad_m_k", "ad_mbar", "ad_I", "ad_m_x", "ad_fric_l", "ad_fric_r", "ad_active")
    assert COLUMNS[i - 1] == "hal_fault_ticks"
    assert COLUMNS[:2] == ("t", "x_est")
