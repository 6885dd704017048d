"""The `sim:` keys that make the simulated robot imperfect the way real robots are.

Each default leaves the plant ideal (the seed's model), so the seed scenarios stay
reproducible; each key declares its unit, bounds and meaning (docs/reference/config.md). They
are options of the one plant (sim_hal/plant.py), which its compiled kernel and its Python step
integrate alike.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from ddrt.config.schema import RESTART, ConfigError, Section, setting
from ddrt.config.wiring import SimWiring
from ddrt.params.mpu_parts import part_by_name

# Open-circuit voltage of one Li-ion (NMC/graphite) cell against its state of charge, at rest
# and 25 degC: a typical published curve (3.0 V empty, 3.7 V around half, 4.2 V full), the
# pack's default when `sim.battery.ocv_table` is empty.
LI_ION_CELL_OCV: tuple[tuple[float, float], ...] = (
    (0.00, 3.00), (0.05, 3.30), (0.10, 3.45), (0.20, 3.55), (0.30, 3.62), (0.40, 3.67),
    (0.50, 3.72), (0.60, 3.78), (0.70, 3.85), (0.80, 3.93), (0.90, 4.05), (1.00, 4.20),
)


def _interp(table: tuple[tuple[float, float], ...], x: float) -> float:
    """Piecewise-linear through `table` (sorted by x), held flat beyond its ends."""
    if x <= table[0][0]:
        return table[0][1]
    for (x0, y0), (x1, y1) in zip(table, table[1:]):
        if x <= x1:
            return y0 + (y1 - y0) * (x - x0) / (x1 - x0)
    return table[-1][1]


@dataclass(frozen=True)
class BatteryTruth(Section):
    """`sim.battery`: the pack that feeds both motor drivers (null: an ideal supply at the plant
    motors' supply_v). Terminal voltage = OCV(state of charge) - resistance_ohm * current."""

    cells: int = setting(
        3, ge=1, le=24,
        doc="Series Li-ion cells, with a typical cell's open-circuit curve (3.0 V empty, 3.72 V at half, "
            "4.2 V full) when `ocv_table` is empty.")
    ocv_table: tuple[tuple[float, float], ...] = setting(
        (), unit="[-, V]",
        doc="The pack's open-circuit voltage as `[[soc, volts], ...]`, state of charge increasing within "
            "[0, 1], volts in (0, 1000], linear in between; empty: `cells` x the Li-ion curve.")
    resistance_ohm: float = setting(
        0.0, unit="ohm", ge=0.0, le=100.0, doc="Internal resistance of the pack (cells, wiring, driver).")
    capacity_ah: float = setting(
        2.2, unit="A h", gt=0, doc="Charge of a full pack; the charge drawn lowers the state of charge.")
    start_soc: float = setting(
        1.0, ge=0.0, le=1.0, doc="State of charge at the start (3 cells at 0.15: 10.5 V open circuit).")

    def validate(self, where: str) -> None:
        table = self.ocv_table
        if table:
            if len(table) < 2:
                raise ConfigError(f"{where}.ocv_table: needs at least two (soc, volts) pairs")
            socs = [s for s, _ in table]
            if any(b <= a for a, b in zip(socs, socs[1:])) or socs[0] < 0.0 or socs[-1] > 1.0:
                raise ConfigError(f"{where}.ocv_table: state of charge must increase within [0, 1], got {socs}")
            if any(not 0.0 < v <= 1000.0 for _, v in table):
                raise ConfigError(f"{where}.ocv_table: volts must be in (0, 1000], got {[v for _, v in table]}")

    def ocv_v(self, soc: float) -> float:
        """Open-circuit pack voltage (V) at state of charge `soc` (0..1)."""
        if self.ocv_table:
            return _interp(self.ocv_table, soc)
        return self.cells * _interp(LI_ION_CELL_OCV, soc)


@dataclass(frozen=True)
class WanderingScale(Section):
    """A relative scale error 1 + mean + s(t), s an Ornstein-Uhlenbeck process (stationary
    standard deviation `sigma`, correlation time `tau_s`) started at 0."""

    mean: float = setting(0.0, gt=-0.5, lt=0.5, doc="Mean scale error (-0.003: counts 0.3 % short).")
    sigma: float = setting(0.0, ge=0.0, lt=0.2, doc="Stationary standard deviation of the wandering part.")
    tau_s: float = setting(10.0, unit="s", gt=0, doc="Correlation time of the wandering part.")

    @property
    def active(self) -> bool:
        return self.mean != 0.0 or self.sigma != 0.0


@dataclass(frozen=True)
class EncoderTruth(Section):
    """`sim.encoder`: the front omni wheel's roller slip, a slowly wandering scale on its count."""

    slip: WanderingScale = setting(
        factory=WanderingScale,
        doc="Roller slip as a wandering scale on the count: 1 + mean + s(t), s an Ornstein-Uhlenbeck process.")


@dataclass(frozen=True)
class WheelsTruth(Section):
    """`sim.wheels`: how the drive wheels' own encoders depart from the ground's motion (the
    omni wheel does not see this): the wheel turns more than the ground moves under traction."""

    slip_per_nm: float = setting(
        0.0, unit="1/(N m)", ge=0.0, le=1.0,
        doc="Longitudinal slip ratio per N m of wheel torque: the wheel turns (1 + slip_per_nm x torque) times "
            "what the ground moves under it (the omni wheel does not see it).")
    scale: WanderingScale = setting(
        factory=WanderingScale,
        doc="A wandering scale on each drive wheel's count (`mean`, `sigma`, `tau_s` as `sim.encoder.slip`).")


@dataclass(frozen=True)
class ActuatorTruth(Section):
    """`sim.actuators`: the motor driver's deadband and the gearboxes' backlash."""

    deadband: float = setting(0.0, ge=0.0, lt=0.5, doc="A duty of smaller magnitude applies nothing.")
    backlash_deg: float = setting(
        0.0, unit="deg", ge=0.0, le=20.0,
        doc="Total play of each gearbox at the wheel: across it the motor turns free (its own inertia, torque "
            "and friction) and the wheel gets no torque.")
    motor_inertia_kgm2: float = setting(
        2e-4, unit="kg m^2", gt=0, doc="The motor side's inertia at the wheel, free across the play.")


@dataclass(frozen=True)
class PayloadEvent(Section):
    """A mass put on the robot at `at_s`; its centre at (x_m, y_m) in the body frame of A."""

    at_s: float = setting(unit="s", ge=0.0, doc="When the mass is put on (sim time).")
    mass_kg: float = setting(unit="kg", gt=0, le=100.0, doc="The mass put on the robot.")
    inertia_kgm2: float = setting(0.0, unit="kg m^2", ge=0.0, doc="Its yaw inertia about its own centre.")
    x_m: float = setting(0.0, unit="m", ge=-2.0, le=2.0, doc="Its centre in the body frame of A, forward.")
    y_m: float = setting(0.0, unit="m", ge=-2.0, le=2.0, doc="Its centre in the body frame of A, to the left.")


@dataclass(frozen=True)
class FloorPatch(Section):
    """A rectangle of floor (world frame) where the wheels' friction is scaled."""

    x_min: float = setting(unit="m", doc="The rectangle's least x (world frame).")
    y_min: float = setting(unit="m", doc="Its least y.")
    x_max: float = setting(unit="m", doc="Its largest x, above x_min.")
    y_max: float = setting(unit="m", doc="Its largest y, above y_min.")
    friction_scale: float = setting(
        2.0, ge=0.0, le=100.0, doc="Times the motors' viscous and Coulomb friction while A is inside.")

    def validate(self, where: str) -> None:
        if not (self.x_min < self.x_max and self.y_min < self.y_max):
            raise ConfigError(f"{where}: needs x_min < x_max and y_min < y_max")


@dataclass(frozen=True)
class EventsTruth(Section):
    """`sim.events`: what happens to the robot during a run."""

    payloads: tuple[PayloadEvent, ...] = setting(
        (), doc="Masses put on the robot; from `at_s` the platform's mass, centre and inertia include each.")
    floor: tuple[FloorPatch, ...] = setting(
        (), doc="Patches of floor where the motors' viscous and Coulomb friction are scaled while A is inside.")


PPM_LIMIT = 50_000.0  # a crystal or an RC oscillator this far off is no clock


# ------------------------------------------------- the sim: section itself

@dataclass(frozen=True)
class SlipConfig(Section):
    """The seed's torque slip noise: per wheel and plant step, with this probability."""

    probability: float = setting(
        0.25, ge=0.0, le=1.0, doc="Chance, per wheel and plant step, that a slip torque is added.")
    sigma_nm: float = setting(
        0.01, unit="N m", ge=0.0, le=100.0, doc="Standard deviation of the slip torque, drawn from N(0.01 tau, sigma).")


@dataclass(frozen=True)
class GyroTruth(Section):
    """How the simulated gyro departs from the truth, and which part it is."""

    noise_dps_rthz: float = setting(
        0.005, unit="deg/s/sqrt(Hz)", ge=0.0, doc="White rate-noise density before the low-pass.")
    bias_dps: float = setting(
        1.5, unit="deg/s", doc="Constant zero-rate bias (the estimator calibrates it away at rest).")
    scale_error: float = setting(
        0.0, gt=-0.5, lt=0.5, doc="Relative sensitivity error (0.01 = reads 1 % high).")
    dlpf_hz: float = setting(
        98.0, unit="Hz", gt=0, doc="Cut-off of the gyro's digital low-pass (98 Hz is DLPF_CFG = 2).")
    # Zero-rate bias = bias_dps + bias_per_c_dps * (T - temp_start_c) + drift_dps_per_s * t, with the
    # die warming as T = temp_start_c + warmup_rise_c * (1 - exp(-t / warmup_tau_s)).
    temp_start_c: float = setting(
        25.0, unit="degC", ge=-60.0, le=100.0,
        doc="Die temperature at power-on (what TEMP_OUT reports before any warm-up).")
    warmup_rise_c: float = setting(
        0.0, unit="degC", ge=-80.0, le=80.0,
        doc="How much the die warms after power-on: T(t) = temp_start_c + warmup_rise_c (1 - exp(-t / "
            "warmup_tau_s)).")
    warmup_tau_s: float = setting(120.0, unit="s", gt=0, doc="Time constant of that warm-up.")
    bias_per_c_dps: float = setting(
        0.0, unit="deg/s per degC", doc="Zero-rate bias change per degree of die warming (added to `bias_dps`).")
    drift_dps_per_s: float = setting(0.0, unit="deg/s per s", doc="Linear drift of the zero-rate bias with time.")
    register_hold: bool = setting(
        False,
        doc="`true`: the output register holds the low-passed rate of the last sample instant, refreshed at "
            "1 kHz / (1 + `hal.imu.sample_rate_div`) (200 Hz at the default 4), so a read is 0 to one sample "
            "period old; `false`: read at the tick.")
    clock_ppm: float = setting(
        0.0, unit="ppm", ge=-PPM_LIMIT, le=PPM_LIMIT,
        doc="Error of the MPU's own oscillator, which sets its sample instants (the part's internal oscillator "
            "is good to about 1 %).")
    bias_step_dps: float = setting(
        0.0, unit="deg/s", ge=-50.0, le=50.0,
        doc="A step in the zero-rate bias at `sim.gyro.bias_step_at_s` (what tracking the bias on the move "
            "must follow: bench/wheel_encoders.py).")
    bias_step_at_s: float = setting(
        0.0, unit="s", ge=0.0,
        doc="Sim time of that step (since the plant started: calibration and `sim.start_delay_s` included).")
    part: str = setting(
        "MPU-6050",
        doc="Which part the emulated gyro is (`hal.imu.bus: sim`): `MPU-6050` (WHO_AM_I 0x68), `MPU-6500` "
            "(0x70), `MPU-9250` (0x71), `ICM-20689` (0x98), each with its own WHO_AM_I, temperature formula, "
            "FIFO size and power-on state ([hardware.md](hardware.md), \"The gyro: which boards work\"). The "
            "driver finds it by WHO_AM_I.")

    def validate(self, where: str) -> None:
        # A name, forgiven its case and a missing hyphen (ddrt.params.mpu_parts); the error lists the known parts.
        try:
            part_by_name(self.part)
        except ValueError as e:
            raise ConfigError(f"{where}.part: {e}") from None


@dataclass(frozen=True)
class SimConfig(Section):
    """The simulated robot's own settings (the plant's truth beyond its parameters)."""

    APPLY: ClassVar[str] = RESTART  # the simulated robot is built once

    # Bounds on the work of a run: plant steps per simulated second, seconds of standing still.
    step_hz: float = setting(1000.0, unit="Hz", ge=10.0, le=100_000.0, doc="Plant integration rate.")
    friction: bool = setting(
        True, doc="`false` zeroes the plant motors' viscous and Coulomb friction (the seed's ideal case).")
    seed: int = setting(1, doc="Seed of the random slip and sensor noise; same seed, same run.")
    # Latencies beyond 0.1 s are not a robot this controller can drive.
    command_latency_s: float = setting(
        0.0015, unit="s", ge=0.0, le=0.1, doc="Delay from a duty command to the motor voltage.")
    sensor_latency_s: float = setting(
        0.001, unit="s", ge=0.0, le=0.1, doc="Age of the state a sensor reading reports.")
    slip: SlipConfig = setting(factory=SlipConfig, doc="The seed's random slip torque.")
    gyro: GyroTruth = setting(
        factory=GyroTruth,
        doc="How the simulated gyro departs from the truth, and which part of the MPU family it is.")
    sensors_freeze_after_s: float | None = setting(
        None, unit="s", ge=0.0,
        doc="Fault injection: after this many seconds of simulated time the simulated sensors stop delivering "
            "fresh samples (they repeat the last one, flagged not fresh). The loop holds the robot and, if the "
            "freeze outlasts `estimator.fault_latch_s`, latches a fault.")
    sensors_freeze_for_s: float | None = setting(
        None, unit="s", gt=0,
        doc="How long that freeze lasts; `null`: for good. Needs `sim.sensors_freeze_after_s`.")
    start_delay_s: float = setting(
        2.0, unit="s", ge=0.0, le=60.0,
        doc="`ddrt sim`: how long the simulated robot stands still after the calibration before it starts the "
            "path (the estimator keeps refining the gyro bias at rest, as on a robot waiting for its first "
            "command).")
    battery_measured: bool = setting(
        True,
        doc="The simulated microcontroller reports the supply voltage at the driver (`SimRobot.battery_v`), as "
            "protocol v2 does; `false`: it does not (a v1 MCU), and the loop uses `robot.motor.supply_v`.")
    # The realistic plant: every default below is the ideal plant.
    battery: BatteryTruth | None = setting(
        None,
        doc="The pack feeding both motor drivers; `null`: an ideal supply at the plant motors' `supply_v`. "
            "With a pack the motors see duty x terminal voltage, terminal = open-circuit voltage(state of "
            "charge) - `resistance_ohm` x pack current. Any of the realistic plant's keys away from its default "
            "(`sim.battery`, the `sim.gyro` warm-up, drift, step and clock keys, `sim.encoder`, `sim.wheels`, "
            "`sim.actuators`, `sim.events`) is an option of the one plant (sim_hal/plant.py, "
            "[model.md](model.md)), integrated by its compiled kernel and its Python step alike.")
    encoder: EncoderTruth = setting(factory=EncoderTruth, doc="The front omni wheel's encoder.")
    wheels: WheelsTruth = setting(
        factory=WheelsTruth,
        doc="The drive wheels as their own encoders see them (`sensors` says whether they are counted).")
    actuators: ActuatorTruth = setting(factory=ActuatorTruth, doc="The motor driver and gearboxes.")
    events: EventsTruth = setting(factory=EventsTruth, doc="What happens during a run.")
    mcu_clock_ppm: float = setting(
        0.0, unit="ppm", ge=-PPM_LIMIT, le=PPM_LIMIT,
        doc="The emulated microcontroller's crystal error: its time (the t_us it stamps, its STATE period, its "
            "watchdog) runs 1 + ppm 1e-6 times the plant's.")
    wiring: SimWiring = setting(
        factory=SimWiring,
        doc="Fault injection: the simulated robot wired wrongly, as `ddrt commission`'s wiring step finds it "
            "([commissioning.md](commissioning.md)). All `false`: wired right.")

    def validate(self, where: str) -> None:
        if self.sensors_freeze_for_s is not None and self.sensors_freeze_after_s is None:
            raise ConfigError(f"{where}.sensors_freeze_for_s: needs sim.sensors_freeze_after_s (when the freeze starts)")
