"""Reversing in closed loop where test_reverse.py does not go: the other controllers and
pursuit modes, adaptation, a start that backs straight onto its path, a stop and a sensor gap
on a reverse leg, the estimator's sign, and the energy of a reversed path against its mirror.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np
import pytest

from ddrt.config import load_config, with_overrides
from ddrt.loop import ControlLoop, LoopState
from ddrt.path.spec import load_path, speed_limits
from ddrt.simrun.runner import run_sim
from hal.registry import open_hal
from tests.support.repo import SIM_YAML
from tests.support.reverse_paths import THREE_POINT, parallel_park_points


def _cfg(**overrides: Any):
    cfg = load_config(SIM_YAML)
    return with_overrides(cfg, overrides) if overrides else cfg


def _three_point(cfg, tmp_path):
    f = tmp_path / "three_point.csv"
    f.write_text(THREE_POINT)
    return load_path(f, speed_limits(cfg), paths=cfg.paths)


def _reverse_mask(path, sigma: np.ndarray) -> np.ndarray:
    """Ticks whose progress lies on a reversing, driving interval of `path`."""
    d = np.asarray(path.direction)
    piv = np.asarray(path.seg_pivot)
    i = np.clip(np.searchsorted(path.sigma, sigma, side="right") - 1, 0, len(d) - 1)
    return (d[i] < 0) & ~piv[i]


def _drove_as_marked(path, r, *, xt_max: float) -> None:
    m = r.metrics
    assert m["completed"], m
    assert m["rms_cross_track_m"] < xt_max and m["final_pos_err_m"] < 5e-3, m
    assert m["saturated_fraction"] < 0.01, m
    rev = _reverse_mask(path, r.column("sigma"))
    v = r.column("v")
    assert rev.sum() > 50 and np.mean(v[rev] < 0.0) > 0.9 and v[rev].min() < -0.15
    fwd = ~rev & (r.column("v_ref") > 0.1)
    assert fwd.any() and np.all(v[fwd] > -0.02)  # forward legs are not driven backwards


@pytest.mark.parametrize("overrides, xt_max", [
    ({"controller": {"mode": "kinematic"}}, 6e-3),
    ({"pursuit": {"mode": "time"}}, 3e-3),
    ({"controller": {"adaptation": {"enabled": True}}}, 3e-3),
], ids=["kinematic", "time-indexed", "adaptation"])
def test_a_three_point_turn_under_each_mode(tmp_path, overrides, xt_max) -> None:
    cfg = _cfg(**overrides)
    path = _three_point(cfg, tmp_path)
    r = run_sim(cfg, path, seed=2, keep_rows=True)
    _drove_as_marked(path, r, xt_max=xt_max)


def test_the_estimated_speed_has_the_true_speed_sign_on_reverse_legs(tmp_path) -> None:
    cfg = _cfg()
    path = load_path(parallel_park_points(), speed_limits(cfg), paths=cfg.paths)
    r = run_sim(cfg, path, seed=3, keep_rows=True)
    v, v_est = r.column("v"), r.column("v_est")
    back = v < -0.02
    assert back.sum() > 100
    assert np.all(v_est[back] < 0.0)
    assert np.max(np.abs(v_est - v)) < 0.02


def test_a_robot_told_to_back_along_a_path_behind_it_does_not_turn_first() -> None:
    """The robot faces +x; the path runs from beside it towards -x, marked reverse: its heading
    along the path is the robot's own, so the start is a join driven backwards, no turn."""
    cfg = _cfg()
    lim = speed_limits(cfg)
    path = load_path({"shape": "line", "length": 0.8, "heading_deg": 180.0, "speed": 0.3, "reverse": True},
                     lim, paths=cfg.paths)
    assert path.theta[0] == pytest.approx(0.0, abs=1e-9)
    for start in ((0.0, 0.0, 0.0), (0.02, 0.03, 0.15), (0.0, -0.04, -0.3)):
        r = run_sim(cfg, path, seed=1, start=start, keep_rows=True)
        m = r.metrics
        assert m["completed"] and m["final_pos_err_m"] < 3e-3, (start, m)
        th, v = r.column("theta"), r.column("v")
        # The heading moves only by the join's approach (within 30 deg of the line), never round.
        assert np.max(np.abs(th - start[2])) < abs(start[2]) + math.radians(30.0), start
        assert v.max() < 0.03 and v.min() < -0.25, start  # it backed all the way
        assert r.column("x")[-1] == pytest.approx(-0.8, abs=3e-3)


def test_facing_the_way_a_reversed_path_travels_is_a_turn_of_half_a_circle() -> None:
    """The same line driven in reverse from a robot facing along its travel: it must face the
    other way to back along it, so it turns in place by pi first (the path's start heading)."""
    cfg = _cfg()
    path = load_path({"shape": "line", "length": 0.5, "heading_deg": 0.0, "speed": 0.3, "reverse": True},
                     speed_limits(cfg), paths=cfg.paths)
    r = run_sim(cfg, path, seed=1, start=(0.0, 0.0, 0.0), keep_rows=True)
    assert r.metrics["completed"]
    assert abs(math.remainder(r.column("theta")[-1], 2 * math.pi)) == pytest.approx(math.pi, abs=0.03)
    assert r.column("x")[-1] == pytest.approx(0.5, abs=3e-3)


# ---------------------------------------------------------------- stepped by hand


class _Stepper:
    """A calibrated loop on the unpaced simulated robot following `path`, ticked in sim time."""

    def __init__(self, cfg, path) -> None:
        self.path = path
        self.hal = open_hal(cfg, start=path.start_pose, seed=4)
        self.robot = self.hal.robot
        self.loop = ControlLoop(cfg, self.hal)
        self.loop.calibrate(self.hal.sleep_until, self.hal.now)
        self.loop.follow(path, path.start_pose)
        self.t0 = self.t = self.hal.now()
        self.rows: list[dict[str, float | str]] = []

    def run(self, until: Callable[["_Stepper"], bool], limit_s: float = 40.0) -> None:
        while not until(self) and self.t - self.t0 < limit_s and self.loop.state not in (LoopState.FAULT,):
            self.t += self.loop.period
            self.hal.sleep_until(self.t)
            self.loop.tick()
            v, _ = self.robot.velocity
            self.rows.append({"t": self.t - self.t0, "v": v, "v_ref": self.loop.setpoint.v_d,
                              "state": self.loop.state, "sigma": self.loop.reference.sigma})

    def close(self) -> None:
        self.hal.close()


def _on_reverse_leg(path, past: float) -> Callable[[_Stepper], bool]:
    cusp = path.cusps[0]
    return lambda s: s.loop.reference.sigma > cusp + past and s.robot.velocity[0] < -0.15


def test_a_stop_on_a_reverse_leg_brakes_towards_zero_and_never_backs_faster() -> None:
    cfg = _cfg()
    path = load_path(parallel_park_points(), speed_limits(cfg), paths=cfg.paths)
    s = _Stepper(cfg, path)
    try:
        s.run(_on_reverse_leg(path, 0.15))
        v0 = s.robot.velocity[0]
        assert v0 < -0.15
        n0 = len(s.rows)
        s.loop.stop()
        s.run(lambda st: st.loop.state == LoopState.STOPPED, limit_s=s.t - s.t0 + 3.0)
        after = s.rows[n0:]
        assert s.loop.state == LoopState.STOPPED and not s.loop.path_completed
        v_ref = np.array([r["v_ref"] for r in after])
        v = np.array([r["v"] for r in after])
        assert np.all(v_ref <= 1e-12) and np.all(np.diff(v_ref) >= -1e-12)  # towards zero from below
        assert v_ref[0] >= v0 - 0.01
        assert v.min() >= v0 - 0.02 and v.max() < 0.02  # never faster backwards, never forwards
        assert abs(v[-1]) < 0.01
        # At cfg.daemon.stop_decel (or the motors' braking, if lower) it takes about |v0| / decel.
        t_stop = after[-1]["t"] - after[0]["t"]
        assert t_stop == pytest.approx(abs(v0) / cfg.daemon.stop_decel, abs=0.25)
    finally:
        s.close()


def test_a_sensor_gap_on_a_reverse_leg_holds_and_resumes_backwards() -> None:
    cfg = _cfg()
    path = load_path(parallel_park_points(), speed_limits(cfg), paths=cfg.paths)
    s = _Stepper(cfg, path)
    try:
        s.run(_on_reverse_leg(path, 0.1))
        t_freeze = s.t - s.t0
        s.hal.freeze(s.t + 0.005, 0.150)
        s.run(lambda st: st.loop.state == LoopState.STOPPED)
        rec = s.loop.recovery
        assert s.loop.path_completed, (s.loop.state, s.loop.fault, rec)
        assert rec.holds == 1 and rec.resumes == 1 and rec.latched == 0, rec
        held = [r for r in s.rows if r["state"] == LoopState.HOLDING]
        assert held and held[0]["t"] >= t_freeze
        # Held and resumed backwards: the reference never goes forward on the reverse leg.
        later = [r for r in s.rows if r["t"] >= t_freeze]
        assert max(r["v_ref"] for r in later) <= 1e-9
        after = [r for r in later if r["t"] > held[-1]["t"]]
        assert min(r["v"] for r in after) < -0.1  # it backed on after the hold
        x, y, _ = s.robot.pose
        assert math.hypot(x - path.x[-1], y - path.y[-1]) < 5e-3
    finally:
        s.close()


# ---------------------------------------------------------------- energy against the mirror image


def _energy(cfg, spec: dict) -> tuple[float, float, float]:
    """(electromagnetic work, friction loss, kinetic energy left) in J over the run of `spec`."""
    path = load_path(spec, speed_limits(cfg), paths=cfg.paths)
    s = _Stepper(cfg, path)
    try:
        s.run(lambda st: st.loop.state == LoopState.STOPPED)
        assert s.loop.path_completed
        e = s.robot.energy
        v, w = s.robot.velocity
        return e.electromagnetic_j, e.friction_loss_j, abs(v) + abs(w)
    finally:
        s.close()


def test_a_reversed_path_takes_the_energy_of_its_mirror_image_driven_forward() -> None:
    """A ccw circle driven backwards is (v, omega) -> (-v, -omega) of the cw circle (its mirror
    image) driven forwards. The wheels' speeds are then the same up to sign and left/right, and
    so are the friction losses; the model's only terms that are not symmetric under the map,
    h = (-m_x omega^2, m_x v omega) (docs/model.md; m_x = m_p d_xc + m_3 H, the centre of mass
    ahead of the axle), do no work (eta . h = 0), and the kinetic energy is zero at both ends.
    So the motors' electromagnetic work (K i w at each wheel: the wheels' mechanical work plus
    friction) agrees; m_x only changes how the torque is split over time, hence a little the
    copper losses, which are not compared. Slip off, so both runs meet the same disturbances.
    The map keeps each wheel's speed magnitude on the same wheel; the left/right reflection (the
    ccw circle forwards) does not, and the simulated motors differ per wheel (configs/sim.yaml),
    so that one must differ: the comparison can fail."""
    cfg = _cfg(sim={"slip": {"probability": 0.0, "sigma_nm": 0.0}})
    base = {"shape": "circle", "radius": 0.4, "laps": 1.25, "speed": 0.5}
    em_b, fr_b, rest_b = _energy(cfg, {**base, "direction": "ccw", "reverse": True})
    em_f, fr_f, rest_f = _energy(cfg, {**base, "direction": "cw"})
    assert rest_b < 0.01 and rest_f < 0.01
    assert em_b > 0.5 and em_f > 0.5  # work was done (friction alone: ~0.6 N over 3 m)
    # Energy balance, run by run: electromagnetic work = friction losses + the kinetic energy
    # gained (none, rest to rest), to a few per cent (the robot's last mm/s, integration).
    for em, fr in ((em_b, fr_b), (em_f, fr_f)):
        assert abs(em - fr) < 1e-3 * em, (em, fr)
    assert em_b == pytest.approx(em_f, rel=0.01)
    assert fr_b == pytest.approx(fr_f, rel=0.01)
    em_swapped, _, _ = _energy(cfg, {**base, "direction": "ccw"})
    assert abs(em_swapped - em_f) > 0.03 * em_f


# ---------------------------------------------------------------- fuzz, end to end


def test_random_marked_reverse_manoeuvres_are_driven_end_to_end() -> None:
    """~50 random three-point turns, parking manoeuvres and zig-zags (lab/cusp_inputs.py),
    recorded with 1-2 mm of noise at 5-15 mm spacing and marked with negative v on the reverse
    legs, loaded and driven: each completes or is refused at load with a PathError, and the
    driven ones meet the targets for sampled input: the true pose within 3 mm RMS of the curve the
    samples came from on every run, the reference within the tolerance of every input point
    (the runs share each cusp, ddrt/path/cusp.py, so nothing is shifted onto it), and no turn
    in place where the curve has none."""
    from ddrt.path.spec import PathError
    from lab.cusp_inputs import random_manoeuvre
    from lab.path_inputs import curve_distance

    cfg = _cfg()
    lim = speed_limits(cfg)
    rng = np.random.default_rng(2024)
    driven = refused = shared = cusps = 0
    worst: list[float] = []  # true RMS from the curve
    for trial in range(50):
        m = random_manoeuvre(rng)
        speed = float(rng.uniform(0.15, 0.4))
        xy, v = m.recording(rng, speed, spacing=(0.005, 0.015), noise=float(rng.uniform(0.001, 0.002)))
        spec = {"points": [[float(a), float(b), float(c)] for (a, b), c in zip(xy, v)]}
        try:
            path = load_path(spec, lim, paths=cfg.paths)
        except PathError:
            refused += 1
            continue
        assert len(path.cusps) == m.cusps, trial
        cusps += m.cusps
        shared += path.conditioning.extra["cusps_shared"]
        a = path.arrays()
        assert path.deviation_m <= path.conditioning.tolerance_m, (trial, path.deviation_m)
        assert not np.any(a["seg_pivot"]), trial  # the curve turns nowhere in place
        r = run_sim(cfg, path, seed=trial, keep_rows=True)
        met = r.metrics
        assert met["completed"], (trial, met)
        assert met["saturated_fraction"] <= 0.01, (trial, met)
        d = curve_distance(m.xy(), np.column_stack((r.column("x"), r.column("y"))))
        rms = float(np.sqrt(np.mean(d ** 2)))
        worst.append(rms)
        # Measured: median 0.71 mm, worst 1.39 mm over these 50 (each run fitted alone and
        # shifted onto the previous one's end: median 1.77 mm, worst 4.51 mm, 3 above 3 mm).
        assert rms <= 3e-3, (trial, rms)
        driven += 1
    assert driven >= 45, (driven, refused)
    assert shared >= 0.9 * cusps, (shared, cusps)
    assert float(np.median(worst)) < 1.5e-3
