"""WSKPN: the weight-sharing kernel prediction network (Fan et al. 2021), for 1-spp real-time denoising.

ImportanceNet (sec. 4.1): a chain of RepVGG blocks (``widths``; default six blocks 10 -> 14 x 5 -> 12,
the width of the public reimplementation, since fig. 2's widths are not in the text). During training a
block sums a 1x1, a 3x3 and a 5x5 convolution and, where input and output widths agree, the identity,
then applies ReLU (the last block has no activation). :meth:`WSKPN.for_inference` fuses every block
into the single 5x5 convolution that computes the same function (``RepVGGBlock.fuse``); ``evaluate``
and ``bench`` run that form.

Its 12 outputs are 6 importance maps I_i and 6 fusion logits. Kernel i has size k_i = 3, 5, ..., 13 and
weights w_p(q) = exp(I_i(q)) / sum_{q' in window(p)} exp(I_i(q')) (eq. 3): the softmax of the unfolded
importance over the window, with pixels outside the frame at -inf (they get weight 0, so borders are
not darkened). The filtered image is R_i(p) = sum_q w_p(q) r(q) (eq. 4) and the results are fused by
eq. 5 with the softmax of the fusion logits.

Because the weight of q does not depend on p except through the normalisation, eq. 4 is a ratio of two
box filters, R_i = box_k(e^I r) / box_k(e^I), with zero padding standing for the -inf importance
outside the frame; the k x k per-pixel kernels are never materialised (:func:`explicit_filter` is the
unfold-and-softmax form, kept as the test oracle). The exponent is taken relative to the map's
maximum (the softmax's max subtraction; a constant per map cancels in the ratio) and floored at
-80, so e^(I - max) never underflows to zero and a window's weight sum is never 0 (windows whose
importances all lie 80 below the map's maximum become box filters, instead of 0/0).
"""
from __future__ import annotations

import copy

import torch
import torch.nn as nn
import torch.nn.functional as F

from core.checks import need

from ..errors import ConfigError
from ._pixel import ALBEDO_OFFSET, PixelDenoiser
from .common import conv_fmas
from .registry import register

EXP_FLOOR = -80.0          # e^-80 = 1.8e-35: a normal float32 even with denormals flushed


class RepVGGBlock(nn.Module):
    """1x1 + 3x3 + 5x5 convolutions (+ identity when ``cin == cout``), summed, then ReLU (``act``)."""

    def __init__(self, cin: int, cout: int, act: bool = True):
        super().__init__()
        self.cin, self.cout, self.act = cin, cout, act
        self.conv1 = nn.Conv2d(cin, cout, 1)
        self.conv3 = nn.Conv2d(cin, cout, 3, padding=1)
        self.conv5 = nn.Conv2d(cin, cout, 5, padding=2)
        self.identity = cin == cout

    def forward(self, x):
        y = self.conv1(x) + self.conv3(x) + self.conv5(x)
        if self.identity:
            y = y + x
        return F.relu(y) if self.act else y

    def fuse(self) -> nn.Sequential:
        """The single 5x5 convolution (+ ReLU) equal to this block: the 1x1 and 3x3 kernels padded to
        5x5 and the identity as a centre tap, all summed (Ding et al. 2021). It is made on the device
        and in the dtype of this block's weights (a model moved to CUDA, float64 or ``meta`` fuses
        there)."""
        w = self.conv5.weight.detach().clone()
        w += F.pad(self.conv3.weight.detach(), (1, 1, 1, 1))
        w += F.pad(self.conv1.weight.detach(), (2, 2, 2, 2))
        if self.identity:
            i = torch.arange(self.cout, device=w.device)
            w[i, i, 2, 2] += 1.0
        b = (self.conv1.bias + self.conv3.bias + self.conv5.bias).detach().clone()
        conv = nn.Conv2d(self.cin, self.cout, 5, padding=2, device=w.device, dtype=w.dtype)
        with torch.no_grad():
            conv.weight.copy_(w)
            conv.bias.copy_(b)
        return nn.Sequential(conv, nn.ReLU()) if self.act else nn.Sequential(conv)


def box(x: torch.Tensor, k: int) -> torch.Tensor:
    """Sum over the k x k window around each pixel, zero outside the frame; separable (2k adds a pixel
    instead of k^2). x (B C H W)."""
    r = k // 2
    y = F.avg_pool2d(x, (k, 1), stride=1, padding=(r, 0), count_include_pad=True)
    return F.avg_pool2d(y, (1, k), stride=1, padding=(0, r), count_include_pad=True) * (k * k)


def importance_weights(importance: torch.Tensor) -> torch.Tensor:
    """e^(I - max I) per map (B M H W), floored at e^-80 (see the module docstring)."""
    return torch.exp(torch.clamp(importance - importance.detach().amax(dim=(2, 3), keepdim=True), min=EXP_FLOOR))


def box_ratio(radiance: torch.Tensor, e: torch.Tensor, k: int) -> torch.Tensor:
    """box(e r) / box(e) for ``radiance (B C H W)`` and weights ``e (B 1 H W)``: numerator and
    denominator filtered together as one (C+1)-channel image."""
    c = radiance.shape[1]
    s = box(torch.cat((e * radiance, e), dim=1), k)
    return s[:, :c] / s[:, c:]


def box_filter(radiance: torch.Tensor, importance: torch.Tensor, k: int) -> torch.Tensor:
    """Eq. 3-4 in box form: ``radiance (B C H W)`` filtered with the softmax kernels of ``importance
    (B 1 H W)`` over k x k windows: box(e^I r) / box(e^I)."""
    return box_ratio(radiance, importance_weights(importance), k)


def explicit_kernels(importance: torch.Tensor, k: int) -> torch.Tensor:
    """The per-pixel kernels (B k*k H W) of eq. 3, materialised: the unfolded importance (-inf outside
    the frame) through a softmax over the window. For tests; the model uses :func:`box_filter`."""
    b, _, h, w = importance.shape
    padded = F.pad(importance, (k // 2,) * 4, value=float("-inf"))
    cols = F.unfold(padded, k).view(b, k * k, h, w)
    return torch.softmax(cols, dim=1)


def explicit_filter(radiance: torch.Tensor, importance: torch.Tensor, k: int) -> torch.Tensor:
    b, c, h, w = radiance.shape
    kern = explicit_kernels(importance, k)
    cols = F.unfold(radiance, k, padding=k // 2).view(b, c, k * k, h, w)
    return (cols * kern.unsqueeze(1)).sum(dim=2)


@register("wskpn")
class WSKPN(PixelDenoiser):
    train_defaults = dict(loss="smape", lr=1e-3, grad_clip_norm=0.0, grad_clip_value=0.0, warmup=0)
    tiny = dict(widths=(6, 6), kernel_sizes=(3, 5))

    def __init__(self, widths=(14, 14, 14, 14, 14), kernel_sizes=(3, 5, 7, 9, 11, 13), fused: bool = False,
                 temporal_frames: int = 1, temporal_alpha: float = 0.2,
                 albedo_offset: float = ALBEDO_OFFSET, keep_lights: bool = True):
        widths = tuple(int(c) for c in widths)
        kernel_sizes = tuple(int(k) for k in kernel_sizes)
        need(all(c >= 1 for c in widths), '"widths"', "positive block widths", widths, ConfigError)
        need(bool(kernel_sizes) and all(k >= 1 and k % 2 for k in kernel_sizes), '"kernel_sizes"',
             "one or more odd sizes >= 1", kernel_sizes, ConfigError)
        super().__init__(temporal_frames=temporal_frames, temporal_alpha=temporal_alpha, albedo_offset=albedo_offset,
                         keep_lights=keep_lights,
                         widths=widths, kernel_sizes=kernel_sizes, fused=bool(fused))
        self.kernel_sizes = kernel_sizes
        chans = (10, *widths, 2 * len(kernel_sizes))
        blocks = [RepVGGBlock(a, b, act=i < len(chans) - 2) for i, (a, b) in enumerate(zip(chans[:-1], chans[1:]))]
        self.net = nn.Sequential(*(b.fuse() if fused else b for b in blocks))

    def for_inference(self) -> "WSKPN":
        """A copy whose RepVGG blocks are fused into single 5x5 convolutions (same outputs)."""
        if self.config["fused"]:
            return super().for_inference()
        fused = copy.deepcopy(self)
        fused.net = nn.Sequential(*(b.fuse() for b in self.net))
        fused.config = {**self.config, "fused": True}
        return super(WSKPN, fused).for_inference()

    def filter(self, irradiance, net_in):
        out = self.net(net_in)
        m = len(self.kernel_sizes)
        alpha = torch.softmax(out[:, m:], dim=1)
        e = importance_weights(out[:, :m])
        res = 0.0
        for i, k in enumerate(self.kernel_sizes):
            res = res + alpha[:, i:i + 1] * box_ratio(irradiance, e[:, i:i + 1], k)
        return res

    def fmas_per_pixel(self, spp: int) -> float:
        # the fused network; per kernel: e^I r (3) and the two separable box passes over 4 channels,
        # the ratio (3) and the fusion (3)
        if self.config["fused"]:
            net = conv_fmas(self.net)
        else:
            net = sum(b.cin * b.cout * 25 for b in self.net)
        return spp * 3 + net + len(self.kernel_sizes) * (3 + 4 * 4 + 3 + 3)
