"""The config: sections (typed dataclasses), the schema walker, loading and the reload policy."""

from ddrt.config.load import (
    RESTART_KEYS, changed_keys, config_from_mapping, load_config, needs_restart, with_overrides,
)
from ddrt.config.schema import ConfigError
from ddrt.config.sections import (
    AdaptationConfig, BridgeConfig, Config, ControllerConfig, DaemonConfig, EstimatorConfig, GyroTruth,
    HalConfig, ImuConfig, LimitsConfig, OuterGains, PathsConfig, PidGains, PursuitConfig, PwmSysfsConfig,
    SensorsConfig, SimConfig, SlipConfig, WheelPidGains,
)

__all__ = [
    "AdaptationConfig", "BridgeConfig", "Config", "ConfigError", "ControllerConfig", "DaemonConfig",
    "EstimatorConfig", "GyroTruth", "HalConfig", "ImuConfig", "LimitsConfig", "OuterGains", "PathsConfig",
    "PidGains", "PursuitConfig", "PwmSysfsConfig", "RESTART_KEYS", "SensorsConfig", "SimConfig",
    "SlipConfig", "WheelPidGains", "changed_keys", "config_from_mapping",
    "load_config", "needs_restart", "with_overrides",
]
