"""Tone mapping of the layer-embedding paper (Munkberg & Hasselgren 2020, eqs. 7-8).

``x' = srgb(log(x + 1))`` with the sRGB transfer function. Works on torch tensors and numpy arrays
of any layout (element-wise). Negative radiance is clamped to 0 first (radiance is non-negative;
the clamp keeps ``log`` defined for slightly negative denoiser outputs).
"""
from __future__ import annotations

import numpy as np
import torch

SRGB_A = 0.055
SRGB_THRESHOLD = 0.0031308


def srgb(x):
    """sRGB transfer function Gamma (eq. 8), element-wise; x >= 0."""
    if isinstance(x, torch.Tensor):
        # clamp inside pow so the unused branch has a finite gradient at 0
        hi = (1.0 + SRGB_A) * torch.pow(torch.clamp(x, min=SRGB_THRESHOLD), 1.0 / 2.4) - SRGB_A
        return torch.where(x > SRGB_THRESHOLD, hi, 12.92 * x)
    x = np.asarray(x)
    hi = (1.0 + SRGB_A) * np.power(np.maximum(x, SRGB_THRESHOLD), 1.0 / 2.4) - SRGB_A
    return np.where(x > SRGB_THRESHOLD, hi, 12.92 * x)


def tonemap(x):
    """Eq. 7: ``srgb(log(max(x, 0) + 1))``. Radiance (float32, any layout) -> tone-mapped, same layout."""
    if isinstance(x, torch.Tensor):
        return srgb(torch.log1p(torch.clamp(x, min=0.0)))
    x = np.asarray(x)
    return srgb(np.log1p(np.maximum(x, 0.0)))
