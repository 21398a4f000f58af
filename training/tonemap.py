"""The tone map of the layer-embedding paper (Munkberg & Hasselgren 2020, eqs. 7-8):
``x' = srgb(log(max(x, 0) + 1))``, on torch tensors and numpy arrays (element-wise).

One implementation serves training, the scene previews and the store exports: it lives in
:mod:`stores.imageio` (numpy only, imports nothing of ``training``); this module re-exports it for
the training code.
"""
from __future__ import annotations

from stores.imageio import SRGB_A, SRGB_THRESHOLD, srgb, tonemap

__all__ = ["SRGB_A", "SRGB_THRESHOLD", "srgb", "tonemap"]
