"""The log space of the temporal adaptive-sampling paper (Hasselgren et al. 2020, sec. 2.2).

Inputs are clamped to [0, 65535] and transformed as ``x' = log(x + 1) ^ (1 / 2.2)`` ("the 2^e exposure
scaling of most tonemappers", then gamma); the networks filter and the losses compare in that space.
``pow`` has an infinite slope at 0, so the log is offset by ``LOG_OFFSET`` inside the power and the
offset's image subtracted: ``x' = (log(x + 1) + e)^(1/2.2) - e^(1/2.2)``, still 0 at 0, with a finite
slope there (68), and within 2e-4 of the paper's curve above x = 0.1. NaN and -Inf become 0, +Inf
the clamp's top.
"""
from __future__ import annotations

import torch

CLAMP = 65535.0
GAMMA = 2.2
LOG_OFFSET = 1e-4
_BASE = LOG_OFFSET ** (1.0 / GAMMA)


def squeeze(x: torch.Tensor) -> torch.Tensor:
    """Linear radiance (any layout) -> the paper's log space, element-wise."""
    x = torch.nan_to_num(x, nan=0.0, posinf=CLAMP, neginf=0.0).clamp(0.0, CLAMP)
    return (torch.log1p(x) + LOG_OFFSET).pow(1.0 / GAMMA) - _BASE


TOP = float((torch.log1p(torch.tensor(CLAMP)) + LOG_OFFSET) ** (1.0 / GAMMA) - _BASE)


def unsqueeze(y: torch.Tensor) -> torch.Tensor:
    """The inverse of :func:`squeeze` on [0, squeeze(CLAMP)]: ``exp((y + e^(1/2.2))^2.2 - e) - 1``."""
    z = (y.clamp(min=0.0, max=TOP) + _BASE).pow(GAMMA) - LOG_OFFSET
    return torch.expm1(z.clamp(min=0.0))
