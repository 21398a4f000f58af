"""LAYER_w: the layer-embedding denoiser with weighted compositing (eq. 6) instead of alpha blending.

Same networks as :mod:`.layer`; no ordering between layers and no occupancy buffer. Each layer's
filtered radiance is normalised by its filtered weight and the layers are averaged with the filtered
weights: o = sum_l w~^l (L~^l / w~^l) / sum_l w~^l = sum_l L~^l / sum_l w~^l (eq. 6 with the
normalised layer radiance).
"""
from __future__ import annotations

from .common import EPS
from .layer import LayerDenoiser
from .registry import register


@register("layer-w")
class LayerWeightedDenoiser(LayerDenoiser):
    compositing = "weighted"

    def composite(self, rad, weight, occ):
        return rad.sum(dim=1) / (weight.sum(dim=1) + EPS)
