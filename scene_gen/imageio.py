"""Image files for scene previews and probes: re-exported from :mod:`stores.imageio`, the one module
for OpenEXR files, PNG previews and the tone map (numpy only).

Previews use the training tone map, fixed (no per-image auto exposure): ``exposure`` scale, then
``log(1 + x)`` (the layer paper's eq. 7) and the sRGB curve, or with ``mode="clamp"`` the sRGB curve
of the clipped value. ``tonemap`` here is that display form (:func:`stores.imageio.display`, values in
[0, 1]); the unclipped eq. 7 is :func:`stores.imageio.tonemap`.
"""
from __future__ import annotations

from stores.imageio import display as tonemap
from stores.imageio import read_exr, write_exr, write_png

__all__ = ["read_exr", "tonemap", "write_exr", "write_png"]
