"""Confidence intervals (training.stats): a bootstrap over clips, and paired differences between methods."""
from __future__ import annotations

import numpy as np
import pytest

from training import stats


def test_the_interval_holds_the_mean_and_narrows_with_more_clips():
    rng = np.random.default_rng(0)
    small = rng.normal(1.0, 0.5, 16)
    large = rng.normal(1.0, 0.5, 400)
    lo, hi = stats.mean_ci(small)
    assert lo < small.mean() < hi
    lo2, hi2 = stats.mean_ci(large)
    assert hi2 - lo2 < (hi - lo) / 3                       # ~ 1/sqrt(n): 5x narrower for 25x the values
    # near the normal interval of a mean (1.96 standard errors) for independent values
    se = large.std(ddof=1) / np.sqrt(large.size)
    assert hi2 - lo2 == pytest.approx(2 * 1.96 * se, rel=0.15)
    assert stats.mean_ci(small) == stats.mean_ci(small)     # a fixed seed: reproducible


def test_frames_of_a_clip_are_resampled_together():
    """Ten clips of eight identical frames carry the information of ten values, not eighty."""
    rng = np.random.default_rng(1)
    per_clip = rng.normal(0.0, 1.0, 10)
    values = np.repeat(per_clip, 8)
    clips = np.repeat(np.arange(10), 8)
    as_clips = stats.mean_ci(values, clips)
    as_frames = stats.mean_ci(values)
    assert as_clips == pytest.approx(stats.mean_ci(per_clip), abs=0.05)
    assert (as_clips[1] - as_clips[0]) > 2 * (as_frames[1] - as_frames[0])


def test_no_interval_from_one_clip_or_non_finite_values():
    assert stats.mean_ci([1.0, 2.0, 3.0], [7, 7, 7]) is None
    assert stats.mean_ci([1.0, float("inf")]) is None
    assert stats.mean_ci([]) is None


def test_a_paired_difference_is_shown_only_when_its_interval_excludes_zero():
    rng = np.random.default_rng(2)
    hard = rng.exponential(1.0, 40)                          # frames differ far more than the methods do
    a = {i: float(v) for i, v in enumerate(hard)}
    b = {i: float(v) - 0.01 for i, v in enumerate(hard)}    # b better by exactly 0.01 on every frame
    d = stats.paired_difference(a, b)
    assert d["mean"] == pytest.approx(-0.01) and d["shown"] and d["ci95"][1] < 0 and d["frames"] == 40
    noise = {i: float(v) + float(e) for (i, v), e in zip(a.items(), rng.normal(0, 0.05, 40))}
    n = stats.paired_difference(a, noise)
    assert not n["shown"] and n["ci95"][0] <= 0 <= n["ci95"][1]
    # unpaired, the two methods' own intervals overlap almost entirely
    lo_a, hi_a = stats.mean_ci(list(a.values()))
    assert hi_a - lo_a > 20 * (d["ci95"][1] - d["ci95"][0])
    assert stats.paired_difference(a, {100: 1.0}) is None   # no shared frame


def test_the_report_says_when_an_interval_cannot_be_known():
    """Frames of one clip give no interval; the report says so rather than "no difference shown"."""
    from training.report import difference_cell as _difference_cell
    a = {i: 0.1 for i in range(8)}
    b = {i: 0.05 for i in range(8)}
    one_clip = stats.paired_difference(a, b, {i: 0 for i in range(8)})
    assert one_clip["ci95"] is None and not one_clip["shown"]
    assert _difference_cell(one_clip, "{:+.4f}", -1) == "-0.0500 no interval (one clip)"
    rng = np.random.default_rng(0)
    c = {i: 0.05 + 0.001 * rng.standard_normal() for i in range(8)}
    clips = stats.paired_difference(a, c, {i: i // 2 for i in range(8)})
    assert clips["shown"] and _difference_cell(clips, "{:+.4f}", -1).endswith(" better")
    level = stats.paired_difference(a, a, {i: i // 2 for i in range(8)})
    assert _difference_cell(level, "{:+.4f}", -1).endswith("no difference shown")
