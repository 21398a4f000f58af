"""PIXELGATHER: per-pixel kernel-predicting denoiser (Munkberg & Hasselgren 2020, sec. 5, appendix B;
after Bako et al. 2017 / Gharbi et al. 2019's PixelGather, without albedo demodulation).

Per-pixel mean and variance (over samples) of the 20 normalised inputs -> pixel reducer
([40, 32], [32, 32], [32, 32]) -> U-net (fig. 3) -> 128 context features -> kernel generator
([160, 128], [128, 128], [128, 17*17]) once per pixel -> exp(kernel - max) -> gather on the per-pixel
mean radiance, normalised by the gathered kernel weights.
"""
from __future__ import annotations

import torch

from .common import EPS, IN_FEATURES, KernelBaseline, clean_radiance, conv_fmas, exp_kernels, gather
from .registry import register


@register("pixelgather")
class PixelGatherDenoiser(KernelBaseline):
    reducer_inputs = 2 * IN_FEATURES                    # the per-pixel mean and variance of each input

    def pixel_kernels(self, radiance, features):
        """Per-pixel kernels (float32, B k*k H W), exponentiated with the per-pixel max subtracted."""
        x = self.prepare_inputs(radiance, features)
        mean = x.mean(dim=1)
        var = (x - mean.unsqueeze(1)).square().mean(dim=1)              # 20x faster than Tensor.var(dim=1)
        stats = torch.cat((mean, var), dim=1)
        e = self.reducer(stats)
        ctx, _ = self.unet(e)
        return exp_kernels(self.kernel_gen(torch.cat((e, ctx), dim=1)), dims=1)

    def denoise(self, radiance, features):
        kernels = self.pixel_kernels(radiance, features)
        mean = self.bound(clean_radiance(radiance)).mean(dim=1)
        ones = torch.ones_like(mean[:, :1])
        f = gather(torch.cat((mean, ones), dim=1), kernels, self.kernel_size)
        return f[:, :3] / (f[:, 3:4] + EPS)

    def fmas_per_pixel(self, spp: int) -> float:
        # mean and variance of the inputs are additions/multiplies per sample (2 * 20), then per pixel
        return spp * 2 * IN_FEATURES + conv_fmas(self.reducer) + self.unet.fmas_per_pixel() \
            + conv_fmas(self.kernel_gen) + 4 * self.kernel_size ** 2
