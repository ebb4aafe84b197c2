"""The one singularity rule: the 2-norm condition number of the Jacobian.

Where cond(J) = sigma_max / sigma_min exceeds TIP_FORCE_MAX_COND the tip force solved from the
joint torques (J^T F = tau) is not reported: a relative error e in the torques (strain-gauge
noise, calibration) becomes up to cond * e in the force, and at the singularity itself some
force direction is carried by the structure and shows in no joint at all. 100 keeps every
ordinary RBE3001 pose (cond 2-15 inside the joint limits) and refuses the last few degrees
before the elbow stretches or folds and a tip over the base axis (at cond 100, 0.1 N m of
shoulder torque would already read ~11 N). Every route and every sample uses this constant.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

__all__ = ["TIP_FORCE_MAX_COND", "condition_number", "singular_reason"]

TIP_FORCE_MAX_COND = 100.0


def condition_number(j: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """cond(J) over leading axes ((..., m, n) -> (...)); inf where J loses rank."""
    s = np.linalg.svd(np.asarray(j, dtype=np.float64), compute_uv=False)
    with np.errstate(divide="ignore", invalid="ignore"):
        c = s[..., 0] / s[..., -1]
    return np.asarray(np.where(np.isfinite(c), c, np.inf), dtype=np.float64)


def singular_reason(j: npt.ArrayLike, max_cond: float = TIP_FORCE_MAX_COND) -> str | None:
    """Why no tip force can be given at a single Jacobian (m, n), or None where it can."""
    c = float(condition_number(j))
    if c <= max_cond:
        return None
    shown = "infinite" if not np.isfinite(c) else f"{c:.3g}"
    return (f"near a singularity: the Jacobian's condition number is {shown}, above "
            f"{max_cond:g}, so the joint torques do not determine the tip force (the arm is "
            "stretched out, folded, or the tip is over the base axis)")
