"""Image quality metrics. numpy in, float out; images are (H, W, 3) float arrays, linear radiance.

relMSE and SMAPE are computed on linear radiance; PSNR and SSIM on tone-mapped values (eq. 7 of the
layer paper: sRGB(log(x+1))) with a peak of 1 and no clipping (as NVlabs/layerdenoise's ``PSNR``);
SSIM is scikit-image's ``structural_similarity`` with Wang et al.'s settings;
tPSNR is PSNR of temporal finite differences of tone-mapped clips (Hasselgren et al. 2020);
FLIP is HDR-FLIP from the ``flip-evaluator`` package on linear radiance.
"""
from __future__ import annotations

import numpy as np

from core.images import tonemap

RELMSE_EPS = 0.01
SMAPE_EPS = 0.01
SSIM_SIGMA = 1.5
SSIM_WINDOW = 11         # the Gaussian window scikit-image takes for sigma 1.5 (truncate 3.5 sigma, as Wang et al.)
SSIM_K1, SSIM_K2 = 0.01, 0.03

METRIC_NAMES = ("relmse", "smape", "psnr", "ssim", "flip")


def _pair(d, r):
    d = np.asarray(d, dtype=np.float64)
    r = np.asarray(r, dtype=np.float64)
    if d.shape != r.shape:
        raise ValueError(f"denoised {d.shape} and reference {r.shape} differ in shape")
    return d, r


def relmse(denoised, reference, eps: float = RELMSE_EPS) -> float:
    """Relative MSE: mean over pixels and channels of (d - r)^2 / (r^2 + eps), linear radiance."""
    d, r = _pair(denoised, reference)
    return float(np.mean((d - r) ** 2 / (r ** 2 + eps)))


def smape(denoised, reference, eps: float = SMAPE_EPS) -> float:
    """Eq. 9: mean |d - r| / (|d| + |r| + eps), linear radiance."""
    d, r = _pair(denoised, reference)
    return float(np.mean(np.abs(d - r) / (np.abs(d) + np.abs(r) + eps)))


def psnr_ldr(denoised, reference, peak: float = 1.0) -> float:
    """PSNR of two already display-referred images: 10 log10(peak^2 / MSE); inf for identical images."""
    d, r = _pair(denoised, reference)
    mse = float(np.mean((d - r) ** 2))
    return float("inf") if mse == 0.0 else float(10.0 * np.log10(peak ** 2 / mse))


def psnr(denoised, reference) -> float:
    """PSNR on tone-mapped values (eq. 7), peak 1."""
    d, r = _pair(denoised, reference)
    return psnr_ldr(tonemap(d), tonemap(r))


def ssim_ldr(denoised, reference, data_range: float = 1.0) -> float:
    """Mean SSIM (Wang et al. 2004: Gaussian 11x11 window, sigma 1.5, population covariances) over channels
    and valid pixels of two display-referred (H, W, C) or (H, W) images: scikit-image's
    ``structural_similarity``. Needs H, W >= 11."""
    from skimage.metrics import structural_similarity

    x, y = _pair(denoised, reference)
    if min(x.shape[0], x.shape[1]) < SSIM_WINDOW:
        raise ValueError(f"SSIM needs images of at least {SSIM_WINDOW} px, got {x.shape[:2]}")
    return float(structural_similarity(y, x, data_range=data_range, channel_axis=-1 if x.ndim == 3 else None,
                                       gaussian_weights=True, sigma=SSIM_SIGMA, use_sample_covariance=False,
                                       K1=SSIM_K1, K2=SSIM_K2))


def ssim(denoised, reference) -> float:
    """SSIM on tone-mapped values (eq. 7)."""
    d, r = _pair(denoised, reference)
    return ssim_ldr(tonemap(d), tonemap(r))


def tpsnr(denoised_clip, reference_clip) -> float:
    """Temporal PSNR of clips (T, H, W, 3), T >= 2: PSNR (peak 1) of the finite differences
    x_t - x_{t-1} of tone-mapped frames, over all t."""
    d, r = _pair(denoised_clip, reference_clip)
    if d.ndim != 4 or d.shape[0] < 2:
        raise ValueError(f"tPSNR needs clips (T>=2, H, W, C), got {d.shape}")
    td, tr = tonemap(d), tonemap(r)
    return psnr_ldr(np.diff(td, axis=0), np.diff(tr, axis=0))


def flip(denoised, reference) -> float:
    """Mean HDR-FLIP error (flip-evaluator) of linear radiance images (H, W, 3); lower is better."""
    import flip_evaluator

    d, r = _pair(denoised, reference)
    d = np.ascontiguousarray(np.maximum(np.nan_to_num(d, nan=0.0, posinf=0.0), 0.0), dtype=np.float32)
    r = np.ascontiguousarray(np.maximum(r, 0.0), dtype=np.float32)
    if not r.any():
        # HDR-FLIP takes its exposure range from the reference; a black one has none and flip-evaluator
        # ends the process ("Start exposure must be smaller than stop exposure!"). Black against black
        # is no error; otherwise the range comes from the test image.
        if not d.any():
            return 0.0
        _, _, params = flip_evaluator.evaluate(d, d, "HDR", inputsRGB=False, applyMagma=False)
        keep = {k: params[k] for k in ("startExposure", "stopExposure", "numExposures") if k in params}
        _, mean_error, _ = flip_evaluator.evaluate(r, d, "HDR", inputsRGB=False, applyMagma=False, parameters=keep)
        return float(mean_error)
    _, mean_error, _ = flip_evaluator.evaluate(r, d, "HDR", inputsRGB=False, applyMagma=False)
    return float(mean_error)


def mean_ratio(denoised, reference) -> float:
    """The image's mean radiance over the reference's (1 where a method keeps the frame's energy; a
    black reference: 1 for a black output, else its mean over 1e-8)."""
    d, r = float(np.mean(np.asarray(denoised, np.float64))), float(np.mean(np.asarray(reference, np.float64)))
    return 1.0 if r == 0.0 and d == 0.0 else d / max(r, 1e-8)


def all_metrics(denoised, reference, with_flip: bool = True) -> dict[str, float]:
    """relMSE, SMAPE, PSNR, SSIM, the mean ratio (and FLIP) of one frame (H, W, 3)."""
    out = {"relmse": relmse(denoised, reference), "smape": smape(denoised, reference),
           "psnr": psnr(denoised, reference), "ssim": ssim(denoised, reference),
           "mean_ratio": mean_ratio(denoised, reference)}
    if with_flip:
        out["flip"] = flip(denoised, reference)
    return out
