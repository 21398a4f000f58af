"""UNET: Intel Open Image Denoise's U-Net, written here and trained on this project's data, so that beside
OIDN's official weights what differs is the data and the training, not the architecture.

The network is OIDN's ``UNet`` (its ``training/model.py``, the default ``unet`` of its training toolkit):
3x3 convolutions with ReLU, an encoder of widths 32, 32 | 48 | 64 | 80 | 96, 96 with a 2x2 max pool after
the second, third, fourth and fifth, and a decoder that upsamples (nearest, 2x), concatenates the
encoder's pooled features of that scale (the input itself at full resolution) and convolves: 112, 112 |
96, 96 | 64, 64 | 64, 32 | 3. Its input is what OIDN's filter takes for an HDR colour with albedo and
normal (9 channels): the colour through OIDN's automatic exposure (0.18 over the geometric mean of the
image's luminance) and a log transfer, ``log1p`` (in place of OIDN's perceptually uniform curve, which
is also logarithmic over the HDR range), the albedo in [0, 1] and the normal mapped to [0, 1]. It predicts
the colour in that space, which is mapped back (``expm1``, then the exposure undone), clamped to
[0, the image's brightest input value of the channel] (so a black frame stays black: the network's biases
alone would paint it). An image whose size is not a multiple of 16 is padded (replicated edge) and the
output cropped.

``width`` scales every width (1: OIDN's; the tests' tiny model uses 1/4). Training (``train_defaults``):
L1 on the tone-mapped colour at lr 1e-3 (OIDN trains a mix of L1 and MS-SSIM on its transferred colour
with a one-cycle schedule peaking at 2e-4; here its per-pixel siblings' recipe).
"""
from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from core.checks import is_number, need

from ..errors import ConfigError
from ..inputs import InputSpec
from ._pixel import clean_albedo
from .common import Denoiser, clean_radiance, conv_fmas
from .registry import register

ENCODER = (32, 32, 48, 64, 80, 96, 96)       # enc_conv0, 1, 2, 3, 4, 5a, 5b
DECODER = (112, 112, 96, 96, 64, 64, 64, 32)  # dec_conv4a, 4b, 3a, 3b, 2a, 2b, 1a, 1b
ALIGN = 16                                    # four 2x2 pools
KEY = 0.18                                    # OIDN's autoexposure: the geometric mean's target
LUMA = (0.2126, 0.7152, 0.0722)


def autoexposure(radiance: torch.Tensor) -> torch.Tensor:
    """OIDN's exposure of each image (B 1 1 1): 0.18 over the geometric mean of its luminance (pixels of
    luminance at least 1e-8), 1 for a black image."""
    lum = sum(w * radiance[:, c] for c, w in enumerate(LUMA))
    ok = lum > 1e-8
    logs = torch.where(ok, torch.log(lum.clamp(min=1e-8)), torch.zeros_like(lum))
    n = ok.sum(dim=(1, 2)).clamp(min=1)
    gmean = torch.exp(logs.sum(dim=(1, 2)) / n)
    e = torch.where(ok.any(dim=(1, 2)), KEY / gmean, torch.ones_like(gmean))
    return e.clamp(1e-6, 1e6).view(-1, 1, 1, 1)


@register("unet")
class UNet(Denoiser):
    inputs = InputSpec("pixels", frames=1, default_spp=1)
    train_defaults = dict(loss="l1", lr=1e-3, grad_clip_norm=0.0, grad_clip_value=0.0, warmup=0)
    tiny = dict(width=0.25)

    def __init__(self, width: float = 1.0):
        need(is_number(width, finite=True) and 0.05 <= width <= 4.0, '"width"', "a number in [0.05, 4] (1: OIDN's)",
             width, ConfigError)
        super().__init__(width=float(width))
        e = [max(4, round(c * width)) for c in ENCODER]
        d = [max(4, round(c * width)) for c in DECODER]
        conv = lambda i, o: nn.Conv2d(i, o, 3, padding=1)   # noqa: E731
        self.enc = nn.ModuleList([conv(9, e[0]), conv(e[0], e[1]), conv(e[1], e[2]), conv(e[2], e[3]),
                                  conv(e[3], e[4]), conv(e[4], e[5]), conv(e[5], e[6])])
        self.dec = nn.ModuleList([conv(e[6] + e[3], d[0]), conv(d[0], d[1]), conv(d[1] + e[2], d[2]), conv(d[2], d[3]),
                                  conv(d[3] + e[1], d[4]), conv(d[4], d[5]), conv(d[5] + 9, d[6]), conv(d[6], d[7])])
        self.out = conv(d[7], 3)

    def declared_inputs(self) -> InputSpec:
        return type(self).inputs

    def network(self, x: torch.Tensor) -> torch.Tensor:
        """OIDN's U-Net on its 9 input channels (B 9 H W, H and W multiples of 16)."""
        e = self.enc
        y = F.relu(e[1](F.relu(e[0](x))))
        p1 = F.max_pool2d(y, 2)
        p2 = F.max_pool2d(F.relu(e[2](p1)), 2)
        p3 = F.max_pool2d(F.relu(e[3](p2)), 2)
        y = F.max_pool2d(F.relu(e[4](p3)), 2)
        y = F.relu(e[6](F.relu(e[5](y))))
        for i, skip in enumerate((p3, p2, p1, x)):
            y = torch.cat((F.interpolate(y, scale_factor=2, mode="nearest"), skip), dim=1)
            y = F.relu(self.dec[2 * i + 1](F.relu(self.dec[2 * i](y))))
        return self.out(y)

    def forward(self, batch: dict) -> torch.Tensor:
        rad = clean_radiance(batch["radiance"])
        if rad.dim() != 4 or rad.shape[1] != 3:
            raise ConfigError(f"radiance must be (B, 3, H, W), got {tuple(batch['radiance'].shape)}")
        exposure = autoexposure(rad)
        normal = torch.nan_to_num(batch["normal"], nan=0.0).clamp(-1.0, 1.0)
        x = torch.cat((torch.log1p(rad * exposure), clean_albedo(batch["albedo"]), (normal + 1.0) * 0.5), dim=1)
        h, w = x.shape[-2:]
        ph, pw = -h % ALIGN, -w % ALIGN
        if ph or pw:
            x = F.pad(x, (0, pw, 0, ph), mode="replicate")
        y = self.network(x)[..., :h, :w]
        out = torch.expm1(y.clamp(max=80.0)).clamp(min=0.0) / exposure
        return torch.minimum(out, rad.amax(dim=(2, 3), keepdim=True))

    def fmas_per_pixel(self, spp: int) -> float:
        # the convolutions at their resolution: level k runs at 1 / 4^k of the pixels
        e, d = self.enc, self.dec
        levels = [(e[0], 0), (e[1], 0), (e[2], 1), (e[3], 2), (e[4], 3), (e[5], 4), (e[6], 4), (d[0], 3), (d[1], 3),
                  (d[2], 2), (d[3], 2), (d[4], 1), (d[5], 1), (d[6], 0), (d[7], 0), (self.out, 0)]
        return spp * 3 + sum(conv_fmas(m) / 4 ** k for m, k in levels)
