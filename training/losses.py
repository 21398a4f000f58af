"""Training losses, found by name: ``build_loss('smape')``.

All take ``denoised, reference`` as float32 tensors of equal shape, channel-first: images
(B, 3, H, W) or clips (B, T, 3, H, W) for the temporal loss. Linear radiance in, scalar out.
"""
from __future__ import annotations

from typing import Callable

import torch

from .errors import ConfigError
from core.images import tonemap

SMAPE_EPS = 0.01   # eq. 9 of the layer paper

LOSSES: dict[str, Callable[[torch.Tensor, torch.Tensor], torch.Tensor]] = {}


def register_loss(name: str):
    def deco(fn):
        if name in LOSSES:
            raise ConfigError(f"loss {name!r} is already registered")
        LOSSES[name] = fn
        return fn
    return deco


def build_loss(name: str) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
    try:
        return LOSSES[name]
    except KeyError:
        raise ConfigError(f'"loss" must be one of {sorted(LOSSES)}, got {name!r}') from None


@register_loss("smape")
def smape(denoised: torch.Tensor, reference: torch.Tensor, eps: float = SMAPE_EPS) -> torch.Tensor:
    """Eq. 9: mean over pixels and channels of |d - r| / (|d| + |r| + eps), on linear radiance."""
    return torch.mean(torch.abs(denoised - reference) / (torch.abs(denoised) + torch.abs(reference) + eps))


@register_loss("smape-temporal")
def smape_temporal(denoised: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """NPPD's loss (Bálint et al. 2023, ``model.py`` of its code) without its learned perceptual terms:
    both images divided by the reference's mean (per item), then on a window (B, T, 3, H, W)
    ``2 SMAPE`` over every frame plus ``0.2 SMAPE`` of the differences of consecutive frames (the
    temporal term; NPPD warps the previous frame first, this compares them in place, as ``l1-temporal``
    does); a single frame (B, 3, H, W): ``8 SMAPE`` (its one-step weight)."""
    if denoised.dim() not in (4, 5):
        raise ConfigError(f"smape-temporal needs frames (B, C, H, W) or clips (B, T, C, H, W), got {tuple(denoised.shape)}")
    dims = tuple(range(1, reference.dim()))
    mean = reference.mean(dim=dims, keepdim=True).clamp(min=0.0) + 1e-8
    x, y = denoised / mean, reference / mean
    if x.dim() == 4 or x.shape[1] == 1:
        return 8.0 * smape(x, y)
    return 2.0 * smape(x, y) + 0.2 * smape(x[:, 1:] - x[:, :-1], y[:, 1:] - y[:, :-1])


@register_loss("l2-tonemap")
def l2_tonemap(denoised: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """Mean squared error on tone-mapped values (eq. 7), the paper's alternative loss (appendix C)."""
    return torch.mean((tonemap(denoised) - tonemap(reference)) ** 2)


@register_loss("l1")
def l1(denoised: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """Mean absolute error on tone-mapped values (eq. 7)."""
    return torch.mean(torch.abs(tonemap(denoised) - tonemap(reference)))


@register_loss("l1-temporal")
def l1_temporal_log(denoised: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """Eq. 4 of Hasselgren et al. 2020 in their log space (``training.logspace``):
    ``L1(x_T, y_T) + L1(dx_T, dy_T)``, the spatial term on the last frame of a clip (B, T, 3, H, W)
    and the temporal one on the difference of its last two frames (``dx_T = x_T - x_{T-1}``), equally
    weighted. Single frames (B, 3, H, W) or T = 1: the spatial term only."""
    from .logspace import squeeze
    if denoised.dim() == 4:
        return torch.mean(torch.abs(squeeze(denoised) - squeeze(reference)))
    if denoised.dim() != 5:
        raise ConfigError(f"l1-temporal needs frames (B, C, H, W) or clips (B, T, C, H, W), got {tuple(denoised.shape)}")
    x, y = squeeze(denoised[:, -1]), squeeze(reference[:, -1])
    loss = torch.mean(torch.abs(x - y))
    if denoised.shape[1] >= 2:
        dx = x - squeeze(denoised[:, -2])
        dy = y - squeeze(reference[:, -2])
        loss = loss + torch.mean(torch.abs(dx - dy))
    return loss
