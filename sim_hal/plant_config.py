"""The simulated robot's settings beyond its geometry and motors, and its energy ledgers.

`PlantConfig` holds the plant's flat settings; `Realism` holds its options (battery, gyro
warm-up and register timing, encoder slip, deadband, backlash, events), whose defaults leave
the plant ideal. Each field declares its unit, bounds and meaning as the config's keys do
(`setting`, ddrt/params/decl.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Any, Mapping

from ddrt.config.sim_truth import (
    ActuatorTruth, BatteryTruth, EncoderTruth, EventsTruth, WanderingScale, WheelsTruth,
)
from ddrt.params.gyro_scale import gyro_lsb_per_rad_s
from ddrt.params.decl import check_declared, decl_of, setting
from ddrt.params.numbers import from_known_keys

__all__ = ["EnergyLedger", "PlantConfig", "Realism", "SupplyLedger"]


_KINDS = {"float": float, "int": int, "bool": bool, "int | None": int}


def _check_declared(obj: Any) -> None:
    """Check every declared field of `obj` against its type, normalising a whole number to a
    float where the field is a float, then against its declaration (`check_declared`, the
    check of parameters built in code); ValueError naming `<class>.<field>`. The plant is
    built in code too (tests, benches), not only from a config the walker has checked."""
    owner = type(obj).__name__
    values = vars(obj)
    for f in fields(obj):
        if decl_of(f) is None:
            continue
        where, value = f"{owner}.{f.name}", values[f.name]
        kind = _KINDS[str(f.type)]
        if value is None and str(f.type).endswith("None"):
            continue
        if kind is bool:
            if not isinstance(value, bool):
                raise ValueError(f"{where}: expected true/false, got {value!r}")
            continue
        if isinstance(value, bool) or not isinstance(value, int if kind is int else (int, float)):
            raise ValueError(f"{where}: expected {'an integer' if kind is int else 'a finite number'}, got {value!r}")
        if kind is float:
            if not math.isfinite(value):
                raise ValueError(f"{where}: expected a finite number, got {value!r}")
            object.__setattr__(obj, f.name, float(value))
    check_declared(obj, owner)


def _checked_section(section: Any, where: str) -> None:
    """A `sim:` section built in code: its declared bounds, then its rules across fields."""
    check_declared(section, where)
    section.validate(where)


_MPU_MIN_ODR_HZ = 1000.0 / 256  # SMPLRT_DIV 255 with the DLPF on: the MPU's slowest sample clock


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
    gyro_temp_start_c: float = setting(25.0, unit="degC", ge=-273.15, doc="Die temperature at power-on.")
    gyro_warmup_rise_c: float = setting(0.0, unit="degC", doc="How much the die warms after power-on.")
    gyro_warmup_tau_s: float = setting(120.0, unit="s", gt=0.0, doc="Time constant of the warm-up.")
    gyro_bias_per_c_dps: float = setting(0.0, unit="deg/s/degC", doc="Zero-rate bias change per degree of warming.")
    gyro_drift_dps_per_s: float = setting(0.0, unit="deg/s/s", doc="Linear drift of the zero-rate bias with time.")
    gyro_odr_hz: float = setting(0.0, unit="Hz", ge=0.0, le=8000.0,
                                 doc="The gyro's own sample rate (the MPU samples at most at 8 kHz); 0: read at the tick.")
    gyro_clock_ppm: float = setting(0.0, unit="ppm", gt=-1e6, lt=1e6, doc="Error of the gyro's own oscillator.")
    gyro_bias_step_dps: float = setting(0.0, unit="deg/s", doc="A step added to the bias from gyro_bias_step_at_s on.")
    gyro_bias_step_at_s: float = setting(0.0, unit="s", doc="Plant time of that step.")
    gyro_fifo: bool = setting(False, doc="Each gyro sample also goes into the part's FIFO.")
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
            _checked_section(self.battery, "Realism.battery")
        _checked_section(self.encoder_slip, "Realism.encoder_slip")
        _checked_section(self.wheels, "Realism.wheels")
        _checked_section(self.wheels.scale, "Realism.wheels.scale")
        _checked_section(self.actuators, "Realism.actuators")
        for i, p in enumerate(self.events.payloads):
            _checked_section(p, f"Realism.events.payloads[{i}]")
        for i, f in enumerate(self.events.floor):
            _checked_section(f, f"Realism.events.floor[{i}]")

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


_LATENCY_MAX_S = 1.0  # far beyond any bus, and the sensor rings' length stays small


@dataclass(frozen=True)
class PlantConfig:
    """Everything about the simulated robot that is not its geometry or its motors."""

    step_hz: float = setting(1000.0, unit="Hz", gt=0.0, doc="RK4 rate of the plant, independent of the controller's rate.")
    friction: bool = setting(True, doc="False zeroes the motors' viscous and Coulomb friction.")
    slip: bool = setting(True, doc="The seed's random slip torque.")
    slip_probability: float = setting(0.25, ge=0.0, le=1.0, doc="Chance per wheel per step of a slip term.")
    slip_fraction: float = setting(0.01, ge=0.0, le=1.0, doc="Slip size ~ N(slip_fraction tau, slip_sigma_nm).")
    slip_sigma_nm: float = setting(0.01, unit="N m", ge=0.0, le=100.0,
                                   doc="Spread of the slip torque; beyond 100, the slip alone throws the robot about.")
    seed: int | None = setting(0, doc="Seed of the slip and sensor noise; None: a different run every time.")
    command_latency_s: float = setting(0.0015, unit="s", ge=0.0, le=_LATENCY_MAX_S, doc="Duty command to motor voltage.")
    sensor_latency_s: float = setting(0.001, unit="s", ge=0.0, le=_LATENCY_MAX_S,
                                      doc="Age of the state a reading reports (the rings hold it).")
    encoder_counts_per_rev: int = setting(8192, unit="counts/rev", ge=0, doc="Front wheel, lines x 4; 0: not there.")
    encoder_offset_counts: int = setting(0, unit="counts", doc="Counter value at start (a counter need not start at 0).")
    gyro_range_dps: int = setting(250, unit="deg/s", doc="One of the part's ranges (checked below).")
    gyro_scale_error: float = setting(0.0, gt=-1.0, doc="Relative error of the sensitivity.")
    gyro_bias_dps: float = setting(1.5, unit="deg/s", doc="Constant zero-rate bias.")
    gyro_noise_dps_rthz: float = setting(0.005, unit="deg/s/sqrt(Hz)", ge=0.0, doc="White noise density before the low-pass.")
    gyro_dlpf_hz: float = setting(98.0, unit="Hz", gt=0.0, doc="The part's digital low-pass (98 Hz: DLPF_CFG=2).")
    wheel_counts_per_rev: int = setting(0, unit="counts/rev", ge=0, doc="Drive-wheel encoders, lines x 4; 0: not counted.")
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
