"""SAMPLESPLAT: per-sample kernel-splatting denoiser (Munkberg & Hasselgren 2020, sec. 5, appendix B;
a scaled-down Gharbi et al. 2019).

Sample reducer (20 -> 32 -> 32 -> 32) per sample -> U-net (fig. 3) on the mean embedding -> 128
context features -> kernel generator ([160, 128], [128, 128], [128, 17*17]) once PER SAMPLE ->
exp(kernel - max over all samples' taps of the pixel) -> every sample splats its radiance and its
weight with its own kernel -> output = splatted radiance / splatted weight.

Vectorised: the per-sample contributions are reduced over samples with one einsum before one fold.
"""
from __future__ import annotations

import torch

from .common import EPS, KernelBaseline, clean_radiance, conv_fmas, exp_kernels, splat_columns
from .registry import register


@register("samplesplat")
class SampleSplatDenoiser(KernelBaseline):

    def sample_kernels(self, radiance, features):
        """Per-sample kernels (float32, B S k*k H W), max over (S, taps) subtracted before exp."""
        x = self.prepare_inputs(radiance, features)
        b, s, c, h, w = x.shape
        e = self.reducer(x.reshape(b * s, c, h, w)).view(b, s, self.embed, h, w)
        ctx, _ = self.unet(e.mean(dim=1))
        return exp_kernels(self.kernel_gen(e, ctx), dims=(1, 2))

    def denoise(self, radiance, features):
        kernels = self.sample_kernels(radiance, features)               # B S k2 H W
        lin = self.bound(clean_radiance(radiance))
        vals = torch.cat((lin, torch.ones_like(lin[:, :, :1])), dim=2)  # B S 4 H W
        b, s, k2, h, w = kernels.shape                                   # sum over samples before the fold:
        cols = torch.bmm(vals.permute(0, 3, 4, 2, 1).reshape(b * h * w, 4, s),      # one (4 x S) @ (S x k2)
                         kernels.permute(0, 3, 4, 1, 2).reshape(b * h * w, s, k2))  # product per pixel
        cols = cols.view(b, h, w, 4, k2).permute(0, 3, 4, 1, 2)
        f = splat_columns(cols, self.kernel_size)
        return f[:, :3] / (f[:, 3:4] + EPS)

    def fmas_per_pixel(self, spp: int) -> float:
        per_sample = conv_fmas(self.reducer) + 4 * self.kernel_size ** 2
        context = self.unet.cout
        return spp * per_sample + self.kernel_gen.fmas(spp, context) + self.unet.fmas_per_pixel()
