"""Images for stores, exports and training: the one tone map (the layer paper's eq. 7), its display
form, and OpenEXR / PNG files, re-exported from :mod:`scene_gen.images` (numpy only; see there).

``tonemap(x) = srgb(log(max(x, 0) + 1))`` on numpy arrays or torch tensors; :func:`display` /
:func:`to_srgb8` for screens and PNG previews; :func:`write_exr`, :func:`read_exr` and
:func:`read_exr_channels` for OpenEXR files.
"""
from __future__ import annotations

from scene_gen.images import (MODES, SRGB_A, SRGB_THRESHOLD, display, read_exr, read_exr_channels, srgb, to_srgb8,
                              tonemap, write_exr, write_png)

__all__ = ["MODES", "SRGB_A", "SRGB_THRESHOLD", "display", "read_exr", "read_exr_channels", "srgb", "to_srgb8",
           "tonemap", "write_exr", "write_png"]
