"""The `sim:` keys that make the simulated robot imperfect the way real robots are.

Each default leaves the plant ideal (the seed's model), so the seed scenarios stay
reproducible; docs/config.md documents every key with its unit. The plant
(sim_hal/plant_real.py) is what uses them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar

from ddrt.config.schema import RESTART, ConfigError, non_negative, positive
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
class BatteryTruth:
    """`sim.battery`: the pack that feeds both motor drivers (null: an ideal supply at the plant
    motors' supply_v). Terminal voltage = OCV(state of charge) - resistance_ohm * current."""

    cells: int = 3  # series cells, with the Li-ion curve when ocv_table is empty
    ocv_table: tuple[tuple[float, float], ...] = ()  # (state of charge 0..1, pack volts), increasing
    resistance_ohm: float = 0.0  # internal resistance of the pack (wiring and driver included)
    capacity_ah: float = 2.2
    start_soc: float = 1.0  # state of charge at the start, 0..1

    def validate(self, where: str) -> None:
        positive(where, cells=self.cells, capacity_ah=self.capacity_ah)
        non_negative(where, resistance_ohm=self.resistance_ohm)
        if self.cells > 24:
            raise ConfigError(f"{where}.cells: at most 24, got {self.cells}")
        if self.resistance_ohm > 100.0:
            raise ConfigError(f"{where}.resistance_ohm: at most 100 ohm, got {self.resistance_ohm}")
        if not 0.0 <= self.start_soc <= 1.0:
            raise ConfigError(f"{where}.start_soc: must be in [0, 1], got {self.start_soc}")
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
class WanderingScale:
    """A relative scale error 1 + mean + s(t), s an Ornstein-Uhlenbeck process (stationary
    standard deviation `sigma`, correlation time `tau_s`) started at 0."""

    mean: float = 0.0
    sigma: float = 0.0
    tau_s: float = 10.0

    def validate(self, where: str) -> None:
        non_negative(where, sigma=self.sigma)
        positive(where, tau_s=self.tau_s)
        if abs(self.mean) >= 0.5 or self.sigma >= 0.2:
            raise ConfigError(f"{where}: mean within +-0.5 and sigma below 0.2, got {self.mean}, {self.sigma}")

    @property
    def active(self) -> bool:
        return self.mean != 0.0 or self.sigma != 0.0


@dataclass(frozen=True)
class EncoderTruth:
    """`sim.encoder`: the front omni wheel's roller slip, a slowly wandering scale on its count."""

    slip: WanderingScale = field(default_factory=WanderingScale)


@dataclass(frozen=True)
class WheelsTruth:
    """`sim.wheels`: how the drive wheels' own encoders depart from the ground's motion (the
    omni wheel does not see this): the wheel turns more than the ground moves under traction."""

    slip_per_nm: float = 0.0  # longitudinal slip ratio per N m of wheel torque
    scale: WanderingScale = field(default_factory=WanderingScale)

    def validate(self, where: str) -> None:
        non_negative(where, slip_per_nm=self.slip_per_nm)
        if self.slip_per_nm > 1.0:
            raise ConfigError(f"{where}.slip_per_nm: at most 1 per N m, got {self.slip_per_nm}")


@dataclass(frozen=True)
class ActuatorTruth:
    """`sim.actuators`: the motor driver's deadband and the gearboxes' backlash."""

    deadband: float = 0.0  # |duty| below this applies nothing
    backlash_deg: float = 0.0  # total play of each gearbox at the wheel
    motor_inertia_kgm2: float = 2e-4  # motor side inertia at the wheel, free across the play

    def validate(self, where: str) -> None:
        non_negative(where, deadband=self.deadband, backlash_deg=self.backlash_deg)
        positive(where, motor_inertia_kgm2=self.motor_inertia_kgm2)
        if self.deadband >= 0.5:
            raise ConfigError(f"{where}.deadband: must be below 0.5, got {self.deadband}")
        if self.backlash_deg > 20.0:
            raise ConfigError(f"{where}.backlash_deg: at most 20 degrees, got {self.backlash_deg}")


@dataclass(frozen=True)
class PayloadEvent:
    """A mass put on the robot at `at_s`; its centre at (x_m, y_m) in the body frame of A."""

    at_s: float
    mass_kg: float
    inertia_kgm2: float = 0.0  # about its own centre, vertical axis
    x_m: float = 0.0
    y_m: float = 0.0

    def validate(self, where: str) -> None:
        non_negative(where, at_s=self.at_s, inertia_kgm2=self.inertia_kgm2)
        positive(where, mass_kg=self.mass_kg)
        if self.mass_kg > 100.0 or abs(self.x_m) > 2.0 or abs(self.y_m) > 2.0:
            raise ConfigError(f"{where}: at most 100 kg within 2 m of A, got {self.mass_kg} kg at "
                              f"({self.x_m}, {self.y_m}) m")


@dataclass(frozen=True)
class FloorPatch:
    """A rectangle of floor (world frame) where the wheels' friction is scaled."""

    x_min: float
    y_min: float
    x_max: float
    y_max: float
    friction_scale: float = 2.0  # times the motors' viscous and Coulomb friction

    def validate(self, where: str) -> None:
        non_negative(where, friction_scale=self.friction_scale)
        if not (self.x_min < self.x_max and self.y_min < self.y_max):
            raise ConfigError(f"{where}: needs x_min < x_max and y_min < y_max")
        if self.friction_scale > 100.0:
            raise ConfigError(f"{where}.friction_scale: at most 100, got {self.friction_scale}")


@dataclass(frozen=True)
class EventsTruth:
    """`sim.events`: what happens to the robot during a run."""

    payloads: tuple[PayloadEvent, ...] = ()
    floor: tuple[FloorPatch, ...] = ()


def check_ppm(where: str, key: str, value: float) -> None:
    if not math.isfinite(value) or abs(value) > 50_000.0:
        raise ConfigError(f"{where}.{key}: must be within +-50000 ppm, got {value}")


# ------------------------------------------------- the sim: section itself

@dataclass(frozen=True)
class SlipConfig:
    """The seed's torque slip noise: per wheel and plant step, with this probability."""

    probability: float = 0.25
    sigma_nm: float = 0.01

    def validate(self, where: str) -> None:
        if not 0.0 <= self.probability <= 1.0:
            raise ConfigError(f"{where}.probability: must be in [0, 1], got {self.probability}")
        non_negative(where, sigma_nm=self.sigma_nm)


@dataclass(frozen=True)
class GyroTruth:
    """How the simulated gyro departs from the truth, and which part it is."""

    noise_dps_rthz: float = 0.005
    bias_dps: float = 1.5
    scale_error: float = 0.0
    dlpf_hz: float = 98.0
    # Zero-rate bias = bias_dps + bias_per_c_dps * (T - temp_start_c) + drift_dps_per_s * t, with the
    # die warming as T = temp_start_c + warmup_rise_c * (1 - exp(-t / warmup_tau_s)) (sim_truth.py).
    temp_start_c: float = 25.0
    warmup_rise_c: float = 0.0
    warmup_tau_s: float = 120.0
    bias_per_c_dps: float = 0.0
    drift_dps_per_s: float = 0.0
    register_hold: bool = False  # the output register refreshes at 1 kHz / (1 + hal.imu.sample_rate_div)
    clock_ppm: float = 0.0  # the MPU's own oscillator error (sets when it refreshes)
    bias_step_dps: float = 0.0  # a step in the zero-rate bias (deg/s) ...
    bias_step_at_s: float = 0.0  # ... at this sim time (s): what tracking the bias on the move must follow
    part: str = "MPU-6050"  # the emulated part (hal.imu.bus: sim): a name of ddrt.params.mpu_parts

    def validate(self, where: str) -> None:
        try:
            part_by_name(self.part)
        except ValueError as e:
            raise ConfigError(f"{where}.part: {e}") from None
        non_negative(where, noise_dps_rthz=self.noise_dps_rthz, bias_step_at_s=self.bias_step_at_s)
        if abs(self.bias_step_dps) > 50.0:
            raise ConfigError(f"{where}.bias_step_dps: within +-50 deg/s, got {self.bias_step_dps}")
        positive(where, dlpf_hz=self.dlpf_hz, warmup_tau_s=self.warmup_tau_s)
        if abs(self.scale_error) >= 0.5:
            raise ConfigError(f"{where}.scale_error: must be within +-0.5, got {self.scale_error}")
        if not -60.0 <= self.temp_start_c <= 100.0 or abs(self.warmup_rise_c) > 80.0:
            raise ConfigError(f"{where}: temp_start_c in [-60, 100] and warmup_rise_c within +-80 degC")
        check_ppm(where, "clock_ppm", self.clock_ppm)


@dataclass(frozen=True)
class SimConfig:
    """The simulated robot's own settings (the plant's truth beyond its parameters)."""

    APPLY: ClassVar[str] = RESTART  # the simulated robot is built once

    step_hz: float = 1000.0
    friction: bool = True
    seed: int = 1
    command_latency_s: float = 0.0015
    sensor_latency_s: float = 0.001
    slip: SlipConfig = field(default_factory=SlipConfig)
    gyro: GyroTruth = field(default_factory=GyroTruth)
    sensors_freeze_after_s: float | None = None  # fault injection: no fresh samples after this
    sensors_freeze_for_s: float | None = None  # ... for this long (None: for good)
    start_delay_s: float = 2.0  # `ddrt sim`: stand still this long after calibration (bias settles)
    battery_measured: bool = True  # the simulated MCU reports the supply voltage (false: like protocol v1)
    # Issue 23's realism (ddrt/config/sim_truth.py); every default is the ideal plant of before.
    battery: BatteryTruth | None = None  # null: an ideal supply at the plant motors' supply_v
    encoder: EncoderTruth = field(default_factory=EncoderTruth)
    wheels: WheelsTruth = field(default_factory=WheelsTruth)
    actuators: ActuatorTruth = field(default_factory=ActuatorTruth)
    events: EventsTruth = field(default_factory=EventsTruth)
    mcu_clock_ppm: float = 0.0  # the microcontroller's crystal error, on the t_us it stamps
    wiring: SimWiring = field(default_factory=SimWiring)  # fault injection: miswired motors and sensors

    def validate(self, where: str) -> None:
        positive(where, step_hz=self.step_hz)
        check_ppm(where, "mcu_clock_ppm", self.mcu_clock_ppm)
        non_negative(where, command_latency_s=self.command_latency_s, sensor_latency_s=self.sensor_latency_s,
                     start_delay_s=self.start_delay_s)
        # Bounds on the work of a run: plant steps per simulated second, seconds of standing still.
        if not 10.0 <= self.step_hz <= 100_000.0:
            raise ConfigError(f"{where}.step_hz: must be in [10, 100000] Hz, got {self.step_hz}")
        if self.start_delay_s > 60.0:
            raise ConfigError(f"{where}.start_delay_s: at most 60 s, got {self.start_delay_s}")
        if self.sensors_freeze_after_s is not None:
            non_negative(where, sensors_freeze_after_s=self.sensors_freeze_after_s)
        if self.sensors_freeze_for_s is not None:
            positive(where, sensors_freeze_for_s=self.sensors_freeze_for_s)
            if self.sensors_freeze_after_s is None:
                raise ConfigError(f"{where}.sensors_freeze_for_s: needs sim.sensors_freeze_after_s (when the freeze starts)")
        if self.command_latency_s > 0.1 or self.sensor_latency_s > 0.1:
            raise ConfigError(f"{where}: latencies above 0.1 s are not a robot this controller can drive")
