"""Confidence intervals for the figures a report compares: a bootstrap over frames, clips resampled whole.

Frames of one clip are not independent (the same scene, lights and camera, a few frames apart), so the
unit resampled is the clip: a still is a clip of one frame. An interval is the 2.5th and 97.5th
percentiles of the statistic over :data:`RESAMPLES` resamples of the clips with replacement; the
mean over a resample weighs each frame alike, as the reported mean does. The resamples come from a
fixed seed, so a report's intervals are reproducible.

* :func:`mean_ci`: the interval of a mean (``evaluate``'s ``ci95``).
* :func:`paired_difference`: the mean and interval of the per-frame difference between two methods
  evaluated on the same frames (a report's comparisons): the frames' shared difficulty cancels, so a
  difference far smaller than either method's interval can still be shown.

scipy.stats.bootstrap resamples single observations (or paired ones), not clusters of them, so the
cluster resampling is written here, vectorised: the clips' sums and frame counts are drawn, not frames.
"""
from __future__ import annotations

import numpy as np

RESAMPLES = 4000
LEVEL = 0.95
SEED = 0x5EED


def _by_group(values, groups) -> tuple[np.ndarray, np.ndarray]:
    """Per-group sums and frame counts of ``values`` (1-D), grouped by ``groups`` (same length)."""
    v = np.asarray(values, np.float64)
    _, inv = np.unique(np.asarray(groups), return_inverse=True)
    return np.bincount(inv, weights=v), np.bincount(inv).astype(np.float64)


def mean_ci(values, groups=None, resamples: int = RESAMPLES, level: float = LEVEL,
            seed: int = SEED) -> list[float] | None:
    """``[low, high]``: the ``level`` interval of the mean of ``values`` by a bootstrap over ``groups``
    (clip ids; None: every value its own). None when a value is not finite (the mean is not either) or
    there are fewer than two groups (one clip shows no spread between clips)."""
    v = np.asarray(values, np.float64).reshape(-1)
    if v.size == 0 or not np.isfinite(v).all():
        return None
    sums, counts = _by_group(v, np.arange(v.size) if groups is None else groups)
    if sums.size < 2:
        return None
    rng = np.random.default_rng(seed)
    pick = rng.integers(0, sums.size, size=(resamples, sums.size))
    means = sums[pick].sum(axis=1) / counts[pick].sum(axis=1)
    a = (1.0 - level) / 2.0
    lo, hi = np.quantile(means, [a, 1.0 - a])
    return [float(lo), float(hi)]


def paired_difference(a: dict, b: dict, groups: dict | None = None, **kw) -> dict | None:
    """The mean per-frame difference ``b - a`` over the frames both hold, with its interval.

    ``a``, ``b``: frame -> value; ``groups``: frame -> clip id (None: frames independent). Returns
    ``{"mean", "ci95": [low, high] or None, "frames", "shown"}`` (``shown``: there is an interval and it
    excludes 0), or None when the methods share no frame or a difference is not finite."""
    common = sorted(set(a) & set(b))
    d = np.array([b[f] - a[f] for f in common], np.float64)
    if not common or not np.isfinite(d).all():
        return None
    ci = mean_ci(d, None if groups is None else [groups[f] for f in common], **kw)
    return {"mean": float(d.mean()), "ci95": ci, "frames": len(common),
            "shown": ci is not None and not ci[0] <= 0.0 <= ci[1]}


__all__ = ["mean_ci", "paired_difference", "RESAMPLES", "LEVEL"]
