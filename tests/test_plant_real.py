"""The plant's options (sim_hal/plant.py, `Realism`): battery, deadband, backlash, gyro
warm-up and register timing, encoder slip, drive-wheel counts, events, MCU crystal drift.
Physics checked by physics: energy balance, closed-form sag, symmetry, independent formulas."""

from __future__ import annotations

import math
import random
import statistics

import pytest

from ddrt.config import load_config
from ddrt.config.schema import ConfigError
from ddrt.config.load import config_from_mapping
from ddrt.config.sim_truth import (
    ActuatorTruth, BatteryTruth, EventsTruth, FloorPatch, PayloadEvent, WanderingScale, WheelsTruth,
)
from ddrt.core.model import Dynamics
from ddrt.params.motor import MotorParams
from ddrt.params.robot import RobotParams
from hal.wire import FrameDecoder, State
from sim_hal import plant_native
from sim_hal.factory import plant_config
from sim_hal.mpu_emulator import TEMP_OUT_H, MpuEmulator, SineGyro, temp_out_c, temp_out_raw
from sim_hal.plant import PlantConfig, Realism, SimRobot
from sim_hal.plant_effects import Wanderer, with_payload
from sim_hal.raw_readings import encoder_count
from tests.support.repo import REPO
from tests.support.seed_robot import TABLE_5_1, TABLE_5_2

QUIET = dict(slip=False, gyro_noise_dps_rthz=0.0, command_latency_s=0.0)
SYM = dict(TABLE_5_1, r_L=0.05, r_R=0.05)  # left and right alike
PACK = BatteryTruth(cells=3, resistance_ohm=0.25, start_soc=0.15, capacity_ah=1000.0)  # 10.5 V, OCV constant


def bot(table=TABLE_5_1, motor=None, realism: Realism | None = None, **cfg) -> SimRobot:
    m = motor or MotorParams()
    return SimRobot(RobotParams(**table), m, m, PlantConfig(realism=realism or Realism(), **cfg))


def ke(p: RobotParams, v: float, w: float) -> float:
    return Dynamics.from_params(p).kinetic_energy(v, w)


# --- the choice of integrator ---------------------------------------------------------------


def test_realistic_keys_choose_the_python_integrator_and_it_agrees_with_the_kernel(monkeypatch) -> None:
    """An option set so that it has no effect (the start temperature: the bias depends on the
    warming) runs in the kernel when there is one, and drives the same robot as the Python step
    (forced): same slip draws, same gyro noise, same counts."""
    warm = Realism(gyro_temp_start_c=30.0)
    assert not Realism().active and warm.active
    runs = []
    for mode in ("fast", "python"):
        if mode == "python":
            monkeypatch.setattr(plant_native, "kernel", lambda: None)
        sim = bot(TABLE_5_2, realism=warm, seed=7, slip_probability=0.5, wheel_counts_per_rev=2048)
        assert sim.integrator == ("python" if mode == "python" or plant_native.kernel() is None else "kernel")
        drive, trace, t = random.Random(3), [], 0.0
        for _ in range(300):
            sim.command(drive.uniform(-1.0, 1.0), drive.uniform(-1.0, 1.0))
            t += drive.choice((0.0007, 0.005, 0.0123))
            sim.advance_to(t)
            trace.append((sim.pose + sim.velocity + sim.wheel_angles, sim.read_encoder(),
                          sim.read_wheel_counts(), sim.read_gyro_raw()))
        runs.append(trace)
    for a, b in zip(*runs):
        assert a[0] == pytest.approx(b[0], rel=1e-9, abs=1e-12)
        assert a[1] == b[1] and a[2] == b[2] and abs(a[3] - b[3]) <= 1


def test_default_plant_keeps_the_kernel_and_ideal_readings() -> None:
    sim = bot(seed=1, wheel_counts_per_rev=4096, sensor_latency_s=0.002)
    assert sim.battery_v == MotorParams().supply_v and not sim.options.active
    sim.command(0.5, -0.3)
    sim.advance_to(0.5)
    phl, phr, _ = sim.wheel_angles
    sim_ahead = sim.read_wheel_counts()
    # Ideal counts of the angles two steps ago (the sensor latency), not of the angles now.
    assert sim_ahead != (encoder_count(phl, 4096), encoder_count(phr, 4096))
    sim.command(0.0, 0.0)
    sim.advance_to(3.0)  # at rest: now and two steps ago agree
    phl, phr, _ = sim.wheel_angles
    assert sim.read_wheel_counts() == (encoder_count(phl, 4096), encoder_count(phr, 4096))
    assert bot().read_wheel_counts() == (0, 0)


# --- battery ---------------------------------------------------------------------------------


def test_battery_without_resistance_is_an_ideal_supply_at_its_open_circuit_voltage() -> None:
    e = PACK.ocv_v(PACK.start_soc)
    assert e == pytest.approx(10.5, abs=1e-9)
    stiff = bot(realism=Realism(battery=BatteryTruth(cells=3, start_soc=0.15, capacity_ah=1000.0)), **QUIET)
    ideal = bot(motor=MotorParams(supply_v=e), **QUIET)
    for sim in (stiff, ideal):
        sim.command(0.7, 0.5)
        sim.advance_to(1.5)
    assert stiff.pose == pytest.approx(ideal.pose, rel=1e-6, abs=1e-9)
    assert stiff.battery_v == pytest.approx(e, rel=1e-6)


def test_sag_is_current_times_resistance_and_slows_the_robot() -> None:
    sim = bot(realism=Realism(battery=PACK), **QUIET)
    stiff = bot(realism=Realism(battery=BatteryTruth(cells=3, start_soc=0.15, capacity_ah=1000.0)), **QUIET)
    d = (0.8, 0.6)
    for s in (sim, stiff):
        s.command(*d)
        s.advance_to(0.05)
    # The pack current from the motor equations at the robot's wheel speeds (independently of
    # the plant's closed form): I_i = (d_i V - k w_i) / R_a, I = sum d_i I_i, V = E - R I.
    p, m = sim.params, MotorParams()
    v, w = sim.velocity
    wheels = ((v - p.L * w) / p.r_L, (v + p.R * w) / p.r_R)
    vt = sim.battery_v
    current = sum(di * (di * vt - m.k_nm_per_a * wi) / m.resistance_ohm for di, wi in zip(d, wheels))
    assert current > 0.5
    ocv = sim.supply.ocv_v  # 10.5 V less the little charge drawn
    assert ocv == pytest.approx(10.5, abs=1e-6)
    assert vt == pytest.approx(ocv - 0.25 * current, rel=1e-12)
    assert 9.0 < vt < 10.4
    assert sim.supply.current_a == pytest.approx(current, rel=1e-9)
    assert sim.velocity[0] < stiff.velocity[0]
    for s in (sim, stiff):
        s.advance_to(3.0)
    assert sim.velocity[0] < stiff.velocity[0] - 0.002  # still slower at speed (less current then)


def test_energy_from_the_source_is_resistances_plus_friction_plus_kinetic_energy() -> None:
    sim = bot(TABLE_5_2, realism=Realism(battery=BatteryTruth(cells=3, resistance_ohm=0.3, start_soc=0.5,
                                                               capacity_ah=0.01)),
              slip=False, gyro_noise_dps_rthz=0.0, step_hz=2000.0)
    ke0 = ke(sim.params, *sim.velocity)
    rng = random.Random(4)
    for k in range(1, 41):
        sim.command(rng.uniform(-1, 1), rng.uniform(-1, 1))
        sim.advance_to(k * 0.05)
    real = sim.supply
    dke = ke(sim.params, *sim.velocity) - ke0
    out = real.internal_j + real.armature_j + sim.energy.friction_loss_j + dke
    assert real.internal_j > 0.05 and real.armature_j > 0.5 and sim.energy.friction_loss_j > 0.1
    assert real.source_j == pytest.approx(out, rel=1e-6)
    # The charge drawn moved the state of charge (a small pack: 36 C).
    assert real.soc == pytest.approx(0.5 - real.charge_c / 36.0, rel=1e-12)
    assert real.soc != 0.5


# --- actuators -------------------------------------------------------------------------------


def test_duty_inside_the_deadband_moves_nothing() -> None:
    sim = bot(realism=Realism(actuators=ActuatorTruth(deadband=0.04)), wheel_counts_per_rev=4096, **QUIET)
    sim.command(0.039, -0.039)
    sim.advance_to(1.0)
    assert sim.pose == (0.0, 0.0, 0.0) and sim.wheel_torque == (0.0, 0.0) and sim.read_wheel_counts() == (0, 0)
    sim.command(0.2, 0.2)
    sim.advance_to(1.5)
    assert sim.pose[0] > 0.01


def _backlash_bot(table=SYM, **kw) -> SimRobot:
    return bot(table, realism=Realism(actuators=ActuatorTruth(backlash_deg=1.5, motor_inertia_kgm2=2e-4)), **QUIET, **kw)


def test_no_wheel_torque_while_the_motor_crosses_the_play() -> None:
    sim = _backlash_bot()
    sim.command(0.3, 0.3)
    torques = []
    while sim.t < 0.1 - 1e-9:
        sim.advance_to(sim.t + sim.step_s)
        torques.append(sim.wheel_torque)
    free = next(i for i, tq in enumerate(torques) if tq != (0.0, 0.0))
    # The motor from rest across half the play under its stall torque (the back-EMF is small at
    # these speeds; the friction stays with the wheel): t = sqrt(2 (play / 2) J / tau).
    m = MotorParams()
    tau = m.k_nm_per_a * 0.3 * m.supply_v / m.resistance_ohm
    expect = math.sqrt(2.0 * math.radians(0.75) * 2e-4 / tau)
    assert free * sim.step_s == pytest.approx(expect, rel=0.3)
    assert all(tq == (0.0, 0.0) for tq in torques[:free]) and sim.pose[0] > 0.0
    assert sim.backlash_side == (1, 1)
    # Reversing: the motor leaves the front flank and crosses to the back one; meanwhile the
    # rolling wheel feels only its own friction (gearbox and bearings), none of the motor's torque.
    sim.command(-0.3, -0.3)
    p, free_steps = sim.params, 0
    while sim.t < 0.2 - 1e-9:
        v, w = sim.velocity
        ww = ((v - p.L * w) / p.r_L, (v + p.R * w) / p.r_R)
        sim.advance_to(sim.t + sim.step_s)
        friction = [m.viscous_nms * x + m.coulomb_nm * math.tanh(x / m.coulomb_smoothing_rad_s) for x in ww]
        free_steps += all(abs(tq + fr) < 1e-12 for tq, fr in zip(sim.wheel_torque, friction))
    assert free_steps >= 2 and sim.velocity[0] < 0.0


@pytest.mark.parametrize("k", [0.382, 1.0, 1.84, 4.0])
def test_a_strong_gearmotor_crosses_the_play_and_drives_its_wheel(k: float) -> None:
    """k^2 / (R J) times the step from 0.2 to 20: the free motor's back-EMF damping is stiff for
    the larger ones (an explicit step diverges beyond 2), and still each motor takes up the play
    once, in the time its exact free motion takes, and drives its wheel."""
    m = MotorParams(k_nm_per_a=k, resistance_ohm=4.0)
    sim = bot(SYM, motor=m, realism=Realism(actuators=ActuatorTruth(backlash_deg=1.5, motor_inertia_kgm2=2e-4)),
              **QUIET)
    duty = 0.2
    sim.command(duty, 0.0)
    steps, engaged_at = 0, None
    while sim.t < 0.3 - 1e-9:
        sim.advance_to(sim.t + sim.step_s)
        steps += 1
        if engaged_at is None and sim.backlash_side[0] != 0:
            engaged_at = steps * sim.step_s
    assert engaged_at is not None and sim.backlash_side[0] == 1
    # From rest: w(t) = w_inf (1 - exp(-a t)), a = k^2 / (R J), w_inf = duty V / k; the play's
    # half is crossed when the angle w_inf (t - (1 - exp(-a t)) / a) reaches it.
    a, w_inf, half = k * k / (4.0 * 2e-4), duty * m.supply_v / k, math.radians(0.75)
    t = next(i * 1e-5 for i in range(1, 100000) if w_inf * (i * 1e-5 - (1 - math.exp(-a * i * 1e-5)) / a) >= half)
    assert engaged_at == pytest.approx(t, abs=2.5 * sim.step_s)
    assert sim.pose[0] > 0.0 and sim.pose[2] < 0.0  # the left wheel alone: forward, turning clockwise


def test_backlash_is_symmetric_left_right() -> None:
    mirrored = RobotParams(**TABLE_5_2).mirrored()
    a, same = _backlash_bot(TABLE_5_2), _backlash_bot()
    b = _backlash_bot({n: getattr(mirrored, n) for n in RobotParams.names()})
    rng = random.Random(9)
    for k in range(1, 60):
        dl, dr = rng.uniform(-0.6, 0.6), rng.uniform(-0.6, 0.6)
        a.command(dl, dr)
        b.command(dr, dl)
        same.command(dl, dl)
        for s in (a, b, same):
            s.advance_to(k * 0.02)
        xa, ya, tha = a.pose
        xb, yb, thb = b.pose
        assert (xa, ya, tha) == pytest.approx((xb, -yb, -thb), rel=1e-9, abs=1e-12)
        assert same.pose[2] == 0.0 and same.wheel_torque[0] == same.wheel_torque[1]


# --- gyro --------------------------------------------------------------------------------------


def test_temp_out_formula_round_trips_through_the_register() -> None:
    for temp in (-40.0, 0.0, 25.0, 36.53, 41.7, 85.0):
        assert temp_out_c(temp_out_raw(temp)) == pytest.approx(temp, abs=0.5 / 340.0)
    assert temp_out_raw(36.53) == 0 and temp_out_raw(37.53) == 340
    now = {"T": 31.25}
    mpu = MpuEmulator(SineGyro(0.1, 1.0, lambda: 0.0), temperature_c=lambda: now["T"])
    mpu.write_byte_data(0x68, 0x6B, 0x00)  # wake
    hi, lo = mpu.read_i2c_block_data(0x68, TEMP_OUT_H, 2)
    raw = (hi << 8 | lo) - (0x10000 if hi & 0x80 else 0)
    assert temp_out_c(raw) == pytest.approx(31.25, abs=0.5 / 340.0)


def test_mpu_register_holds_between_refreshes_at_its_sample_rate() -> None:
    clock = {"t": 0.0}
    mpu = MpuEmulator(SineGyro(1.0, 3.0, lambda: clock["t"]), clock=lambda: clock["t"])
    mpu.write_byte_data(0x68, 0x6B, 0x00)
    mpu.write_byte_data(0x68, 0x19, 4)  # SMPLRT_DIV 4: 200 Hz with the DLPF on
    mpu.write_byte_data(0x68, 0x1A, 2)
    assert mpu.sample_period_s == pytest.approx(0.005)
    reads = []
    for i in range(100):  # every 0.5 ms for 50 ms
        clock["t"] = 0.0101 + i * 0.0005
        reads.append((clock["t"], tuple(mpu.read_i2c_block_data(0x68, 0x47, 2))))
    for (t0, r0), (t1, r1) in zip(reads, reads[1:]):
        same_period = math.floor(t0 / 0.005 + 1e-9) == math.floor(t1 / 0.005 + 1e-9)
        assert (r0 == r1) or not same_period
    assert mpu.refreshes == 10
    assert len({r for _, r in reads}) == 10  # the source changed: each refresh shows it


def test_plant_gyro_register_is_0_to_one_period_old_and_differs_per_tick() -> None:
    """At rest with a bias ramping at a known rate, a reading's value says how old it is:
    age = t - (reading - bias0) / ramp. Held at 200 Hz on a clock 2 % fast, read at 200 Hz
    ticks: the DLPF's lag plus 0 to one sample period, a different age from tick to tick;
    read at the tick (no hold), the DLPF's lag alone."""
    ramp = 100.0  # deg/s per s: an LSB (1/131 deg/s) is 76 us of age
    period = 1.0 / (200.0 * 1.02)
    spans = {}
    for odr in (0.0, 200.0):
        sim = bot(realism=Realism(gyro_drift_dps_per_s=ramp, gyro_odr_hz=odr, gyro_clock_ppm=20000.0),
                  gyro_bias_dps=0.0, sensor_latency_s=0.0, **QUIET)
        lsb_dps = sim.gyro_lsb_per_rad_s * math.pi / 180.0
        ages = []
        for k in range(20, 80):
            t = k * 0.005 + 0.0021
            sim.advance_to(t)
            ages.append(sim.t - sim.read_gyro_raw() / lsb_dps / ramp)
        lag = sim.gyro_delay_s
        assert min(ages) == pytest.approx(lag, abs=2e-4)
        spans[odr] = max(ages) - min(ages)
        if odr:
            assert sim.gyro_hold_s == pytest.approx(period)
            assert max(ages) <= lag + period + 2e-4
            assert len({round(a, 4) for a in ages}) >= 10  # differs from tick to tick
    assert spans[0.0] < 2e-4 and spans[200.0] > 0.8 * period


def test_gyro_bias_follows_the_die_warm_up() -> None:
    realism = Realism(gyro_warmup_rise_c=8.0, gyro_warmup_tau_s=20.0, gyro_bias_per_c_dps=0.12)
    sim = bot(realism=realism, seed=2)
    lsb_dps = sim.gyro_lsb_per_rad_s * math.pi / 180.0
    for t_end in (2.0, 60.0):
        expect_rise = 8.0 * (1 - math.exp(-(t_end - 0.5) / 20.0))  # mid-window: nearly linear across it
        sim.advance_to(t_end - 1.0)
        reads = []
        while sim.t < t_end - 1e-9:
            sim.advance_to(sim.t + 0.005)
            reads.append(sim.read_gyro_raw() / lsb_dps)
        assert sim.gyro_die_temp_c == pytest.approx(25.0 + 8.0 * (1 - math.exp(-t_end / 20.0)))
        assert statistics.fmean(reads) == pytest.approx(1.5 + 0.12 * expect_rise, abs=0.02)


def test_linear_drift_and_scale_error() -> None:
    sim = bot(realism=Realism(gyro_drift_dps_per_s=0.01), gyro_scale_error=0.02, **QUIET)
    sim.advance_to(50.0)
    lsb_dps = sim.gyro_lsb_per_rad_s * math.pi / 180.0
    assert sim.read_gyro_raw() / lsb_dps == pytest.approx(1.5 + 0.5, abs=0.01)


# --- encoders --------------------------------------------------------------------------------


def test_omni_wheel_slip_scales_its_count_only() -> None:
    slipping = bot(realism=Realism(encoder_slip=WanderingScale(mean=-0.003)), wheel_counts_per_rev=4096, **QUIET)
    ideal = bot(wheel_counts_per_rev=4096, **QUIET)
    for s in (slipping, ideal):
        s.command(0.5, 0.5)
        s.advance_to(4.0)
        s.command(0.0, 0.0)
        s.advance_to(6.0)
    assert slipping.pose == pytest.approx(ideal.pose, rel=1e-9, abs=1e-12)
    assert slipping.read_wheel_counts() == ideal.read_wheel_counts()
    assert slipping.read_encoder() / ideal.read_encoder() == pytest.approx(0.997, abs=2e-4)


def test_wandering_scale_has_its_sigma_and_time_constant() -> None:
    ou = Wanderer(WanderingScale(sigma=0.01, tau_s=0.05), 0.001)
    rng = random.Random(5)
    xs = []
    for _ in range(200000):  # 4000 time constants
        ou.step(rng.gauss)
        xs.append(ou.s)
    assert statistics.pstdev(xs) == pytest.approx(0.01, rel=0.1)
    lag = 50  # one time constant at 1 kHz: correlation exp(-1)
    mean = statistics.fmean(xs)
    c0 = statistics.fmean((x - mean) ** 2 for x in xs)
    c1 = statistics.fmean((a - mean) * (b - mean) for a, b in zip(xs, xs[lag:]))
    assert c1 / c0 == pytest.approx(math.exp(-1.0), abs=0.08)


def test_drive_wheels_slip_under_traction_and_the_omni_wheel_does_not() -> None:
    slipping = bot(SYM, realism=Realism(wheels=WheelsTruth(slip_per_nm=0.05)), wheel_counts_per_rev=4096, **QUIET)
    ideal = bot(SYM, wheel_counts_per_rev=4096, **QUIET)
    for s in (slipping, ideal):
        s.command(0.9, 0.9)
        s.advance_to(0.5)  # accelerating: a large forward torque
    (sl, sr), (il, ir) = slipping.read_wheel_counts(), ideal.read_wheel_counts()
    assert sl > il * 1.005 and sr > ir * 1.005 and sl == sr
    assert slipping.read_encoder() == ideal.read_encoder()


# --- events ---------------------------------------------------------------------------------


def test_payload_merges_into_the_platform_as_a_rigid_body() -> None:
    p = RobotParams(**TABLE_5_1)
    q = with_payload(p, 1.0, 0.002, 0.05, 0.02)
    d0, d1 = Dynamics.from_params(p), Dynamics.from_params(q)
    assert d1.m_k == pytest.approx(d0.m_k + 1.0)
    assert d1.m_x == pytest.approx(d0.m_x + 1.0 * 0.05)  # first moment about A
    assert d1.I == pytest.approx(d0.I + 0.002 + 1.0 * (0.05**2 + 0.02**2))  # parallel axis about A
    assert d1.mbar == pytest.approx(d0.mbar - 1.0 * 0.02)


def test_payload_at_its_time_slows_the_acceleration() -> None:
    realism = Realism(events=EventsTruth(payloads=(PayloadEvent(at_s=0.5, mass_kg=2.0),)))
    loaded, plain = bot(realism=realism, **QUIET), bot(**QUIET)
    for s in (loaded, plain):
        s.command(0.3, 0.3)
        s.advance_to(0.5)
    assert loaded.pose == pytest.approx(plain.pose, rel=1e-9)
    for s in (loaded, plain):
        s.command(0.9, 0.9)
        s.advance_to(0.6)
    assert loaded.velocity[0] < plain.velocity[0] - 0.01


def test_floor_patch_scales_friction_where_the_robot_is() -> None:
    patch = FloorPatch(x_min=0.3, y_min=-1.0, x_max=5.0, y_max=1.0, friction_scale=3.0)
    sticky, plain = bot(realism=Realism(events=EventsTruth(floor=(patch,))), **QUIET), bot(**QUIET)
    for s in (sticky, plain):
        s.command(0.3, 0.3)
        s.advance_to(1.0)
    assert sticky.pose[0] > 0.3
    assert sticky.velocity[0] < plain.velocity[0] - 0.01


# --- config, emulated devices -------------------------------------------------------------


def test_sim_keys_from_yaml_reach_the_plant_and_bad_ones_name_the_key() -> None:
    cfg = load_config(str(REPO / "configs/sim.yaml"))
    assert plant_config(cfg).realism == Realism()
    base = {"hal": {"backend": "sim"}, "robot": dict(TABLE_5_1)}
    data = dict(base, sim={"battery": {"cells": 3, "resistance_ohm": 0.25, "start_soc": 0.15},
                           "gyro": {"register_hold": True, "warmup_rise_c": 8.0},
                           "actuators": {"deadband": 0.04, "backlash_deg": 1.5},
                           "events": {"payloads": [{"at_s": 3.0, "mass_kg": 1.0}],
                                      "floor": [{"x_min": 0, "y_min": 0, "x_max": 1, "y_max": 1}]}})
    r = plant_config(config_from_mapping(data)).realism
    assert r.active and r.gyro_odr_hz == 200.0 and r.battery.ocv_v(0.15) == pytest.approx(10.5)
    assert r.events.payloads[0].mass_kg == 1.0 and r.actuators.backlash_deg == 1.5
    for bad, key in (({"battery": {"start_soc": 1.5}}, "sim.battery.start_soc"),
                     ({"actuators": {"deadband": 0.7}}, "sim.actuators.deadband"),
                     ({"events": {"floor": [{"x_min": 1, "y_min": 0, "x_max": 0, "y_max": 1}]}}, "sim.events.floor[0]"),
                     ({"gyro": {"clock_ppm": 1e6}}, "sim.gyro.clock_ppm"),
                     ({"wheels": {"scale": {"tau_s": 0}}}, "sim.wheels.scale.tau_s")):
        with pytest.raises(ConfigError, match=key.replace("[", r"\[").replace("]", r"\]")):
            config_from_mapping(dict(base, sim=bad))


def test_mcu_crystal_drift_stretches_its_t_us() -> None:
    from sim_hal.emulated import EmulatedDevices

    cfg = load_config(str(REPO / "configs/sim.yaml"))
    import dataclasses

    for ppm in (0.0, 5000.0):
        c = dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, mcu_clock_ppm=ppm))
        dev = EmulatedDevices(c, (0.0, 0.0, 0.0))
        try:
            dev.time.sleep_until(2.0)
            states = [p.msg for p in FrameDecoder().feed(bytes(dev.link.to_host)) if isinstance(p.msg, State)]
        finally:
            dev.close()
        span_us = states[-1].t_us - states[0].t_us
        n = len(states) - 1
        # STATE every 5 ms of the MCU's time: its t_us steps 5000 per frame whatever the drift,
        # and the frames come (1 + ppm) as often in plant time.
        assert span_us == n * 5000
        assert n == pytest.approx(2.0 / 0.005 * (1 + ppm * 1e-6), abs=1.5)
