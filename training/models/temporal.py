"""Neural temporal adaptive sampling and denoising (Hasselgren, Munkberg, Salvi, Patney & Lefohn 2020).

Two U-nets of 3x3 convolutions (figure 3), run once per frame with the previous output as the only
recurrent state:

* **Sampler** (sec. 2.1): sees the warped previous output and the current albedo as grey (CCIR 601,
  sec. 2.2), the normal, the depth and the motion, and predicts one map ``s``; eq. 2 turns it into
  integer per-pixel counts with mean ``n`` (:mod:`training.adaptive`), and the frame is "rendered" by
  composing the stored sample layers at those counts, with Kuznetsov et al.'s renderer gradient.
* **Denoiser**: sees the sampled radiance, its per-pixel count, the warped previous output and the
  same guides, and predicts at full resolution two 5x5 kernels (the current frame, the warped
  history) and the blend ``alpha'`` (51 channels), and at 1/2 and 1/4 resolution a 5x5 kernel and a
  scale weight ``alpha`` (26 each). The kernels filter the sampled radiance and its 2x and 4x box
  downsamplings; the scales are combined by eq. 3 (Vogels et al. 2018), coarsest first; the filtered
  history is blended in with ``alpha'``.

Everything runs in the paper's log space (:mod:`training.logspace`); kernels are softmax-normalised,
so the output stays within the range of its inputs. Warping is bilinear ``grid_sample`` at
``p + motion`` (the store's motion is ``p_prev - p_cur`` in pixels; ``_pixel.warp``).

**Recurrence.** Training unrolls a window of T frames (5: one to initialise, four unrolled steps,
sec. 2.1): the history of frame 1 is frame 0's noisy uniform ``n``-spp image, and the output has the
window's T frames (frame 0: that noisy image), so eq. 4's loss sees the last two. Evaluation runs
clip by clip with :meth:`step`; a clip's first frame has no history, so it is sampled uniformly at
``n`` spp (the same budget) and its history input is that image itself.

**Settings.** ``size`` ``"large"`` (the paper's LARGE; our widths: a 0.90M-weight denoiser and a
0.56M sampler, against the paper's "~850k" U-nets) or ``"small"`` (its SMALL: 0.31M in all, a third
of LARGE's FMAs); explicit
``sampler_*``/``denoiser_*`` widths override them. ``adaptive=False`` gives the paper's uniform
baseline (a constant map, ``s_hat = n``); ``recurrent=False`` the per-frame one (no history: zero
history input, no temporal kernel). ``frames`` is the unroll length. Registered variants:
``temporal-small`` (SMALL), ``temporal-uniform`` and ``temporal-perframe`` (uniform and per-frame,
for the report's baselines).

Departures: the paper's supplemental widths are not public, so the widths are ours; the sample
count is a denoiser input channel (``log2(1 + s_hat) / 6``), which the paper leaves implicit, so a
pixel given 0 samples is marked; soft-bounded U-net outputs (``common.UNet``).
"""
from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from core.checks import known_keys, need, need_int

from .. import adaptive
from ..errors import ConfigError
from ..inputs import InputSpec
from ..logspace import squeeze, unsqueeze
from ._pixel import clean_albedo, warp
from .common import Denoiser, UNet, replicate_pad, xavier_init
from .registry import register

KERNEL = 5
K2 = KERNEL * KERNEL
GREY = (0.2989, 0.587, 0.114)            # CCIR 601 (sec. 2.2)
SAMPLER_IN = 8                           # grey history, grey albedo, normal 3, depth, motion 2
DENOISER_IN = 16                         # radiance 3, count, history 3, albedo 3, normal 3, depth, motion 2
MOTION_SCALE = 8.0                       # motion input: tanh(m / 8 px)

SIZES = {
    "large": dict(
        sampler_encoder=((24, 24), (32,), (48,), (64,), (80,)), sampler_bottleneck=(96,),
        sampler_decoder=((80, 80), (64, 64), (48, 48), (32, 32), (24, 24)),
        denoiser_encoder=((32, 32), (48,), (64,), (80,), (96,)), denoiser_bottleneck=(96,),
        denoiser_decoder=((96, 96), (80, 80), (64, 64), (48, 48), (32, 32))),
    "small": dict(
        sampler_encoder=((12,), (16,), (24,), (32,)), sampler_bottleneck=(32,),
        sampler_decoder=((32,), (24,), (16,), (12,)),
        denoiser_encoder=((24,), (32,), (48,), (64,)), denoiser_bottleneck=(64,),
        denoiser_decoder=((64,), (48,), (32,), (24,))),
}


def grey(x: torch.Tensor) -> torch.Tensor:
    """CCIR 601 grey of B3HW: the weights are Python numbers, kernel arguments, where a tensor made from
    them at every call was a host-to-device copy (a sync point on a GPU) each time."""
    return x[:, 0:1] * GREY[0] + x[:, 1:2] * GREY[1] + x[:, 2:3] * GREY[2]


def apply_kernel(x: torch.Tensor, logits: torch.Tensor) -> torch.Tensor:
    """``out(p) = sum_t softmax(logits(p))_t x(p + off_t)`` over a 5x5 window, replicate borders.
    x (B C H W), logits (B 25 H W) in ``unfold`` order (row-major offsets)."""
    b, c, h, w = x.shape
    k = torch.softmax(logits, dim=1)
    cols = F.unfold(replicate_pad(x, (KERNEL // 2,) * 4), KERNEL).view(b, c, K2, h, w)
    return (cols * k.unsqueeze(1)).sum(dim=2)


def down(x: torch.Tensor) -> torch.Tensor:
    """D: 2x2 box downsampling."""
    return F.avg_pool2d(x, 2)


def up(x: torch.Tensor) -> torch.Tensor:
    """U: nearest-neighbour 2x upsampling."""
    return F.interpolate(x, scale_factor=2, mode="nearest")


def combine_scales(fine: torch.Tensor, coarse: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Eq. 3, ``o = i^f - alpha U D i^f + alpha U i^c``, with ``alpha`` predicted at the coarse scale
    and upsampled with U (so ``alpha_p = (U alpha)_p``): ``o = i^f + U(alpha (i^c - D i^f))``."""
    return fine + up(alpha * (coarse - down(fine)))


@register("temporal")
class TemporalDenoiser(Denoiser):
    """Sampler and recurrent kernel-predicting denoiser of Hasselgren et al. 2020 (module docstring)."""

    inputs = InputSpec("sampled-layers", frames=5, default_spp=4)
    train_defaults = dict(loss="l1-temporal", lr=1e-3, grad_clip_norm=0.0, grad_clip_value=0.0, warmup=0)
    # tiny widths but for the sampler's bottleneck, which each variant takes from its own size (LARGE's 96
    # channels, SMALL's 32, at 1/8 resolution: cheap), so tiny temporal and temporal-small differ as the
    # full-size ones do and their pinned outputs (tests/test_pinned_outputs.py) tell them apart
    tiny = dict(sampler_encoder=((4,), (4,), (4,)), sampler_decoder=((4,), (4,), (4,)),
                denoiser_encoder=((6,), (6,), (6,)), denoiser_bottleneck=(6,), denoiser_decoder=((6,), (6,), (6,)),
                frames=3)
    realtime = True
    size_default = "large"
    adaptive_default = True
    recurrent_default = True

    def __init__(self, size: str | None = None, adaptive: bool | None = None, recurrent: bool | None = None,
                 frames: int = 5, **widths):
        size = self.size_default if size is None else size
        need(size in SIZES, '"size"', f"one of {sorted(SIZES)}", size, ConfigError)
        adaptive = self.adaptive_default if adaptive is None else adaptive
        recurrent = self.recurrent_default if recurrent is None else recurrent
        need(isinstance(adaptive, bool), '"adaptive"', "true or false", adaptive, ConfigError)
        need(isinstance(recurrent, bool), '"recurrent"', "true or false", recurrent, ConfigError)
        need_int('"frames" (the training unroll)', frames, 2, None, ConfigError)
        known_keys(widths, SIZES["large"], f"{type(self).__name__} widths", ConfigError, noun="setting(s)")
        w = {**SIZES[size], **widths}
        super().__init__(size=size, adaptive=adaptive, recurrent=recurrent, frames=frames, **widths)
        self.adaptive, self.recurrent, self.frames = adaptive, recurrent, frames
        self.sampler = UNet(SAMPLER_IN, 1, w["sampler_encoder"], w["sampler_bottleneck"], w["sampler_decoder"]) \
            if adaptive else None
        self.denoiser = UNet(DENOISER_IN, 2 * K2 + 1, w["denoiser_encoder"], w["denoiser_bottleneck"],
                             w["denoiser_decoder"])
        need(self.denoiser.depth >= 3, "the denoiser U-net's depth (levels)",
             "at least 3 (kernels at 1, 1/2 and 1/4 resolution)", self.denoiser.depth, ConfigError)
        self.head1 = nn.Conv2d(self.denoiser.decoder_channels(1), K2 + 1, 3, padding=1)
        self.head2 = nn.Conv2d(self.denoiser.decoder_channels(2), K2 + 1, 3, padding=1)
        xavier_init(self)

    # ------------------------------------------------------------------ declaration
    def declared_inputs(self) -> InputSpec:
        return InputSpec("sampled-layers", frames=self.frames if self.recurrent else 1,
                         default_spp=self.inputs.default_spp)

    # ------------------------------------------------------------------ parts
    @staticmethod
    def guides(frame: dict) -> tuple[torch.Tensor, ...]:
        alb = clean_albedo(frame["albedo"])
        nrm = (torch.nan_to_num(frame["normal"], nan=0.0).clamp(-1.0, 1.0) + 1.0) * 0.5
        d = torch.nan_to_num(frame["depth"], nan=0.0, posinf=0.0).clamp(min=0.0)
        d = d / (d.amax(dim=(1, 2, 3), keepdim=True) + 1e-6)
        mot = torch.tanh(torch.nan_to_num(frame["motion"], nan=0.0, posinf=0.0, neginf=0.0) / MOTION_SCALE)
        return alb, nrm, d, mot

    def sample_map(self, history: torch.Tensor, guides) -> torch.Tensor:
        alb, nrm, d, mot = guides
        x = torch.cat((grey(history), grey(alb), nrm, d, mot), dim=1)
        return self.sampler(x)[0]

    def denoise(self, rad: torch.Tensor, counts: torch.Tensor, history: torch.Tensor, guides) -> torch.Tensor:
        """Filtered image in log space (B 3 H W) from sampled log-space radiance ``rad``, ``counts``
        (B 1 H W) and the warped log-space ``history``."""
        alb, nrm, d, mot = guides
        h, w = rad.shape[-2:]
        ph, pw = (-h) % 4, (-w) % 4                     # three scales: sizes divisible by 4
        cnt = torch.log2(1.0 + counts.to(rad.dtype)) / 6.0
        x = torch.cat((rad, cnt, history, alb, nrm, d, mot), dim=1)
        if ph or pw:
            pad = (0, pw, 0, ph)
            x, rad, history = (replicate_pad(t, pad) for t in (x, rad, history))
        out0, dec = self.denoiser(x)
        out1, out2 = self.head1(dec[1]), self.head2(dec[2])
        i0 = rad
        i1 = down(i0)
        i2 = down(i1)
        f2 = apply_kernel(i2, out2[:, :K2])
        f1 = combine_scales(apply_kernel(i1, out1[:, :K2]), f2, torch.sigmoid(out2[:, K2:]))
        f0 = combine_scales(apply_kernel(i0, out0[:, :K2]), f1, torch.sigmoid(out1[:, K2:]))
        if self.recurrent:
            a = torch.sigmoid(out0[:, 2 * K2:])
            f0 = a * apply_kernel(history, out0[:, K2:2 * K2]) + (1.0 - a) * f0
        return f0[..., :h, :w]

    def budget(self, frame: dict) -> torch.Tensor:
        """The average budget ``n`` per pixel of each item (B,): the dataset's ``spp``."""
        b, dev = frame["layers"].shape[0], frame["layers"].device
        n = frame.get("spp")
        if isinstance(n, torch.Tensor):
            return n.to(device=dev, dtype=torch.float32).reshape(-1).expand(b)
        # a number is the fill value of a kernel, not a tensor copied from the host at every call
        return torch.full((b,), float(self.inputs.default_spp if n is None else n), device=dev)

    # ------------------------------------------------------------------ recurrence
    def step(self, frame: dict, state: dict | None):
        """One frame: ``frame`` holds ``layers (B L 3 H W)``, ``albedo``, ``normal``, ``depth``,
        ``motion`` and optionally ``spp`` (B,); ``state`` the previous step's (None: a clip's first
        frame). Returns ``(radiance (B 3 H W) linear, new state, {"counts": (B 1 H W) int64})``. Nothing is
        read back from the device: the layers are taken to hold 1, 2, 4 ... samples and the budget to lie
        within them, as the dataset that reads them checks (:class:`training.datasets.LayerFrames`)."""
        layers = adaptive.clean_layers(frame["layers"])
        cap = 2 ** layers.shape[1] - 1
        n = self.budget(frame)
        guides = self.guides(frame)
        if state is None:                                        # first frame: uniform n spp
            counts = adaptive.uniform_counts(layers[:, 0], n)
            rad = squeeze(adaptive.compose(layers, counts, checked=False))
            history = rad if self.recurrent else torch.zeros_like(rad)
        else:
            history = warp(state["history"], frame["motion"])[0] if self.recurrent else torch.zeros_like(
                state["history"])
            if self.adaptive:
                cont, counts = adaptive.sample_counts(self.sample_map(history, guides), n, cap)
                rad = squeeze(adaptive.compose(layers, counts, cont, checked=False))
            else:
                counts = adaptive.uniform_counts(layers[:, 0], n)
                rad = squeeze(adaptive.compose(layers, counts, checked=False))
        out = self.denoise(rad, counts, history, guides)
        return unsqueeze(out), {"history": out}, {"counts": counts}

    def first_frame(self, frame: dict):
        """A window's first frame (training over windows, :meth:`training.inputs.InputKind.unroll`): the
        noisy uniform image at the budget, which starts the history, frames 1.. being the steps."""
        n = self.budget(frame)
        noisy = squeeze(adaptive.compose(adaptive.clean_layers(frame["layers"]),
                                         adaptive.uniform_counts(frame["layers"][:, 0], n), checked=False))
        return unsqueeze(noisy), {"history": noisy}

    # ------------------------------------------------------------------ costs
    def fmas_per_pixel(self, spp: int) -> float:
        from .common import conv_fmas
        total = self.denoiser.fmas_per_pixel() + conv_fmas(self.head1) / 4 + conv_fmas(self.head2) / 16
        total += 3 * K2 * (1 + 1 / 4 + 1 / 16) + (3 * K2 if self.recurrent else 0)   # kernel taps
        if self.sampler is not None:
            total += self.sampler.fmas_per_pixel()
        return float(total)


@register("temporal-small")
class TemporalSmall(TemporalDenoiser):
    """The paper's SMALL configuration (a third of LARGE's cost)."""

    size_default = "small"


@register("temporal-uniform")
class TemporalUniform(TemporalDenoiser):
    """The paper's "our uniform": the recurrent denoiser on uniform n-spp input (a constant map)."""

    adaptive_default = False
    tiny = {**TemporalDenoiser.tiny, "adaptive": False}


@register("temporal-perframe")
class TemporalPerFrame(TemporalDenoiser):
    """Per-frame denoising without recurrence (the paper's "KPN"): uniform n spp, no history."""

    adaptive_default = False
    recurrent_default = False
    tiny = {**TemporalDenoiser.tiny, "adaptive": False, "recurrent": False}
