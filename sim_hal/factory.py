"""Build the simulated robot from a validated config (`hal.backend: sim`)."""

from __future__ import annotations

from typing import Any

from ddrt.config import Config
from sim_hal.plant import PlantConfig, Realism, SimRobot
from sim_hal.backend import SimHal
from sim_hal.wiring import WiringFaults


def plant_config(cfg: Config, seed: int | None = None) -> PlantConfig:
    """The plant's settings from the config's sim: and sensors: sections; a value the plant
    refuses is named by its config key."""
    s = cfg.sim
    keys = {  # PlantConfig field: (the config key it comes from, its value)
        "step_hz": ("sim.step_hz", s.step_hz),
        "friction": ("sim.friction", s.friction),
        "slip_probability": ("sim.slip.probability", s.slip.probability),
        "slip_sigma_nm": ("sim.slip.sigma_nm", s.slip.sigma_nm),
        "seed": ("sim.seed", s.seed if seed is None else seed),
        "command_latency_s": ("sim.command_latency_s", s.command_latency_s),
        "sensor_latency_s": ("sim.sensor_latency_s", s.sensor_latency_s),
        "encoder_counts_per_rev": ("sensors.encoder_counts_per_rev", cfg.sensors.encoder_counts_per_rev),
        "gyro_range_dps": ("sensors.gyro_range_dps", cfg.sensors.gyro_range_dps),
        "gyro_bias_dps": ("sim.gyro.bias_dps", s.gyro.bias_dps),
        "gyro_noise_dps_rthz": ("sim.gyro.noise_dps_rthz", s.gyro.noise_dps_rthz),
        "gyro_scale_error": ("sim.gyro.scale_error", s.gyro.scale_error),
        "gyro_dlpf_hz": ("sim.gyro.dlpf_hz", s.gyro.dlpf_hz),
        "wheel_counts_per_rev": ("sensors.wheel_counts_per_rev", cfg.sensors.wheel_counts_per_rev),
    }
    try:
        return PlantConfig(**{f: v for f, (_, v) in keys.items()},
                           realism=Realism.from_sim(s, cfg.hal.imu.sample_rate_div, cfg.sensors.gyro_fifo))
    except ValueError as e:
        msg = str(e)
        for f, (key, _) in keys.items():
            if msg.startswith(f"PlantConfig.{f}:"):
                raise ValueError(f"{key}{msg[len(f'PlantConfig.{f}'):]}") from None
        raise


def open_sim_hal(cfg: Config, start: tuple[float, float, float] = (0.0, 0.0, 0.0),
                 seed: int | None = None, paced: bool = False, **_: Any) -> SimHal:
    """A SimHal around the plant described by `cfg` (truth: plant:, sim:, sensors:)."""
    robot = SimRobot(cfg.plant, cfg.plant_motor_l, cfg.plant_motor_r, plant_config(cfg, seed), start=start)
    hal = SimHal(robot, paced=paced, battery_measured=cfg.sim.battery_measured,
                 wiring=WiringFaults.from_config(cfg.sim.wiring), gyro_temp_hz=cfg.sensors.gyro_temp_hz)
    if cfg.sim.sensors_freeze_after_s is not None:
        hal.freeze(robot.t + cfg.sim.sensors_freeze_after_s, cfg.sim.sensors_freeze_for_s)
    return hal
