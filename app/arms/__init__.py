"""The arm-type registry: arm type name -> the package that implements it.

Adding an arm type is one package under app/arms/<name>/ (see app/arms/base.py) and one line
here. A package is imported the first time its type is asked for (bleak loads its backends
this way), so a server hosting one arm type never imports another's driver or maths.
"""

from __future__ import annotations

import importlib
import importlib.util
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from app.arms.base import ArmType
    from app.arms.model import KinematicsModel

#: Arm type name -> module of its package (the package's ``ARM`` is the ArmType).
ARM_TYPES: dict[str, str] = {
    "rbe3001": "app.arms.rbe3001",
    "angler": "app.arms.angler",
    "openmanipulator_x": "app.arms.openmanipulator_x",
}

__all__ = ["ARM_TYPES", "all_arm_types", "arm_routers", "arm_type", "builtin_profiles", "known",
           "model_for"]

_LOADED: dict[str, ArmType] = {}


def _arm_type_class() -> type[ArmType]:
    from app.arms.base import ArmType

    return ArmType


def known() -> str:
    """The registered names, for messages: `"angler", "rbe3001"`."""
    return ", ".join(f'"{n}"' for n in sorted(ARM_TYPES))


def arm_type(name: str) -> ArmType:
    """The arm type called `name`, its package imported on first use. An unknown name raises
    ValueError naming the known ones."""
    t = _LOADED.get(name)
    if t is not None:
        return t
    module = ARM_TYPES.get(name)
    if module is None:
        raise ValueError(f"unknown arm type {name!r}: the known arm types are {known()}")
    t = importlib.import_module(module).ARM
    if not isinstance(t, _arm_type_class()):
        raise TypeError(f"{module}.ARM is not an ArmType")
    if t.name != name:
        raise ValueError(f"{module}.ARM is named {t.name!r}, registered as {name!r}")
    _LOADED[name] = t
    return t


def model_for(profile: Any) -> KinematicsModel:
    """The kinematics model of `profile`'s arm type, bound to it (app/arms/model.py is the
    contract; each arm type binds its own maths)."""
    return arm_type(profile.model).model(profile)


def all_arm_types() -> list[ArmType]:
    """Every registered arm type (imports every package: for building the app, discovery)."""
    return [arm_type(n) for n in ARM_TYPES]


def builtin_profiles() -> dict[str, Path]:
    """Every profile shipped inside an arm type's package (`*.toml`): profile file stem ->
    path, in registry order (the default server hosts them all). Reads the package
    directories without importing the packages."""
    out: dict[str, Path] = {}
    for module in ARM_TYPES.values():
        spec = importlib.util.find_spec(module)
        if spec is None or not spec.submodule_search_locations:
            raise ValueError(f"arm type package {module} not found")
        for path in sorted(Path(spec.submodule_search_locations[0]).glob("*.toml")):
            out[path.stem] = path
    return out


def _router_modules() -> list[Any]:
    """The modules the registered arm types name in `routers`, each once however many types
    name it, in registry order."""
    seen: dict[str, Any] = {}
    for t in all_arm_types():
        for module in t.routers:
            if module not in seen:
                seen[module] = importlib.import_module(module)
    return list(seen.values())


def arm_routers() -> list[Any]:
    """The pass-through routers (FastAPI APIRouter) of every registered arm type, each module
    once however many types name it, in registry order: the app mounts them all, so the
    routes are the same whichever arms a server hosts."""
    return [m.router for m in _router_modules()]


def arm_fast_paths() -> list[Any]:
    """The ASGI layers the routers' modules declare in `FAST_PATHS` (e.g. the Dynamixel
    register write's, app/arms/dynamixel/api.py), each module once, in registry order: the
    app installs them innermost, inside every gate."""
    return [layer for m in _router_modules() for layer in getattr(m, "FAST_PATHS", ())]
