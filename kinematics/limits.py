"""Joint-limit checks and human-readable violation messages.

Limits are arguments (they come from the arm profile), never constants.
Positions are radians for revolute joints and metres for prismatic ones;
``kinds`` says which, so that messages carry the right unit.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from kinematics.errors import Unreachable

__all__ = ["corners", "draw", "first_violation", "unit", "violations", "within"]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


def unit(kind: str) -> str:
    """Unit of a joint kind: ``"rad"`` for revolute, ``"m"`` for prismatic."""
    if kind == "revolute":
        return "rad"
    if kind == "prismatic":
        return "m"
    raise ValueError(f"unknown joint kind {kind!r}: expected 'revolute' or 'prismatic'")


def within(
    q: npt.ArrayLike, lower: npt.ArrayLike, upper: npt.ArrayLike, tol: float = 1e-9
) -> BoolArray:
    """True where every joint of ``q`` lies in ``[lower - tol, upper + tol]``.

    q: (..., n) joint positions; lower, upper: (n,). Returns (...,) bool;
    NaN joints count as outside.
    """
    qa = np.asarray(q, dtype=np.float64)
    lo = np.asarray(lower, dtype=np.float64)
    hi = np.asarray(upper, dtype=np.float64)
    ok = (qa >= lo - tol) & (qa <= hi + tol)
    return np.asarray(np.all(ok, axis=-1))


def _fmt(value: float, kind: str, excess: float) -> str:
    """Enough decimals that a small excess still shows between value and limit."""
    base = 2 if kind == "revolute" else 3
    extra = int(np.ceil(-np.log10(excess))) + 1 if 0 < excess < np.inf else 0
    return f"{value:.{min(max(base, extra), 6)}f} {unit(kind)}"


def violations(
    q: npt.ArrayLike,
    names: Sequence[str],
    lower: npt.ArrayLike,
    upper: npt.ArrayLike,
    kinds: Sequence[str] | None = None,
    tol: float = 1e-9,
) -> list[str]:
    """Messages for every joint of one configuration ``q`` (n,) outside its limits.

    e.g. ``"shoulder 1.90 rad is above its limit 1.75 rad by 0.15 rad"``.
    ``kinds`` defaults to all revolute. An empty list means ``q`` is inside.
    """
    qa = np.asarray(q, dtype=np.float64).reshape(-1)
    lo = np.broadcast_to(np.asarray(lower, dtype=np.float64), qa.shape)
    hi = np.broadcast_to(np.asarray(upper, dtype=np.float64), qa.shape)
    ks = list(kinds) if kinds is not None else ["revolute"] * qa.size
    if len(names) != qa.size or len(ks) != qa.size:
        raise ValueError(f"{qa.size} joints but {len(names)} names and {len(ks)} kinds")
    out: list[str] = []
    for i in range(qa.size):
        v, k, u = float(qa[i]), ks[i], unit(ks[i])
        if np.isnan(v):
            out.append(f"{names[i]} has no value (NaN)")
        elif v > hi[i] + tol:
            e = v - float(hi[i])
            out.append(
                f"{names[i]} {_fmt(v, k, e)} is above its limit {_fmt(float(hi[i]), k, e)}"
                f" by {e:.3g} {u}"
            )
        elif v < lo[i] - tol:
            e = float(lo[i]) - v
            out.append(
                f"{names[i]} {_fmt(v, k, e)} is below its limit {_fmt(float(lo[i]), k, e)}"
                f" by {e:.3g} {u}"
            )
    return out


def first_violation(
    q: npt.ArrayLike,
    names: Sequence[str],
    lower: npt.ArrayLike,
    upper: npt.ArrayLike,
    kinds: Sequence[str] | None = None,
    tol: float = 1e-9,
) -> tuple[int, list[str]] | None:
    """Index of the first row of ``q`` (m, n) outside the limits and its messages.

    Returns None when every row is inside. The check is vectorised; only the
    offending row is formatted.
    """
    qa = np.atleast_2d(np.asarray(q, dtype=np.float64))
    bad = np.flatnonzero(~within(qa, lower, upper, tol))
    if bad.size == 0:
        return None
    i = int(bad[0])
    return i, violations(qa[i], names, lower, upper, kinds, tol)


def distinct_solutions(
    q: npt.ArrayLike,
    p: npt.ArrayLike,
    lower: npt.ArrayLike | None = None,
    upper: npt.ArrayLike | None = None,
) -> list[npt.NDArray[np.float64]]:
    """The distinct rows of ``q`` (k, n), the valid IK solutions of point ``p`` (3,) m; with
    limits given, only those within them, and :class:`Unreachable` if none is."""
    out: list[npt.NDArray[np.float64]] = []
    for qi in np.asarray(q, dtype=np.float64):
        if not any(np.allclose(qi, o, atol=1e-12) for o in out):
            out.append(qi)
    if lower is not None and upper is not None:
        inside = [qi for qi in out if bool(within(qi, lower, upper))]
        if not inside:
            pa = np.asarray(p, dtype=np.float64)
            raise Unreachable(
                f"every solution for ({pa[0]:.3f}, {pa[1]:.3f}, {pa[2]:.3f}) m is outside"
                " the joint limits"
            )
        out = inside
    return out


def draw(
    lower: npt.ArrayLike,
    upper: npt.ArrayLike,
    n: int,
    rng: np.random.Generator | None = None,
) -> FloatArray:
    """``n`` joint vectors (n, k) drawn uniformly within the limits (k,): what a sampled
    workspace is made from."""
    r = rng if rng is not None else np.random.default_rng()
    lo = np.asarray(lower, dtype=np.float64)
    return r.uniform(lo, np.asarray(upper, dtype=np.float64), size=(n, lo.size))


def corners(lower: npt.ArrayLike, upper: npt.ArrayLike) -> FloatArray:
    """The 2**k joint vectors (2**k, k) with every joint at one of its limits (k,): the
    extremes a sampled workspace's box adds to its draws."""
    lo = np.asarray(lower, dtype=np.float64)
    hi = np.asarray(upper, dtype=np.float64)
    return np.stack(np.meshgrid(*zip(lo, hi, strict=True), indexing="ij"), -1).reshape(-1, lo.size)
