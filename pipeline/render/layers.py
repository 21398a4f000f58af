"""The sample layers of a frame: layer n is ``mi.render`` of 2^n independent samples (n < L), one seed
each, time-sliced as the frame's motion needs (``FrameScene.slices_for``)."""
from __future__ import annotations

import numpy as np

from pipeline.render.launches import MOMENT_CHANNELS, moments_of, render_sliced, sanitize_image, valid_moments
from pipeline.render.scene import FrameScene
from pipeline.render.settings import STREAM_LAYER


def render_layers(fs: FrameScene) -> tuple[np.ndarray, int]:
    """Sample layers (float32, LHWC): layer n is the mean of 2**n independent samples; non-finite count."""
    W, H = fs.cfg.res
    out = np.zeros((fs.cfg.layer_levels, H, W, 3), np.float32)
    # the reference's kernel (one compilation a scene for both); batch_means renders as it always did
    integrator = moments_of(fs) if fs.cfg.reference == "moments" and fs.cfg.ref_spp else None
    bad = 0
    for lvl in range(fs.cfg.layer_levels):
        img = render_sliced(fs, 2 ** lvl, STREAM_LAYER, lvl, integrator=integrator,
                            channels=MOMENT_CHANNELS if integrator else 3)
        nan = np.zeros(img.shape[:2], bool)
        if integrator is not None:          # the mean of the pixel's samples that were not NaN
            img, _, f = valid_moments(img)
            nan = f[..., 0] > 0
        bad += int((nan | ~np.isfinite(img).all(axis=-1)).sum())     # a NaN sample, or Inf in the mean
        out[lvl] = sanitize_image(img, fs.cfg.max_value)[0]
    return out, bad

