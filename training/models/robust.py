"""Outlier bounds: what a kernel-predicting denoiser may spread to its neighbours (every model's filter input).

A kernel, a bilateral grid or a partitioning pyramid outputs convex combinations of its input, so one
very bright value (a firefly sample, the sun's pixel, a lamp, a caustic path, or the irradiance of a
black-albedo pixel demodulated by a small offset) reaches every pixel whose kernel covers it, in
proportion to its value: a 2e4 sample under a 13x13 kernel raises 169 pixels by 118 where the reference
may be 0.1 (relMSE ~1e6 each). On the hard-case suite that is what took nbg, wskpn, pixelgather and
layer-optimized to relMSE 20-66,500 where their noisy input was at 0.1-2.3 (docs/hard-cases.md).

So each model bounds the values its filter sees, per pixel, by the pixel's neighbourhood:

    level(p) = exp(mean_{q in W(p), q != p} log(1 + lum(q))) - 1      (W: the 5x5 window; pixel means)
    bound(p) = k * level(p) + floor

and every value of pixel ``p`` (each sample of a per-sample model, the pixel of a per-pixel one) whose
luminance exceeds ``bound(p)`` is scaled down to it, hue kept (:func:`bound_outliers`). The level leaves
the pixel out and is a geometric mean of its neighbours, which one outlier among them raises by a factor
of at most ``(1 + V)^(1/24)``, so a value's bound never follows the value. Whatever a filter makes of the
bounded values, what it carries to a pixel is at most about ``k`` times the level around its source; the
cut energy is dropped, not filtered, so the output underestimates the few true small emitters (the sun's
disc, a lamp): their relMSE is then at most about 1 a pixel, where spreading cost up to 1e6 a pixel.

**Lights stay where they are** (the per-pixel models' setting ``keep_lights``, on by default since issue 55):
a value cut at a pixel of which at least :data:`BLOB` of the 8 neighbours are cut too is a light seen
directly (a lamp, the sun's disc: several pixels above their neighbourhood), not a firefly (one pixel):
its excess over the bound is added back to the output at that pixel, unfiltered
(:func:`light_excess`), so the filter still never spreads it and the image keeps the light's energy.
On the real-scene suite's ``metals`` (two tiny lamps of radiance 5,000-8,000 in view) nbg and wskpn
kept 26-29% of the image's mean without it (docs/real-scenes.md). An isolated cut value is dropped as
before.

``k`` (the model setting ``outliers``; 0 turns the bound off) was chosen by measurement on the held-out
hard-case suite and ordinary frames (docs/hard-cases.md): 16 kept nbg and wskpn below their input on the
sun where 64 did not always; the floor keeps values below 1 (dim frames) from ever being cut. A checkpoint
written before the setting existed builds with ``outliers: 0`` (``legacy_config``), as it was trained.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from core.checks import is_number, need

from ..errors import ConfigError

OUTLIER_K = 16.0        # bound: this many times the neighbourhood's level ...
BLOB = 2                # a cut pixel with at least this many cut neighbours (of 8) is a light: kept (light_excess)
OUTLIER_FLOOR = 1.0     # ... plus this (radiance units: values below it are never cut)
WINDOW = 5              # the neighbourhood, centre excluded
LUMA = (0.2126, 0.7152, 0.0722)


def check_outliers(k) -> float:
    """The ``outliers`` setting: 0 (off) or a factor >= 1."""
    need(is_number(k, finite=True) and (k == 0 or k >= 1), '"outliers"', "0 (off) or a factor >= 1 of the "
         "neighbourhood's level", k, ConfigError)
    return float(k)


def luminance(x: torch.Tensor, dim: int) -> torch.Tensor:
    """Rec. 709 luminance of non-negative radiance ``x`` along its channel axis ``dim`` (kept, size 1)."""
    # the weights as Python numbers (kernel arguments): a tensor made from them at every call was a
    # host-to-device copy each time on a GPU
    return x.narrow(dim, 0, 1) * LUMA[0] + x.narrow(dim, 1, 1) * LUMA[1] + x.narrow(dim, 2, 1) * LUMA[2]


def neighbourhood_level(lum: torch.Tensor) -> torch.Tensor:
    """``level`` of the module docstring for pixel luminance ``lum`` (B 1 H W, >= 0): the geometric mean
    of ``1 + lum`` over the 5x5 window without its centre (and without pixels outside the frame), minus 1."""
    log = torch.log1p(lum)
    r = WINDOW // 2
    area = WINDOW * WINDOW
    total = F.avg_pool2d(log, WINDOW, stride=1, padding=r, count_include_pad=True) * area
    count = F.avg_pool2d(torch.ones_like(log), WINDOW, stride=1, padding=r, count_include_pad=True) * area
    return torch.expm1((total - log) / (count - 1.0).clamp(min=1.0))


def bound_outliers(radiance: torch.Tensor, k: float, floor: float = OUTLIER_FLOOR) -> torch.Tensor:
    """``radiance`` (non-negative, linear; B 3 H W per pixel or B S 3 H W per sample) with every value whose
    luminance exceeds its pixel's bound scaled down to it (module docstring); unchanged where ``k`` is 0.
    The bound is data, not a function of the weights: no gradient flows through it."""
    if not k:
        return radiance
    per_sample = radiance.dim() == 5
    cdim = 2 if per_sample else 1
    with torch.no_grad():
        lum = luminance(radiance, cdim)                                     # B [S] 1 H W
        pixel = lum.mean(dim=1) if per_sample else lum                      # B 1 H W
        bound = k * neighbourhood_level(pixel) + floor
        if per_sample:
            bound = bound.unsqueeze(1)
        scale = torch.where(lum > bound, bound / lum.clamp(min=1e-30), torch.ones_like(lum))
    return radiance * scale


def light_excess(radiance: torch.Tensor, bounded: torch.Tensor) -> torch.Tensor:
    """What :func:`bound_outliers` cut from per-pixel ``radiance`` (B 3 H W) where it is a light seen directly:
    the excess ``radiance - bounded`` of each cut pixel with at least :data:`BLOB` cut neighbours among its 8
    (module docstring), 0 elsewhere. Added to a model's output it puts the light's energy back at its
    pixels, unfiltered. Data, not a function of the weights: no gradient flows through it."""
    with torch.no_grad():
        excess = (radiance - bounded).clamp(min=0.0)
        cut = (luminance(excess, 1) > 0).to(radiance.dtype)
        neighbours = F.avg_pool2d(cut, 3, stride=1, padding=1, count_include_pad=True) * 9.0 - cut
        keep = (cut > 0) & (neighbours >= BLOB - 0.5)
    return excess * keep.to(radiance.dtype)
