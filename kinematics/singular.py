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

__all__ = ["TIP_FORCE_MAX_COND", "condition_number", "singular_reason", "well_conditioned"]

TIP_FORCE_MAX_COND = 100.0


def condition_number(j: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """cond(J) over leading axes ((..., m, n) -> (...)); inf where J loses rank."""
    s = np.linalg.svd(np.asarray(j, dtype=np.float64), compute_uv=False)
    with np.errstate(divide="ignore", invalid="ignore"):
        c = s[..., 0] / s[..., -1]
    return np.asarray(np.where(np.isfinite(c), c, np.inf), dtype=np.float64)


def well_conditioned(j: npt.NDArray[np.float64], max_cond: float = TIP_FORCE_MAX_COND) -> bool:
    """cond(J) <= max_cond for one Jacobian (m, n), cheaply where it is clearly so.

    For a square J, |det J| = s1 s2 ... sn >= s_min s1^(n-1) and s1 <= ||J||_F, so
    cond = s1 / s_min <= ||J||_F^n / |det J|: when that bound is within max_cond the exact
    value is too (no SVD: this runs for every telemetry sample). Otherwise, or for a
    non-square J, the exact condition number decides."""
    if j.shape[0] == j.shape[1]:
        det = abs(float(np.linalg.det(j)))
        fro = float(np.sqrt(np.sum(j * j)))
        if det > 0.0 and fro ** j.shape[0] <= max_cond * det:
            return True
    return float(condition_number(j)) <= max_cond


def singular_reason(j: npt.ArrayLike, max_cond: float = TIP_FORCE_MAX_COND) -> str | None:
    """Why no tip force can be given at a single Jacobian (m, n), or None where it can."""
    ja = np.asarray(j, dtype=np.float64)
    if well_conditioned(ja, max_cond):
        return None
    c = float(condition_number(ja))
    shown = "infinite" if not np.isfinite(c) else f"{c:.3g}"
    return (f"near a singularity: the Jacobian's condition number is {shown}, above "
            f"{max_cond:g}, so the joint torques do not determine the tip force (the arm is "
            "stretched out, folded, or the tip is over the base axis)")
