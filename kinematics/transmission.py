"""Joint units (rad, m) <-> motor units (encoder ticks, ticks/s, Dynamixel rpm units).

One :class:`Transmission` covers all joints of an arm, vectorised over the
last axis (n joints)::

    ticks = offset_ticks + sign * q * ticks_per_rev / per_rev

where ``per_rev`` is 2 pi rad for a revolute joint and the lead (metres per
motor revolution) for a prismatic one: 8 mm ball screws, a 0.1257 m winch.
Ticks are floats here; rounding to the integer register is the caller's
choice (:meth:`Transmission.to_ticks_int`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from functools import cached_property
from typing import Any

import numpy as np
import numpy.typing as npt

__all__ = ["RPM_PER_UNIT", "Transmission"]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

RPM_PER_UNIT = 0.229
"""Dynamixel MX-28 (Protocol 2.0) velocity unit, rev/min per register unit."""


def _vec(v: npt.ArrayLike, n: int | None = None) -> FloatArray:
    a = np.atleast_1d(np.asarray(v, dtype=np.float64))
    if a.ndim != 1 or (n is not None and a.size != n):
        raise ValueError(f"expected a vector of {n} joint values, got shape {a.shape}")
    return a


def _frozen(a: FloatArray) -> FloatArray:
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class Transmission:
    """Per-joint motor parameters, each (n,).

    ``lead_m`` is NaN for revolute joints (2 pi rad per motor revolution) and
    the travel per motor revolution in metres for prismatic joints.
    ``sign`` is +1 or -1 (motor direction relative to the joint).
    """

    ticks_per_rev: FloatArray
    offset_ticks: FloatArray
    sign: FloatArray
    lead_m: FloatArray

    def __post_init__(self) -> None:
        n = self.ticks_per_rev.shape
        for name in ("offset_ticks", "sign", "lead_m"):
            if getattr(self, name).shape != n:
                raise ValueError(f"{name} has shape {getattr(self, name).shape}, expected {n}")
        if not np.all(np.abs(self.sign) == 1.0):
            raise ValueError(f"sign must be +1 or -1, got {self.sign.tolist()}")
        if not np.all(self.ticks_per_rev > 0):
            raise ValueError("ticks_per_rev must be positive")
        lead = self.lead_m[~np.isnan(self.lead_m)]
        if not np.all(lead > 0):
            raise ValueError("lead_m must be positive (or NaN for a revolute joint)")
        for name in ("ticks_per_rev", "offset_ticks", "sign", "lead_m"):
            getattr(self, name).setflags(write=False)  # frozen whole: homing makes a new one

    def with_offset(self, k: int, offset_ticks: float) -> Transmission:
        """The same transmission with joint `k`'s offset (ticks) changed: homing's."""
        offsets = np.array(self.offset_ticks, dtype=np.float64)
        offsets[k] = offset_ticks
        return replace(self, offset_ticks=offsets)

    @classmethod
    def from_joints(
        cls,
        ticks_per_rev: npt.ArrayLike,
        offset_ticks: npt.ArrayLike,
        sign: npt.ArrayLike,
        lead_m_or_none: Sequence[float | None] | None = None,
    ) -> Transmission:
        """Build from per-joint lists; ``None`` (or no list at all) means revolute."""
        tpr = _vec(ticks_per_rev)
        n = tpr.size
        leads = [np.nan] * n if lead_m_or_none is None else [
            np.nan if v is None else float(v) for v in lead_m_or_none]
        return cls(tpr, _vec(offset_ticks, n), _vec(sign, n), _vec(leads, n))

    @classmethod
    def from_joint_tables(cls, joints: Sequence[Mapping[str, Any]]) -> Transmission:
        """Build from profile ``[[joints]]`` tables (keys ticks_per_rev, offset_ticks,
        sign, and lead_m for prismatic joints)."""
        return cls.from_joints(
            [j["ticks_per_rev"] for j in joints],
            [j.get("offset_ticks", 0) for j in joints],
            [j.get("sign", 1) for j in joints],
            [j.get("lead_m") if j.get("kind", "revolute") == "prismatic" else None
             for j in joints],
        )

    # The two below are computed once (the fields are read-only): every sample converts
    # through them, hundreds of times a second.
    @cached_property
    def per_rev(self) -> FloatArray:
        """Joint travel per motor revolution (n,): 2 pi rad or the lead in m."""
        return _frozen(np.where(np.isnan(self.lead_m), 2.0 * np.pi, self.lead_m))

    @cached_property
    def ticks_per_unit(self) -> FloatArray:
        """Signed ticks per rad or per m (n,)."""
        return _frozen(np.asarray(self.sign * self.ticks_per_rev / self.per_rev))

    def to_ticks(self, q: npt.ArrayLike) -> FloatArray:
        """Encoder ticks (..., n), float, for joint positions ``q`` (..., n) rad or m."""
        return np.asarray(self.offset_ticks + np.asarray(q, dtype=np.float64) * self.ticks_per_unit)

    def to_ticks_int(self, q: npt.ArrayLike) -> IntArray:
        """:meth:`to_ticks` rounded to the nearest integer register value."""
        return np.rint(self.to_ticks(q)).astype(np.int64)

    def from_ticks(self, ticks: npt.ArrayLike) -> FloatArray:
        """Joint positions (..., n) rad or m for encoder ticks (..., n)."""
        t = np.asarray(ticks, dtype=np.float64)
        return np.asarray((t - self.offset_ticks) / self.ticks_per_unit)

    def velocity_to_ticks(self, qd: npt.ArrayLike) -> FloatArray:
        """Motor speed (..., n) ticks/s for joint rates ``qd`` (..., n) rad/s or m/s."""
        return np.asarray(np.asarray(qd, dtype=np.float64) * self.ticks_per_unit)

    def velocity_from_ticks(self, tps: npt.ArrayLike) -> FloatArray:
        """Joint rates (..., n) rad/s or m/s for motor speeds ``tps`` (..., n) ticks/s."""
        return np.asarray(np.asarray(tps, dtype=np.float64) / self.ticks_per_unit)

    def velocity_to_rpm_units(self, qd: npt.ArrayLike) -> FloatArray:
        """Dynamixel velocity register units (0.229 rpm each), float, (..., n)."""
        rpm = np.asarray(qd, dtype=np.float64) * self.sign / self.per_rev * 60.0
        return np.asarray(rpm / RPM_PER_UNIT)

    def velocity_from_rpm_units(self, units: npt.ArrayLike) -> FloatArray:
        """Joint rates (..., n) rad/s or m/s for Dynamixel velocity units (..., n)."""
        rpm = np.asarray(units, dtype=np.float64) * RPM_PER_UNIT
        return np.asarray(rpm / 60.0 * self.per_rev * self.sign)
