"""The config: sections (typed dataclasses), the schema walker, loading and the reload policy."""

from ddrt.config.load import (
    config_from_mapping, load_config, with_overrides,
)
from ddrt.config.schema import ConfigError
from ddrt.config.sections import (
    AdaptationConfig, BridgeConfig, Config, ControllerConfig, DaemonConfig, DriveConfig, EstimatorConfig,
    HalConfig, ImuConfig, LimitsConfig, OuterGains, PathsConfig, PidGains, PursuitConfig, PwmSysfsConfig,
    SensorsConfig,
)
from ddrt.config.sim_truth import GyroTruth, SimConfig, SlipConfig

__all__ = [
    "AdaptationConfig", "BridgeConfig", "Config", "ConfigError", "ControllerConfig", "DaemonConfig", "DriveConfig",
    "EstimatorConfig", "GyroTruth", "HalConfig", "ImuConfig", "LimitsConfig", "OuterGains", "PathsConfig",
    "PidGains", "PursuitConfig", "PwmSysfsConfig", "SensorsConfig", "SimConfig",
    "SlipConfig", "config_from_mapping",
    "load_config", "with_overrides",
]
