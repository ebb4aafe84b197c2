"""The only places that touch a library's internals, one module per library."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from importlib import metadata
from typing import Any


class DoorError(RuntimeError):
    """An installed library lacks an internal that one of these doors relies on."""


def installed(dist: str) -> str:
    """The installed version of the distribution `dist` ("not installed" if it is not)."""
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return "not installed"


def uses(fn: Any, *names: str) -> bool:
    """Whether the function `fn` (a method, or a class's `__init__`) exists and names every one
    of `names` (attributes it reads or sets: its code's `co_names`), without running it."""
    code = getattr(fn, "__code__", None)
    return code is not None and set(names) <= set(code.co_names)


def require(door: str, dist: str, checked: str,
            needs: Iterable[tuple[str, Callable[[], bool], str]]) -> None:
    """Raise DoorError unless every need holds: (the internal, a test that it is there, what
    breaks without it). The message names the library, its installed version, the version the
    door was checked with, and each internal that is missing."""
    missing = []
    for what, present, breaks in needs:
        try:
            ok = present()
        except Exception:  # noqa: BLE001  (a test that cannot run: the internal is missing)
            ok = False
        if not ok:
            missing.append(f"  - {what}: {breaks}")
    if missing:
        raise DoorError(
            f"{dist} {installed(dist)} lacks internals that {door} relies on (checked with {dist} "
            f"{checked}; pyproject.toml bounds its version):\n" + "\n".join(missing)
            + f"\nInstall {dist} within pyproject.toml's bounds, or update {door}.")
