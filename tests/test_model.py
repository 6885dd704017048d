"""The reduced model and the motor model, checked against derivations written here.

The reference derivation below does not use the reduced model's structure at all: it writes
the kinetic energy of the four bodies in the inertial frame with all six coordinates
(X, Y, theta, phi_L, phi_R, phi_3), forms Lagrange's equations with multipliers for the four
velocity constraints, and solves that 10x10 linear system. Derivatives of the mass matrix,
of the constraint matrix and of T are taken by complex-step differentiation, which is exact
to rounding, so the comparison can be made at 1e-9 relative.
"""

from __future__ import annotations

import dataclasses
import math
import random

import numpy as np
import pytest

from ddrt.core.model import Dynamics, forward_dynamics, inverse_dynamics, wheel_rates
from ddrt.params.robot import RobotParams
from ddrt.core.motor import Motor
from ddrt.params.motor import MotorParams
from tests.support.repo import SIM_YAML
from tests.support.seed_robot import TABLE_5_1, TABLE_5_2

POSITIVE_FIELDS = [n for n in TABLE_5_1 if n not in ("d_xc", "d_yc")]


def random_params(rng: random.Random) -> RobotParams:
    u = rng.uniform
    return RobotParams(
        H=u(0.05, 0.3), L=u(0.05, 0.2), R=u(0.05, 0.2), r_L=u(0.02, 0.1), r_R=u(0.02, 0.1),
        r_3=u(0.02, 0.1), d_xc=u(-0.1, 0.2), d_yc=u(-0.05, 0.05), m_p=u(0.2, 3.0),
        m_L=u(0.2, 2.0), m_R=u(0.2, 2.0), m_3=u(0.1, 1.0), I_p=u(1e-3, 2e-2), I_L=u(1e-4, 1e-3),
        I_R=u(1e-4, 1e-3), I_3=u(1e-4, 1e-3), I_wL=u(1e-4, 1e-3), I_wR=u(1e-4, 1e-3),
        I_w3=u(1e-4, 1e-3),
    )


# --- the independent derivation ---------------------------------------------------------------

_CS = 1e-30  # complex step


def _points(p: RobotParams) -> list[tuple[float, float, float]]:
    """(mass, x, y) of each body's centre in the body frame."""
    return [(p.m_p, p.d_xc, p.d_yc), (p.m_L, 0.0, p.L), (p.m_R, 0.0, -p.R), (p.m_3, p.H, 0.0)]


def _kinetic(p: RobotParams, q, qd):
    """T(q, qdot) in the inertial frame; works on complex q for complex-step derivatives."""
    th = q[2]
    c, s = np.cos(th), np.sin(th)
    total = 0.0
    for m, bx, by in _points(p):
        # Position (X + bx c - by s, Y + bx s + by c), differentiated by hand in time.
        vx = qd[0] - qd[2] * (bx * s + by * c)
        vy = qd[1] + qd[2] * (bx * c - by * s)
        total = total + 0.5 * m * (vx * vx + vy * vy)
    total = total + 0.5 * (p.I_p + p.I_L + p.I_R + p.I_3) * qd[2] ** 2
    total = total + 0.5 * (p.I_wL * qd[3] ** 2 + p.I_wR * qd[4] ** 2 + p.I_w3 * qd[5] ** 2)
    return total


def _mass_matrix(p: RobotParams, q) -> np.ndarray:
    """Hessian of T in qdot by polarisation (T is exactly quadratic in qdot)."""
    n = 6
    eye = np.eye(n)
    diag = [_kinetic(p, q, eye[i]) for i in range(n)]
    m = np.zeros((n, n), dtype=complex)
    for i in range(n):
        for j in range(n):
            m[i, j] = 2.0 * diag[i] if i == j else _kinetic(p, q, eye[i] + eye[j]) - diag[i] - diag[j]
    return m


def _constraints(p: RobotParams, q) -> np.ndarray:
    """A(q) with A qdot = 0: no side slip at A, rolling without slip of the three wheels."""
    c, s = np.cos(q[2]), np.sin(q[2])
    z = 0.0 * c
    return np.array([
        [-s, c, z, z, z, z],
        [c, s, -p.L + z, -p.r_L + z, z, z],
        [c, s, p.R + z, z, -p.r_R + z, z],
        [c, s, z, z, z, -p.r_3 + z],
    ])


def reference_forward(p: RobotParams, theta: float, v: float, w: float,
                      tau_l: float, tau_r: float) -> tuple[float, float]:
    """(dv/dt, domega/dt) from Lagrange's equations with multipliers in all six coordinates."""
    q = np.array([0.3, -0.2, theta, 0.1, 0.2, 0.3])
    c, s = math.cos(theta), math.sin(theta)
    qd = np.array([v * c, v * s, w, (v - p.L * w) / p.r_L, (v + p.R * w) / p.r_R, v / p.r_3])
    mass = _mass_matrix(p, q).real
    mdot = _mass_matrix(p, q + 1j * _CS * qd).imag / _CS  # dM/dt along the motion
    dT_dq = np.array([_kinetic(p, q + 1j * _CS * e, qd).imag / _CS for e in np.eye(6)])
    a = _constraints(p, q).real
    adot = _constraints(p, q + 1j * _CS * qd).imag / _CS
    forces = np.array([0.0, 0.0, 0.0, tau_l, tau_r, 0.0])  # motor torques on the wheel spins
    kkt = np.zeros((10, 10))
    kkt[:6, :6] = mass
    kkt[:6, 6:] = -a.T
    kkt[6:, :6] = a
    rhs = np.concatenate([forces + dT_dq - mdot @ qd, -adot @ qd])
    qdd = np.linalg.solve(kkt, rhs)[:6]
    # v = c Xdot + s Ydot, and the side speed -s Xdot + c Ydot is zero.
    return c * qdd[0] + s * qdd[1], qdd[2]


def reference_inverse(p, theta, v, w, v_dot, w_dot):
    """Torques for given accelerations: the reference is affine in the torques, so invert it."""
    a0 = np.array(reference_forward(p, theta, v, w, 0.0, 0.0))
    j = np.column_stack([np.array(reference_forward(p, theta, v, w, *e)) - a0 for e in np.eye(2)])
    return tuple(np.linalg.solve(j, np.array([v_dot, w_dot]) - a0))


def _close(a, b, rel):
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.max(np.abs(a - b))) <= rel * max(float(np.max(np.abs(b))), 1e-300)


# --- the model against the derivation -------------------------------------------------------


def test_reference_derivation_is_not_trivial():
    """Guard the guard: the reference must see the m_x terms and m_L L^2 that the seed lost."""
    p = RobotParams(**TABLE_5_2)
    seed = Dynamics.from_params(p, seed_report=True)
    ref = reference_forward(p, 0.4, 0.5, 2.0, 0.3, 0.1)
    wrong = seed.forward(0.5, 2.0, 0.3, 0.1)
    assert not _close(wrong, ref, 1e-3)


def test_forward_dynamics_matches_independent_derivation():
    rng = random.Random(11)
    for _ in range(60):
        p = random_params(rng)
        v, w = rng.uniform(-1.5, 1.5), rng.uniform(-6.0, 6.0)
        tau = (rng.uniform(-1.5, 1.5), rng.uniform(-1.5, 1.5))
        ref = reference_forward(p, rng.uniform(-math.pi, math.pi), v, w, *tau)
        got = forward_dynamics(p, (v, w), tau)
        assert _close(got, ref, 1e-9), (p, v, w, tau, got, ref)


def test_inverse_dynamics_matches_independent_derivation():
    rng = random.Random(12)
    for _ in range(40):
        p = random_params(rng)
        v, w = rng.uniform(-1.5, 1.5), rng.uniform(-6.0, 6.0)
        acc = (rng.uniform(-3.0, 3.0), rng.uniform(-20.0, 20.0))
        ref = reference_inverse(p, rng.uniform(-math.pi, math.pi), v, w, *acc)
        got = inverse_dynamics(p, (v, w), acc)
        assert _close(got, ref, 1e-9), (p, v, w, acc, got, ref)


def test_table_values_match_derivation_at_turning_states():
    for table in (TABLE_5_1, TABLE_5_2):
        p = RobotParams(**table)
        for v, w in ((0.3, 1.0), (-0.2, 3.0), (0.0, -2.0)):
            ref = reference_forward(p, 1.0, v, w, 0.2, -0.1)
            assert _close(forward_dynamics(p, (v, w), (0.2, -0.1)), ref, 1e-9)


def test_inverse_of_forward_is_identity():
    rng = random.Random(13)
    for _ in range(200):
        p = random_params(rng)
        eta = (rng.uniform(-2, 2), rng.uniform(-8, 8))
        tau = (rng.uniform(-2, 2), rng.uniform(-2, 2))
        back = inverse_dynamics(p, eta, forward_dynamics(p, eta, tau))
        assert _close(back, tau, 1e-11)
        acc = (rng.uniform(-3, 3), rng.uniform(-20, 20))
        assert _close(forward_dynamics(p, eta, inverse_dynamics(p, eta, acc)), acc, 1e-11)


def test_mass_matrix_symmetric_positive_definite_and_equal_to_energy_hessian():
    rng = random.Random(14)
    for _ in range(100):
        p = random_params(rng)
        dyn = Dynamics.from_params(p)
        (a, b), (c, d) = dyn.mass_matrix()
        assert b == c
        assert a > 0 and a * d - b * c > 0
        # The reduced mass matrix is S^T M S: the full one seen through the constraints.
        th = rng.uniform(-math.pi, math.pi)
        full = _mass_matrix(p, np.array([0, 0, th, 0, 0, 0])).real
        cs, sn = math.cos(th), math.sin(th)
        s_mat = np.array([
            [cs, 0], [sn, 0], [0, 1], [1 / p.r_L, -p.L / p.r_L], [1 / p.r_R, p.R / p.r_R], [1 / p.r_3, 0],
        ])
        reduced = s_mat.T @ full @ s_mat
        assert _close([[a, b], [c, d]], reduced, 1e-12)
        v, w = rng.uniform(-1, 1), rng.uniform(-5, 5)
        assert math.isclose(dyn.kinetic_energy(v, w), 0.5 * np.array([v, w]) @ reduced @ np.array([v, w]),
                            rel_tol=1e-12)


def test_mirror_image_robot_mirrors_accelerations():
    rng = random.Random(15)
    for _ in range(50):
        p = random_params(rng)
        v, w = rng.uniform(-1, 1), rng.uniform(-5, 5)
        tl, tr = rng.uniform(-1, 1), rng.uniform(-1, 1)
        dv, dw = forward_dynamics(p, (v, w), (tl, tr))
        mdv, mdw = forward_dynamics(p.mirrored(), (v, -w), (tr, tl))
        assert math.isclose(mdv, dv, rel_tol=1e-12, abs_tol=1e-12)
        assert math.isclose(mdw, -dw, rel_tol=1e-12, abs_tol=1e-12)
    assert p.mirrored().mirrored() == p


def test_straight_run_with_mass_centre_on_axle():
    """Symmetric robot, m_x = 0: (m + k) dv/dt = tau_L/r_L + tau_R/r_R and no yaw."""
    base = dict(TABLE_5_1, r_R=TABLE_5_1["r_L"], d_yc=0.0)
    base["d_xc"] = -base["m_3"] * base["H"] / base["m_p"]
    p = RobotParams(**base)
    m = p.m_p + p.m_L + p.m_R + p.m_3
    k = p.I_wL / p.r_L**2 + p.I_wR / p.r_R**2 + p.I_w3 / p.r_3**2
    for v in (0.0, 0.4, -0.7):
        dv, dw = forward_dynamics(p, (v, 0.0), (0.3, 0.3))
        assert math.isclose((m + k) * dv, 0.3 / p.r_L + 0.3 / p.r_R, rel_tol=1e-12)
        assert abs(dw) < 1e-12
    # With m_x != 0 the same state is not free of the centripetal term once it turns.
    p2 = RobotParams(**TABLE_5_1)
    dv_turn, _ = forward_dynamics(p2, (0.0, 2.0), (0.0, 0.0))
    assert dv_turn > 0.0  # the mass ahead of the axle pulls A forward in a spin


def test_seed_report_model_drops_rear_wheel_inertia():
    p = RobotParams(**TABLE_5_1)
    true, seed = Dynamics.from_params(p), Dynamics.from_params(p, seed_report=True)
    expected = p.m_L * p.L**2 + p.m_R * p.R**2
    assert math.isclose(expected, 0.0279936, rel_tol=1e-6)
    assert math.isclose(true.I - seed.I, expected, rel_tol=1e-12)
    assert true.I - seed.I > seed.I - (p.I_p + p.m_p * p.d_xc**2)  # more than most of I
    assert seed.m_x == 0.0 and true.m_x == pytest.approx(p.m_p * p.d_xc + p.m_3 * p.H)
    assert (seed.m_k, seed.mbar) == (true.m_k, true.mbar)


def test_wheel_rates_follow_rolling_constraints():
    p = RobotParams(**TABLE_5_2)
    wl, wr, w3 = wheel_rates(p, 0.3, 1.2)
    # Each wheel centre's forward speed, v -/+ track * omega, over its radius.
    assert wl == pytest.approx((0.3 - 0.108 * 1.2) / 0.049)
    assert wr == pytest.approx((0.3 + 0.108 * 1.2) / 0.051)
    assert w3 == pytest.approx(0.3 / 0.052)


# --- RobotParams validation -----------------------------------------------------------------


@pytest.mark.parametrize("name", POSITIVE_FIELDS)
@pytest.mark.parametrize("bad", [0.0, -0.1, math.nan, math.inf])
def test_robot_params_rejects_bad_positive_field(name, bad):
    with pytest.raises(ValueError, match=name):
        RobotParams(**dict(TABLE_5_1, **{name: bad}))


@pytest.mark.parametrize("name", ["d_xc", "d_yc"])
def test_robot_params_offsets_may_be_negative_but_finite(name):
    assert getattr(RobotParams(**dict(TABLE_5_1, **{name: -0.05})), name) == -0.05
    for bad in (math.nan, -math.inf, "0.1", True):
        with pytest.raises(ValueError, match=name):
            RobotParams(**dict(TABLE_5_1, **{name: bad}))


def test_robot_params_from_mapping_and_kwargs():
    p = RobotParams(**TABLE_5_1)
    assert dataclasses.asdict(p) == TABLE_5_1
    assert RobotParams.from_mapping(dict(TABLE_5_1, extra=1)) == p
    partial = dict(TABLE_5_1)
    del partial["I_w3"]
    with pytest.raises(ValueError, match="I_w3"):
        RobotParams.from_mapping(partial)
    assert isinstance(RobotParams(**dict(TABLE_5_1, m_p=1)).m_p, float)


# --- motor model -------------------------------------------------------------------------


def test_motor_documented_defaults():
    mp = MotorParams()
    assert mp.stall_torque_nm == pytest.approx(1.2, rel=1e-9)
    assert mp.no_load_speed_rad_s == pytest.approx(300 * 2 * math.pi / 60, rel=1e-3)
    frictionless = Motor(dataclasses.replace(mp, viscous_nms=0.0, coulomb_nm=0.0))
    assert frictionless.torque(1.0, 0.0) == pytest.approx(1.2, rel=1e-9)
    assert frictionless.torque(1.0, mp.no_load_speed_rad_s) == pytest.approx(0.0, abs=1e-12)
    assert frictionless.torque(-1.0, -mp.no_load_speed_rad_s) == pytest.approx(0.0, abs=1e-12)
    # With friction the real no-load speed is lower and draws ~0.15 A.
    m = Motor(mp)
    lo, hi = 0.0, mp.no_load_speed_rad_s
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if m.torque(1.0, mid) > 0 else (lo, mid)
    current = (mp.supply_v - mp.k_nm_per_a * lo) / mp.resistance_ohm
    assert current == pytest.approx(0.15, rel=0.05)  # the docstring rounds


def test_motor_torque_and_duty_round_trip():
    rng = random.Random(21)
    for _ in range(200):
        mp = MotorParams(resistance_ohm=rng.uniform(1, 10), k_nm_per_a=rng.uniform(0.1, 1.0),
                         viscous_nms=rng.uniform(0, 0.01), coulomb_nm=rng.uniform(0, 0.1))
        motor = Motor(mp)
        duty, speed = rng.uniform(-1, 1), rng.uniform(-30, 30)
        tau = motor.torque(duty, speed)
        back, saturated = motor.duty_for_torque(tau, speed)
        assert back == pytest.approx(duty, abs=1e-12)
        assert not saturated


def test_motor_pair_methods_are_the_single_ones_bit_for_bit():
    """net_torques and duties_at (the hot path's two-wheel calls) give exactly, not just nearly,
    what the one-wheel methods give: the simulator's telemetry must not change."""
    rng = random.Random(5)
    for _ in range(500):
        motor = Motor(MotorParams(resistance_ohm=rng.uniform(1, 10), k_nm_per_a=rng.uniform(0.1, 1.0),
                                  viscous_nms=rng.uniform(0, 0.01), coulomb_nm=rng.uniform(0, 0.1),
                                  supply_v=rng.uniform(6, 14)))
        dl, dr = rng.uniform(-1, 1), rng.uniform(-1, 1)
        wl, wr = rng.uniform(-30, 30), rng.choice([0.0, rng.uniform(-0.05, 0.05), rng.uniform(-30, 30)])
        tl, tr = motor.net_torques(dl, wl, dr, wr)
        assert tl == motor.electromagnetic_torque(dl, wl) - motor.friction(wl)
        assert tr == motor.electromagnetic_torque(dr, wr) - motor.friction(wr)
        assert tl != tr or (dl, wl) == (dr, wr)  # the wheels are not mixed up
        ul, ur = motor.duties_at(tl, wl, tr, wr)
        assert ul == motor.duty_for_torque(tl, 0.0, wl, wl)[0]
        assert ur == motor.duty_for_torque(tr, 0.0, wr, wr)[0]
        assert ul == pytest.approx(dl, abs=1e-9) and ur == pytest.approx(dr, abs=1e-9)  # the inverse


def test_motor_friction_opposes_motion():
    m = Motor(MotorParams())
    for w in (-20.0, -0.5, 0.5, 20.0):
        assert m.friction(w) * w > 0
    assert m.friction(0.0) == 0.0
    assert m.friction(10.0) == pytest.approx(0.00086 * 10 + 0.03, rel=1e-6)


def test_motor_saturation_is_reported_not_clipped():
    m = Motor(MotorParams())
    duty, saturated = m.duty_for_torque(2.0, 0.0)
    assert saturated and duty > 1.0
    assert duty == pytest.approx((3.82 * (2.0 + 0.0) / 0.382) / 12.0, rel=1e-9)
    duty, saturated = m.duty_for_torque(-0.5, -40.0)
    assert saturated and duty < -1.0
    with pytest.raises(ValueError):
        m.torque(1.01, 0.0)
    with pytest.raises(ValueError):
        m.torque(math.nan, 0.0)


def test_motor_params_validation():
    with pytest.raises(ValueError, match="resistance_ohm"):
        MotorParams(resistance_ohm=0.0)
    with pytest.raises(ValueError, match="coulomb_nm"):
        MotorParams(coulomb_nm=-0.01)
    with pytest.raises(ValueError, match="supply_v"):
        MotorParams(supply_v=math.nan)
    with pytest.raises(ValueError, match="bogus"):
        MotorParams.from_mapping({"bogus": 1.0})


@pytest.mark.parametrize(("name", "value"), [("R", 1e20), ("r_L", 2.0), ("m_p", 5000.0), ("I_p", 1e4),
                                             ("d_xc", -1.0), ("d_yc", 0.5)])
def test_implausible_robots_are_refused(name: str, value: float) -> None:
    """A value no wheeled robot of this kind has (a typo, a unit slip) is refused by name."""
    import dataclasses as _dc

    base = _seed_params_for_bounds()
    with pytest.raises(ValueError, match=f"RobotParams.{'d_xc' if name.startswith('d_') else name}"):
        _dc.replace(base, **{name: value})


def _seed_params_for_bounds():
    import yaml as _yaml

    raw = _yaml.safe_load(SIM_YAML.read_text())["robot"]
    return RobotParams(**{k: v for k, v in raw.items() if k != "motor"})
