"""OPTIMIZED: the interactive layer denoiser (Munkberg & Hasselgren 2020, sec. 6, fig. 9, eq. 10).

Differences from :mod:`.layer`:
- hierarchical kernel prediction: instead of one 17x17 kernel per pixel and layer, a 5x5 kernel per
  layer on three scales (full, 1/2, 1/4); layer radiance, weight, occupancy and embeddings are
  2x2/4x4 average-pooled, and the kernel generator of scale i sees the pooled layer embedding and the
  U-net decoder output at that resolution (fig. 9);
- every scale is filtered and alpha-composited to completion, giving a normalised global mip level
  G_i; the output is sum_i Upscale(G_i, 2^i) * lambda_i (eq. 10), where the lambda_i come from an
  extra output channel of the kernel generator of the first layer (normalised with a softmax over the
  three scales so the result stays a convex combination);
- reduced widths: kernel generators 32 features throughout ([32 + c_i, 32], [32, 32], [32, 5*5 + 1]);
  U-net encoder's first two convolutions 32 features, the decoder's last four 64 features, and 64
  context features (the paper does not give this last count; 64 matches the decoder's last width).
"""
from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from core.checks import need_int
from ..errors import ConfigError
from .common import (IN_FEATURES, Denoiser, UNet, check_kernel_size, check_sigma, clean_radiance, conv_fmas,
                     exp_kernels, gaussian_kernel_bias, mlp, replicate_pad, splat, xavier_init)
from .layer import MAX_LAYERS, LayerDenoiser
from .registry import register
from .robust import OUTLIER_K

OPT_UNET = dict(
    unet_encoder=((32, 32), (128,), (256,), (512,), (512,)),
    unet_bottleneck=(512,),
    unet_decoder=((512, 512), (256, 256), (128, 128), (64, 64), (64, 64)),
)


@register("layer-optimized")
class LayerOptimizedDenoiser(Denoiser):
    outlier_bound = OUTLIER_K
    tiny = dict(embed=8, context=8, unet_encoder=((8,), (8,), (8,)), unet_bottleneck=(8,), unet_decoder=((8,), (8,), (8,)), kernel_size=3, partition_hidden=(8,), kernel_hidden=(8,))

    def __init__(self, layers: int = 2, kernel_size: int = 5, kernel_sigma: float = 1.0, levels: int = 3,
                 embed: int = 32, context: int = 64,
                 partition_hidden=(32, 16), kernel_hidden=(32, 32), unet_encoder=OPT_UNET["unet_encoder"],
                 unet_bottleneck=OPT_UNET["unet_bottleneck"], unet_decoder=OPT_UNET["unet_decoder"]):
        need_int('"layers"', layers, 1, MAX_LAYERS, ConfigError, numpy=True)
        need_int('"levels" (at most the U-net\'s depth)', levels, 1, len(unet_decoder), ConfigError, numpy=True)
        layers, levels = int(layers), int(levels)
        kernel_size = check_kernel_size(kernel_size)
        kernel_sigma = check_sigma(kernel_sigma)
        super().__init__(layers=layers, kernel_size=kernel_size, kernel_sigma=kernel_sigma, levels=levels,
                         embed=embed, context=context,
                         partition_hidden=tuple(partition_hidden), kernel_hidden=tuple(kernel_hidden),
                         unet_encoder=unet_encoder, unet_bottleneck=unet_bottleneck, unet_decoder=unet_decoder)
        self.layers, self.kernel_size, self.levels, self.embed = layers, kernel_size, levels, embed
        self.reducer = mlp(IN_FEATURES, (embed, embed), embed, last_act=True)
        self.unet = UNet(embed, context, unet_encoder, unet_bottleneck, unet_decoder)
        self.partitioner = mlp(context + embed, partition_hidden, layers)
        k2 = kernel_size * kernel_size
        chans = [context] + [self.unet.decoder_channels(i) for i in range(1, levels)]
        # one extra output: the scale weight lambda_i, read from the first layer only (eq. 10)
        self.kernel_gens = nn.ModuleList(mlp(embed + c, kernel_hidden, k2 + 1) for c in chans)
        xavier_init(self)
        for g in self.kernel_gens:                                      # each scale starts as a Gaussian
            gaussian_kernel_bias(g[-1], kernel_size, kernel_sigma)

    embed_samples = LayerDenoiser.embed_samples
    composite = LayerDenoiser.composite

    def partition(self, e, ctx):
        return LayerDenoiser.partition(self, e, ctx)

    def denoise(self, radiance, features):
        x = self.prepare_inputs(radiance, features)
        b, s, c, h, w = x.shape
        e = self.reducer(x.reshape(b * s, c, h, w)).view(b, s, self.embed, h, w)
        ctx, decoder = self.unet(e.mean(dim=1))
        lin = self.bound(clean_radiance(radiance))
        wts = self.partition(e, ctx)                                    # B S L H W
        nl = self.layers
        l_rad = (wts.unsqueeze(3) * lin.unsqueeze(2)).sum(dim=1)
        l_w = wts.sum(dim=1)
        l_e = (wts.unsqueeze(3) * e.unsqueeze(2)).sum(dim=1)
        l_n = torch.flip(torch.cumsum(torch.flip(l_w, (1,)), dim=1), (1,))
        data = torch.cat((l_rad, l_w.unsqueeze(2), l_n.unsqueeze(2), l_e), dim=2)
        data = data.reshape(b, nl * (5 + self.embed), h, w)
        m = 2 ** (self.levels - 1)
        ph, pw = (-h) % m, (-w) % m
        data = F.pad(data, (0, pw, 0, ph))                              # padded pixels hold no samples
        hp, wp = h + ph, w + pw
        guides = [ctx] + [decoder[i] for i in range(1, self.levels)]
        mips, lambdas = [], []
        for i in range(self.levels):                                    # three scales (not pixels/samples)
            d = F.avg_pool2d(data, 2 ** i) if i else data
            hi, wi = d.shape[-2:]
            g = guides[i]
            g = replicate_pad(g, (0, wi - g.shape[-1], 0, hi - g.shape[-2]))
            d = d.view(b, nl, 5 + self.embed, hi, wi)
            out = self.kernel_gens[i](d[:, :, 5:], g)                    # B L k2+1 hi wi
            lambdas.append(out[:, 0, -1:])                               # first layer's extra channel
            kernels = exp_kernels(out[:, :, :-1], dims=(1, 2))
            f = splat(d[:, :, :5].reshape(b * nl, 5, hi, wi), kernels.reshape(b * nl, -1, hi, wi), self.kernel_size)
            f = f.view(b, nl, 5, hi, wi)
            g_i = self.composite(f[:, :, :3], f[:, :, 3:4], f[:, :, 4:5])
            if i:
                g_i = F.interpolate(g_i, size=(hp, wp), mode="bilinear", align_corners=False)
                lambdas[-1] = F.interpolate(lambdas[-1], size=(hp, wp), mode="bilinear", align_corners=False)
            mips.append(g_i)
        lam = torch.softmax(torch.cat(lambdas, dim=1), dim=1)           # B levels H W
        outp = (torch.stack(mips, dim=1) * lam.unsqueeze(2)).sum(dim=1)
        return outp[..., :h, :w]

    def fmas_per_pixel(self, spp: int) -> float:
        k2 = self.kernel_size ** 2
        per_sample = conv_fmas(self.reducer) + self.layers * (3 + self.embed)
        context = self.unet.cout
        filters = sum((g.fmas(self.layers, g[0].in_channels - self.embed) + self.layers * 5 * k2) / 4 ** i
                      for i, g in enumerate(self.kernel_gens))
        return spp * per_sample + self.partitioner.fmas(spp, context) + self.unet.fmas_per_pixel() + filters
