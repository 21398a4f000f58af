"""LAYER: the layer-embedding denoiser with alpha compositing (Munkberg & Hasselgren 2020, sec. 3,
eqs. 2-5, appendix A/B).

sample reducer (20 -> 32 -> 32 -> 32) per sample -> U-net (fig. 3) on the mean embedding -> 128 context
features -> sample partitioner ([160, 32], [32, 16], [16, layers]) + softmax / S per sample -> per-layer
sums w, n (occupancy), L, E (eq. 2) -> kernel generator ([160, 128], [128, 128], [128, 17*17]) per
layer -> exp(kernel - max) -> splat of (L, w, n) with each layer's kernel (eq. 3) -> normalise by
filtered occupancy (eq. 4) -> front-to-back alpha compositing (eq. 5).

Occupancy follows appendix A (and NVlabs/layerdenoise): a sample adds its weight for layer j to the
occupancy of every layer 0..j, i.e. n^l = sum_s sum_{k>=l} w^k_s (the samples that reach layer l).
Eq. 2 as printed (sum over k < l) would give n^0 = 0; with appendix A's form, kernel size 1 composites
to exactly the per-pixel mean (tested).
"""
from __future__ import annotations

import torch

from core.checks import need_int
from ..errors import ConfigError
from .common import (EPS, IN_FEATURES, PAPER_UNET, Denoiser, UNet, check_kernel_size, check_sigma,
                     clean_radiance, conv_fmas, exp_kernels, gaussian_kernel_bias, mlp, splat,
                     xavier_init)
from .registry import register
from .robust import OUTLIER_K

MAX_LAYERS = 5


@register("layer")
class LayerDenoiser(Denoiser):
    compositing = "alpha"
    outlier_bound = OUTLIER_K
    tiny = dict(embed=8, context=8, unet_encoder=((8,), (8,), (8,)), unet_bottleneck=(8,), unet_decoder=((8,), (8,), (8,)), kernel_size=5, partition_hidden=(8,), kernel_hidden=(8,))

    def __init__(self, layers: int = 2, kernel_size: int = 17, kernel_sigma: float = 2.0, embed: int = 32,
                 context: int = 128, partition_hidden=(32, 16), kernel_hidden=(128, 128),
                 unet_encoder=PAPER_UNET["unet_encoder"], unet_bottleneck=PAPER_UNET["unet_bottleneck"],
                 unet_decoder=PAPER_UNET["unet_decoder"]):
        need_int('"layers"', layers, 1, MAX_LAYERS, ConfigError, numpy=True)
        layers = int(layers)
        kernel_size = check_kernel_size(kernel_size)
        kernel_sigma = check_sigma(kernel_sigma)
        super().__init__(layers=layers, kernel_size=kernel_size, kernel_sigma=kernel_sigma, embed=embed,
                         context=context, partition_hidden=tuple(partition_hidden),
                         kernel_hidden=tuple(kernel_hidden),
                         unet_encoder=unet_encoder, unet_bottleneck=unet_bottleneck, unet_decoder=unet_decoder)
        self.layers, self.kernel_size, self.embed, self.context = layers, kernel_size, embed, context
        self.reducer = mlp(IN_FEATURES, (embed, embed), embed, last_act=True)
        self.unet = UNet(embed, context, unet_encoder, unet_bottleneck, unet_decoder)
        self.partitioner = mlp(context + embed, partition_hidden, layers)
        self.kernel_gen = mlp(context + embed, kernel_hidden, kernel_size * kernel_size)
        xavier_init(self)
        gaussian_kernel_bias(self.kernel_gen[-1], kernel_size, kernel_sigma)

    # -- stages ----------------------------------------------------------------------------------
    def embed_samples(self, radiance, features):
        """Sample embeddings E (BSeHW) and context C (B context HW)."""
        x = self.prepare_inputs(radiance, features)
        b, s, c, h, w = x.shape
        e = self.reducer(x.reshape(b * s, c, h, w)).view(b, s, self.embed, h, w)
        ctx, _ = self.unet(e.mean(dim=1))
        return e, ctx

    def partition(self, e, ctx):
        """Per-sample layer weights w (float32, BSLHW): softmax over layers, divided by S (eq. 1)."""
        logits = self.partitioner(e, ctx)                              # B S L H W
        return torch.softmax(logits, dim=2) / e.shape[1]

    def layer_kernels(self, layer_e, ctx):
        """Kernels (float32, B L k*k H W), exponentiated with the max over all layers' taps subtracted."""
        return exp_kernels(self.kernel_gen(layer_e, ctx), dims=(1, 2))

    def denoise(self, radiance, features):
        e, ctx = self.embed_samples(radiance, features)
        lin = self.bound(clean_radiance(radiance))
        w = self.partition(e, ctx)                                      # B S L H W
        b, s, nl, h, wd = w.shape
        l_rad = (w.unsqueeze(3) * lin.unsqueeze(2)).sum(dim=1)             # eq. 2, L^l
        l_w = w.sum(dim=1)                                              # w^l        (B L H W)
        l_e = (w.unsqueeze(3) * e.unsqueeze(2)).sum(dim=1)                  # E^l
        l_n = torch.flip(torch.cumsum(torch.flip(l_w, (1,)), dim=1), (1,))  # n^l = sum_{k>=l} w^k
        kernels = self.layer_kernels(l_e, ctx)                           # B L k2 H W
        stacked = torch.cat((l_rad, l_w.unsqueeze(2), l_n.unsqueeze(2)), dim=2)   # B L 5 H W
        f = splat(stacked.reshape(b * nl, 5, h, wd), kernels.reshape(b * nl, -1, h, wd), self.kernel_size)
        f = f.view(b, nl, 5, h, wd)                                     # eq. 3
        return self.composite(f[:, :, :3], f[:, :, 3:4], f[:, :, 4:5])

    def composite(self, rad, weight, occ):
        """Eqs. 4-5: L^ = rad / (occ + eps), alpha = weight / (occ + eps), front-to-back over layers.
        rad (B L 3 H W), weight and occ (B L 1 H W) -> (B 3 H W)."""
        n = occ + EPS
        lhat = rad / n
        alpha = torch.clamp(weight / n, 0.0, 1.0)
        trans = torch.cumprod(torch.cat((torch.ones_like(alpha[:, :1]), 1.0 - alpha[:, :-1]), dim=1), dim=1)
        return (trans * lhat).sum(dim=1)

    # -- cost ------------------------------------------------------------------------------------
    def fmas_per_pixel(self, spp: int) -> float:
        k2 = self.kernel_size ** 2
        # per sample: reducer, and splatting radiance (3) + embedding into every layer; the partitioner
        # and kernel generator see the context once per pixel (MLP's split first layer)
        per_sample = conv_fmas(self.reducer) + self.layers * (3 + self.embed)
        return spp * per_sample + self.partitioner.fmas(spp, self.context) + self.unet.fmas_per_pixel() \
            + self.kernel_gen.fmas(self.layers, self.context) + self.layers * 5 * k2   # + splat of (L, w, n)
