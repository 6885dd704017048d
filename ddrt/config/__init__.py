"""The config: sections (typed dataclasses), the schema walker, loading and the reload policy."""

from ddrt.config.load import (
    config_from_mapping, load_config, with_overrides,
)
from ddrt.config.schema import ConfigError
from ddrt.config.sections import (
    AdaptationConfig, Config, ControllerConfig, DaemonConfig, EstimatorConfig, GyroTruth, HalConfig,
    LimitsConfig, OuterGains, PidGains, PursuitConfig, SensorsConfig, SimConfig, SlipConfig,
    WheelPidGains,
)

__all__ = [
    "AdaptationConfig", "Config", "ConfigError", "ControllerConfig", "DaemonConfig", "EstimatorConfig",
    "GyroTruth", "HalConfig", "LimitsConfig", "OuterGains", "PidGains", "PursuitConfig",
    "SensorsConfig", "SimConfig", "SlipConfig", "WheelPidGains", "config_from_mapping",
    "load_config", "with_overrides",
]
