"""The reference: monotone projection, pivots by heading, cross-track, speed, timed mode."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from ddrt.path import Path, SpeedLimits, load_path
from ddrt.core.types import Setpoint
from ddrt.path.pursuit import PurePursuit, Reference
from ddrt.path.reference import PathReference
from tests.support.repo import REPO

CONFIGS = REPO / "configs" / "paths"
LIM = SpeedLimits()


def _load(name: str) -> Path:
    return load_path(CONFIGS / name, LIM)


def test_progress_never_jumps_at_the_figure_eight_crossing() -> None:
    path = _load("figure8_slow.yaml")
    pp = PurePursuit(path)
    rng = np.random.default_rng(7)
    n = 4000
    prev = 0.0
    crossings = 0
    for k in range(n + 1):
        true = path.length * k / n  # about 0.9 mm per step
        q = path.at(true)
        x, y = q.x + rng.normal(0.0, 0.002), q.y + rng.normal(0.0, 0.002)
        ref = pp.update(x, y, q.theta + rng.normal(0.0, 0.02))
        assert ref.sigma >= prev
        assert ref.sigma - prev < 0.02  # never skips more than 2 cm in one step
        assert abs(ref.sigma - true) < 0.01  # and stays on the right branch
        if math.hypot(q.x, q.y) < 0.005:
            crossings += 1
        prev = ref.sigma
    assert crossings >= 3  # the test did pass through the crossing (start, middle, end)
    assert ref.done and ref.sigma == path.length


def test_progress_is_monotone_and_windowed() -> None:
    path = _load("figure8_slow.yaml")
    pp = PurePursuit(path, search_window_m=0.3)
    q = path.at(0.5)
    pp.update(q.x, q.y, q.theta)  # first call: at most one window (0.3 m) ahead
    assert pp.update(q.x, q.y, q.theta).sigma == pytest.approx(0.5, abs=1e-3)
    back = path.at(0.2)
    assert pp.update(back.x, back.y, back.theta).sigma == pytest.approx(0.5, abs=1e-3)  # no going back
    far = path.at(2.0)  # teleported far ahead: progress advances at most one window per call
    s1 = pp.update(far.x, far.y, far.theta).sigma
    assert 0.5 < s1 <= 0.8 + 1e-9
    pp.reset(1.9)
    assert pp.update(far.x, far.y, far.theta).sigma == pytest.approx(2.0, abs=1e-3)


def test_cross_track_on_a_line() -> None:
    path = load_path({"shape": "line", "length": 1.0, "speed": 0.2}, LIM)
    for offset in (0.03, -0.02, 0.1):
        pp = PurePursuit(path)
        pp.reset(0.45)
        ref = pp.update(0.5, offset, 0.0)
        assert ref.cross_track == pytest.approx(offset, abs=1e-12)
        assert ref.sigma == pytest.approx(0.5, abs=1e-12)
        assert (ref.x_d, ref.y_d, ref.theta_d) == pytest.approx((0.5, 0.0, 0.0), abs=1e-12)
        assert ref.v_d == pytest.approx(0.2)
        # The goal point is 5 cm further on; pure pursuit steers back towards the path.
        assert (ref.lookahead_x, ref.lookahead_y) == pytest.approx((0.55, 0.0), abs=1e-12)
        assert math.copysign(1.0, ref.pp_curvature) == -math.copysign(1.0, offset)
        assert ref.pp_curvature == pytest.approx(2 * -offset / (0.05**2 + offset**2), rel=1e-9)


def test_cross_track_on_a_circle() -> None:
    r = 0.5
    path = load_path({"shape": "circle", "radius": r, "direction": "ccw", "speed": 0.3}, LIM)  # centre (0, r)
    for phi in (0.3, 2.0, 4.5):
        for d in (0.04, -0.06):  # positive: towards the centre, the left of a ccw circle
            x, y = (r - d) * math.sin(phi), r - (r - d) * math.cos(phi)
            pp = PurePursuit(path)
            pp.reset(r * phi - 0.02)
            ref = pp.update(x, y, phi)
            assert ref.cross_track == pytest.approx(d, abs=2e-6)
            assert ref.sigma == pytest.approx(r * phi, abs=1e-6)
            assert ref.kappa == pytest.approx(1 / r)
            assert ref.omega_d == pytest.approx(ref.v_d / r, rel=1e-9)
            timed = PathReference(path, 0.05, 0.3, 0.005, time_indexed=True)
            timed.pursuit.reset(r * phi - 0.02)
            timed.t_sched = path.at(r * phi).t - 0.005
            timed.update(x, y, phi, Setpoint(), 0.005)
            assert timed.cross_track == pytest.approx(d, abs=2e-6)


def test_pivot_progress_follows_the_turned_angle() -> None:
    path = _load("rectangle.yaml")  # ccw: left turns in place at (1.2, 0), (1.2, 0.8), (0, 0.8)
    b = path.pivot_radius
    pp = PurePursuit(path)
    # Drive to the first corner along the first side.
    for x in np.linspace(0.0, 1.2, 200):
        ref = pp.update(float(x), 0.0, 0.0)
    s0 = ref.sigma
    assert s0 == pytest.approx(1.2, abs=1e-9) and ref.pivot
    assert ref.v_d == 0.0 and ref.omega_d > 0.0  # a robot at rest is told to start turning
    for deg in (5.0, 20.0, 45.0, 80.0):
        ref = pp.update(1.2, 0.0, math.radians(deg))
        assert ref.sigma - s0 == pytest.approx(b * math.radians(deg), abs=1e-9)
        assert ref.pivot and ref.v_d == 0.0 and ref.omega_d > 0.0
        assert (ref.x_d, ref.y_d) == pytest.approx((1.2, 0.0), abs=1e-12)
        assert ref.theta_d == pytest.approx(math.radians(deg), abs=1e-9)
    # Turning back does not undo progress; small xy noise does not move it either.
    assert pp.update(1.201, 0.001, math.radians(70.0)).sigma - s0 == pytest.approx(b * math.radians(80.0))
    ref = pp.update(1.2, 0.0, math.radians(89.9))  # within the pivot tolerance: turn complete
    assert ref.sigma == pytest.approx(s0 + b * math.pi / 2) and not ref.pivot
    ref = pp.update(1.2, 0.1, math.pi / 2)  # then driving up the second side
    assert ref.sigma == pytest.approx(s0 + b * math.pi / 2 + 0.1, abs=1e-9) and ref.v_d > 0.0


def test_start_off_the_path_and_kick_from_rest() -> None:
    square = _load("seed_square.yaml")
    pp = PurePursuit(square)
    ref = pp.update(*square.start_pose)  # 50 mm right of the first side, at rest
    assert ref.sigma == 0.0 and ref.cross_track == pytest.approx(-0.05)
    assert 0.0 < ref.v_d < 0.01 and ref.a_d == pytest.approx(0.0025)
    assert not ref.done
    ellipse = _load("seed_ellipse.yaml")
    ref = PurePursuit(ellipse).update(*ellipse.start_pose)
    assert ref.sigma == 0.0 and ref.cross_track == pytest.approx(-0.1) and ref.v_d > 0.0
    # Behind the start: still projects onto the start.
    ref = PurePursuit(ellipse).update(-0.08, 0.03, 0.0)
    assert ref.sigma == 0.0 and ref.cross_track == pytest.approx(0.03)


def _drive(path: Path, dt: float = 0.005, t_max: float | None = None) -> tuple[Reference, float, float]:
    """Unicycle under the seed's outer law (eq. 4.3) tracking the pursuit reference."""
    kx, ky, kth = 10.0, 64.0, 16.0
    x, y, th = path.start_pose
    pp = PurePursuit(path)
    t, worst = 0.0, 0.0
    t_max = 2.0 * path.duration + 5.0 if t_max is None else t_max
    while t < t_max:
        ref = pp.update(x, y, th)
        if ref.done:
            break
        dx, dy = ref.x_d - x, ref.y_d - y
        xe = dx * math.cos(th) + dy * math.sin(th)
        ye = -dx * math.sin(th) + dy * math.cos(th)
        te = math.remainder(ref.theta_d - th, 2 * math.pi)
        v = ref.v_d * math.cos(te) + kx * xe
        w = ref.omega_d + ref.v_d * (ky * ye + kth * math.sin(te))
        x += v * math.cos(th) * dt
        y += v * math.sin(th) * dt
        th += w * dt
        t += dt
        worst = max(worst, abs(ref.cross_track))
    return ref, t, worst


@pytest.mark.parametrize("name", ["rectangle.yaml", "waypoints_sparse.csv", "s_curve.yaml"])
def test_a_simple_robot_completes_the_path(name: str) -> None:
    path = _load(name)
    ref, t, worst = _drive(path)
    assert ref.done
    assert t == pytest.approx(path.duration, rel=0.1, abs=0.5)
    assert worst < 0.01


def test_timed_reference_is_the_profile_at_time_t() -> None:
    """PathReference's time-indexed mode (the seed's): q_d = path.at_time(t), whatever the robot does."""
    path = _load("seed_circle.yaml")
    dt = 0.005
    tr = PathReference(path, 0.05, 0.3, dt, time_indexed=True)
    sp = Setpoint()
    t = 0.0
    for t_check in (10.0, 40.0, 79.0):
        while t < t_check - 1e-9:  # a robot exactly on the schedule
            q = path.at_time(tr.t_sched)
            tr.update(q.x, q.y, q.theta, sp, dt)
            t += dt
        assert tr.t_sched == pytest.approx(t_check, abs=1e-9)
        q = path.at_time(tr.t_sched)
        assert (sp.x_d, sp.y_d, sp.theta_d, sp.v_d, sp.omega_d, sp.a_d, sp.alpha_d) == (
            q.x, q.y, q.theta, q.v, q.omega, q.a, q.alpha)
        assert sp.along_err == 0.0 and not sp.path_frame and sp.kappa == q.kappa
        # The robot's progress: it stood one tick behind the schedule (0.16 mm at 31 mm/s),
        # and within the last mm before the stop the projection snaps to the end.
        expected = path.length if path.length - q.sigma <= 1e-3 else q.sigma
        assert tr.sigma == pytest.approx(expected, abs=2e-4)
        assert abs(tr.cross_track) < 1e-5 and not tr.done
    # A robot 20 mm outside a clockwise circle is on its left: positive cross-track, and the
    # reference does not wait for it.
    q = path.at_time(tr.t_sched)
    rx, ry = q.x * (0.32 / 0.3), -0.3 + (q.y + 0.3) * (0.32 / 0.3)
    tr.update(rx, ry, q.theta, sp, dt)
    assert tr.cross_track == pytest.approx(0.02, abs=1e-5)
    assert (sp.x_d, sp.y_d) == (path.at_time(tr.t_sched).x, path.at_time(tr.t_sched).y)
    end = path.at(path.length)
    while tr.t_sched < 80.5:
        tr.update(end.x, end.y, end.theta, sp, dt)
    assert tr.done


def test_pursuit_is_fast() -> None:
    path = _load("figure8_fast.yaml")
    poses = [(p.x + 0.003, p.y - 0.002, p.theta) for p in (path.at(path.length * k / 10000) for k in range(10000))]
    pp = PurePursuit(path)
    t0 = time.thread_time()  # the CPU it takes, which a loaded host does not inflate
    for x, y, th in poses:
        pp.update(x, y, th)
    elapsed = time.thread_time() - t0
    assert elapsed < 1.5
    assert pp.sigma == pytest.approx(path.length, abs=0.01)


def test_bad_parameters() -> None:
    path = _load("seed_line45.yaml")
    with pytest.raises(ValueError, match="search_window_m"):
        PurePursuit(path, search_window_m=0.0)
    with pytest.raises(ValueError, match="lookahead_m"):
        PurePursuit(path, lookahead_m=float("nan"))
