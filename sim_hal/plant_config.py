"""The simulated robot's settings beyond its geometry and motors, and its energy ledger.

`PlantConfig` holds what the seed's plant had (flat); `Realism` bundles the
imperfections (battery, gyro warm-up and register timing, encoder slip, deadband, backlash,
events), whose defaults leave the plant exactly as it was. A plant whose `Realism` is not the
default integrates in Python (sim_hal/plant_real.py), the default one in the compiled kernel.
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

__all__ = ["EnergyLedger", "PlantConfig", "Realism"]


@dataclass(frozen=True)
class Realism:
    """What makes the simulated robot real (ddrt/config/sim_truth.py and docs/config.md's
    `sim:` keys say what each is); the default is the ideal plant of before.

    The gyro's die temperature is T(t) = temp_start_c + warmup_rise_c (1 - exp(-t / warmup_tau_s));
    its zero-rate bias adds bias_per_c_dps (T - temp_start_c) + drift_dps_per_s t to
    PlantConfig.gyro_bias_dps. `gyro_odr_hz` > 0: the output register holds the low-passed rate
    sampled at that rate (the MPU's own clock, off by `gyro_clock_ppm`); 0: read at the tick.
    `gyro_fifo` (`sensors.gyro_fifo`): each sample also goes into the MPU's FIFO (512 samples of
    gyro z, the oldest lost when full), which `SimRobot.read_gyro_fifo` drains; it needs the
    sample clock, so `from_sim` sets `gyro_odr_hz` for it even without the register's hold.
    """

    battery: BatteryTruth | None = None
    gyro_temp_start_c: float = 25.0
    gyro_warmup_rise_c: float = 0.0
    gyro_warmup_tau_s: float = 120.0
    gyro_bias_per_c_dps: float = 0.0
    gyro_drift_dps_per_s: float = 0.0
    gyro_odr_hz: float = 0.0
    gyro_clock_ppm: float = 0.0
    gyro_bias_step_dps: float = 0.0  # added to the bias from gyro_bias_step_at_s on
    gyro_bias_step_at_s: float = 0.0
    gyro_fifo: bool = False
    encoder_slip: WanderingScale = field(default_factory=WanderingScale)
    wheels: WheelsTruth = field(default_factory=WheelsTruth)
    actuators: ActuatorTruth = field(default_factory=ActuatorTruth)
    events: EventsTruth = field(default_factory=EventsTruth)

    def __post_init__(self) -> None:
        for name in ("gyro_temp_start_c", "gyro_warmup_rise_c", "gyro_warmup_tau_s", "gyro_bias_per_c_dps",
                     "gyro_drift_dps_per_s", "gyro_odr_hz", "gyro_clock_ppm", "gyro_bias_step_dps",
                     "gyro_bias_step_at_s"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"Realism.{name}: expected a finite number, got {value!r}")
            object.__setattr__(self, name, float(value))
        if self.gyro_warmup_tau_s <= 0 or self.gyro_odr_hz < 0 or abs(self.gyro_clock_ppm) >= 1e6:
            raise ValueError("Realism: gyro_warmup_tau_s must be > 0, gyro_odr_hz >= 0, |gyro_clock_ppm| < 1e6")
        if self.gyro_fifo and self.gyro_odr_hz == 0.0:
            raise ValueError("Realism.gyro_fifo: the FIFO needs the gyro's sample clock (gyro_odr_hz > 0)")
        # The config's sections validate themselves when read from YAML; built here directly
        # (tests, benches) they are checked the same way.
        for name, value in (("battery", self.battery), ("encoder_slip", self.encoder_slip),
                            ("wheels", self.wheels), ("wheels.scale", self.wheels.scale),
                            ("actuators", self.actuators)):
            if value is not None and hasattr(value, "validate"):
                value.validate(f"Realism.{name}")
        for i, p in enumerate(self.events.payloads):
            p.validate(f"Realism.events.payloads[{i}]")
        for i, f in enumerate(self.events.floor):
            f.validate(f"Realism.events.floor[{i}]")

    @property
    def active(self) -> bool:
        """Anything but the ideal plant: the plant then integrates in Python (plant_real.py)."""
        return self != Realism()

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


@dataclass(frozen=True)
class PlantConfig:
    """Everything about the simulated robot that is not its geometry or its motors."""

    step_hz: float = 1000.0  # RK4 rate of the plant, independent of the controller's rate
    friction: bool = True  # False zeroes the motors' viscous and Coulomb friction
    slip: bool = True  # the seed's random slip torque
    slip_probability: float = 0.25  # chance per wheel per step that a slip term is added
    slip_fraction: float = 0.01  # slip size ~ N(slip_fraction * tau, slip_sigma_nm)
    slip_sigma_nm: float = 0.01
    seed: int | None = 0  # None: a different run every time
    command_latency_s: float = 0.0015  # duty command -> motor voltage
    sensor_latency_s: float = 0.001  # age of the state a reading reports
    encoder_counts_per_rev: int = 8192  # front wheel, lines x 4
    encoder_offset_counts: int = 0  # counter value at start (a counter need not start at 0)
    gyro_range_dps: int = 250
    gyro_scale_error: float = 0.0  # relative error of the gyro's sensitivity
    gyro_bias_dps: float = 1.5
    gyro_noise_dps_rthz: float = 0.005  # white noise density before the low-pass
    gyro_dlpf_hz: float = 98.0  # MPU-6050 digital low-pass (DLPF_CFG=2)
    wheel_counts_per_rev: int = 0  # drive-wheel encoders, lines x 4 (0: not counted)
    realism: Realism = field(default_factory=lambda: Realism())  # a real robot's imperfections

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name == "realism":
                if not isinstance(value, Realism):
                    raise ValueError(f"PlantConfig.realism: expected a Realism, got {value!r}")
                continue
            if f.name in ("friction", "slip"):
                if not isinstance(value, bool):
                    raise ValueError(f"PlantConfig.{f.name}: expected true/false, got {value!r}")
                continue
            if f.name == "seed" and value is None:
                continue
            if f.name in ("seed", "encoder_counts_per_rev", "encoder_offset_counts", "gyro_range_dps",
                          "wheel_counts_per_rev"):
                if isinstance(value, bool) or not isinstance(value, int):
                    raise ValueError(f"PlantConfig.{f.name}: expected an integer, got {value!r}")
                continue
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"PlantConfig.{f.name}: expected a finite number, got {value!r}")
            object.__setattr__(self, f.name, float(value))
        positive = ("step_hz", "gyro_dlpf_hz")
        non_negative = ("slip_fraction", "slip_sigma_nm", "command_latency_s", "sensor_latency_s",
                        "gyro_noise_dps_rthz")
        for name in positive:
            if getattr(self, name) <= 0:
                raise ValueError(f"PlantConfig.{name}: must be > 0, got {getattr(self, name)!r}")
        for name in non_negative:
            if getattr(self, name) < 0:
                raise ValueError(f"PlantConfig.{name}: must be >= 0, got {getattr(self, name)!r}")
        if not 0.0 <= self.slip_probability <= 1.0:
            raise ValueError(
                f"PlantConfig.slip_probability: must be in [0, 1], got {self.slip_probability!r}"
            )
        for name in ("encoder_counts_per_rev", "wheel_counts_per_rev"):  # 0: that encoder is not there
            if getattr(self, name) < 0:
                raise ValueError(f"PlantConfig.{name}: must be >= 0, got {getattr(self, name)!r}")
        if self.gyro_scale_error <= -1.0:
            raise ValueError(f"PlantConfig.gyro_scale_error: must be > -1, got {self.gyro_scale_error!r}")
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
