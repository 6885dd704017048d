"""The one plant and its options (sim_hal/plant.py): the compiled kernel against the Python
reference step, each option alone against the ideal plant, mirror symmetry and energy with
options on, the options' declared bounds. Physics checked by physics, not by the code's numbers."""

from __future__ import annotations

import math
import random
from typing import Any

import pytest

from ddrt.config.sim_truth import (
    ActuatorTruth, BatteryTruth, EventsTruth, FloorPatch, PayloadEvent, WanderingScale, WheelsTruth,
)
from ddrt.core.model import Dynamics
from ddrt.params.motor import MotorParams
from ddrt.params.robot import RobotParams
from sim_hal import plant_native
from sim_hal.plant import PlantConfig, Realism, SimRobot
from tests.support.seed_robot import TABLE_5_1, TABLE_5_2

QUIET = dict(slip=False, gyro_noise_dps_rthz=0.0, command_latency_s=0.0)
PACK = BatteryTruth(cells=3, resistance_ohm=0.25, start_soc=0.5, capacity_ah=0.02)  # sags, and drains visibly
PLAY = ActuatorTruth(backlash_deg=1.5, motor_inertia_kgm2=2e-4)
SYM = dict(TABLE_5_1, r_L=0.05, r_R=0.05)  # left and right alike

# The options one at a time, each with what it may change: "motion" (pose, speeds, torques,
# the counts and the gyro that follow the motion), "front" (the omni wheel's count), "wheels"
# (the drive wheels' counts), "gyro" (the gyro's reading), "supply" (battery_v).
ALONE: dict[str, tuple[Realism, frozenset[str]]] = {
    "battery": (Realism(battery=PACK), frozenset({"motion", "front", "wheels", "gyro", "supply"})),
    "warm-up": (Realism(gyro_warmup_rise_c=8.0, gyro_warmup_tau_s=2.0, gyro_bias_per_c_dps=0.1), frozenset({"gyro"})),
    "drift": (Realism(gyro_drift_dps_per_s=0.05), frozenset({"gyro"})),
    "bias step": (Realism(gyro_bias_step_dps=0.5, gyro_bias_step_at_s=1.0), frozenset({"gyro"})),
    "register hold": (Realism(gyro_odr_hz=200.0, gyro_clock_ppm=5000.0), frozenset({"gyro"})),
    "deadband": (Realism(actuators=ActuatorTruth(deadband=0.3)), frozenset({"motion", "front", "wheels", "gyro"})),
    "backlash": (Realism(actuators=PLAY), frozenset({"motion", "front", "wheels", "gyro"})),
    "omni slip": (Realism(encoder_slip=WanderingScale(mean=-0.01, sigma=0.005, tau_s=0.5)), frozenset({"front"})),
    "drive-wheel slip": (Realism(wheels=WheelsTruth(slip_per_nm=0.05, scale=WanderingScale(sigma=0.005))),
                         frozenset({"wheels"})),
    "payload": (Realism(events=EventsTruth(payloads=(PayloadEvent(at_s=1.0, mass_kg=1.5, x_m=0.05),))),
                frozenset({"motion", "front", "wheels", "gyro"})),
    "floor": (Realism(events=EventsTruth(floor=(FloorPatch(x_min=-9, y_min=-9, x_max=9, y_max=9, friction_scale=3.0),))),
              frozenset({"motion", "front", "wheels", "gyro"})),
}


def bot(realism: Realism = Realism(), table: dict = TABLE_5_2, ml: MotorParams | None = None,
        mr: MotorParams | None = None, **cfg: Any) -> SimRobot:
    return SimRobot(RobotParams(**table), ml or MotorParams(), mr or MotorParams(),
                    PlantConfig(realism=realism, **cfg))


def channels(sim: SimRobot) -> dict[str, Any]:
    e = sim.energy
    return {"motion": (*sim.pose, *sim.velocity, *sim.wheel_angles, *sim.wheel_torque,
                       e.electromagnetic_j, e.friction_loss_j, e.slip_j),
            "front": sim.read_encoder(), "wheels": sim.read_wheel_counts(), "gyro": sim.read_gyro_raw(),
            "supply": sim.battery_v}


def random_drive(sims: list[SimRobot], seconds: float, seed: int, mirror: bool = False) -> list[list[dict]]:
    """Drive every sim with the same random duties (held for uneven stretches), mirrored (left
    and right swapped) for every sim but the first when `mirror`; each sim's channels after each stretch."""
    rng = random.Random(seed)
    out: list[list[dict]] = [[] for _ in sims]
    t = 0.0
    while t < seconds - 1e-12:
        dl, dr = rng.uniform(-1, 1), rng.uniform(-1, 1)
        for i, s in enumerate(sims):
            s.command(*((dr, dl) if mirror and i else (dl, dr)))
        t += rng.choice((0.0007, 0.005, 0.0123, 0.05))
        for i, s in enumerate(sims):
            s.advance_to(t)
            out[i].append(channels(s))
    return out


def force_python(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(plant_native, "kernel", lambda: None)


# --- the kernel and the reference step ------------------------------------------------------------


def test_every_option_runs_in_the_kernel_when_there_is_one(monkeypatch: pytest.MonkeyPatch) -> None:
    """No option needs the Python step: each alone runs in the kernel (where a C compiler is),
    and DDRT_PLANT=python's path (no kernel) takes the Python step whatever the options."""
    have = plant_native.kernel() is not None
    for name, (opt, _) in ALONE.items():
        assert bot(opt).integrator == ("kernel" if have else "python"), name
    force_python(monkeypatch)
    assert {bot(opt).integrator for opt, _ in ALONE.values()} == {"python"}


@pytest.mark.parametrize("realism", [Realism(), *(opt for opt, _ in ALONE.values()),
                                     Realism(gyro_warmup_rise_c=6.0, gyro_bias_per_c_dps=-0.2, gyro_drift_dps_per_s=0.01,
                                             gyro_bias_step_dps=-0.3, gyro_bias_step_at_s=0.7, gyro_odr_hz=250.0,
                                             gyro_fifo=True, actuators=ActuatorTruth(deadband=0.05, backlash_deg=1.2),
                                             battery=BatteryTruth(cells=2, ocv_table=((0.0, 6.0), (0.6, 7.4), (1.0, 8.4)),
                                                                  resistance_ohm=0.4, start_soc=0.62, capacity_ah=0.01),
                                             encoder_slip=WanderingScale(mean=0.01, sigma=0.01, tau_s=0.2),
                                             wheels=WheelsTruth(slip_per_nm=0.02, scale=WanderingScale(sigma=0.003, tau_s=1.0)),
                                             events=EventsTruth(payloads=(PayloadEvent(at_s=0.4, mass_kg=0.5, y_m=0.03),
                                                                          PayloadEvent(at_s=2.2, mass_kg=1.0, x_m=-0.02)),
                                                                floor=(FloorPatch(x_min=-1, y_min=-1, x_max=0.02, y_max=1,
                                                                                  friction_scale=4.0),)))])
def test_kernel_and_python_step_agree_on_a_random_drive(realism: Realism, monkeypatch: pytest.MonkeyPatch) -> None:
    """Every option off, each option alone, and all of them together: the two integrators give
    the same numbers (to the bit; asserted to 1e-12), slip and gyro noise on, on a random drive."""
    if plant_native.kernel() is None:
        pytest.skip("no C compiler: the plant runs in Python only")
    kw = dict(seed=11, slip_probability=0.4, wheel_counts_per_rev=2048)
    fast = bot(realism, **kw)
    force_python(monkeypatch)
    ref = bot(realism, **kw)
    assert (fast.integrator, ref.integrator) == ("kernel", "python")
    a, b = random_drive([fast, ref], 3.0, seed=4)
    moved = False
    for ra, rb in zip(a, b):
        assert ra["motion"] == pytest.approx(rb["motion"], rel=1e-12, abs=1e-15)
        assert (ra["front"], ra["wheels"], ra["gyro"], ra["supply"]) == (rb["front"], rb["wheels"], rb["gyro"],
                                                                        rb["supply"])
        moved = moved or math.hypot(ra["motion"][0], ra["motion"][1]) > 0.02 or abs(ra["motion"][2]) > 0.3
    assert moved
    assert fast.gyro_die_temp_c == ref.gyro_die_temp_c and fast.supply == ref.supply
    assert fast.backlash_side == ref.backlash_side
    if realism.gyro_fifo:
        fa, fb = fast.read_gyro_fifo(), ref.read_gyro_fifo()
        assert fa == fb and len(fa[0]) == 512 < fast.fifo_pushed and fa[1]  # 3 s at 250 Hz: it overflowed


def test_the_kernel_reads_the_constants_in_the_python_steps_order() -> None:
    """plant_kernel.c's NC (where the options' constants start in c[]) is the number of the
    Python step's constants, and its state enum has plant_native.NSTATE entries."""
    import re

    from sim_hal.plant import _Consts

    src = plant_native.SOURCE.read_text(encoding="utf-8")
    assert int(re.search(r"#define NC (\d+)", src).group(1)) == len(_Consts._fields)
    enum = re.search(r"enum \{ (X, .*?), NSTATE \};", src, re.S).group(1)
    assert len([n for n in enum.replace("\n", " ").split(",") if n.strip()]) == plant_native.NSTATE


# --- each option alone ----------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(ALONE))
def test_each_option_alone_changes_what_it_should_and_nothing_else(name: str) -> None:
    """Against the ideal plant on the same random drive and seed (slip and noise on): the option
    changes the channels it acts on and leaves every other one bit for bit as it was."""
    opt, changes = ALONE[name]
    ideal, real = bot(seed=5, wheel_counts_per_rev=4096), bot(opt, seed=5, wheel_counts_per_rev=4096)
    a, b = random_drive([ideal, real], 3.0, seed=6)
    changed = set()
    for ra, rb in zip(a, b):
        for ch in ra:
            if ra[ch] != rb[ch]:
                changed.add(ch)
    assert changed == changes, (name, changed)


def test_deadband_applies_nothing_inside_and_the_duty_outside() -> None:
    """Duties inside the band: no torque, no motion; outside: exactly the ideal plant's motion."""
    opt = Realism(actuators=ActuatorTruth(deadband=0.2))
    inside = bot(opt, **QUIET)
    inside.command(0.199, -0.199)
    inside.advance_to(1.0)
    assert inside.pose == (0.0, 0.0, 0.0) and inside.wheel_torque == (0.0, 0.0) and inside.energy.net_j == 0.0
    outside, ideal = bot(opt, **QUIET), bot(**QUIET)
    for s in (outside, ideal):
        s.command(0.2, -0.6)
        s.advance_to(1.0)
    assert outside.pose == ideal.pose and outside.applied_duty == (0.2, -0.6)


def test_backlash_passes_no_torque_inside_the_play() -> None:
    """Reversing duty on a rolling robot: while a motor crosses the play its wheel's torque is
    its friction alone (no motor torque passes), and the robot keeps rolling on its momentum."""
    m = MotorParams()
    sim = bot(Realism(actuators=PLAY), SYM, **QUIET)
    sim.command(0.5, 0.5)
    sim.advance_to(0.5)
    assert sim.backlash_side == (1, 1)
    sim.command(-0.5, -0.5)
    p, crossing = sim.params, 0
    while sim.t < 0.6 - 1e-9:
        v, w = sim.velocity
        ww = ((v - p.L * w) / p.r_L, (v + p.R * w) / p.r_R)
        sim.advance_to(sim.t + sim.step_s)
        if sim.backlash_side == (0, 0):
            crossing += 1
            friction = [m.viscous_nms * x + m.coulomb_nm * math.tanh(x / m.coulomb_smoothing_rad_s) for x in ww]
            assert sim.wheel_torque == pytest.approx((-friction[0], -friction[1]), abs=1e-12)
            assert sim.velocity[0] > 0.0
    assert crossing >= 2 and sim.backlash_side == (-1, -1)
    assert sim.supply.free_motor_j != 0.0


def test_battery_voltage_falls_with_the_current_drawn() -> None:
    """V = E(soc) - R_int I at every instant, so among the instants of one drive, more current
    is less voltage; the state of charge falls with the charge drawn."""
    sim = bot(Realism(battery=PACK), **QUIET)
    rng = random.Random(2)
    points = []
    for k in range(1, 61):
        sim.command(rng.uniform(-1, 1), rng.uniform(-1, 1))
        sim.advance_to(k * 0.05)
        s = sim.supply
        assert s.terminal_v == pytest.approx(s.ocv_v - PACK.resistance_ohm * s.current_a, rel=1e-12, abs=1e-12)
        assert s.soc == pytest.approx(PACK.start_soc - s.charge_c / (3600.0 * PACK.capacity_ah), rel=1e-12)
        points.append((s.current_a, s.terminal_v, s.ocv_v))
    assert max(c for c, _, _ in points) > 1.0 and min(v for _, v, _ in points) < PACK.ocv_v(0.5) - 0.25
    # With the open-circuit voltage as good as constant over a few steps, the sag orders by current.
    by_current = sorted(points)
    assert all(b[1] - b[2] <= a[1] - a[2] + 1e-12 for a, b in zip(by_current, by_current[1:]))
    assert sim.supply.soc < PACK.start_soc


@pytest.mark.parametrize("realism", [Realism(battery=PACK), Realism(battery=PACK, actuators=PLAY)])
def test_battery_energy_balance_source_is_losses_plus_wheels_plus_kinetic(realism: Realism) -> None:
    """Out of the open-circuit source = its resistance + the armatures + what the motors deliver
    (to the wheels, and to motors free in the play); at the wheels, what arrives less friction
    and slip is the change of kinetic energy."""
    sim = bot(realism, seed=3, step_hz=2000.0)
    ke0 = Dynamics.from_params(sim.params).kinetic_energy(*sim.velocity)
    random_drive([sim], 2.0, seed=8)
    s, e = sim.supply, sim.energy
    dke = Dynamics.from_params(sim.params).kinetic_energy(*sim.velocity) - ke0
    assert s.internal_j > 0.01 and s.armature_j > 0.1 and e.friction_loss_j > 0.05
    assert s.source_j == pytest.approx(s.internal_j + s.armature_j + e.electromagnetic_j + s.free_motor_j, rel=1e-9)
    assert e.net_j == pytest.approx(dke, rel=1e-6, abs=1e-6)


def test_gyro_zero_rate_output_follows_the_declared_temperature_curve() -> None:
    """At rest without noise, the reading is the bias of the die temperature the plant reports:
    bias0 + slope (T(t) - T0), T(t) = T0 + rise (1 - exp(-t / tau)), within a count and the
    low-pass's lag."""
    rise, tau, slope = 8.0, 5.0, 0.12
    sim = bot(Realism(gyro_temp_start_c=22.0, gyro_warmup_rise_c=rise, gyro_warmup_tau_s=tau,
                      gyro_bias_per_c_dps=slope), **QUIET)
    lsb = sim.gyro_lsb_per_rad_s * math.pi / 180.0
    for t in (0.5, 2.0, 5.0, 10.0, 30.0):
        sim.advance_to(t)
        temp = 22.0 + rise * (1.0 - math.exp(-t / tau))
        assert sim.gyro_die_temp_c == pytest.approx(temp, rel=1e-12)
        t_seen = t - sim.gyro_delay_s - sim.cfg.sensor_latency_s
        expect = 1.5 + slope * rise * (1.0 - math.exp(-t_seen / tau))
        assert abs(sim.read_gyro_raw() - expect * lsb) <= 1.0, t
    assert sim.read_gyro_raw() / lsb == pytest.approx(1.5 + slope * rise, abs=0.01)


# --- symmetry -------------------------------------------------------------------------------------


def test_mirrored_duties_give_a_mirrored_trajectory_with_options_on() -> None:
    """The mirror image robot (motors and patches swapped too) under left/right swapped duties,
    with the battery, deadband, backlash, a payload off the axis, a floor patch, drive-wheel
    slip and the warming gyro on: y and theta change sign, the wheels' counts swap."""
    def realism(sign: float) -> Realism:
        return Realism(battery=PACK, actuators=ActuatorTruth(deadband=0.05, backlash_deg=1.0),
                       gyro_warmup_rise_c=5.0, gyro_bias_per_c_dps=0.1,
                       wheels=WheelsTruth(slip_per_nm=0.05), encoder_slip=WanderingScale(mean=-0.004),
                       events=EventsTruth(payloads=(PayloadEvent(at_s=0.8, mass_kg=1.0, y_m=sign * 0.04),),
                                          floor=(FloorPatch(x_min=0.05, y_min=min(0.0, sign * 9), x_max=9,
                                                            y_max=max(0.0, sign * 9), friction_scale=2.5),)))
    ml, mr = MotorParams(), MotorParams(resistance_ohm=4.1, coulomb_nm=0.04)
    mirrored = RobotParams(**TABLE_5_2).mirrored()
    a = bot(realism(1.0), TABLE_5_2, ml, mr, wheel_counts_per_rev=4096, gyro_bias_dps=0.0, **QUIET)
    b = bot(realism(-1.0), {n: getattr(mirrored, n) for n in RobotParams.names()}, mr, ml,
            wheel_counts_per_rev=4096, gyro_bias_dps=0.0, **QUIET)
    ra, rb = random_drive([a, b], 3.0, seed=12, mirror=True)
    for pa, pb in zip(ra, rb):
        (xa, ya, tha), (xb, yb, thb) = pa["motion"][:3], pb["motion"][:3]
        assert (xb, yb, thb) == pytest.approx((xa, -ya, -tha), rel=1e-9, abs=1e-12)
        assert pb["supply"] == pytest.approx(pa["supply"], rel=1e-9)
        assert pb["front"] == pa["front"]
        assert abs(pb["wheels"][0] - pa["wheels"][1]) <= 1 and abs(pb["wheels"][1] - pa["wheels"][0]) <= 1
    assert abs(a.pose[2]) > 0.2 and a.pose[0] > 0.05  # it turned, and reached the patch


# --- declared bounds ------------------------------------------------------------------------------


@pytest.mark.parametrize(("cls", "field", "bad", "good"), [
    (PlantConfig, "step_hz", 0.0, 1e-3), (PlantConfig, "slip_probability", 1.0001, 1.0),
    (PlantConfig, "gyro_scale_error", -1.0, -0.999), (PlantConfig, "wheel_counts_per_rev", -1, 0),
    (PlantConfig, "seed", 1.5, None), (PlantConfig, "slip", 1, False), (PlantConfig, "command_latency_s", math.inf, 0.0),
    (Realism, "gyro_warmup_tau_s", 0.0, 1e-6), (Realism, "gyro_odr_hz", -0.1, 0.0), (Realism, "gyro_odr_hz", 8000.5, 8000),
    (Realism, "gyro_clock_ppm", -1e6, -999999.0), (Realism, "gyro_fifo", "yes", False),
    (Realism, "gyro_bias_per_c_dps", math.nan, -0.5), (Realism, "gyro_odr_hz", 3.0, 3.91),
    (PlantConfig, "sensor_latency_s", 1.01, 1.0), (PlantConfig, "command_latency_s", 2.0, 0.5),
])
def test_each_bound_refuses_outside_and_accepts_inside_naming_the_field(cls: type, field: str, bad: Any,
                                                                        good: Any) -> None:
    with pytest.raises(ValueError, match=f"{cls.__name__}.{field}"):
        cls(**{field: bad})
    cls(**{field: good})


@pytest.mark.parametrize("at_s", [0.0, 0.0005, 0.001, 0.0123, 0.7, 1.0 / 3.0, 2.9999999999999])
def test_a_payload_lands_on_the_same_step_in_both_integrators(at_s: float, monkeypatch: pytest.MonkeyPatch) -> None:
    """Payload times on, between and a rounding error off the plant's steps, advanced in uneven
    stretches: the kernel stops where the Python step applies the payload (the same motion)."""
    opt = Realism(events=EventsTruth(payloads=(PayloadEvent(at_s=at_s, mass_kg=3.0, x_m=0.1),)))
    fast = bot(opt, **QUIET)
    force_python(monkeypatch)
    ref = bot(opt, **QUIET)
    for s in (fast, ref):
        s.command(0.9, 0.7)
    a, b = random_drive([fast, ref], 3.2, seed=round(at_s * 1e4))
    assert [r["motion"] for r in a] == [r["motion"] for r in b]
    assert fast.dynamics == ref.dynamics != Dynamics.from_params(RobotParams(**TABLE_5_2))


def test_fuzzed_settings_are_refused_by_name_or_give_a_finite_plant() -> None:
    """Random values (in and out of range, wrong types) for the plant's declared fields: each
    either raises ValueError naming the field, or builds a plant whose random drive stays finite."""
    from dataclasses import fields

    rng = random.Random(31)
    candidates = (-1e9, -2.0, -1.0, -0.5, 0.0, 1e-6, 0.3, 1.0, 2.0, 250, 1000, 9000.0, 1e6, 1e12,
                  math.nan, math.inf, -math.inf, True, False, None, "1", 7)
    declared = [(cls, f.name) for cls in (PlantConfig, Realism) for f in fields(cls) if "decl" in f.metadata]
    built = refused = 0
    for _ in range(300):
        cls, name = rng.choice(declared)
        value = rng.choice(candidates)
        try:
            made = cls(**{name: value})
        except ValueError as e:
            assert f"{cls.__name__}.{name}" in str(e) or name == "gyro_range_dps" or "gyro_fifo" in str(e), (name, value, e)
            refused += 1
            continue
        cfg = made if cls is PlantConfig else PlantConfig(realism=made)
        if cfg.step_hz < 10.0 or cfg.step_hz > 1e5:
            continue  # a valid but absurd step: too slow or too long to drive here
        sim = SimRobot(RobotParams(**TABLE_5_1), MotorParams(), MotorParams(), cfg)
        random_drive([sim], 0.2, seed=built)
        assert all(math.isfinite(x) for x in (*sim.pose, *sim.velocity)), (name, value)
        built += 1
    assert built > 50 and refused > 50


def test_a_config_value_the_plant_refuses_is_named_by_its_key() -> None:
    """The plant's bound on sim.slip.sigma_nm is the config key's declared bound: a value beyond
    it is refused when the config loads, naming the key, before any plant is built."""
    from ddrt.config.load import config_from_mapping
    from ddrt.config.schema import ConfigError
    from sim_hal.factory import plant_config

    base = {"hal": {"backend": "sim"}, "robot": dict(TABLE_5_1)}
    assert plant_config(config_from_mapping(dict(base, sim={"slip": {"sigma_nm": 100.0}}))).slip_sigma_nm == 100.0
    with pytest.raises(ConfigError, match=r"sim\.slip\.sigma_nm: must be <= 100 N m.*got 1000\.0$"):
        config_from_mapping(dict(base, sim={"slip": {"sigma_nm": 1000.0}}))
