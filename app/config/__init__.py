"""Server settings (environment, prefix ARMSERVER_) and arm profiles (TOML files).

An arm profile holds everything that differs between arms and between a simulated and a
real link: geometry, joint limits, encoder and transmission data, link address and rates.
Code never hard-codes these; the built-in profiles carry the design documents' values.

A package: profiles.py (the profile models, plain data: they know no arm type), settings.py
(the server's settings); every name is re-exported here, so `from app.config import ...` is
the one way in. Reading profiles and config files, and checking a profile against its arm
type, is app/arms/loading.py: the registry's side, so that config depends on nothing above it
and the arm types may name ArmProfile in their types without a cycle.
"""

from __future__ import annotations

from app.config.profiles import (
    ArmProfile,
    CartesianLimits,
    ConfigError,
    FaultConfig,
    ForceConfig,
    GripperConfig,
    JointConfig,
    KeepOutBox,
    LinkConfig,
    Point3,
    SafetyConfig,
    SafetySettings,
    homed_at_start,
    invalid_config,
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
    "Point3",
    "SETTING_RANGES",
    "SafetyConfig",
    "SafetySettings",
    "Settings",
    "env_name",
    "homed_at_start",
    "invalid_config",
    "settings_error",
]
