"""The simulated robot: physics checked against quantities computed here, sensors as hardware."""

from __future__ import annotations

import math
import random
import statistics
import time

import pytest

from ddrt.core.model import forward_dynamics, wheel_rates
from ddrt.params.robot import RobotParams
from ddrt.core.motor import Motor
from ddrt.params.motor import MotorParams
from ddrt.core.wrap import wrap_i32
from sim_hal import PlantConfig, SimRobot
from sim_hal.raw_readings import encoder_count, gyro_raw
from tests.support.seed_robot import TABLE_5_1, TABLE_5_2

QUIET = dict(slip=False, gyro_noise_dps_rthz=0.0)


def robot(table=TABLE_5_1, motor_l=None, motor_r=None, start=(0.0, 0.0, 0.0), **cfg) -> SimRobot:
    return SimRobot(RobotParams(**table), motor_l or MotorParams(), motor_r or MotorParams(),
                    PlantConfig(**cfg), start=start)


def multibody_kinetic_energy(p: RobotParams, v: float, w: float) -> float:
    """T from each body's own velocity: v_point = v x_hat + omega z_hat x r (body frame)."""
    total = 0.0
    for m, x, y in ((p.m_p, p.d_xc, p.d_yc), (p.m_L, 0.0, p.L), (p.m_R, 0.0, -p.R), (p.m_3, p.H, 0.0)):
        vx, vy = v - w * y, w * x
        total += 0.5 * m * (vx * vx + vy * vy)
    total += 0.5 * (p.I_p + p.I_L + p.I_R + p.I_3) * w * w
    for iw, spin in ((p.I_wL, (v - p.L * w) / p.r_L), (p.I_wR, (v + p.R * w) / p.r_R), (p.I_w3, v / p.r_3)):
        total += 0.5 * iw * spin * spin
    return total


def drive_randomly(bot: SimRobot, seconds: float, rng: random.Random, hold_s: float = 0.05) -> None:
    t = bot.t
    while t < seconds - 1e-12:
        bot.command(rng.uniform(-1, 1), rng.uniform(-1, 1))
        t += hold_s
        bot.advance_to(t)


# --- physics --------------------------------------------------------------------------------


@pytest.mark.parametrize("table", [TABLE_5_1, TABLE_5_2])
@pytest.mark.parametrize(("step_hz", "tol"), [(1000.0, 3e-7), (4000.0, 1e-8)])
def test_energy_balance_against_multibody_kinetic_energy(table, step_hz, tol):
    """Work of the net wheel torques = change of T; RK4's error shrinks fast with the step."""
    bot = robot(table, seed=3, step_hz=step_hz)
    p = bot.params
    ke0 = multibody_kinetic_energy(p, *bot.velocity)
    drive_randomly(bot, 1.5, random.Random(5))
    ke1 = multibody_kinetic_energy(p, *bot.velocity)
    e = bot.energy
    assert e.friction_loss_j > 0.1 and e.slip_j != 0.0 and ke1 > 0.01  # all terms are in play
    scale = e.electromagnetic_j + e.friction_loss_j + abs(e.slip_j)
    assert abs(e.net_j - (ke1 - ke0)) <= tol * scale, (e, ke1 - ke0)
    assert e.net_j == pytest.approx(e.electromagnetic_j - e.friction_loss_j + e.slip_j)


def test_energy_balance_holds_over_every_interval():
    bot = robot(TABLE_5_2, seed=4, step_hz=2000.0)
    rng = random.Random(6)
    for _ in range(20):
        ke0, w0 = multibody_kinetic_energy(bot.params, *bot.velocity), bot.energy.net_j
        bot.command(rng.uniform(-1, 1), rng.uniform(-1, 1))
        bot.advance_to(bot.t + 0.03)
        dke = multibody_kinetic_energy(bot.params, *bot.velocity) - ke0
        assert bot.energy.net_j - w0 == pytest.approx(dke, rel=1e-7, abs=1e-9)


def test_plant_torque_is_the_motor_model():
    bot = robot(TABLE_5_2, slip=False, command_latency_s=0.0)
    motors = (Motor(bot.motor_l), Motor(bot.motor_r))
    rng = random.Random(7)
    for _ in range(30):
        bot.command(rng.uniform(-1, 1), rng.uniform(-1, 1))
        bot.advance_to(bot.t + 0.02)
        v, w = bot.velocity
        before = (v - bot.params.L * w) / bot.params.r_L, (v + bot.params.R * w) / bot.params.r_R
        bot.advance_to(bot.t + bot.step_s)  # one step: torque is evaluated at its start
        dl, dr = bot.applied_duty
        assert bot.wheel_torque[0] == pytest.approx(motors[0].torque(dl, before[0]), rel=1e-12, abs=1e-15)
        assert bot.wheel_torque[1] == pytest.approx(motors[1].torque(dr, before[1]), rel=1e-12, abs=1e-15)


@pytest.mark.parametrize(("step_hz", "rel", "abs_"), [(16000.0, 1e-7, 1e-9), (1000.0, 2e-3, 1e-3)])
def test_inlined_integrator_matches_model_and_motor_functions(step_hz, rel, abs_):
    """The hot loop inlines the formulas: check it against forward_dynamics + Motor.torque
    integrated by scipy at tight tolerance, on the robot with the offset mass (m_x, mbar != 0).

    A wheel whose speed changes sign crosses the smoothed Coulomb step (0.02 rad/s wide)
    within one plant step, which fixed-step RK4 cannot resolve: an error of about
    tau_c * step in impulse per crossing. So the tight check runs at a fine step and the
    default 1 kHz is checked for staying within a small, physically negligible bound.
    """
    from scipy.integrate import solve_ivp

    ml, mr = MotorParams(), MotorParams(resistance_ohm=4.4, viscous_nms=0.002, coulomb_nm=0.05)
    params = RobotParams(**TABLE_5_2)
    cfg = PlantConfig(slip=False, command_latency_s=0.0, step_hz=step_hz)
    bot = SimRobot(params, ml, mr, cfg, start=(0.2, 0.1, 0.3))
    motors = Motor(ml), Motor(mr)

    def rhs(_t, s, dl, dr):
        x, y, th, v, w, phi3 = s
        wl, wr, w3 = wheel_rates(params, v, w)
        dv, dw = forward_dynamics(params, (v, w), (motors[0].torque(dl, wl), motors[1].torque(dr, wr)))
        return [v * math.cos(th), v * math.sin(th), w, dv, dw, w3]

    state = [0.2, 0.1, 0.3, 0.0, 0.0, 0.0]
    rng = random.Random(10)
    crossings = 0
    for _ in range(8):
        dl, dr = rng.uniform(-1, 1), rng.uniform(-1, 1)
        bot.command(dl, dr)
        t0 = bot.t
        before = wheel_rates(params, *bot.velocity)
        bot.advance_to(t0 + 0.1)
        sol = solve_ivp(rhs, (t0, bot.t), state, args=(dl, dr), method="DOP853", rtol=1e-11, atol=1e-14)
        state = list(sol.y[:, -1])
        got = (*bot.pose, *bot.velocity, bot.wheel_angles[2])
        assert got == pytest.approx(state, rel=rel, abs=abs_)
        after = wheel_rates(params, *bot.velocity)
        crossings += sum(a * b < 0 for a, b in zip(before, after))
    assert crossings >= 2  # the run does go through the friction's sign changes


def test_straight_run_matches_closed_form():
    """Symmetric robot, centre of mass on the axle, no friction: v(t) is a first-order lag."""
    table = dict(TABLE_5_1, r_R=TABLE_5_1["r_L"], d_yc=0.0)
    table["d_xc"] = -table["m_3"] * table["H"] / table["m_p"]
    bot = robot(table, friction=False, command_latency_s=0.0, **QUIET)
    p, mp = bot.params, bot.motor_l
    m_eff = p.m_p + p.m_L + p.m_R + p.m_3 + p.I_wL / p.r_L**2 + p.I_wR / p.r_R**2 + p.I_w3 / p.r_3**2
    duty, r = 0.6, p.r_L
    # (m + k) dv/dt = 2/r * K (duty V - K v/r) / R_a
    v_inf = duty * mp.supply_v * r / mp.k_nm_per_a
    rate = 2.0 * mp.k_nm_per_a**2 / (mp.resistance_ohm * r * r * m_eff)
    bot.command(duty, duty)
    for t in (0.1, 0.5, 1.0, 2.0):
        bot.advance_to(t)
        v, w = bot.velocity
        assert v == pytest.approx(v_inf * (1.0 - math.exp(-rate * t)), rel=1e-9)
        x, y, th = bot.pose
        assert x == pytest.approx(v_inf * (t - (1.0 - math.exp(-rate * t)) / rate), rel=1e-9)
        assert abs(w) < 1e-12 and abs(y) < 1e-12 and abs(th) < 1e-12
        assert bot.wheel_angles[2] == pytest.approx(x / p.r_3, rel=1e-12)


def test_mirror_image_robot_mirrors_the_motion():
    ml, mr = MotorParams(), MotorParams(resistance_ohm=4.1, coulomb_nm=0.04)
    a = SimRobot(RobotParams(**TABLE_5_2), ml, mr, PlantConfig(**QUIET))
    b = SimRobot(RobotParams(**TABLE_5_2).mirrored(), mr, ml, PlantConfig(**QUIET))
    rng = random.Random(8)
    for _ in range(20):
        dl, dr = rng.uniform(-1, 1), rng.uniform(-1, 1)
        a.command(dl, dr)
        b.command(dr, dl)
        a.advance_to(a.t + 0.05)
        b.advance_to(b.t + 0.05)
        (va, wa), (vb, wb) = a.velocity, b.velocity
        assert vb == pytest.approx(va, rel=1e-9, abs=1e-12)
        assert wb == pytest.approx(-wa, rel=1e-9, abs=1e-12)
    (xa, ya, tha), (xb, yb, thb) = a.pose, b.pose
    assert abs(ya) > 0.01 and abs(tha) > 0.1  # it really turned
    assert (xb, yb, thb) == pytest.approx((xa, -ya, -tha), rel=1e-9, abs=1e-12)


def test_pose_is_the_integral_of_the_velocities():
    """X, Y, theta against a trapezoid integral of v cos(theta), v sin(theta), omega."""
    bot = robot(TABLE_5_2, start=(1.0, -2.0, 0.5), seed=1)
    rng = random.Random(3)
    x, y, th = bot.pose
    prev = (bot.velocity[0], bot.velocity[1], th)
    for k in range(1500):
        if k % 100 == 0:
            bot.command(rng.uniform(-1, 1), rng.uniform(-1, 1))
        bot.advance_to(bot.t + bot.step_s)
        v, w = bot.velocity
        th_now = bot.pose[2]
        half = 0.5 * bot.step_s
        x += half * (prev[0] * math.cos(prev[2]) + v * math.cos(th_now))
        y += half * (prev[0] * math.sin(prev[2]) + v * math.sin(th_now))
        th += half * (prev[1] + w)
        prev = (v, w, th_now)
    assert abs(th - 0.5) > 0.3 and math.hypot(x - 1.0, y + 2.0) > 0.05  # it went somewhere
    assert bot.pose == pytest.approx((x, y, th), abs=2e-5)


def test_friction_makes_a_coasting_robot_stop():
    runs = {}
    for friction in (True, False):
        bot = robot(friction=friction, **QUIET)
        bot.command(0.8, 0.6)
        bot.advance_to(1.0)
        start = bot.velocity
        bot.command(0.0, 0.0)
        bot.advance_to(1.6)
        runs[friction] = (start, bot.velocity)
    (v0, w0), (v1, w1) = runs[True]
    assert abs(v0) > 0.3 and abs(w0) > 0.5
    assert abs(v1) < 1e-6 and abs(w1) < 1e-5
    (_, _), (v1_free, _) = runs[False]
    assert abs(v1_free) > 1e-4  # back-EMF braking alone only decays exponentially


def test_slip_noise_statistics():
    """About 25% of wheel-steps get a slip term of random sign, size ~ N(0.01 tau, 0.01 N m)."""
    bot = robot(command_latency_s=0.0, seed=9)
    motor = Motor(bot.motor_l)
    hits, sizes, expected = 0, [], []
    bot.command(0.3, 0.3)
    n = 4000
    for _ in range(n):
        v, w = bot.velocity
        bot.advance_to(bot.t + bot.step_s)
        clean = motor.torque(bot.applied_duty[0], (v - bot.params.L * w) / bot.params.r_L)
        extra = bot.wheel_torque[0] - clean
        if abs(extra) > 1e-15:
            hits += 1
            sizes.append(abs(extra))
            mu, sig = 0.01 * clean, 0.01  # mean of the folded normal |N(mu, sig)|
            expected.append(sig * math.sqrt(2 / math.pi) * math.exp(-mu * mu / (2 * sig * sig))
                            + mu * math.erf(mu / (sig * math.sqrt(2))))
    assert hits / n == pytest.approx(0.25, abs=0.03)
    assert statistics.fmean(sizes) == pytest.approx(statistics.fmean(expected), rel=0.08)
    ref = robot(slip=False)
    ref.command(0.3, 0.3)
    ref.advance_to(0.1)
    assert ref.energy.slip_j == 0.0 and ref.energy.electromagnetic_j > 0.0


# --- timing ----------------------------------------------------------------------------------


def test_command_latency():
    bot = robot(**QUIET)
    bot.advance_to(0.010)
    bot.command(0.7, -0.4)
    seen = None
    while bot.t < 0.020:
        bot.advance_to(bot.t + bot.step_s)
        if seen is None and bot.wheel_torque != (0.0, 0.0):
            seen = bot.t - bot.step_s  # start of the step in which the torque appeared
    assert seen is not None
    assert 0.010 + 0.0015 - 1e-12 <= seen <= 0.010 + 0.0015 + bot.step_s
    assert bot.applied_duty == (0.7, -0.4)


def test_zero_latency_acts_from_the_next_step():
    bot = robot(command_latency_s=0.0, **QUIET)
    bot.command(0.5, 0.5)
    bot.advance_to(bot.step_s)
    assert bot.wheel_torque[0] > 0.5


@pytest.mark.parametrize(("latency", "steps"), [(0.003, 3), (0.0015, 2), (0.0, 0)])
def test_sensor_latency_reports_the_past(latency, steps):
    # A DLPF far above the step rate makes the gyro show the delayed rate without lag.
    bot = robot(sensor_latency_s=latency, gyro_bias_dps=0.0, gyro_dlpf_hz=1e9, **QUIET)
    cpr = bot.encoder_counts_per_rev
    bot.command(0.6, 0.3)
    history = []
    for _ in range(300):
        history.append((bot.wheel_angles[2], bot.velocity[1]))
        bot.advance_to(bot.t + bot.step_s)
    history.append((bot.wheel_angles[2], bot.velocity[1]))
    # The reading now is the state `steps` plant steps ago: never newer than the latency.
    past_phi3, past_w = history[-1 - steps]
    assert bot.read_encoder() == math.floor(past_phi3 * cpr / (2 * math.pi))
    assert bot.read_gyro_raw() == round(math.degrees(past_w) * 131.0) != 0
    if steps:
        assert bot.read_encoder() != math.floor(history[-1][0] * cpr / (2 * math.pi))


def test_advance_to_takes_whole_steps():
    bot = robot(**QUIET)
    bot.advance_to(0.003)
    assert bot.t == pytest.approx(0.003, abs=1e-15)
    bot.advance_to(0.0031)
    assert bot.t == pytest.approx(0.004, abs=1e-15)
    bot.advance_to(0.001)  # the past: nothing happens
    assert bot.t == pytest.approx(0.004, abs=1e-15)
    for k in range(5, 400):
        bot.advance_to(k * 0.001)
        assert round(bot.t / bot.step_s) == k


# --- sensors ---------------------------------------------------------------------------------


def test_encoder_count_is_floored_front_wheel_angle():
    bot = robot(**QUIET, sensor_latency_s=0.0)
    bot.command(-0.5, -0.3)
    for t in (0.2, 0.7, 1.3):
        bot.advance_to(t)
        phi3 = bot.wheel_angles[2]
        assert bot.read_encoder() == math.floor(phi3 * 8192 / (2 * math.pi))
    assert bot.read_encoder() < -1000  # reversing counts down, through zero


def test_encoder_wraps_like_int32():
    assert wrap_i32(2**31 - 1) == 2**31 - 1
    assert wrap_i32(2**31) == -(2**31)
    assert wrap_i32(-(2**31) - 1) == 2**31 - 1
    assert encoder_count(2 * math.pi, 8192, offset=2**31 - 8192) == -(2**31)
    bot = robot(encoder_offset_counts=2**31 - 100, **QUIET)
    assert bot.read_encoder() == 2**31 - 100
    bot.command(0.5, 0.5)
    bot.advance_to(0.5)
    count = bot.read_encoder()
    assert count < 0
    # The difference modulo 2^32 still gives the distance, as a decoder would compute it.
    travelled = wrap_i32(count - (2**31 - 100))
    assert travelled == pytest.approx(bot.wheel_angles[2] * 8192 / (2 * math.pi), abs=40)


def _gyro_at_rest(step_hz: float, n: int, **cfg) -> list[int]:
    bot = robot(slip=False, step_hz=step_hz, **cfg)
    out = []
    for _ in range(n):
        bot.advance_to(bot.t + 0.001)
        out.append(bot.read_gyro_raw())
    assert bot.velocity == (0.0, 0.0)
    return out


@pytest.mark.parametrize("step_hz", [1000.0, 2000.0])
def test_gyro_noise_and_bias_statistics_at_rest(step_hz):
    raw = _gyro_at_rest(step_hz, 6000, seed=2)
    lsb = 131.0
    assert statistics.fmean(raw) == pytest.approx(1.5 * lsb, abs=1.0)
    # White noise of density rho through a one-pole low-pass of fc: sigma = rho sqrt(pi fc / 2).
    expected_std = 0.005 * math.sqrt(math.pi * 98.0 / 2.0) * lsb
    assert statistics.pstdev(raw) == pytest.approx(expected_std, rel=0.1)


def test_gyro_noise_is_filtered():
    """Successive samples of low-passed noise are correlated; white noise would not be."""
    raw = _gyro_at_rest(1000.0, 4000, seed=5, gyro_bias_dps=0.0)
    mean = statistics.fmean(raw)
    dev = [r - mean for r in raw]
    lag1 = sum(a * b for a, b in zip(dev, dev[1:])) / sum(d * d for d in dev)
    assert 0.35 < lag1 < 0.75  # theory: 1 - a = exp(-2 pi 98 / 1000) = 0.54


def test_gyro_reads_rate_with_scale_error_and_bias():
    for scale_error in (0.0, 0.03):
        bot = robot(gyro_scale_error=scale_error, gyro_bias_dps=-2.0, **QUIET)
        bot.command(-0.3, 0.3)
        bot.advance_to(2.0)
        w = bot.velocity[1]
        assert 0.5 < w < 4.0  # turning left in place, within the +-250 dps range
        bot.advance_to(2.01)  # steady: the lag of filter and latency no longer matters
        expected = ((1 + scale_error) * math.degrees(bot.velocity[1]) - 2.0) * 131.0
        assert bot.read_gyro_raw() == pytest.approx(expected, abs=1.0)
        assert bot.gyro_lsb_per_rad_s * bot.velocity[1] == pytest.approx(math.degrees(w) * 131, rel=1e-3)


def test_gyro_saturates_at_int16():
    assert gyro_raw(1e6, 131.0) == 32767 and gyro_raw(-1e6, 131.0) == -32768
    bot = robot(**QUIET)
    bot.command(-1.0, 1.0)  # spin in place as fast as the motors go
    bot.advance_to(2.0)
    assert bot.velocity[1] > bot.gyro_full_scale_rad_s
    assert bot.read_gyro_raw() == 32767
    bot.command(1.0, -1.0)
    bot.advance_to(5.0)
    assert bot.read_gyro_raw() == -32768
    assert bot.gyro_full_scale_rad_s == pytest.approx(math.radians(32767 / 131.0))
    wide = robot(gyro_range_dps=2000, **QUIET)
    assert wide.gyro_lsb_per_rad_s == pytest.approx(16.4 * 180 / math.pi)


def test_same_seed_same_run_different_seed_different_run():
    def run(seed):
        bot = robot(TABLE_5_2, seed=seed)
        rng = random.Random(1)
        out = []
        for _ in range(40):
            bot.command(rng.uniform(-1, 1), rng.uniform(-1, 1))
            bot.advance_to(bot.t + 0.01)
            out.append((bot.read_encoder(), bot.read_gyro_raw(), bot.pose))
        return out

    assert run(3) == run(3)
    assert run(3) != run(4)
    assert [g for _, g, _ in run(3)] != [g for _, g, _ in run(4)]


# --- API ---------------------------------------------------------------------------------


@pytest.mark.parametrize("bad", [1.0001, -1.5, math.nan, math.inf])
def test_command_rejects_bad_duty(bad):
    bot = robot()
    with pytest.raises(ValueError, match="duty_l"):
        bot.command(bad, 0.0)
    with pytest.raises(ValueError, match="duty_r"):
        bot.command(0.0, bad)
    bot.advance_to(0.01)
    assert bot.applied_duty == (0.0, 0.0)


def test_bad_inputs_raise_naming_the_field():
    with pytest.raises(ValueError, match="step_hz"):
        PlantConfig(step_hz=0.0)
    with pytest.raises(ValueError, match="slip_probability"):
        PlantConfig(slip_probability=1.5)
    with pytest.raises(ValueError, match="gyro_range_dps"):
        PlantConfig(gyro_range_dps=300)
    with pytest.raises(ValueError, match="sensor_latency_s"):
        PlantConfig(sensor_latency_s=math.nan)
    with pytest.raises(ValueError, match="friction"):
        PlantConfig(friction="yes")
    with pytest.raises(ValueError, match="encoder_counts_per_rev"):
        PlantConfig(encoder_counts_per_rev=8192.5)
    with pytest.raises(ValueError, match="bogus"):
        PlantConfig.from_mapping({"bogus": 1})
    assert PlantConfig.from_mapping({"step_hz": 500}).step_hz == 500.0
    with pytest.raises(ValueError, match="start"):
        robot(start=(0.0, math.nan, 0.0))
    with pytest.raises(ValueError):
        robot().advance_to(math.nan)


def test_friction_switch_zeroes_viscous_and_coulomb():
    bot = robot(friction=False)
    assert bot.motor_l.viscous_nms == 0.0 and bot.motor_r.coulomb_nm == 0.0
    assert bot.motor_l.resistance_ohm == MotorParams().resistance_ohm
    bot.command(0.5, 0.5)
    bot.advance_to(0.5)
    assert bot.energy.friction_loss_j == 0.0


def test_ten_seconds_of_plant_run_fast():
    bot = robot(TABLE_5_2)
    rng = random.Random(2)
    start = time.thread_time()  # the CPU it takes, which a loaded host does not inflate
    for k in range(1, 101):
        bot.command(rng.uniform(-1, 1), rng.uniform(-1, 1))
        bot.advance_to(k * 0.1)
    elapsed = time.thread_time() - start
    assert round(bot.t / bot.step_s) == 10000
    assert elapsed < 3.0, elapsed


def test_compiled_plant_is_bit_identical_to_the_python_integrator(monkeypatch) -> None:
    """The C kernel (sim_hal/plant_native.py) must give the Python integrator's numbers bit for
    bit: slip and gyro noise on, duty changes landing mid-stretch, uneven advance steps, a burst."""
    from sim_hal import plant_native

    if plant_native.kernel() is None:
        pytest.skip("no C compiler: the plant runs in Python only")
    runs = []
    for mode in ("native", "python"):
        if mode == "python":
            monkeypatch.setattr(plant_native, "kernel", lambda: None)
        sim = robot(TABLE_5_2, seed=7, slip_probability=0.5, start=(0.1, -0.2, 0.3), wheel_counts_per_rev=4096)
        assert (sim._kernel is None) == (mode == "python")
        drive = random.Random(3)
        trace = []
        t = 0.0
        for n in range(400):
            for _ in range(150 if n == 200 else 1):  # a burst: the kernel's command ring grows
                sim.command(drive.uniform(-1.0, 1.0), drive.uniform(-1.0, 1.0))
            t += drive.choice((0.0007, 0.005, 0.0123))
            sim.advance_to(t)
            trace.append((sim.pose, sim.velocity, sim.wheel_angles, sim.applied_duty, sim.wheel_torque,
                          sim.energy, sim.read_encoder(), sim.read_gyro_raw(), sim.read_wheel_counts(), sim.t))
        runs.append(trace)
    assert runs[0] == runs[1]
