"""Errors raised by the kinematics package.

One root, :class:`KinematicsError` (a ``ValueError``: the caller asked for
something the arm cannot do), with precise subclasses. Every message is meant
to be read by a person and acted on: it names the point, the joint, the limit
and by how much it was missed, in SI units.
"""

from __future__ import annotations

__all__ = ["KinematicsError", "LimitViolation", "Singular", "TrajectoryError", "Unreachable"]


class KinematicsError(ValueError):
    """Root of every kinematics failure; the message says what to change."""


class Unreachable(KinematicsError):
    """No joint configuration places the tip at the target.

    Examples of messages: ``"out of reach: 0.52 m from the shoulder, reach is
    0.37 m"``, ``"inside the inner hole: 0.02 m from the shoulder, the arm
    cannot fold closer than 0.04 m"``.
    """


class Singular(KinematicsError):
    """The Jacobian is (near) singular; the message carries its condition number."""

    def __init__(self, message: str, cond: float) -> None:
        super().__init__(message)
        self.cond = cond


class LimitViolation(KinematicsError):
    """A joint position or velocity would leave its configured limits."""


class TrajectoryError(KinematicsError):
    """The trajectory generator found no trajectory; ``ruckig_code`` is its result number
    (e.g. -101: the move would last too long), the message says what it means."""

    def __init__(self, message: str, ruckig_code: int) -> None:
        super().__init__(message)
        self.ruckig_code = ruckig_code
