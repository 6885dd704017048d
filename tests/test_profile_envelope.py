"""The speed profile from the motors, checked by physics: the torques the dynamic model needs
along a profiled path stay within what the motors give at every sample (an independent check
with ddrt.core.model.inverse_dynamics and ddrt.core.motor.Motor), no sample could go faster,
mirror images give the same profile, a heavier robot is slower, headroom 0 reaches the motors'
limits; limits above the motors' are reported; the build stays fast."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from ddrt.config import load_config
from ddrt.core.envelope import Envelope, resolve_limits
from ddrt.core.model import Dynamics, inverse_dynamics, wheel_rates
from ddrt.core.motor import Motor
from ddrt.loop import LoopState
from ddrt.path import load_path
from ddrt.path.spec import speed_limits
from tests.support.repo import REPO, SIM_YAML

PATHS = REPO / "configs" / "paths"
DERIVED = {"limits": {"v_max": None, "accel": None, "torque_max_nm": None}}

# Robots: the seed robot with its limits derived from its motors; a heavy, slow one whose
# centre of mass is off to the side on unequal wheels; a light, quick one on a strong motor.
ROBOTS = {
    "seed": DERIVED,
    "heavy_asymmetric": {**DERIVED, "robot": {
        "m_p": 9.0, "d_yc": 0.02, "d_xc": 0.06, "I_p": 0.08, "r_L": 0.048, "r_R": 0.052, "L": 0.12, "R": 0.10,
        "motor": {"supply_v": 24.0, "resistance_ohm": 6.0, "k_nm_per_a": 0.9, "viscous_nms": 0.002,
                  "coulomb_nm": 0.06}}},
    "light_quick": {**DERIVED, "robot": {
        "m_p": 0.3, "m_L": 0.25, "m_R": 0.25, "m_3": 0.1, "I_p": 1.2e-3, "I_wL": 1.5e-4, "I_wR": 1.5e-4,
        "motor": {"supply_v": 7.4, "resistance_ohm": 2.0, "k_nm_per_a": 0.12, "viscous_nms": 0.0003,
                  "coulomb_nm": 0.008}}},
}
# The kinematic caps opened wide, so the motors are the only limit.
WIDE = {"limits": {"lateral_accel": 1e3, "omega_max": 25.0, "alpha_max": 1e4}, "sensors": {"gyro_range_dps": 2000}}
SPECS = {
    "figure8": {"shape": "figure_eight", "width": 1.2, "height": 0.6, "speed": 3.0},
    "rectangle": {"shape": "rectangle", "width": 1.2, "height": 0.8, "direction": "ccw"},
    "s_curve": PATHS / "s_curve.yaml",
    "sparse": PATHS / "waypoints_sparse.csv",
    "circle": {"shape": "circle", "radius": 0.25, "laps": 1.5, "direction": "cw"},
}


def _cfg(robot: str, headroom: float | None = None, extra: dict | None = None):
    over = {k: dict(v) if isinstance(v, dict) else v for k, v in ROBOTS[robot].items()}
    if headroom is not None:
        over["limits"] = dict(over["limits"], feedback_headroom=headroom)
    for k, v in (extra or {}).items():
        over[k] = dict(over.get(k, {}), **v)
    return load_config(SIM_YAML, over)


def _path(cfg, spec):
    return load_path(spec, speed_limits(cfg), paths=cfg.paths)


def envelope_use(cfg, path) -> tuple[float, float]:
    """Largest |duty| / duty_max and |tau| / torque limit over every sample, each interval's
    acceleration at its first sample (what the Path reports there), from the model and the
    motor directly."""
    robot = cfg.robot
    motor = Motor(cfg.robot_motor)
    m = cfg.robot_motor
    t_cap = m.k_nm_per_a * cfg.limits.duty_max * m.supply_v / m.resistance_ohm
    if cfg.limits.torque_max_nm is not None:
        t_cap = min(t_cap, cfg.limits.torque_max_nm)
    arr = path.arrays()
    v, w, a, al = arr["v"], arr["omega"], arr["a"], arr["alpha"]
    duty = tau = 0.0
    for i in range(len(v) - 1):
        tl, tr = inverse_dynamics(robot, (float(v[i]), float(w[i])), (float(a[i]), float(al[i])))
        wl, wr, _ = wheel_rates(robot, float(v[i]), float(w[i]))
        dl, _ = motor.duty_for_torque(tl, wl)
        dr, _ = motor.duty_for_torque(tr, wr)
        duty = max(duty, abs(dl), abs(dr))
        tau = max(tau, abs(tl), abs(tr))
    return duty / cfg.limits.duty_max, tau / t_cap


@pytest.mark.parametrize("robot", sorted(ROBOTS))
@pytest.mark.parametrize("spec", sorted(SPECS))
def test_profiled_torques_and_voltages_stay_within_the_envelope(robot: str, spec: str) -> None:
    for extra in (None, WIDE):
        cfg = _cfg(robot, extra=extra)
        h = cfg.limits.feedback_headroom
        path = _path(cfg, SPECS[spec])
        duty, tau = envelope_use(cfg, path)
        assert duty <= (1.0 - h) * (1.0 + 1e-9), (duty, h)
        assert tau <= (1.0 - h) * (1.0 + 1e-9), (tau, h)
    # With the kinematic caps opened wide the profile uses what the motors give: somewhere a
    # wheel is at the envelope.
    assert max(duty, tau) >= (1.0 - h) * (1.0 - 1e-6), (duty, tau)


@pytest.mark.parametrize("robot", sorted(ROBOTS))
def test_headroom_zero_reaches_the_motors_limits(robot: str) -> None:
    cfg = _cfg(robot, headroom=0.0)
    duty, tau = envelope_use(cfg, _path(cfg, SPECS["rectangle"]))
    assert max(duty, tau) == pytest.approx(1.0, abs=1e-6)
    assert duty <= 1.0 + 1e-9 and tau <= 1.0 + 1e-9
    # A larger headroom is a slower profile.
    fast = _path(cfg, SPECS["figure8"]).duration
    slow = _path(_cfg(robot, headroom=0.5), SPECS["figure8"]).duration
    assert slow > fast


def _excess(cfg, u: np.ndarray, path, i: int) -> float:
    """How far interval i (speeds u[i], u[i + 1]) is beyond the envelope or the profile's own
    caps, as a fraction of the bound (> 0: beyond), computed from the model and the motor."""
    robot = cfg.robot
    motor = Motor(cfg.robot_motor)
    lim = speed_limits(cfg)
    env = lim.envelope
    arr = path.arrays()
    s, k, piv, turn = arr["sigma"], arr["kappa"], arr["seg_pivot"], arr["turn"]
    b = path.pivot_radius
    ds = s[i + 1] - s[i]
    u0, u1 = u[i], u[i + 1]
    acc = (u1 * u1 - u0 * u0) / (2.0 * ds)
    dt = 2.0 * ds / (u0 + u1)
    if piv[i]:
        v, w0, w1, a = 0.0, turn[i] * u0 / b, turn[i] * u1 / b, 0.0
    else:
        v, w0, w1, a = u0, u0 * k[i], u1 * k[i + 1], acc
    alpha = (w1 - w0) / dt
    tl, tr = inverse_dynamics(robot, (v, w0), (a, alpha))
    wl, wr, _ = wheel_rates(robot, v, w0)
    h = cfg.limits.feedback_headroom
    worst = -math.inf
    for tau, ws in ((tl, wl), (tr, wr)):
        duty, _ = motor.duty_for_torque(tau, ws)
        worst = max(worst, abs(duty) / ((1.0 - h) * cfg.limits.duty_max) - 1.0,
                    abs(tau) / env.torque_bound_nm - 1.0)
    worst = max(worst, u0 / lim.v_max - 1.0)
    return worst


@pytest.mark.parametrize("robot", sorted(ROBOTS))
@pytest.mark.parametrize("spec", ["figure8", "rectangle"])
def test_no_sample_can_be_raised_without_leaving_the_envelope(robot: str, spec: str) -> None:
    """Time-optimal: raising any one sample's speed (by 1e-6 of u^2) breaks a bound on the
    interval before it or the one after it (the kinematic caps opened wide: the motors and
    the top speed are the only limits)."""
    cfg = _cfg(robot, extra=WIDE)
    path = _path(cfg, SPECS[spec])
    u = path.arrays()["u"].copy()
    n = len(u)
    moving = [i for i in range(1, n - 1) if u[i] > 0.0]
    for i in (i for i in range(1, n - 1) if u[i] > 0.0):
        assert _excess(cfg, u, path, i - 1) <= 1e-9 and _excess(cfg, u, path, i) <= 1e-9, i
    rng = np.random.default_rng(7)
    picked = rng.choice(moving, size=min(400, len(moving)), replace=False)
    for i in sorted(picked):
        raised = u.copy()
        raised[i] = u[i] * math.sqrt(1.0 + 1e-6)
        excess = max(_excess(cfg, raised, path, i - 1), _excess(cfg, raised, path, i))
        assert excess > 0.0, (i, float(path.sigma[i]), float(u[i]))


def _mirror_points(points: list[tuple[float, float]]) -> list[list[float]]:
    return [[x, -y] for x, y in points]


def test_mirror_images_give_the_same_profile() -> None:
    """The mirrored robot on the mirrored path has the profile of the robot on the path; a
    robot that is its own mirror image drives a path and its mirror image alike."""
    cfg = _cfg("heavy_asymmetric")
    pts = [(0.0, 0.0), (0.8, 0.0), (1.2, 0.3), (1.0, 0.9), (0.2, 0.7), (-0.2, 1.2)]
    p = _path(cfg, {"points": [list(q) for q in pts]})
    r = cfg.robot.mirrored()
    names = r.__dataclass_fields__
    mirror_robot = {n: getattr(r, n) for n in names}
    cfg_m = load_config(SIM_YAML, {**{k: v for k, v in ROBOTS["heavy_asymmetric"].items() if k != "robot"},
                              "robot": dict(mirror_robot, motor=ROBOTS["heavy_asymmetric"]["robot"]["motor"])})
    mirrored = _path(cfg_m, {"points": _mirror_points(pts)})
    np.testing.assert_allclose(mirrored.arrays()["u"], p.arrays()["u"], rtol=1e-9, atol=1e-12)
    assert mirrored.duration == pytest.approx(p.duration, rel=1e-9)
    seed = _cfg("seed")
    ccw = _path(seed, {"shape": "rectangle", "width": 1.2, "height": 0.8, "direction": "ccw"})
    cw = _path(seed, {"shape": "rectangle", "width": 1.2, "height": 0.8, "direction": "cw"})
    sym = Dynamics.from_params(seed.robot)
    assert sym.mbar == 0.0
    np.testing.assert_allclose(cw.arrays()["u"], ccw.arrays()["u"], rtol=1e-9, atol=1e-12)


def test_a_heavier_robot_is_slower() -> None:
    base = _cfg("seed")
    r = base.robot
    heavy = load_config(SIM_YAML, {**DERIVED, "robot": {"m_p": r.m_p + 4.0, "I_p": r.I_p * 3.0}})
    for spec, slower in (("figure8", 1.02), ("rectangle", 1.02), ("sparse", 1.002)):  # sparse: its waypoints cap 0.3 m/s
        light_path = _path(base, SPECS[spec])
        heavy_path = _path(heavy, SPECS[spec])
        assert heavy_path.duration > slower * light_path.duration, spec
        assert np.all(heavy_path.arrays()["u"] <= light_path.arrays()["u"] * (1 + 1e-9) + 1e-12), spec


def test_derived_limits_follow_the_motors() -> None:
    cfg = _cfg("seed")
    res = resolve_limits(cfg.limits, cfg.robot, cfg.robot_motor)
    m = cfg.robot_motor
    stall = m.k_nm_per_a * m.supply_v / m.resistance_ohm
    assert res.limits.torque_max_nm == pytest.approx(stall)
    # Top speed: the no-load wheel speed at the headroom's voltage, friction included.
    h = cfg.limits.feedback_headroom
    w = res.profile_v_max / min(cfg.robot.r_L, cfg.robot.r_R)
    net = Motor(m).torque(1.0 - h, w)
    assert net == pytest.approx(0.0, abs=1e-9)
    assert res.limits.v_max == pytest.approx(Envelope(Dynamics.from_params(cfg.robot), m, headroom=0.0).top_speed())
    # The seed robot's configs keep their own caps: the user's numbers, below the motors'.
    seed = load_config(SIM_YAML)
    assert resolve_limits(seed.limits, seed.robot, seed.robot_motor).limits.v_max == 1.0
    assert speed_limits(seed).v_max == 1.0 and speed_limits(seed).accel == 1.0


def test_limits_above_the_motors_are_reported_naming_the_key() -> None:
    cfg = load_config(SIM_YAML, {"limits": {"v_max": 5.0, "accel": 50.0, "torque_max_nm": 9.0}})
    path = _path(cfg, SPECS["rectangle"])
    text = "\n".join(path.warnings)
    for key in ("limits.v_max", "limits.accel", "limits.torque_max_nm"):
        assert key in text, text
    duty, tau = envelope_use(cfg, path)
    assert duty <= (1.0 - cfg.limits.feedback_headroom) * (1 + 1e-9)
    # A limit below the motors' is the user's to choose, and said nothing about.
    quiet = load_config(SIM_YAML, {"limits": {"v_max": 0.5, "accel": 0.5}})
    p = _path(quiet, SPECS["rectangle"])
    assert p.warnings == [] and max(p.v) <= 0.5 + 1e-12 and max(p.a) <= 0.5 + 1e-12
    # A path's own speed above what the motors give is clamped and reported.
    fast = _path(_cfg("seed"), {"shape": "line", "length": 3.0, "speed": 9.0})
    assert any("speed" in w and "limits.v_max" in w for w in fast.warnings), fast.warnings


def test_a_100k_sample_path_builds_in_seconds() -> None:
    """A regression bound, not the benchmark: 0.7-1.1 s of CPU on this virtual machine on a day
    it ran everything at half its usual speed."""
    cfg = _cfg("seed")
    lim = speed_limits(cfg)
    spec = {"shape": "figure_eight", "width": 1.2, "height": 0.6, "laps": 55}
    t0 = time.process_time()
    path = load_path(spec, lim, paths=cfg.paths)
    cpu = time.process_time() - t0
    assert len(path.sigma) >= 100_000
    assert cpu < 4.0, cpu


def test_profile_without_a_robot_is_unchanged() -> None:
    """A path built with no robot in mind keeps the constant-acceleration profile."""
    from ddrt.path import SpeedLimits

    path = load_path(PATHS / "figure8_fast.yaml", SpeedLimits())
    a = np.asarray(path.a)
    assert a.max() == pytest.approx(1.0) and a.min() == pytest.approx(-1.0)
    assert path.limits.envelope is None


# --------------------------------------------------------------------------- the controlled stop


def _ride(ref, path, sp, ticks: int, dt: float = 0.005) -> list[tuple[float, float, float]]:
    """Drive a perfect robot along the reference for `ticks`: (v_d, a_d, sigma) each tick."""
    out = []
    for _ in range(ticks):
        s = ref._stop_sigma if ref.stopping else path.at_time(ref.t_sched).sigma
        p = path.at(s)
        ref.update(p.x, p.y, p.theta, sp, dt)
        out.append((sp.v_d, sp.a_d, ref._stop_sigma if ref.stopping else path.at_time(ref.t_sched).sigma))
    return out


def test_a_controlled_stop_brakes_no_harder_than_the_motors_and_never_outruns_the_profile() -> None:
    from ddrt.core.types import Setpoint
    from ddrt.path.reference import PathReference

    # A heavy robot on weak brakes (high resistance): its envelope brakes well below 50 m/s^2.
    cfg = _cfg("heavy_asymmetric")
    env = speed_limits(cfg).envelope
    path = _path(cfg, {"shape": "line", "length": 4.0})
    ref = PathReference(path, 0.05, 0.3, 0.005)
    sp = Setpoint()
    _ride(ref, path, sp, 300)  # 1.5 s: at speed
    v_before = sp.v_d
    assert v_before > 0.5
    ref.request_stop(50.0)
    rows = _ride(ref, path, sp, 2000)
    vs = [v_before] + [r[0] for r in rows]
    assert vs[-1] == 0.0 and ref.done
    for k in range(1, len(vs)):
        if vs[k - 1] > 0.0 and vs[k] > 0.0:
            decel = (vs[k - 1] - vs[k]) / 0.005
            assert decel <= env.decel_at(vs[k - 1]) * (1 + 1e-9) + 1e-9, k
    assert max((vs[k - 1] - vs[k]) / 0.005 for k in range(1, len(vs))) < 50.0
    # A gentle stop just before a turn in place follows the profile down to the corner.
    seed = _cfg("seed")
    rect = _path(seed, {"shape": "rectangle", "width": 1.2, "height": 0.8, "direction": "ccw"})
    ref = PathReference(rect, 0.05, 0.3, 0.005)
    t_corner = next(rect.t[i] for i in range(len(rect.t)) if rect.seg_pivot[i])
    _ride(ref, rect, sp, int(0.8 * t_corner / 0.005))
    ref.request_stop(0.01)
    rows = _ride(ref, rect, sp, 4000)
    for v, _, s in rows:
        assert v <= rect.at(s).v + 1e-9
    assert rows[-1][0] == 0.0 and rows[-1][2] <= rect.sigma[rect.seg_pivot.index(True)] + 1e-6


def test_a_resume_ramp_accelerates_no_harder_than_the_motors_give() -> None:
    """limits.accel null: the profile's accel cap is unbounded and only the motors limit the
    resume ramp, which must then take their figure at each speed, not an infinite one."""
    from ddrt.core.types import Setpoint
    from ddrt.path.reference import PathReference

    cfg = _cfg("heavy_asymmetric")
    lim = speed_limits(cfg)
    assert lim.accel == math.inf
    env = lim.envelope
    path = _path(cfg, {"shape": "line", "length": 4.0})
    ref = PathReference(path, 0.05, 0.3, 0.005)
    sp = Setpoint()
    p = path.at(1.0)
    ref.resume(p.x, p.y, p.theta)  # from rest, 1 m along the line
    assert ref.resuming
    vs = [0.0]
    s = 1.0
    for _ in range(2000):
        q = path.at(s)
        ref.update(q.x, q.y, q.theta, sp, 0.005)
        if not ref.resuming:
            break
        vs.append(sp.v_d)
        s = ref._ramp_s
    assert not ref.resuming and len(vs) > 20  # it ramped, over more than 0.1 s, and met the profile
    for k in range(1, len(vs)):
        # (at the motors' top speed they give nothing more: the ramp's floor, 1 mm/s^2, lets it merge)
        assert (vs[k] - vs[k - 1]) / 0.005 <= max(env.accel_at(vs[k - 1]), 1e-3) * (1 + 1e-9), k
    # and it is the motors' figure that limits it (not some lower constant).
    assert max((vs[k] - vs[k - 1]) / 0.005 for k in range(1, len(vs))) > 0.9 * env.accel_at(0.0)


# --------------------------------------------------------------------------- a reload that changes the robot


def _loop(cfg):
    from ddrt.loop import ControlLoop
    from hal.registry import open_hal

    hal = open_hal(cfg, start=(0.0, 0.0, 0.0))
    loop = ControlLoop(cfg, hal)
    loop.calibrate(hal.sleep_until, hal.now)
    return loop, hal


def _tick(loop, hal, n: int) -> None:
    for _ in range(n):
        hal.sleep_until(hal.now() + loop.period)
        loop.tick()
        if loop.state != LoopState.FOLLOWING:
            break


def test_a_heavier_robot_on_reload_re_profiles_the_rest_of_the_path() -> None:
    from ddrt.config import with_overrides

    cfg = load_config(SIM_YAML, {**DERIVED, "estimator": {"calibration_s": 0.05}})
    loop, hal = _loop(cfg)
    path = _path(cfg, {"shape": "rectangle", "width": 1.2, "height": 0.8, "direction": "ccw"})
    loop.follow(path, (0.0, 0.0, 0.0))
    _tick(loop, hal, 150)
    assert loop.state == LoopState.FOLLOWING
    t_sched = loop.reference.t_sched
    before = path.at_time(t_sched)
    # Lighter: the profile is still within the motors: nothing changes.
    lighter = with_overrides(cfg, {"robot": {"m_p": 0.9 * cfg.robot.m_p}})
    loop.reconfigure(lighter)
    assert loop.path is path and loop.reprofiled == ""
    heavy = with_overrides(cfg, {"robot": {"m_p": cfg.robot.m_p + 3.0, "I_p": 3.0 * cfg.robot.I_p}})
    loop.reconfigure(heavy)
    new = loop.path
    assert new is not path and loop.reference.path is new and loop.reference.pursuit.path is new
    assert "re-profiled" in loop.reprofiled
    first = path.index(path.at_time(t_sched).sigma) + 1
    # What the schedule is reading does not move; the rest is slower, within the new motors.
    assert new.u[:first + 1] == path.u[:first + 1] and new.t[:first + 1] == path.t[:first + 1]
    now = new.at_time(t_sched)
    assert (now.sigma, now.v) == pytest.approx((before.sigma, before.v), abs=1e-12)
    assert new.duration > path.duration
    assert path.envelope_excess(speed_limits(heavy).envelope, first) > 1e-3
    assert new.envelope_excess(speed_limits(heavy).envelope, first) <= 1e-9
    _tick(loop, hal, int(new.duration / loop.period) + 400)
    assert loop.state == LoopState.STOPPED, loop.fault
    hal.close()


@pytest.mark.parametrize("robot", ["seed", "heavy_asymmetric"])
def test_a_reversed_profile_keeps_the_motors_within_their_envelope(robot: str) -> None:
    """Inverse dynamics and the motor model at every sample of a reversed path, independent of
    the profile's own coefficients: the duty within 1 - headroom, and the envelope used."""
    c = _cfg(robot)
    path = _path(c, {"shape": "figure_eight", "width": 1.2, "height": 0.6, "speed": 3.0, "reverse": True})
    assert max(path.v) <= 0.0
    duty, tau = envelope_use(c, path)
    h = c.limits.feedback_headroom
    assert duty <= (1.0 - h) * (1 + 1e-6) and tau <= (1.0 - h) * (1 + 1e-6)
    assert max(duty, tau) > 0.9 * (1.0 - h)  # the motors, not some other cap, set the speed somewhere
