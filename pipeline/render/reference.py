"""The reference of a frame and its standard error, by ``cfg.reference``:

- ``moments`` (the default): one ``mi.render`` launch a shutter time with the scene's integrator wrapped to
  add each sample's squared R, G, B (:func:`pipeline.render.launches.moment_integrator`), so each launch gives every pixel's mean
  and sample variance; the launches are strata of one estimator and the standard error is
  ``sqrt(sum(n_i var_i)) / N``. A static frame is one launch; a moving frame takes as many distinct
  shutter times as its motion needs (``pipeline.render.settings.reference_time_count``, at most
  ``ref_max_times``). With a filter other than the box, a launch of ``n`` samples a pixel counts as
  ``n`` times the filter's gain (``FrameScene.film_filter``): a filtered pixel averages the samples of
  its neighbours too.
- ``batch_means`` (stores made before ``reference`` existed resume with it): ``ref_passes`` passes, each
  ``mi.render`` at ``ref_time_slices`` times; the standard error is the batch-means estimate.

With ``ref_target_rel_stderr`` the reference stops once at least ``ref_min_passes`` passes' samples are
done and the image's relative standard error (:func:`rel_stderr`) is under the target.
"""
from __future__ import annotations

import math

import numpy as np

from pipeline.render.launches import MOMENT_CHANNELS, mi_render, moments_of, valid_moments
from pipeline.render.scene import FrameScene
from pipeline.render.settings import (LUMA, STREAM_REFERENCE, reference_times, stream_seed, time_rng,
                                      van_der_corput)

REL_STDERR_EPS = 0.01

def rel_stderr(mean: np.ndarray, stderr: np.ndarray) -> float:
    """Mean over pixels of ``stderr_Y / (mean_Y + 0.01)`` (Y: Rec. 709 luminance); HWC inputs."""
    y = np.abs(mean @ LUMA)
    e = stderr @ LUMA
    return float(np.mean(e / (y + REL_STDERR_EPS))) if y.size else 0.0


def render_reference(fs: FrameScene) -> dict:
    """The frame's reference: ``reference`` and ``reference_stderr`` (float64, HWC), ``reference_spp``
    (samples taken), ``reference_rel_stderr``, ``nonfinite_reference`` and ``ref_time_slices`` (distinct
    shutter times), by ``cfg.reference``."""
    cfg = fs.cfg
    W, H = cfg.res
    if cfg.ref_spp == 0:
        z = np.zeros((H, W, 3))
        return _reference(z, z.copy(), 0, 0, 1)
    if cfg.reference == "batch_means":
        return _reference_batch_means(fs)
    return _reference_moments(fs)


def _reference(mean, stderr, spp: int, bad: int, times: int) -> dict:
    return {"reference": mean, "reference_stderr": stderr, "reference_spp": int(spp),
            "reference_rel_stderr": rel_stderr(mean, stderr) if spp else 0.0, "nonfinite_reference": int(bad),
            "ref_time_slices": int(times)}




def _reference_moments(fs: FrameScene) -> dict:
    """``moments``: each launch renders one shutter time with the moment integrator, so every launch
    gives each pixel's mean and sample variance. The launches are strata of one estimator: the mean
    weighs each by its samples, and its variance is ``sum(n_i var_i) / N^2`` (``N`` samples in all), an
    unbiased estimate with ``N - launches`` degrees of freedom. A launch's NaN pixel is left out of that
    pixel (counted); ``+-Inf`` is clamped to ``max_value`` and its variance taken as ``max_value^2``.

    Without ``ref_target_rel_stderr`` the reference is one round: one launch a time. With it, a first
    round of ``ref_min_passes`` passes' samples, then rounds predicted from the measured error (it falls
    as 1/sqrt(samples)) until the target or ``ref_spp``; a stop lands on a whole number of passes."""
    cfg = fs.cfg
    W, H = cfg.res
    pass_spp = cfg.ref_spp // cfg.ref_passes
    T = fs.ref_time_slices
    times = reference_times(T) if fs.has_motion else np.zeros(1)
    gain = fs.film_filter.gain if fs.film_filter is not None else 1.0     # a filtered pixel's effective samples
    acc = {"A": np.zeros((H, W, 3)), "B": np.zeros((H, W, 3)), "N": np.zeros((H, W, 1)), "bad": 0}
    target = cfg.ref_target_rel_stderr
    done, want, rnd = 0, (cfg.ref_min_passes if target is not None else cfg.ref_passes), 0
    while True:
        n = (want - done) * pass_spp // T
        for k, t in enumerate(times):
            fs.set_time(float(t))
            img = mi_render(fs, n, stream_seed(fs.seed, fs.frame, STREAM_REFERENCE, rnd, k, offset=cfg.seed_offset),
                             integrator=moments_of(fs), channels=MOMENT_CHANNELS)
            _add_launch(acc, img, n * gain, cfg.max_value)
        done, rnd = want, rnd + 1
        if target is None or done >= cfg.ref_passes:
            break
        mean, err = _moment_stats(acc)
        rel = rel_stderr(mean, err)
        if rel <= target:
            break
        # the passes the measured error predicts, 5% over (the estimate itself is noisy), at least one more
        want = min(cfg.ref_passes, max(done + 1, math.ceil(done * (rel / target) ** 2 * 1.05)))
    mean, err = _moment_stats(acc)
    return _reference(mean, err, done * pass_spp, acc["bad"], T)


def _add_launch(acc: dict, img: np.ndarray, n: int, max_value: float) -> None:
    """Fold one launch (:func:`pipeline.render.launches.moment_integrator`'s channels of ``n`` effective samples a pixel: its samples
    times the filter's gain) into ``acc``: a pixel weighs as its samples that were not NaN (:func:`valid_moments`); a pixel whose mean is still
    not finite (an Inf sample, or Inf times 0) is left out if NaN, else clamped with variance
    ``max_value**2``. Pixels with any non-finite sample are counted."""
    m, q, f = valid_moments(img)
    nv = n * (1.0 - f)                          # the samples that count, per pixel
    nan = np.isnan(m).any(axis=-1, keepdims=True) | np.isnan(q).any(axis=-1, keepdims=True) | (nv <= 0)
    inf = ~nan & ~(np.isfinite(m).all(axis=-1, keepdims=True) & np.isfinite(q).all(axis=-1, keepdims=True))
    acc["bad"] += int(((f > 0) | ~np.isfinite(img[..., :6]).all(axis=-1, keepdims=True)).sum())
    m = np.where(nan, 0.0, np.clip(m, -max_value, max_value))
    var = np.where(nv > 1, np.maximum(np.where(nan | inf, 0.0, q) - m * m, 0.0) * nv / np.maximum(nv - 1, 1e-300), 0.0)
    var = np.where(inf, max_value * max_value, var)
    w = np.where(nan, 0.0, nv)
    acc["A"] += w * m
    acc["B"] += w * var
    acc["N"] += w


def _moment_stats(acc: dict) -> tuple[np.ndarray, np.ndarray]:
    N = acc["N"]
    has = N > 0
    Nn = np.where(has, N, 1.0)
    return np.where(has, acc["A"] / Nn, 0.0), np.where(has, np.sqrt(acc["B"]) / Nn, 0.0)


def _reference_batch_means(fs: FrameScene) -> dict:
    """``batch_means`` (stores made before ``reference`` existed resume with it): ``ref_passes`` passes,
    each of ``ref_time_slices`` times, consecutive blocks of a shifted van der Corput sequence; the error
    is the batch-means estimate from the pass means."""
    cfg = fs.cfg
    W, H = cfg.res
    passes = cfg.ref_passes
    pass_spp = cfg.ref_spp // passes
    k = fs.ref_time_slices
    shift = time_rng(fs.seed, fs.frame, cfg, STREAM_REFERENCE).random()
    times = np.minimum((van_der_corput(passes * k) + shift) % 1.0, np.nextafter(1.0, 0.0)).reshape(passes, k)
    cnt = np.zeros((H, W, 1))
    s1 = np.zeros((H, W, 3))
    s2 = np.zeros((H, W, 3))
    bad = 0
    done = 0
    mean = std = None
    for p in range(passes):
        img = 0.0
        for j in range(k):
            fs.set_time(float(times[p, j]) if fs.has_motion else 0.0)
            img = img + mi_render(fs, pass_spp // k, stream_seed(fs.seed, fs.frame, STREAM_REFERENCE, p, j,
                                                                  offset=cfg.seed_offset))
        img = img / k
        nan = np.isnan(img).any(axis=-1, keepdims=True)
        b = ~np.isfinite(img).all(axis=-1)
        bad += int(b.sum())
        img = np.where(nan, 0.0, np.clip(img, -cfg.max_value, cfg.max_value))
        ok = (~nan).astype(np.float64)
        cnt += ok
        s1 += img * ok
        s2 += img * img * ok
        done = p + 1
        if cfg.ref_target_rel_stderr is not None and done >= cfg.ref_min_passes and done < passes:
            mean, std = _batch_stats(cnt, s1, s2)
            if rel_stderr(mean, std) <= cfg.ref_target_rel_stderr:
                break
    mean, std = _batch_stats(cnt, s1, s2)
    return _reference(mean, std, done * pass_spp, bad, k * done if fs.has_motion else 1)


def _batch_stats(cnt, s1, s2):
    n = np.maximum(cnt, 1.0)
    mean = s1 / n
    var = np.maximum(s2 - n * mean * mean, 0.0) / np.maximum(cnt - 1.0, 1.0)
    stderr = np.where(cnt > 1, np.sqrt(var / n), 0.0)
    return mean, stderr
