"""The simulated robot and the HAL backend that drives it (also the loop's clock in CI)."""

from sim_hal.plant import EnergyLedger, PlantConfig, SimRobot
from sim_hal.backend import SimHal

__all__ = ["EnergyLedger", "PlantConfig", "SimHal", "SimRobot"]
