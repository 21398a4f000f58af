"""Shared parts of the per-pixel real-time denoisers (``nbg``, ``wskpn``): albedo demodulation, the
network inputs both papers use, and temporal accumulation with reprojection.

Layouts: images (float32, B C H W); clips (float32, B T C H W); motion (float32, B 2 H W) in pixels,
``p_prev - p_cur`` (the store's convention, x right, y down).

* **Demodulation** (NBG sec. 4.1, WSKPN sec. 4.2): the filters run on irradiance ``r / (a + eps)`` and
  the result is multiplied by ``(a + eps)`` again, so a zero albedo (misses, black surfaces) neither
  divides by zero nor changes the radiance of a pixel the filter leaves alone. A filter that mixes a
  black pixel's irradiance into a white one's multiplies its radiance by up to ``(1 + eps) / eps``: 101
  with the papers' 0.01, which took nbg to 20-50 where the reference is 0.1 next to black metal in a
  sunlit frame. The models' offset (``albedo_offset``) is 0.1, at most 11x; measured on the held-out
  hard-case suite and ordinary frames it was also 0.5-0.9 dB better on ordinary frames (docs/hard-cases.md).
  A checkpoint without the setting was trained with 0.01 and builds with it (``legacy_config``).
* **Network inputs** (NBG sec. 5, WSKPN sec. 5.1): 10 channels in [0, 1]: tone-mapped radiance (3, the
  layer paper's ``srgb(log(1 + x))``, which keeps HDR values finite where a clipped gamma would
  saturate), albedo (3), normal mapped to ``(n + 1) / 2`` (3) and depth over the frame's largest (1).
* **Temporal accumulation** (NBG sec. 4.6, WSKPN sec. 4.1, after SVGF): the history is reprojected with
  the motion vectors (bilinear ``grid_sample`` at ``p + motion``), kept where the reprojected depth and
  normal agree with the current frame, and blended ``alpha * history + (1 - alpha) * current`` with
  the papers' ``alpha = 0.2``; pixels failing the test keep their current value. Over a window of T
  frames the history is exact up to a weight ``alpha^T`` (0.0016 for T = 4) on the dropped frames.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from core.checks import is_number, need, need_int
from ..errors import ConfigError
from ..inputs import InputSpec
from core.images import tonemap
from .common import Denoiser, clean_radiance
from .robust import OUTLIER_K, light_excess

DEMOD_EPS = 1e-2          # the papers' albedo offset of the demodulation (OIDN and KPCN use 0.00316-0.01) ...
ALBEDO_OFFSET = 0.1       # ... and the models' default (setting "albedo_offset"; docs/hard-cases.md, measured)
DEPTH_TOL = 0.1           # relative depth difference that fails the reprojection test
NORMAL_TOL = 0.9          # cosine between normals below which the reprojection test fails


def demodulate(radiance: torch.Tensor, albedo: torch.Tensor, eps: float = DEMOD_EPS) -> torch.Tensor:
    """Irradiance ``r / (a + eps)`` of clean radiance (non-finite -> 0, negatives clamped)."""
    return clean_radiance(radiance) / (clean_albedo(albedo) + eps)


def remodulate(irradiance: torch.Tensor, albedo: torch.Tensor, eps: float = DEMOD_EPS) -> torch.Tensor:
    return irradiance * (clean_albedo(albedo) + eps)


def clean_albedo(albedo: torch.Tensor) -> torch.Tensor:
    return torch.nan_to_num(albedo, nan=0.0, posinf=1.0, neginf=0.0).clamp(0.0, 1.0)


def network_inputs(radiance: torch.Tensor, albedo: torch.Tensor, normal: torch.Tensor,
                   depth: torch.Tensor) -> torch.Tensor:
    """The 10 network input channels (float32, B 10 H W), each in [0, 1] (see module docstring)."""
    n = torch.nan_to_num(normal, nan=0.0).clamp(-1.0, 1.0)
    d = torch.nan_to_num(depth, nan=0.0, posinf=0.0).clamp(min=0.0)
    d = d / (d.amax(dim=(1, 2, 3), keepdim=True) + 1e-6)
    x = torch.cat((tonemap(clean_radiance(radiance)), clean_albedo(albedo), (n + 1.0) * 0.5, d), dim=1)
    # channels-last: oneDNN's native layout; the narrow 5x5 convolutions run 2-3x faster on this CPU
    return x.contiguous(memory_format=torch.channels_last)


def warp(image: torch.Tensor, motion: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``image`` (B C H W) of the previous frame resampled at ``p + motion`` (bilinear), and the mask
    (B 1 H W) of pixels whose reprojected position lies inside the previous frame."""
    b, _, h, w = image.shape
    ys, xs = torch.meshgrid(torch.arange(h, dtype=image.dtype, device=image.device),
                            torch.arange(w, dtype=image.dtype, device=image.device), indexing="ij")
    m = torch.nan_to_num(motion, nan=0.0, posinf=0.0, neginf=0.0)
    px, py = xs + m[:, 0], ys + m[:, 1]
    inside = ((px >= 0) & (px <= w - 1) & (py >= 0) & (py <= h - 1)).unsqueeze(1)
    grid = torch.stack((2 * px / max(w - 1, 1) - 1, 2 * py / max(h - 1, 1) - 1), dim=-1)
    out = F.grid_sample(image, grid, mode="bilinear", padding_mode="border", align_corners=True)
    return out, inside


def accumulate(irradiance: torch.Tensor, motion: torch.Tensor, depth: torch.Tensor, normal: torch.Tensor,
               alpha: float = 0.2) -> torch.Tensor:
    """Temporally accumulated irradiance of the last frame of a clip.

    ``irradiance (B T 3 H W)``, ``motion (B T 2 H W)`` (frame t to t-1), ``depth (B T 1 H W)``,
    ``normal (B T 3 H W)``; returns (B 3 H W). See the module docstring for the test and the blend."""
    acc = irradiance[:, 0]
    for t in range(1, irradiance.shape[1]):
        guides = torch.cat((acc, depth[:, t - 1], normal[:, t - 1]), dim=1)
        prev, inside = warp(guides, motion[:, t])
        d_prev, n_prev = prev[:, 3:4], prev[:, 4:7]
        d_cur, n_cur = depth[:, t], normal[:, t]
        ok_depth = (d_prev - d_cur).abs() <= DEPTH_TOL * torch.maximum(d_cur.abs(), d_prev.abs()) + 1e-6
        ok_normal = (n_prev * n_cur).sum(dim=1, keepdim=True) >= NORMAL_TOL * (
            n_prev.norm(dim=1, keepdim=True) * n_cur.norm(dim=1, keepdim=True))
        keep = (inside & ok_depth & ok_normal).to(acc.dtype)
        acc = irradiance[:, t] + keep * alpha * (prev[:, :3] - irradiance[:, t])
    return acc


class PixelDenoiser(Denoiser):
    """Base of the per-pixel denoisers: input kind ``pixels`` at 1 spp by default; with
    ``temporal_frames = T > 1`` it reads windows of T frames and accumulates them (off for stills).

    Subclasses implement ``filter(irradiance (B3HW), net_in (B10HW)) -> irradiance (B3HW)``."""

    inputs = InputSpec("pixels", frames=1, default_spp=1)
    realtime = True
    outlier_bound = OUTLIER_K

    legacy_config = {**Denoiser.legacy_config, "albedo_offset": DEMOD_EPS, "keep_lights": False}

    def __init__(self, temporal_frames: int = 1, temporal_alpha: float = 0.2, albedo_offset: float = ALBEDO_OFFSET,
                 keep_lights: bool = True, **config):
        need_int('"temporal_frames" (1: no temporal accumulation)', temporal_frames, 1, None, ConfigError)
        need(is_number(temporal_alpha) and 0.0 <= temporal_alpha < 1.0, '"temporal_alpha"', "a number in [0, 1)",
             temporal_alpha, ConfigError)
        need(is_number(albedo_offset, finite=True) and 1e-4 <= albedo_offset <= 1.0, '"albedo_offset"',
             "a number in [1e-4, 1] (demodulation divides by albedo + offset)", albedo_offset, ConfigError)
        need(isinstance(keep_lights, bool), '"keep_lights"', "true or false", keep_lights, ConfigError)
        super().__init__(temporal_frames=temporal_frames, temporal_alpha=float(temporal_alpha),
                         albedo_offset=float(albedo_offset), keep_lights=keep_lights, **config)
        self.temporal_frames, self.temporal_alpha = temporal_frames, float(temporal_alpha)
        self.albedo_offset, self.keep_lights = float(albedo_offset), keep_lights

    def declared_inputs(self) -> InputSpec:
        return InputSpec("pixels", frames=self.temporal_frames, default_spp=self.inputs.default_spp)

    def forward(self, batch: dict) -> torch.Tensor:
        rad, alb, nrm, dep = batch["radiance"], batch["albedo"], batch["normal"], batch["depth"]
        eps = self.albedo_offset
        if rad.dim() == 5:                                     # a window of frames: accumulate, then filter the last
            irr = accumulate(demodulate(rad, alb, eps), batch["motion"], dep, nrm, self.temporal_alpha)
            rad, alb, nrm, dep = rad[:, -1], alb[:, -1], nrm[:, -1], dep[:, -1]
            rad_in = remodulate(irr, alb, eps)
        else:
            irr = demodulate(rad, alb, eps)
            rad_in = rad
        if rad.dim() != 4 or rad.shape[1] != 3:
            raise ConfigError(f"radiance must be (B, 3, H, W) or (B, T, 3, H, W), got {tuple(batch['radiance'].shape)}")
        bounded = self.bound(irr)
        out = self.filter(bounded, network_inputs(rad_in, alb, nrm, dep))
        if self.keep_lights and self.outliers:          # a light's cut energy back at its pixels (training.models.robust)
            out = out + light_excess(irr, bounded)
        return remodulate(out, alb, eps)

    def filter(self, irradiance: torch.Tensor, net_in: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError
