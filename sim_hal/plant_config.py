"""The simulated robot's settings beyond its geometry and motors, and its energy ledgers.

`PlantConfig` holds the plant's flat settings; `Realism` holds its options (battery, gyro
warm-up and register timing, encoder slip, deadband, backlash, events), whose defaults leave
the plant ideal. Each number's bounds are declared with its field (`Bound`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Any, Mapping

from ddrt.config.sim_truth import (
    ActuatorTruth, BatteryTruth, EncoderTruth, EventsTruth, WanderingScale, WheelsTruth,
)
from ddrt.params.gyro_scale import gyro_lsb_per_rad_s
from ddrt.params.numbers import from_known_keys

__all__ = ["Bound", "EnergyLedger", "PlantConfig", "Realism", "SupplyLedger"]


@dataclass(frozen=True)
class Bound:
    """What one field accepts: its type (float, int or bool), None or not, and an interval
    whose ends are each open or closed (None: unbounded)."""

    kind: type = float
    low: float | None = None
    high: float | None = None
    open_low: bool = False
    open_high: bool = False
    optional: bool = False

    def check(self, where: str, value: Any) -> Any:
        """`value` as the field holds it (an int as float for a float field), or ValueError
        naming `where`."""
        if value is None and self.optional:
            return None
        if self.kind is bool:
            if not isinstance(value, bool):
                raise ValueError(f"{where}: expected true/false, got {value!r}")
            return value
        if self.kind is int:
            if isinstance(value, bool) or not isinstance(value, int):
                raise ValueError(f"{where}: expected an integer, got {value!r}")
        elif isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ValueError(f"{where}: expected a finite number, got {value!r}")
        else:
            value = float(value)
        if self.low is not None and (value < self.low or (self.open_low and value == self.low)):
            raise ValueError(f"{where}: must be {'>' if self.open_low else '>='} {self.low:g}, got {value!r}")
        if self.high is not None and (value > self.high or (self.open_high and value == self.high)):
            raise ValueError(f"{where}: must be {'<' if self.open_high else '<='} {self.high:g}, got {value!r}")
        return value


def _f(default: Any, bound: Bound = Bound(), **kw: Any) -> Any:
    """A dataclass field with its bound declared."""
    return field(default=default, metadata={"bound": bound}, **kw)


def _check_declared(obj: Any) -> None:
    """Check (and normalise) every field of `obj` that declares a Bound."""
    values = vars(obj)
    for f in fields(obj):
        bound = f.metadata.get("bound")
        if bound is not None:
            object.__setattr__(obj, f.name, bound.check(f"{type(obj).__name__}.{f.name}", values[f.name]))


_POSITIVE = Bound(low=0.0, open_low=True)
_MPU_MIN_ODR_HZ = 1000.0 / 256  # SMPLRT_DIV 255 with the DLPF on: the MPU's slowest sample clock
_NON_NEGATIVE = Bound(low=0.0)


@dataclass(frozen=True)
class Realism:
    """The plant's options: what makes the simulated robot real (ddrt/config/sim_truth.py and
    docs/config.md's `sim:` keys say what each is); the default is the ideal plant.

    The gyro's die temperature is T(t) = temp_start_c + warmup_rise_c (1 - exp(-t / warmup_tau_s));
    its zero-rate bias adds bias_per_c_dps (T - temp_start_c) + drift_dps_per_s t to
    PlantConfig.gyro_bias_dps. `gyro_odr_hz` > 0: the output register holds the low-passed rate
    sampled at that rate (the MPU's own clock, off by `gyro_clock_ppm`); 0: read at the tick.
    `gyro_fifo` (`sensors.gyro_fifo`): each sample also goes into the MPU's FIFO (512 samples of
    gyro z, the oldest lost when full), which `SimRobot.read_gyro_fifo` drains; it needs the
    sample clock, so `from_sim` sets `gyro_odr_hz` for it even without the register's hold.
    """

    battery: BatteryTruth | None = None
    gyro_temp_start_c: float = _f(25.0, Bound(low=-273.15))
    gyro_warmup_rise_c: float = _f(0.0)
    gyro_warmup_tau_s: float = _f(120.0, _POSITIVE)
    gyro_bias_per_c_dps: float = _f(0.0)
    gyro_drift_dps_per_s: float = _f(0.0)
    gyro_odr_hz: float = _f(0.0, Bound(low=0.0, high=8000.0))  # the MPU-6050 samples at most at 8 kHz
    gyro_clock_ppm: float = _f(0.0, Bound(low=-1e6, high=1e6, open_low=True, open_high=True))
    gyro_bias_step_dps: float = _f(0.0)  # added to the bias from gyro_bias_step_at_s on
    gyro_bias_step_at_s: float = _f(0.0)
    gyro_fifo: bool = _f(False, Bound(kind=bool))
    encoder_slip: WanderingScale = field(default_factory=WanderingScale)
    wheels: WheelsTruth = field(default_factory=WheelsTruth)
    actuators: ActuatorTruth = field(default_factory=ActuatorTruth)
    events: EventsTruth = field(default_factory=EventsTruth)

    def __post_init__(self) -> None:
        _check_declared(self)
        if 0.0 < self.gyro_odr_hz < _MPU_MIN_ODR_HZ:
            raise ValueError(f"Realism.gyro_odr_hz: 0 (read at the tick) or {_MPU_MIN_ODR_HZ:g} to 8000 Hz "
                             f"(the part's sample rates), got {self.gyro_odr_hz!r}")
        if self.gyro_fifo and self.gyro_odr_hz == 0.0:
            raise ValueError("Realism.gyro_fifo: the FIFO needs the gyro's sample clock (gyro_odr_hz > 0)")
        # The config's sections validate themselves when read from YAML; built here directly
        # (tests, benches) they are checked the same way.
        if self.battery is not None:
            self.battery.validate("Realism.battery")
        self.encoder_slip.validate("Realism.encoder_slip")
        self.wheels.validate("Realism.wheels")
        self.wheels.scale.validate("Realism.wheels.scale")
        self.actuators.validate("Realism.actuators")
        for i, p in enumerate(self.events.payloads):
            p.validate(f"Realism.events.payloads[{i}]")
        for i, f in enumerate(self.events.floor):
            f.validate(f"Realism.events.floor[{i}]")

    @property
    def active(self) -> bool:
        """Any option on (not the ideal plant)."""
        return self != Realism()

    @property
    def gyro_bias_varies(self) -> bool:
        """The zero-rate bias changes with time (warm-up, drift or a step)."""
        return (self.gyro_bias_per_c_dps * self.gyro_warmup_rise_c != 0.0 or self.gyro_drift_dps_per_s != 0.0
                or self.gyro_bias_step_dps != 0.0)

    @classmethod
    def from_sim(cls, sim: Any, sample_rate_div: int = 4, gyro_fifo: bool = False) -> "Realism":
        """From the config's `sim:` section (SimConfig), the MPU's configured divider and whether
        its FIFO is read (`sensors.gyro_fifo`)."""
        g = sim.gyro
        enc: EncoderTruth = sim.encoder
        return cls(
            battery=sim.battery, gyro_temp_start_c=g.temp_start_c, gyro_warmup_rise_c=g.warmup_rise_c,
            gyro_warmup_tau_s=g.warmup_tau_s, gyro_bias_per_c_dps=g.bias_per_c_dps,
            gyro_drift_dps_per_s=g.drift_dps_per_s,
            gyro_odr_hz=1000.0 / (1 + sample_rate_div) if g.register_hold or gyro_fifo else 0.0,
            gyro_clock_ppm=g.clock_ppm, gyro_bias_step_dps=g.bias_step_dps, gyro_bias_step_at_s=g.bias_step_at_s,
            gyro_fifo=bool(gyro_fifo),
            encoder_slip=enc.slip, wheels=sim.wheels, actuators=sim.actuators, events=sim.events,
        )


_INT = Bound(kind=int)
_LATENCY = Bound(low=0.0, high=1.0)  # a second: far beyond any bus, and the sensor rings' length stays small
_COUNTS = Bound(kind=int, low=0)  # 0: that encoder is not there


@dataclass(frozen=True)
class PlantConfig:
    """Everything about the simulated robot that is not its geometry or its motors."""

    step_hz: float = _f(1000.0, _POSITIVE)  # RK4 rate of the plant, independent of the controller's rate
    friction: bool = _f(True, Bound(kind=bool))  # False zeroes the motors' viscous and Coulomb friction
    slip: bool = _f(True, Bound(kind=bool))  # the seed's random slip torque
    slip_probability: float = _f(0.25, Bound(low=0.0, high=1.0))  # chance per wheel per step of a slip term
    slip_fraction: float = _f(0.01, Bound(low=0.0, high=1.0))  # slip size ~ N(slip_fraction * tau, slip_sigma_nm)
    slip_sigma_nm: float = _f(0.01, Bound(low=0.0, high=100.0))  # beyond, the slip alone throws the robot about
    seed: int | None = _f(0, Bound(kind=int, optional=True))  # None: a different run every time
    command_latency_s: float = _f(0.0015, _LATENCY)  # duty command -> motor voltage
    sensor_latency_s: float = _f(0.001, _LATENCY)  # age of the state a reading reports (the rings hold it)
    encoder_counts_per_rev: int = _f(8192, _COUNTS)  # front wheel, lines x 4
    encoder_offset_counts: int = _f(0, _INT)  # counter value at start (a counter need not start at 0)
    gyro_range_dps: int = _f(250, _INT)  # one of the part's ranges (checked below)
    gyro_scale_error: float = _f(0.0, Bound(low=-1.0, open_low=True))  # relative error of the sensitivity
    gyro_bias_dps: float = _f(1.5)
    gyro_noise_dps_rthz: float = _f(0.005, _NON_NEGATIVE)  # white noise density before the low-pass
    gyro_dlpf_hz: float = _f(98.0, _POSITIVE)  # MPU-6050 digital low-pass (DLPF_CFG=2)
    wheel_counts_per_rev: int = _f(0, _COUNTS)  # drive-wheel encoders, lines x 4 (0: not counted)
    realism: Realism = field(default_factory=lambda: Realism())  # the plant's options

    def __post_init__(self) -> None:
        _check_declared(self)
        if not isinstance(self.realism, Realism):
            raise ValueError(f"PlantConfig.realism: expected a Realism, got {self.realism!r}")
        gyro_lsb_per_rad_s(self.gyro_range_dps)  # raises for a range the part lacks

    @classmethod
    def from_mapping(cls, mapping: Mapping[str, Any]) -> "PlantConfig":
        return from_known_keys(cls, mapping)


@dataclass(frozen=True, slots=True)
class EnergyLedger:
    """Cumulative work (J) at the wheels since the start, for energy-balance tests.

    `electromagnetic_j` is the motors' armature torque times wheel speed, `friction_loss_j`
    the work lost to viscous and Coulomb friction, `slip_j` the work of the slip torque.
    Their balance `net_j` equals the change of the robot's kinetic energy.
    """

    electromagnetic_j: float
    friction_loss_j: float
    slip_j: float

    @property
    def net_j(self) -> float:
        return self.electromagnetic_j - self.friction_loss_j + self.slip_j


@dataclass(frozen=True, slots=True)
class SupplyLedger:
    """The battery's state and its energy since the start (`Realism.battery`; without one the
    supply is ideal, with no internal resistance, and only the voltages mean something).

    `source_j` is the work of the open-circuit voltage on the pack current; it goes into the
    pack's resistance (`internal_j`), the armatures' (`armature_j`), the motors turning free in
    the gearboxes' play (`free_motor_j`) and the wheels (`EnergyLedger.electromagnetic_j`).
    """

    ocv_v: float  # open-circuit voltage now
    terminal_v: float  # at the motor driver, under load
    current_a: float  # out of the pack
    soc: float  # state of charge, 0..1
    charge_c: float  # drawn since the start
    source_j: float
    internal_j: float
    armature_j: float
    free_motor_j: float
