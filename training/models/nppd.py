"""NPPD: neural partitioning pyramids (Bálint, Wolski, Myszkowski, Seidel and Mantiuk, "Neural Partitioning
Pyramids for Denoising Monte Carlo Renderings", SIGGRAPH 2023), a recurrent per-sample denoiser of the
``clips`` kind. Written from the paper and its public code (github balintio/nppd, ``model.py`` and
``partitioning_pyramid.py``), not copied from it.

One step, frame ``t`` with the state of frame ``t - 1``:

1. **Reprojection.** The state (the blended input colour, the output and the pixel features of the
   previous frame, 3 + 3 + ``embed`` channels) is resampled at ``p + motion`` (bilinear; the store's
   per-pixel motion, ``p_prev - p_cur``); zeros on a clip's first frame.
2. **Per-sample encoder.** Each sample's log depth ``log(1 + 1/d)`` (0 on a miss), normal, albedo and
   ``log(1 + L / mean L)`` (radiance over the frame's mean) go through three 1x1 convolutions (10 -> 32
   -> 32 -> 32, leaky ReLU 0.3); the embeddings are averaged over the samples: the pixel features.
3. **Weight predictor.** A U-net of the stack (:class:`.common.UNet`, 5 pooling levels) reads the
   previous and current mean colour (``log(1 + x / mean)``, jointly normalised), the previous and
   current pixel features (70 channels with ``embed`` 32) and predicts, per pyramid level ``i``: a
   5x5 kernel (25 logits); at level 0 also a 5x5 kernel for the previous output, its blend ``t_mu``,
   the input blend ``t_lambda`` and the ``K`` partition logits; at levels 1..K-1 a 4x4 upsampling
   kernel (16 logits). Level 0 is the U-net's own output convolution; the others are 1x1
   convolutions of its decoder at 1/2^i.
4. **Temporal input blend.** ``colour = t_lambda * previous colour + (1 - t_lambda) * colour`` and
   the same for the pixel features (what the next frame reprojects).
5. **Partitioning pyramid.** The colour is split into ``K`` partitions by a per-pixel softmax;
   partition ``i`` is average-pooled to 1/2^i and filtered there with its softmax-normalised 5x5
   kernel (splatting: each source pixel spreads its value, so energy is kept); from the coarsest level
   up, each level is upsampled by its learned 4x4 transposed kernel (softmax times 4: a coarse pixel
   spreads onto the 4x4 fine pixels around it, its mass kept) and added to the next finer level.
6. **Temporal output blend.** The reprojected previous output, filtered with its own 5x5 kernel, is
   blended in with ``t_mu``: the frame's output, which the state carries on.

Defaults are the paper's (its 15M "ConvUNet" network, the one of its 2- and 4-spp models: widths
96-128-192-256-384 and a 512-512-384 bottleneck; its 8-spp ConvNeXt U-net is not built here, ``K = 5`` levels, 5x5 kernels, a 32-wide sample encoder; Adam at 1e-4 with the loss
``smape-temporal``). Departures, all stated in docs/training.md: the normals are world-space (the
format's ``normal``; NPPD turns them into camera space), the U-net is the stack's (its skips are the
pooled encoder outputs, bilinear upsampling, leaky ReLU 0.01 and outputs bounded per pixel: see
:class:`.common.UNet`), the loss has no perceptual terms (its learned network is not available here),
training unrolls windows of ``frames`` consecutive frames from a zero state (NPPD carries the detached
state through whole 64-frame sequences, two frames at a time), and there is no learning-rate decay.
``--model-cfg '{"size": "small"}'`` is a CPU-sized network of the same structure.
"""
from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from stores.contract import FEATURE_GROUPS

from core.checks import known_keys, need, need_int

from ..errors import ConfigError
from ..inputs import InputSpec, mask_features
from ._pixel import warp
from .common import Denoiser, UNet, clean_radiance, conv_fmas, replicate_pad, splat, xavier_init
from .registry import register
from .robust import OUTLIER_K

KERNEL = 5
K2 = KERNEL * KERNEL
UP = 16                                  # taps of the 4x4 upsampling kernel
SIZES = {   # U-net widths: encoder blocks (one per pooling level), bottleneck, decoder blocks (coarse to fine)
    "paper": dict(unet_encoder=((96, 96), (96, 128), (128, 192), (192, 256), (256, 384)),
                  unet_bottleneck=(512, 512, 384),
                  unet_decoder=((384, 256), (256, 192), (192, 128), (128, 96), (96, 96))),
    "small": dict(unet_encoder=((16,), (24,), (32,), (48,), (64,)), unet_bottleneck=(64,),
                  unet_decoder=((48,), (32,), (24,), (16,), (16,))),
}


def _leaky() -> nn.Module:
    return nn.LeakyReLU(0.3)


def normalise(x: torch.Tensor) -> torch.Tensor:
    """``log(1 + max(x, 0) / mean(x))``, the mean over every axis but the batch's (NPPD's tone map)."""
    x = clean_radiance(x)
    mean = x.mean(dim=tuple(range(1, x.dim())), keepdim=True) + 1e-8
    return torch.log1p(x / mean)


def upsample(x: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """``x`` (B C h w) to (B C 2h 2w): each coarse pixel spreads onto the 4x4 fine pixels around it with
    ``weights`` (B 16 h w, row-major taps, summing to 4 per pixel: its mass is kept)."""
    b, c, h, w = x.shape
    cols = (x.unsqueeze(2) * weights.unsqueeze(1)).reshape(b, c * UP, h * w)
    return F.fold(cols, (2 * h, 2 * w), 4, stride=2, padding=1)


@register("nppd")
class NPPD(Denoiser):
    """Neural partitioning pyramids (module docstring)."""

    outlier_bound = OUTLIER_K
    inputs = InputSpec("clips", frames=4, default_spp=8, features=("normal", "depth", "albedo"))
    train_defaults = dict(loss="smape-temporal", lr=1e-4, grad_clip_norm=0.0, grad_clip_value=0.0, warmup=0)
    tiny = dict(levels=3, embed=4, unet_encoder=((4,), (4,), (4,)), unet_bottleneck=(4,),
                unet_decoder=((4,), (4,), (4,)), frames=2)

    def __init__(self, size: str = "paper", levels: int = 5, embed: int = 32, frames: int = 4, **widths):
        need(size in SIZES, '"size"', f"one of {sorted(SIZES)}", size, ConfigError)
        need_int('"levels" (of the pyramid)', levels, 1, 8, ConfigError)
        need_int('"embed"', embed, 1, None, ConfigError)
        need_int('"frames" (the training unroll)', frames, 1, None, ConfigError)
        known_keys(widths, SIZES["paper"], "nppd", ConfigError, noun="settings")
        super().__init__(size=size, levels=levels, embed=embed, frames=frames, **widths)
        w = {**SIZES[size], **widths}
        self.levels, self.embed, self.frames = levels, embed, frames
        self.encoder = nn.Sequential(nn.Conv2d(10, embed, 1), _leaky(), nn.Conv2d(embed, embed, 1), _leaky(),
                                     nn.Conv2d(embed, embed, 1))
        self.head0 = 2 * K2 + 2 + levels                      # kernel, temporal kernel, t_mu, t_lambda, partitions
        self.unet = UNet(6 + 2 * embed, self.head0, w["unet_encoder"], w["unet_bottleneck"], w["unet_decoder"])
        if self.unet.depth < levels - 1:
            raise ConfigError(f'the U-net has {self.unet.depth} pooling levels; a pyramid of "levels" {levels} needs '
                              f"at least {levels - 1}")
        self.heads = nn.ModuleList(nn.Conv2d(self.unet.decoder_channels(i), K2 + UP, 1) for i in range(1, levels))
        xavier_init(self)

    def declared_inputs(self) -> InputSpec:
        return InputSpec("clips", frames=self.frames, default_spp=self.inputs.default_spp,
                         features=self.inputs.features)

    # ------------------------------------------------------------------ parts
    def encode(self, radiance: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        """Pixel features (B embed H W): the per-sample encoder averaged over the samples."""
        g = FEATURE_GROUPS
        f = torch.nan_to_num(features, nan=0.0, posinf=0.0, neginf=0.0)
        d = f[:, :, g["depth"]].clamp(min=0.0)
        logd = torch.where(d > 0, torch.log1p(1.0 / d.clamp(min=1e-6)), torch.zeros_like(d))
        x = torch.cat((logd, f[:, :, g["normal"]], f[:, :, g["albedo"]], normalise(radiance)), dim=2)
        b, s, c, h, w = x.shape
        e = self.encoder(x.reshape(b * s, c, h, w))
        return e.view(b, s, self.embed, h, w).mean(dim=1)

    def weights(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The per-level logits: level 0 (B head0 H W), then (B 41 H/2^i W/2^i) for i = 1..K-1."""
        out, decoder = self.unet(x)
        return [out] + [head(decoder[i]) for i, head in enumerate(self.heads, start=1)]

    def pyramid(self, colour: torch.Tensor, w: list[torch.Tensor]) -> torch.Tensor:
        """The partitioned colour filtered level by level and recombined from the coarsest up."""
        parts = F.softmax(w[0][:, 2 * K2 + 2:], dim=1)                              # B K H W
        filtered = []
        for i in range(self.levels):
            p = parts[:, i:i + 1] * colour
            if i:
                p = F.avg_pool2d(p, 2 ** i)
            filtered.append(splat(p, F.softmax(w[i][:, :K2], dim=1), KERNEL))
        out = filtered[-1]
        for i in reversed(range(self.levels - 1)):
            out = filtered[i] + upsample(out, 4.0 * F.softmax(w[i + 1][:, K2:K2 + UP], dim=1))
        return out

    # ------------------------------------------------------------------ the step
    def step(self, frame: dict, state: dict | None):
        """One frame (``radiance (B S 3 H W)``, ``features``, ``motion``) with the previous frame's state."""
        radiance = clean_radiance(frame["radiance"])
        features = frame["features"]
        h, w = radiance.shape[-2:]
        m = 2 ** (self.levels - 1)
        ph, pw = (-h) % m, (-w) % m
        motion = frame["motion"]
        if ph or pw:       # the pyramid halves the frame K - 1 times: pad to a multiple of 2^(K-1)
            pad = lambda t: replicate_pad(t.flatten(0, 1), (0, pw, 0, ph)).unflatten(0, t.shape[:2])  # noqa: E731
            radiance, features = pad(radiance), pad(features)
            motion = replicate_pad(motion, (0, pw, 0, ph))
        colour = self.bound(radiance).mean(dim=1)          # what the pyramid filters (training.models.robust)
        feat = self.encode(radiance, self.masked(features))
        if state is None:
            prev = torch.zeros(colour.shape[0], 6 + self.embed, *colour.shape[-2:], dtype=colour.dtype,
                               device=colour.device)
        else:
            prev = state["history"]
            if ph or pw:
                prev = replicate_pad(prev, (0, pw, 0, ph))
            prev = warp(prev, motion)[0]
        prev_colour, prev_out, prev_feat = prev[:, :3], prev[:, 3:6], prev[:, 6:]
        x = torch.cat((normalise(torch.cat((prev_colour, colour), dim=1)), prev_feat, feat), dim=1)
        wts = self.weights(x)
        lam = torch.sigmoid(wts[0][:, 2 * K2 + 1:2 * K2 + 2])
        colour = lam * prev_colour + (1 - lam) * colour
        feat = lam * prev_feat + (1 - lam) * feat
        out = self.pyramid(colour, wts)
        mu = torch.sigmoid(wts[0][:, 2 * K2:2 * K2 + 1])
        out = mu * splat(prev_out, F.softmax(wts[0][:, K2:2 * K2], dim=1), KERNEL) + (1 - mu) * out
        history = torch.cat((colour, out, feat), dim=1)[..., :h, :w]
        return out[..., :h, :w], {"history": history}, {}

    def masked(self, features: torch.Tensor) -> torch.Tensor:
        return mask_features(features, self.feature_groups)

    def fmas_per_pixel(self, spp: int) -> float:
        heads = sum(conv_fmas(h) / 4 ** i for i, h in enumerate(self.heads, start=1))
        taps = sum(3 * K2 / 4 ** i for i in range(self.levels)) + sum(3 * UP / 4 ** i for i in range(self.levels - 1))
        return float(spp * conv_fmas(self.encoder) + self.unet.fmas_per_pixel() + heads + taps + 3 * K2)
