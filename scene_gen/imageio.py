"""Image files for scene previews: the project's images module (:mod:`scene_gen.images`: OpenEXR files,
PNG previews and the tone map; numpy only) under the names previews use.

Previews use the training tone map, fixed (no per-image auto exposure): ``exposure`` scale, then
``log(1 + x)`` (the layer paper's eq. 7) and the sRGB curve, or with ``mode="clamp"`` the sRGB curve
of the clipped value. ``tonemap`` here is that display form (:func:`scene_gen.images.display`, values in
[0, 1]); the unclipped eq. 7 is :func:`scene_gen.images.tonemap`.
"""
from __future__ import annotations

from scene_gen.images import display as tonemap
from scene_gen.images import read_exr, write_exr, write_png

__all__ = ["read_exr", "tonemap", "write_exr", "write_png"]
