"""Adaptive sampling from the stored sample layers, in torch (Hasselgren et al. 2020, sec. 2.1-2.2;
Kuznetsov et al. 2018, "DASR").

A store holds, per frame, independent sample layers ``layers (L, 3, h, w)``: layer ``l`` is the mean
of ``2^l`` samples (1, 2, 4 ... 32 for ``layer_levels`` 6), so any per-pixel count 0 .. 2^L - 1 is
the sum of the layers of its binary digits (13 = 1 + 4 + 8). This module turns a sampler network's
map into such counts and "renders" by composing layers, on the device.

* :func:`sample_counts`: eq. 2, ``s_hat = round(M n softmax(s))`` over the M pixels of each image,
  with the cap ``2^L - 1``: where the cap bites, the cut samples go to the other pixels in
  proportion (water-filling: a per-image scale ``k`` with ``sum min(cap, k M n softmax(s)) = M n``),
  so the achieved mean stays the asked ``n`` up to rounding (at most half a sample per pixel).
* :func:`compose`: ``c(p) = sum_l b_l(p) 2^l c_l(p) / s_hat(p)`` with ``b_l`` the bits of
  ``s_hat(p)``; a pixel given 0 samples gets radiance 0 (never 0/0), and the count is an input
  channel of the denoiser, so "no samples" is visible to it.

**The gradient through rounding and the renderer** (our form of DASR's approximation, sec. 4.2 of
Kuznetsov et al.). DASR writes a pixel rendered with ``N`` initial and ``s`` adaptive samples as
``I = (N I_N + s I~) / (N + s)`` and holds the mean ``I~`` of the adaptive samples constant:
``dI/ds = (I~ - I) / (N + s)``. We have no initial pass; the continuous count ``s`` (before
rounding) passes rounding straight through, and the "new samples" of a pixel are those of the
layers it did not use (independent samples of the same pixel), with mean ``c_u``:

    d c(p) / d s(p)  =  (c_u(p) - c(p)) / (s_hat(p) + 1)

(``+ 1``: defined at ``s_hat = 0``, where one more sample moves the pixel from 0 to about ``c_u``).
A pixel at the cap has no unused layer and gets gradient 0. Through the chain rule the loss pulls
samples towards pixels where the unused samples would move the value the way the loss wants, i.e.
where the estimate is far from converged. The layers themselves (data) get no gradient.
"""
from __future__ import annotations

import torch

from stores.errors import SampleCountError

WATERFILL_ITERATIONS = 16


def check_layer_spp(layer_spp) -> int:
    """Layers must hold 1, 2, 4 ... samples; returns the cap ``sum = 2^L - 1``. ``layer_spp``: the
    counts (a sequence, or a tensor whose last axis holds them). Checked where layers are read (the
    ``sampled-layers`` dataset, :class:`training.datasets.LayerFrames`), once, on the host: the model's
    step trusts the layout it is given and takes the cap from the number of layers, so it reads
    nothing back from the device."""
    if isinstance(layer_spp, torch.Tensor):
        layer_spp = layer_spp.reshape(-1, layer_spp.shape[-1])[0].tolist()
    spp = [float(v) for v in layer_spp]
    if spp != [2.0 ** n for n in range(len(spp))]:
        raise SampleCountError(f"adaptive sampling needs layers of 1, 2, 4 ... spp, got {list(layer_spp)}")
    return 2 ** len(spp) - 1


def check_budget(n, cap: int) -> None:
    """SampleCountError unless every average budget in ``n`` (a number or a sequence) is in (0, cap]."""
    values = [float(v) for v in (n if isinstance(n, (list, tuple)) else [n])]
    if not all(0 < v <= cap for v in values):
        raise SampleCountError(f"average budget must be in (0, {cap}] samples per pixel, got {values}")


def waterfill_scale(ideal: torch.Tensor, n: torch.Tensor, cap: int) -> torch.Tensor:
    """The water-filling scale ``k >= 1`` (B 1 1 1) with ``sum min(cap, k ideal) = M n`` per image, by
    :data:`WATERFILL_ITERATIONS` fixed iterations on the device (no value is read back: each iteration
    caps the pixels the last scale pushed over ``cap`` and rescales the rest; once no new pixel is
    capped, ``k`` repeats itself exactly). ``ideal (B 1 H W)`` = ``M n softmax(s)``."""
    m = ideal.shape[-2] * ideal.shape[-1]
    k = torch.ones_like(n)
    for _ in range(WATERFILL_ITERATIONS):
        capped = k * ideal >= cap
        free = (ideal * ~capped).sum(dim=(1, 2, 3), keepdim=True)
        want = m * n - cap * capped.sum(dim=(1, 2, 3), keepdim=True)
        k = torch.where(free > 0, want / free.clamp(min=1e-30), k)
    return k


def sample_counts(logits: torch.Tensor, n, cap: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Eq. 2 with the cap: ``logits (B 1 H W)`` (the sampler's unnormalised map), ``n`` the average
    budget per pixel (float or (B,) tensor, 0 < n <= cap) -> ``(continuous (B 1 H W), counts (B 1 H W)
    int64)``. ``continuous`` carries the gradient (softmax over each image); ``counts`` is its
    rounding, in 0..cap. The softmax runs over the unrolled image, as the paper recommends. A budget
    given as a number is checked here; a tensor is not read (it is checked where it is made: the
    dataset's ``spp``, :func:`check_budget`), so the function never waits for the device."""
    b, _, h, w = logits.shape
    if not isinstance(n, torch.Tensor):
        check_budget(n, cap)
    n = torch.as_tensor(n, dtype=logits.dtype, device=logits.device).reshape(-1, 1, 1, 1).expand(b, 1, 1, 1)
    logits = torch.nan_to_num(logits, nan=0.0, posinf=80.0, neginf=-80.0)
    share = torch.softmax(logits.reshape(b, h * w), dim=1).reshape(b, 1, h, w)
    ideal = share * (h * w * n)
    with torch.no_grad():                        # water-filling scale k >= 1 per image (no gradient)
        k = waterfill_scale(ideal, n, cap)
    cont = torch.minimum(k * ideal, torch.full_like(ideal, float(cap)))
    counts = torch.round(cont.detach()).clamp(0, cap).to(torch.int64)
    return cont, counts


def layer_masks(counts: torch.Tensor, levels: int) -> torch.Tensor:
    """Bits of ``counts (B 1 H W)`` int: ``(B L 1 H W)`` float, ``[:, l] = (counts >> l) & 1``."""
    shifts = torch.arange(levels, device=counts.device).view(1, levels, 1, 1, 1)
    return ((counts.unsqueeze(1) >> shifts) & 1).to(torch.float32)


def _compose(layers: torch.Tensor, counts: torch.Tensor):
    levels = layers.shape[1]
    n_l = (2.0 ** torch.arange(levels, device=layers.device, dtype=layers.dtype)).view(1, levels, 1, 1, 1)
    weighted = layers * n_l                                     # sums of each layer's samples
    used = (weighted * layer_masks(counts, levels).to(layers.dtype)).sum(dim=1)
    total = weighted.sum(dim=1)
    s = counts.to(layers.dtype)
    cap = float(2 ** levels - 1)
    c = used / s.clamp(min=1.0)                                 # 0 where the count is 0
    c_unused = torch.where(s < cap, (total - used) / (cap - s).clamp(min=1.0), c)
    return c, c_unused


class _Render(torch.autograd.Function):
    """Composition of layers at the rounded counts; backward: the DASR approximation (module doc)."""

    @staticmethod
    def forward(ctx, cont, layers, counts):
        c, c_unused = _compose(layers, counts)
        ctx.save_for_backward(c, c_unused, counts)
        return c

    @staticmethod
    def backward(ctx, grad_c):
        c, c_unused, counts = ctx.saved_tensors
        slope = (c_unused - c) / (counts.to(c.dtype) + 1.0)
        return (grad_c * slope).sum(dim=1, keepdim=True), None, None


def clean_layers(layers: torch.Tensor, clamp: float = 65535.0) -> torch.Tensor:
    """NaN/-Inf -> 0, +Inf and everything above ``clamp`` -> ``clamp`` (the paper's input clamp)."""
    return torch.nan_to_num(layers, nan=0.0, posinf=clamp, neginf=0.0).clamp(0.0, clamp)


def compose(layers: torch.Tensor, counts: torch.Tensor, cont: torch.Tensor | None = None,
            checked: bool = True) -> torch.Tensor:
    """Radiance ``(B 3 H W)`` of the per-pixel ``counts (B 1 H W)`` (int, 0..2^L-1) from ``layers
    (B L 3 H W)`` (cleaned with :func:`clean_layers`); with ``cont`` (the continuous counts of
    :func:`sample_counts`) the result carries the approximate renderer gradient to ``cont``.
    ``checked``: refuse counts outside 0..2^L-1 (reads them back from the device; False for counts in
    range by construction, those of :func:`sample_counts` and :func:`uniform_counts`)."""
    counts = counts.to(torch.int64)
    cap = 2 ** layers.shape[1] - 1
    if checked and not torch.compiler.is_compiling() and (counts.min() < 0 or counts.max() > cap):
        raise SampleCountError(f"per-pixel sample counts must be in 0..{cap}, got "
                               f"{int(counts.min())}..{int(counts.max())}")
    if cont is None:
        return _compose(layers, counts)[0]
    return _Render.apply(cont, layers, counts)


def uniform_counts(like: torch.Tensor, n) -> torch.Tensor:
    """Counts ``(B 1 H W)`` of ``n`` samples in every pixel (n float or (B,), rounded)."""
    b, _, h, w = like.shape[0], 1, like.shape[-2], like.shape[-1]
    n = torch.as_tensor(n, device=like.device).reshape(-1, 1, 1, 1).expand(b, 1, 1, 1)
    return torch.round(n).to(torch.int64).expand(b, 1, h, w).contiguous()
