"""Per-episode and whole-dataset statistics of the features, as lerobot computes them.

From huggingface/lerobot `src/lerobot/datasets/compute_stats.py`: each numeric feature gets
`min`, `max`, `mean`, `std`, `count` and the quantiles `q01`, `q10`, `q50`, `q90`, `q99`
(`DEFAULT_QUANTILES`) over the episode's frames, per dimension; an image feature gets them per
channel, shape (3, 1, 1), over sampled frames scaled to [0, 1]. The dataset's stats
(`meta/stats.json`) aggregate the episodes' (`aggregate_feature_stats`): counts summed, means
weighted, variances pooled, lower quantiles the smallest and upper ones the largest.
"""

from __future__ import annotations

from typing import Any

import numpy as np

QUANTILES = (0.01, 0.10, 0.50, 0.90, 0.99)
Stats = dict[str, np.ndarray]


def _qname(q: float) -> str:
    return f"q{round(q * 100):02d}"


def feature_stats(values: np.ndarray) -> Stats:
    """Stats of a numeric feature over its frames: `values` (frames,) or (frames, n)."""
    v = np.asarray(values, dtype=np.float64)
    keep = v.ndim == 1
    out: Stats = {
        "min": np.min(v, axis=0, keepdims=keep),
        "max": np.max(v, axis=0, keepdims=keep),
        "mean": np.mean(v, axis=0, keepdims=keep),
        "std": np.std(v, axis=0, keepdims=keep),
        "count": np.array([len(v)]),
    }
    for q in QUANTILES:
        out[_qname(q)] = np.quantile(v, q, axis=0, keepdims=keep)
    return out


def image_stats(images: np.ndarray) -> Stats:
    """Stats of sampled RGB frames (k, H, W, 3) uint8: per channel, shape (3, 1, 1), in [0, 1];
    `count` is the number of frames sampled (lerobot's `sample_images` then
    `get_feature_stats(axis=(0, 2, 3))`)."""
    x = np.asarray(images, dtype=np.float64) / 255.0
    chans = np.moveaxis(x, -1, 0).reshape(x.shape[-1], -1)  # (3, pixels)
    out: Stats = {
        "min": chans.min(axis=1), "max": chans.max(axis=1), "mean": chans.mean(axis=1),
        "std": chans.std(axis=1),
    }
    for q in QUANTILES:
        out[_qname(q)] = np.quantile(chans, q, axis=1)
    shaped = {k: v.reshape(-1, 1, 1) for k, v in out.items()}
    shaped["count"] = np.array([len(images)])
    return shaped


def aggregate(stats: list[Stats]) -> Stats:
    """One feature's stats over several episodes (lerobot's `aggregate_feature_stats`)."""
    means = np.stack([s["mean"] for s in stats])
    variances = np.stack([s["std"] ** 2 for s in stats])
    counts = np.stack([s["count"] for s in stats]).astype(np.float64)
    total = counts.sum(axis=0)
    while counts.ndim < means.ndim:
        counts = np.expand_dims(counts, axis=-1)
    mean = (means * counts).sum(axis=0) / total
    var = ((variances + (means - mean) ** 2) * counts).sum(axis=0) / total
    out: Stats = {
        "min": np.min(np.stack([s["min"] for s in stats]), axis=0),
        "max": np.max(np.stack([s["max"] for s in stats]), axis=0),
        "mean": mean, "std": np.sqrt(var),
        "count": np.stack([s["count"] for s in stats]).sum(axis=0),
    }
    for q in QUANTILES:
        key = _qname(q)
        if all(key in s for s in stats):
            vals = np.stack([s[key] for s in stats])
            out[key] = vals.min(axis=0) if q <= 0.5 else vals.max(axis=0)
    return out


def to_json(stats: dict[str, Stats]) -> dict[str, dict[str, Any]]:
    return {f: {k: v.tolist() for k, v in st.items()} for f, st in stats.items()}


def from_json(raw: dict[str, dict[str, Any]]) -> dict[str, Stats]:
    return {f: {k: np.atleast_1d(np.array(v)) for k, v in st.items()} for f, st in raw.items()}
