"""The fixed time grid of a recording: frame k at `t0 + k / fps`, and the telemetry resampled
onto it.

A state is measured at the poll's times, not the grid's: each column is interpolated linearly
between the two samples around a grid time (the first or last sample beyond the ends). A
camera frame is not interpolated: the frame nearest the grid time is taken.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def grid_times(t0: float, fps: int, frames: int) -> np.ndarray:
    """Wall-clock times (s) of the first `frames` grid points."""
    return t0 + np.arange(frames, dtype=np.float64) / fps


def resample(times: Sequence[float] | np.ndarray, values: np.ndarray,
             at: np.ndarray) -> np.ndarray:
    """`values` (samples, n) measured at increasing `times`, linearly interpolated at `at`
    (frames,): (frames, n). NaN in a column (a value not known) stays NaN around it."""
    t = np.asarray(times, dtype=np.float64)
    v = np.asarray(values, dtype=np.float64)
    if len(t) == 0:
        raise ValueError("no samples to resample")
    out = np.empty((len(at), v.shape[1]), dtype=np.float64)
    for c in range(v.shape[1]):
        out[:, c] = np.interp(at, t, v[:, c])
    return out


def nearest(times: Sequence[float], at: float) -> int:
    """Index of the time nearest `at` in a non-empty sequence."""
    return int(np.argmin(np.abs(np.asarray(times, dtype=np.float64) - at)))
