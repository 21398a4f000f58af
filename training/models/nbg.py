"""NBG: the neural bilateral grid denoiser (Meng et al. 2020), for 1-spp real-time denoising.

GuideNet (sec. 4.1, fig. 2 left; widths of the authors' code): 5x5 conv 10 -> 20, ReLU, 5x5 conv
20 -> 5, sigmoid; ``guide_hidden`` sets the depth and widths. Its 5 outputs are 3 guides (one per
scale, times ``guide_range`` = 255) and 2 blend weights. Each scale s splats the demodulated HDR
irradiance into a bilateral grid with sampling rates (eta, eta, eta) = ``rates[s]`` (4, 8, 16; eq. 8:
ceil(h/eta) x ceil(w/eta) x ceil(255/eta) cells, plus the far corner), using the tent filter of eq. 9
(trilinear weights) and normalising each cell by its weight sum (eq. 10); slicing reads the grid at the
same guide position, trilinearly, renormalised over the non-empty corners (eq. 13). The scales are
blended by eq. 15, ``w0 R0 + w1 R1 + (1 - w0 - w1) R2`` (the papers' form: the last weight is not
clamped), and the albedo is multiplied back.

A cell is **empty** when its weight sum is zero (no pixel splatted into it), not when its value is zero:
a black cell that received weight is a valid, black cell.

Pure PyTorch: splatting is a ``scatter_add`` of the 8 trilinear corners of every pixel per channel,
slicing a gather at the same indices; no loop over pixels, differentiable end to end (the guide's gradient flows
through the tent weights, whose ``|a|`` is smoothed to ``sqrt(a^2 + 1e-7)`` along the guide axis as in
sec. 4.2; the spatial weights are constants, so they keep the exact tent).

Departures (docs/training.md): PyTorch's default initialisation instead of U(-1, 1) (with 250-wide
fan-in, U(-1, 1) saturates the sigmoid at the first step); no outlier suppression (the papers use it
only on their 64-spp Tungsten set; it changes the energy of the image).
"""
from __future__ import annotations

import torch
import torch.nn as nn

from core.checks import need

from ..errors import ConfigError
from ._pixel import ALBEDO_OFFSET, PixelDenoiser
from .common import conv_fmas
from .registry import register

TENT_EPS = 1e-7           # sec. 4.2: |a| -> sqrt(a^2 + eps) in the tent filter


def grid_shape(h: int, w: int, rate: int, guide_range: float) -> tuple[int, int, int]:
    """(D, Hg, Wg): cells along the guide, y and x for an ``h x w`` image at sampling rate ``rate``;
    positions ``m / rate`` and ``guide / rate`` and their upper trilinear corner all fit."""
    return int(guide_range // rate) + 2, (h - 1) // rate + 2, (w - 1) // rate + 2


def corners(guide: torch.Tensor, rate: int, guide_range: float):
    """Trilinear corners of every pixel in its bilateral grid.

    ``guide (float32, B H W)`` in [0, guide_range]. Returns ``index (int64, 8, B, H, W)`` into the
    flattened grid ``(B, D, Hg, Wg)``, ``weight (float32, 8, B, H, W)`` (tent weights, eq. 9/11) and
    the grid shape ``(D, Hg, Wg)``."""
    b, h, w = guide.shape
    D, Hg, Wg = grid_shape(h, w, rate, guide_range)
    dev = guide.device
    y = torch.arange(h, device=dev, dtype=guide.dtype) / rate
    x = torch.arange(w, device=dev, dtype=guide.dtype) / rate
    y0, x0 = y.floor(), x.floor()
    fy, fx = (y - y0).view(1, h, 1), (x - x0).view(1, 1, w)
    y0, x0 = y0.long().view(1, h, 1), x0.long().view(1, 1, w)
    z = guide.clamp(0.0, guide_range) / rate
    z0 = z.detach().floor().clamp(0, D - 2)
    fz = z - z0
    z0 = z0.long()
    base = torch.arange(b, device=dev).view(b, 1, 1) * D
    idx, wts = [], []
    for dz in (0, 1):
        az = fz - dz
        wz = torch.relu(1.0 - torch.sqrt(az * az + TENT_EPS))
        for dy in (0, 1):
            wy = 1.0 - (fy - dy).abs()
            for dx in (0, 1):
                wx = 1.0 - (fx - dx).abs()
                idx.append(((base + z0 + dz) * Hg + (y0 + dy)) * Wg + (x0 + dx))
                wts.append(wz * wy * wx)
    return torch.stack(idx), torch.stack(wts), (D, Hg, Wg)


def splat(values: torch.Tensor, index: torch.Tensor, weight: torch.Tensor, cells: int):
    """Eq. 10: ``values (B C H W)`` splatted with the corner ``index``/``weight`` of :func:`corners` into
    ``cells`` grid cells. Returns ``(value (C, cells), weight_sum (cells,))``; the value of a cell is
    its normalised weighted mean, 0 where the weight sum is 0 (an empty cell)."""
    b, c, h, w = values.shape
    wt = weight.reshape(8, 1, b, h * w)
    src = torch.cat((wt * values.reshape(1, b, c, h * w).transpose(1, 2), wt), dim=1)   # 8 (C+1) B HW
    src = src.transpose(0, 1).reshape(c + 1, -1)
    i = index.reshape(-1)
    # one 1-D scatter_add per channel (channel-major grid): 3x faster on this CPU than a flat
    # scatter of (C+1)-wide rows, and 1.6x faster than index_add
    acc = torch.zeros(c + 1, cells, dtype=values.dtype, device=values.device)
    acc = torch.stack([acc[k].scatter_add(0, i, src[k]) for k in range(c + 1)])
    wsum = acc[c]
    filled = wsum > 0
    return acc[:c] / torch.where(filled, wsum, torch.ones_like(wsum)), wsum


def slice_grid(value: torch.Tensor, wsum: torch.Tensor, index: torch.Tensor, weight: torch.Tensor,
               shape: tuple[int, int, int, int]) -> torch.Tensor:
    """Eq. 13: trilinear read of the grid at each pixel's corners, renormalised over the non-empty
    corners. ``value (C, cells)``; ``shape`` is (B, C, H, W) of the output. Empty cells hold the value 0,
    so the numerator needs no mask; the denominator sums the weights of the filled corners."""
    b, c, h, w = shape
    i = index.reshape(-1)
    wt = weight.reshape(8, -1)
    den = (wt * (wsum > 0).to(wt.dtype).index_select(0, i).view(8, -1)).sum(dim=0)
    den = torch.where(den > 0, den, torch.ones_like(den))
    out = torch.stack([(value[k].index_select(0, i).view(8, -1) * wt).sum(dim=0) for k in range(c)]) / den
    return out.view(c, b, h, w).transpose(0, 1)


def bilateral_filter(values: torch.Tensor, guide: torch.Tensor, rate: int, guide_range: float) -> torch.Tensor:
    """Splat ``values (B C H W)`` into the bilateral grid placed by ``guide (B H W)`` and slice it back."""
    index, weight, (D, Hg, Wg) = corners(guide, rate, guide_range)
    value, wsum = splat(values, index, weight, values.shape[0] * D * Hg * Wg)
    return slice_grid(value, wsum, index, weight, tuple(values.shape))


@register("nbg")
class NeuralBilateralGrid(PixelDenoiser):
    train_defaults = dict(loss="l1", lr=1e-4, grad_clip_norm=0.0, grad_clip_value=0.0, warmup=0)
    tiny = dict(guide_hidden=(6,), guide_kernel=3)

    def __init__(self, guide_hidden=(20,), guide_kernel: int = 5, rates=(4, 8, 16), guide_range: float = 255.0,
                 temporal_frames: int = 1, temporal_alpha: float = 0.2,
                 albedo_offset: float = ALBEDO_OFFSET, keep_lights: bool = True):
        guide_hidden = tuple(int(c) for c in guide_hidden)
        rates = tuple(int(r) for r in rates)
        need(all(c >= 1 for c in guide_hidden), '"guide_hidden"', "positive widths (one per hidden conv layer)",
             guide_hidden, ConfigError)
        need(guide_kernel >= 1 and guide_kernel % 2 == 1, '"guide_kernel"', "an odd integer >= 1", guide_kernel,
             ConfigError)
        need(bool(rates) and all(r >= 1 for r in rates), '"rates"', "one or more sampling rates >= 1 (one grid each)",
             rates, ConfigError)
        need(guide_range > 0, '"guide_range"', "> 0", guide_range, ConfigError)
        super().__init__(temporal_frames=temporal_frames, temporal_alpha=temporal_alpha, albedo_offset=albedo_offset,
                         keep_lights=keep_lights,
                         guide_hidden=guide_hidden, guide_kernel=int(guide_kernel), rates=rates,
                         guide_range=float(guide_range))
        self.rates, self.guide_range = rates, float(guide_range)
        layers, prev = [], 10
        for c in guide_hidden:
            layers += [nn.Conv2d(prev, c, guide_kernel, padding=guide_kernel // 2), nn.ReLU(inplace=True)]
            prev = c
        layers += [nn.Conv2d(prev, 2 * len(rates) - 1, guide_kernel, padding=guide_kernel // 2), nn.Sigmoid()]
        self.guide_net = nn.Sequential(*layers)

    def guides(self, net_in: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Guides (B S H W) in [0, guide_range] and blend weights (B S H W) summing to 1 (eq. 15)."""
        out = self.guide_net(net_in)
        s = len(self.rates)
        w = out[:, s:]
        return out[:, :s] * self.guide_range, torch.cat((w, 1.0 - w.sum(dim=1, keepdim=True)), dim=1)

    def filter(self, irradiance, net_in):
        guides, blend = self.guides(net_in)
        out = 0.0
        for s, rate in enumerate(self.rates):
            out = out + blend[:, s:s + 1] * bilateral_filter(irradiance, guides[:, s], rate, self.guide_range)
        return out

    def fmas_per_pixel(self, spp: int) -> float:
        # GuideNet, then per scale: 8 corners x 4 channels to splat and to slice
        return spp * 3 + conv_fmas(self.guide_net) + len(self.rates) * 2 * 8 * 4
