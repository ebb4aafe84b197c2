"""Server settings (environment, prefix ARMSERVER_) and arm profiles (TOML files).

An arm profile holds everything that differs between arms and between a simulated and a
real link: geometry, joint limits, encoder and transmission data, link address and rates.
Code never hard-codes these; the built-in profiles carry the design documents' values.

A package (issue 13's module size): profiles.py (the profile models), loading.py (profile
and config files), settings.py (the server's settings); every name is re-exported here, so
`from app.config import ...` is the one way in.
"""

from __future__ import annotations

from app.config.loading import (
    MAX_COPIES,
    ConfigError,
    ServerConfig,
    homed_at_start,
    load_arms,
    load_profile,
)
from app.config.profiles import (
    ArmProfile,
    CartesianLimits,
    FaultConfig,
    ForceConfig,
    GripperConfig,
    JointConfig,
    KeepOutBox,
    LinkConfig,
    Point3,
    SafetyConfig,
    SafetySettings,
)
from app.config.settings import (
    LOG_LEVELS,
    SETTING_RANGES,
    Settings,
    env_name,
    settings_error,
)

__all__ = [
    "ArmProfile",
    "CartesianLimits",
    "ConfigError",
    "FaultConfig",
    "ForceConfig",
    "GripperConfig",
    "JointConfig",
    "KeepOutBox",
    "LOG_LEVELS",
    "LinkConfig",
    "MAX_COPIES",
    "Point3",
    "SETTING_RANGES",
    "SafetyConfig",
    "SafetySettings",
    "ServerConfig",
    "Settings",
    "env_name",
    "homed_at_start",
    "load_arms",
    "load_profile",
    "settings_error",
]
