"""Shared parts of the kernel-predicting denoisers (Munkberg & Hasselgren 2020, appendix B).

Layouts: per-sample radiance (float32, BS3HW) linear; per-sample features (float32, BS17HW) in the
order of ``stores.contract.FEATURE_NAMES``; kernels (float32, B k*k H W) non-negative; images
(float32, BCHW). All fully connected parts are 1x1 convolutions, activations leaky ReLU 0.01,
Xavier-uniform initialisation with zero biases.

Kernel application is vectorised with ``unfold`` (gather) and ``fold`` (splat); no Python loop runs
over pixels, samples or layers.
"""
from __future__ import annotations

from dataclasses import replace
from typing import Sequence

import torch
import torch.nn as nn
import torch.nn.functional as F

from stores.contract import FEATURE_GROUPS, NUM_FEATURES

from core.checks import need
from ..errors import ConfigError
from ..inputs import InputSpec, check_feature_groups, mask_features
from .robust import OUTLIER_K, bound_outliers, check_outliers

NEG_SLOPE = 0.01
EPS = 1e-6            # occupancy / weight-sum epsilon (NVlabs/layerdenoise EPSILON)
IN_FEATURES = 3 + NUM_FEATURES   # 20 floats per sample

# Figure 3 U-net, feature counts of NVlabs/layerdenoise (layer_network.py): five 2x2 max-pool levels.
PAPER_UNET = dict(
    unet_encoder=((64, 64), (128,), (256,), (512,), (512,)),
    unet_bottleneck=(512,),
    unet_decoder=((512, 512), (256, 256), (128, 128), (128, 128), (128, 128)),
)


def flush_denormals() -> None:
    """Flush float32 denormals to zero on the CPU (a process-wide torch setting). Kernel taps
    exp(logit - max) far below the largest underflow into denormals as training sharpens the kernels;
    CPU arithmetic on them is slow: one LAYER training step at 64x64 took 4.2 s with them and 2.2 s
    without (step 400 of configs/train-cpu.yaml). Values below 1.2e-38 change nothing in the output."""
    torch.set_flush_denormal(True)


def act() -> nn.Module:
    """Leaky ReLU 0.01, in place (every activation follows a convolution whose output is fresh)."""
    return nn.LeakyReLU(NEG_SLOPE, inplace=True)


def _pointwise(weight: torch.Tensor, bias, x: torch.Tensor) -> torch.Tensor:
    """1x1 convolution of x (N, Cin, P) as one batched matmul: (N, Cout, P). PyTorch's CPU conv sends
    1x1 kernels through im2col + gemm; a bmm skips the copy (1.4-2.7x on this CPU)."""
    wt = weight.reshape(weight.shape[0], -1)
    y = torch.bmm(wt.expand(x.shape[0], *wt.shape), x)          # bmm beats matmul's transposed copy
    return y if bias is None else y + bias.view(-1, 1)


class MLP(nn.Sequential):
    """Fully connected network as 1x1 convolutions (``nn.Conv2d`` children, so checkpoints and FMA
    counts see ordinary convolutions), evaluated as matmuls.

    ``mlp(x)`` takes x (float32, N C H W). ``mlp(items, shared)`` takes per-item inputs
    items (float32, B K Cx H W) (K samples or layers) and per-pixel inputs shared (float32, B Cc H W)
    and returns (B K Cout H W), equal to running the network on ``cat((items, shared broadcast over
    K), dim=2)``; the first layer is split as W [x; c] = W_x x + W_c c, so the shared part is computed
    once per pixel instead of K times and the broadcast concatenation is never materialised.
    """

    def forward(self, x: torch.Tensor, shared: torch.Tensor | None = None) -> torch.Tensor:
        mods = list(self)
        first = mods[0]
        if shared is None:
            n, _, h, w = x.shape
            y = _pointwise(first.weight, first.bias, x.reshape(n, x.shape[1], h * w))
            lead = (n,)
        else:
            b, k, cx, h, w = x.shape
            cc = shared.shape[1]
            if first.in_channels != cx + cc:
                raise ConfigError(f"MLP expects {first.in_channels} input channels, got {cx} + {cc} shared")
            wt = first.weight.view(first.out_channels, -1)
            y = _pointwise(wt[:, :cx], None, x.reshape(b * k, cx, h * w)).view(b, k, -1, h * w)
            y = y + _pointwise(wt[:, cx:], first.bias, shared.reshape(b, cc, h * w)).unsqueeze(1)
            y = y.view(b * k, first.out_channels, h * w)
            lead = (b, k)
        for m in mods[1:]:
            if isinstance(m, nn.Conv2d):
                y = _pointwise(m.weight, m.bias, y)
            else:
                y = m(y)
        return y.view(*lead, y.shape[1], h, w)

    def fmas(self, items: int = 1, shared: int = 0) -> int:
        """FMAs per pixel of ``forward`` on ``items`` items whose last ``shared`` input channels are
        the per-pixel shared input (computed once, not per item)."""
        return items * conv_fmas(self) - (items - 1) * shared * self[0].out_channels


def mlp(cin: int, hidden: Sequence[int], cout: int, last_act: bool = False) -> MLP:
    """Fully connected network as 1x1 convolutions: cin -> hidden... -> cout, leaky ReLU between."""
    layers: list[nn.Module] = []
    prev = cin
    for h in hidden:
        layers += [nn.Conv2d(prev, h, 1), act()]
        prev = h
    layers.append(nn.Conv2d(prev, cout, 1))
    if last_act:
        layers.append(act())
    return MLP(*layers)


def conv_fmas(module: nn.Module) -> int:
    """FMAs per output pixel of all Conv2d in ``module`` (Cin/groups * Cout * kh * kw each), bias ignored."""
    total = 0
    for m in module.modules():
        if isinstance(m, nn.Conv2d):
            kh, kw = m.kernel_size
            total += (m.in_channels // m.groups) * m.out_channels * kh * kw
    return total


def xavier_init(module: nn.Module) -> None:
    for m in module.modules():
        if isinstance(m, nn.Conv2d):
            nn.init.xavier_uniform_(m.weight)
            if m.bias is not None:
                nn.init.zeros_(m.bias)


def gaussian_kernel_bias(conv: nn.Conv2d, kernel_size: int, sigma: float) -> None:
    """Start a kernel generator's output layer ``conv`` (first k*k outputs: tap logits in ``unfold``
    order) at a Gaussian of ``sigma`` pixels: bias_t = -|off_t|^2 / (2 sigma^2); further outputs keep
    bias 0; sigma 0 leaves the zero bias.

    With zero biases (plain Xavier) every k x k kernel starts as a box filter: for 17x17 that blurs
    far too much, and the gradient that sharpens it runs through the whole unnormalised U-net, whose
    context then grows until each kernel is one random tap (the LAYER and SAMPLESPLAT splats shifted
    the image instead of filtering it). A Gaussian start is already a denoiser the network refines.
    """
    if sigma <= 0:
        return
    r = torch.arange(kernel_size, dtype=torch.float32) - kernel_size // 2
    d2 = (r[:, None] ** 2 + r[None, :] ** 2).flatten()
    with torch.no_grad():
        conv.bias[: kernel_size * kernel_size].copy_(-d2 / (2.0 * sigma * sigma))


def check_sigma(sigma) -> float:
    sigma = float(sigma)
    need(sigma >= 0, '"kernel_sigma"', ">= 0 pixels (0: box start)", sigma, ConfigError)
    return sigma


def _check_widths(name: str, widths) -> tuple:
    widths = tuple(tuple(int(f) for f in w) if isinstance(w, (list, tuple)) else int(w) for w in widths)
    flat = [f for w in widths for f in (w if isinstance(w, tuple) else (w,))]
    need(bool(flat) and all(f >= 1 for f in flat), f'"{name}"', "non-empty positive feature counts", widths,
         ConfigError)
    return widths


def soft_bound(x: torch.Tensor, dim: int = 1) -> torch.Tensor:
    """x / sqrt(1 + mean over ``dim`` of x^2): the identity while the features are small (at
    initialisation the context has RMS ~0.02), their RMS capped at 1 when they grow."""
    s = x.abs().amax(dim=dim, keepdim=True).clamp(min=1.0)       # computed on x / s: x^2 may overflow
    y = x / s
    return y * torch.rsqrt(s.reciprocal().square() + y.square().mean(dim=dim, keepdim=True))


def replicate_pad(x: torch.Tensor, pad) -> torch.Tensor:
    """``F.pad(x, pad, mode="replicate")`` (``pad``: left, right, top, bottom). Compiled, it is a gather at
    clamped indices, the same values: Inductor's compiled backward of ``replication_pad2d`` fails its own
    stride check on the CPU when a gradient is channels-last (torch 2.13: ``assert_size_stride ...
    replication_pad2d_backward``, "expected stride 1==256"), which stopped ``train --compile`` of the
    temporal family; the gather's backward is a scatter-add with no such check."""
    if not torch.compiler.is_compiling():
        return F.pad(x, pad, mode="replicate")
    left, right, top, bottom = pad
    h, w = x.shape[-2:]
    rows = torch.arange(-top, h + bottom, device=x.device).clamp(0, h - 1)
    cols = torch.arange(-left, w + right, device=x.device).clamp(0, w - 1)
    return x.index_select(-2, rows).index_select(-1, cols)


class UNet(nn.Module):
    """U-net of figure 3: 3x3 convolutions, leaky ReLU 0.01, 2x2 max-pooling, bilinear upsampling,
    skip connections concatenated with the upsampled features, a final 3x3 convolution to ``cout``.

    ``forward(x (float32, BCHW))`` returns ``(out (B cout H W), decoder)`` where ``decoder[i]`` is the
    output of the decoder block at 1/2^i resolution (i = 0 .. depth-1; i = 0 is the last block, before
    the final convolution). Any H, W: the input is padded (replicate) to a multiple of 2^depth and the
    outputs are cropped back to ceil(H / 2^i).

    Both outputs pass through :func:`soft_bound` (per pixel, over channels), the one departure from
    figure 3. Nothing in the unnormalised U-net limits the scale of its output, and Adam grows it:
    kernel sharpness and the sample partition are set by logit magnitudes, and scaling the whole
    context is the cheapest way to change them. On configs/train-cpu.yaml LAYER's context reached RMS
    1e26 by step 1000 (every kernel a single centre tap, the partition all in one layer, the output
    the noisy input, gradients exactly zero). The bound is the identity at initialisation.
    """

    def __init__(self, cin: int, cout: int, encoder, bottleneck, decoder):
        super().__init__()
        encoder = _check_widths("unet_encoder", encoder)
        decoder = _check_widths("unet_decoder", decoder)
        bottleneck = _check_widths("unet_bottleneck", bottleneck)
        if len(encoder) != len(decoder):
            raise ConfigError(f'"unet_decoder" must have as many blocks as "unet_encoder" ({len(encoder)}), '
                              f"got {len(decoder)}")
        self.depth = len(encoder)
        self.cin, self.cout = cin, cout

        def block(prev, feats):
            layers = []
            for f in feats:
                layers += [nn.Conv2d(prev, f, 3, padding=1), act()]
                prev = f
            return nn.Sequential(*layers), prev

        prev = cin
        skips = [cin]
        self.enc = nn.ModuleList()
        for feats in encoder:
            b, prev = block(prev, feats)
            self.enc.append(b)
            skips.append(prev)
        self.bottleneck, prev = block(prev, bottleneck)
        self.dec = nn.ModuleList()
        self.dec_channels = []
        for idx, feats in enumerate(decoder):
            skip = skips[self.depth - 1 - idx]
            b, prev = block(prev + skip, feats)
            self.dec.append(b)
            self.dec_channels.append(prev)
        self.final = nn.Conv2d(prev, cout, 3, padding=1)

    def decoder_channels(self, level: int) -> int:
        """Channels of the decoder output at 1/2^level resolution."""
        return self.dec_channels[self.depth - 1 - level]

    def forward(self, x: torch.Tensor):
        h, w = x.shape[-2:]
        m = 2 ** self.depth
        ph, pw = (-h) % m, (-w) % m
        if ph or pw:
            x = replicate_pad(x, (0, pw, 0, ph))
        x = x.contiguous(memory_format=torch.channels_last)   # oneDNN's native layout: 1.3x on CPU
        skips = [x]
        for b in self.enc:
            x = F.max_pool2d(b(x), 2)
            skips.append(x)
        x = self.bottleneck(x)
        outs = []
        for idx, b in enumerate(self.dec):
            x = F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False)
            x = b(torch.cat((x, skips[self.depth - 1 - idx]), dim=1))
            outs.append(x)
        out = self.final(x)
        decoder = []
        for level in range(self.depth):
            d = outs[self.depth - 1 - level]
            decoder.append(soft_bound(d[..., : -(-h // 2 ** level), : -(-w // 2 ** level)]))
        return soft_bound(out[..., :h, :w]), decoder

    def fmas_per_pixel(self) -> float:
        """Convolution FMAs per full-resolution pixel (each level costs 1/4 of the one above)."""
        total = 0.0
        for i, b in enumerate(self.enc):           # encoder block i runs at 1/2^i before its pool
            total += conv_fmas(b) / 4 ** i
        total += conv_fmas(self.bottleneck) / 4 ** self.depth
        for idx, b in enumerate(self.dec):          # decoder block idx runs at 1/2^(depth-1-idx)
            total += conv_fmas(b) / 4 ** (self.depth - 1 - idx)
        return total + conv_fmas(self.final)


# ---------------------------------------------------------------------------------------------
# Inputs


def _signed_log(x: torch.Tensor) -> torch.Tensor:
    return torch.sign(x) * torch.log1p(torch.abs(x))


def prepare_inputs(radiance: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
    """Robust network inputs (float32, BS20HW) from radiance (BS3HW) and features (BS17HW).

    Radiance -> log1p(max(L, 0)); depth -> depth / per-frame max depth (in [0, 1]); motion and
    circle of confusion (pixels, unbounded) -> sign(x) log1p|x|; the rest (normals, albedo, specular,
    roughness, lens, time) is already bounded. Non-finite values become 0. Kernels still apply to the
    LINEAR radiance; this only feeds the embedding networks.
    """
    if radiance.dim() != 5 or radiance.shape[2] != 3:
        raise ConfigError(f"radiance must be (B, S, 3, H, W), got {tuple(radiance.shape)}")
    if features.dim() != 5 or features.shape[2] != NUM_FEATURES or features.shape[:2] != radiance.shape[:2] \
            or features.shape[-2:] != radiance.shape[-2:]:
        raise ConfigError(f"features must be (B, S, {NUM_FEATURES}, H, W) matching radiance "
                          f"{tuple(radiance.shape)}, got {tuple(features.shape)}")
    rad = torch.log1p(torch.clamp(torch.nan_to_num(radiance, nan=0.0, posinf=0.0, neginf=0.0), min=0.0))
    f = torch.nan_to_num(features, nan=0.0, posinf=0.0, neginf=0.0)
    g = FEATURE_GROUPS
    depth = torch.clamp(f[:, :, g["depth"]], min=0.0)
    dmax = depth.amax(dim=(1, 2, 3, 4), keepdim=True)
    depth = depth / (dmax + EPS)
    parts = [rad, f[:, :, g["normal"]], depth, f[:, :, g["albedo"]], f[:, :, g["specular"]],
             f[:, :, g["roughness"]], _signed_log(f[:, :, g["motion"]]), _signed_log(f[:, :, g["coc"]]),
             f[:, :, g["lens"]], f[:, :, g["time"]]]
    return torch.cat(parts, dim=2)


def clean_radiance(radiance: torch.Tensor) -> torch.Tensor:
    """Linear radiance with non-finite values set to 0 and negatives clamped (any layout)."""
    return torch.clamp(torch.nan_to_num(radiance, nan=0.0, posinf=0.0, neginf=0.0), min=0.0)


# ---------------------------------------------------------------------------------------------
# Kernels


def exp_kernels(logits: torch.Tensor, dims) -> torch.Tensor:
    """exp(logits - max over ``dims``): positive kernel weights whose largest tap is exactly 1, so the
    exponent never overflows and the weight sum never underflows to 0 (appendix A, line 26)."""
    m = logits.detach().amax(dim=dims, keepdim=True)
    return torch.exp(logits - m)


def gather(x: torch.Tensor, kernels: torch.Tensor, kernel_size: int) -> torch.Tensor:
    """Gather: out(p) = sum_t K_p[t] x(p + off_t); x (float32, BCHW), kernels (B k*k H W), zero padding.
    Taps ``t`` are row-major over offsets (-r..r, -r..r), r = k // 2 (``unfold`` order)."""
    b, c, h, w = x.shape
    k2 = kernel_size * kernel_size
    cols = F.unfold(x, kernel_size, padding=kernel_size // 2).view(b, c, k2, h * w)
    return (cols * kernels.reshape(b, 1, k2, h * w)).sum(dim=2).view(b, c, h, w)


def splat_columns(cols: torch.Tensor, kernel_size: int) -> torch.Tensor:
    """Splat precomputed contributions cols (B, C, k*k, H, W): out(q + off_t) += cols[:, :, t, q]."""
    b, c, k2, h, w = cols.shape
    return F.fold(cols.reshape(b, c * k2, h * w), (h, w), kernel_size, padding=kernel_size // 2)


def splat(x: torch.Tensor, kernels: torch.Tensor, kernel_size: int) -> torch.Tensor:
    """Splat (adjoint of :func:`gather`): out(p) = sum_t K_{p - off_t}[t] x(p - off_t).
    x (float32, BCHW), kernels (B k*k H W); contributions that leave the frame are dropped."""
    return splat_columns(x.unsqueeze(2) * kernels.unsqueeze(1), kernel_size)


def check_kernel_size(k: int) -> int:
    k = int(k)
    need(k >= 1 and k % 2 == 1, '"kernel_size"', "an odd integer >= 1", k, ConfigError)
    return k


# ---------------------------------------------------------------------------------------------
# Base class


class Denoiser(nn.Module):
    """Base of every denoiser. ``forward(batch)`` takes a batch dict of the model's input kind (see
    :mod:`training.inputs`; for the default ``samples`` kind: ``radiance`` (float32, BS3HW),
    ``features`` (float32, BS17HW), guides) and returns linear radiance (float32, B3HW). ``config``
    holds the settings that rebuild the model with ``build(name, **config)``.

    Class attributes declare what the model consumes and how it trains by default, so the training
    stack needs no per-model code: ``inputs`` (an :class:`~training.inputs.InputSpec`; override
    :meth:`input_spec` when it depends on settings), ``train_defaults`` (TrainConfig settings such as
    ``loss`` and ``lr`` that differ from the layer family's) and ``tiny`` (settings for test-sized
    models, used by the contract tests); ``realtime`` marks the real-time denoisers, whose compiled form
    on a GPU replays CUDA graphs (:func:`training.accel.compile_options`).
    """

    name = "?"
    inputs = InputSpec("samples", frames=1, default_spp=8)
    train_defaults: dict = {}
    tiny: dict = {}
    realtime = False        # a real-time denoiser: compiled with CUDA graphs on a GPU (training.accel)
    outlier_bound = 0.0     # the default of the setting ``outliers`` (training.models.robust; 0: the model has none)
    # settings a checkpoint written before they existed was trained with (training.checkpoint.build_model)
    legacy_config: dict = {"outliers": 0.0}

    def __init__(self, **config):
        super().__init__()
        self.config = dict(config)
        self.feature_groups: tuple[str, ...] = type(self).inputs.features    # use_features narrows them
        self.use_outliers(type(self).outlier_bound)

    def declared_inputs(self) -> InputSpec:
        """The model's input declaration (override where it depends on settings)."""
        return type(self).inputs

    def input_spec(self) -> InputSpec:
        """:meth:`declared_inputs` with the feature groups the model reads (:meth:`use_features`)."""
        spec = self.declared_inputs()
        return spec if self.feature_groups == spec.features else replace(spec, features=self.feature_groups)

    def prepare_inputs(self, radiance: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        """:func:`prepare_inputs` of the feature groups the model reads (the others 0)."""
        return prepare_inputs(radiance, mask_features(features, self.feature_groups))

    def use_features(self, groups) -> "Denoiser":
        """Read only the per-sample feature ``groups`` (names of ``stores.contract.FEATURE_GROUPS``): the
        others reach the network as 0 (:func:`training.inputs.mask_features`), so a model trains on data
        that lacks them (Noisebase has no specular, roughness, CoC, lens or time). The model setting
        ``features`` (``--model-cfg '{"features": ["normal", "depth", "albedo", "motion"]}'``)."""
        self.feature_groups = check_feature_groups(groups, f"model {self.name!r}: setting \"features\"")
        self.config["features"] = list(self.feature_groups)
        return self

    def use_outliers(self, k) -> "Denoiser":
        """Bound what the model's filter spreads: values above ``k`` times their neighbourhood's level are
        cut before filtering (:func:`training.models.robust.bound_outliers`; 0: off). The model setting
        ``outliers`` (``--model-cfg '{"outliers": 0}'``); the kernel-predicting models default to
        :data:`training.models.robust.OUTLIER_K`. The temporal family has no bound (it stayed below its
        input on the fireflies and the sun without one): it refuses ``outliers`` above 0."""
        k = check_outliers(k)
        if k and not type(self).outlier_bound:
            raise ConfigError(f'model {self.name!r} does not bound its filter input: "outliers" must be 0, got {k:g}')
        self.outliers = k
        self.config["outliers"] = self.outliers
        return self

    def bound(self, radiance: torch.Tensor) -> torch.Tensor:
        """``radiance`` (non-negative, linear) as the model's filter may see it (:meth:`use_outliers`)."""
        return bound_outliers(radiance, self.outliers)

    def for_inference(self) -> "Denoiser":
        """The form ``evaluate``, ``denoise`` and ``bench`` run (e.g. with re-parameterised branches
        fused); the same function as this model in eval mode. Its weights are channels-last, the layout
        its inputs are given in (:func:`training.accel.prepare`): the same outputs bit for bit; on 2 CPU
        threads at 128x128, nppd 1.13-1.19x faster in three runs of 12-30 paired passes, layer-optimized
        0.94-1.17x, the other models within 0.98-1.06x."""
        return self.eval().to(memory_format=torch.channels_last)

    @property
    def stepwise(self) -> bool:
        """Recurrent: the model defines ``step(frame, state) -> (output, state, extra)``; its input kind
        unrolls it over a window's frames, and evaluation steps it frame by frame in clip order."""
        return type(self).step is not Denoiser.step

    def forward(self, batch: dict) -> torch.Tensor:
        """The kind's way of running the model (:meth:`training.inputs.InputKind.forward`): ``denoise``
        for per-sample frames, ``step`` over the frames of a clip."""
        return self.input_spec().input_kind.forward(self, batch)

    def denoise(self, radiance: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def step(self, frame: dict, state: dict | None):
        raise NotImplementedError(f"model {self.name!r} is not recurrent (it has no step)")

    def first_frame(self, frame: dict):
        """``(output, state)`` of a window's first frame when the input kind unrolls the model over a
        window (:meth:`training.inputs.InputKind.unroll`): its first step, unless a model starts otherwise."""
        out, state, _ = self.step(frame, None)
        return out, state

    def fmas_per_pixel(self, spp: int) -> float:
        """Analytic FMAs per output pixel at ``spp`` samples per pixel (conv layers + kernel taps)."""
        raise NotImplementedError

    def param_count(self) -> int:
        return sum(p.numel() for p in self.parameters())


class KernelBaseline(Denoiser):
    """What PIXELGATHER and SAMPLESPLAT share (Munkberg & Hasselgren 2020, appendix B): a reducer of
    :attr:`reducer_inputs` channels (the per-pixel mean and variance of the 20 inputs, or one sample's 20),
    the fig. 3 U-net on its embedding, and a kernel generator ([embed + context, 128, 128, k*k]) whose last
    layer starts as a Gaussian of ``kernel_sigma``. The two differ in what they reduce and how the kernels
    are applied (gathered per pixel, splatted per sample)."""
    outlier_bound = OUTLIER_K
    reducer_inputs = IN_FEATURES
    tiny = dict(embed=8, context=8, unet_encoder=((8,), (8,), (8,)), unet_bottleneck=(8,),
                unet_decoder=((8,), (8,), (8,)), kernel_size=5, kernel_hidden=(8,))

    def __init__(self, kernel_size: int = 17, kernel_sigma: float = 2.0, embed: int = 32, context: int = 128,
                 kernel_hidden=(128, 128),
                 unet_encoder=PAPER_UNET["unet_encoder"], unet_bottleneck=PAPER_UNET["unet_bottleneck"],
                 unet_decoder=PAPER_UNET["unet_decoder"]):
        kernel_size = check_kernel_size(kernel_size)
        kernel_sigma = check_sigma(kernel_sigma)
        super().__init__(kernel_size=kernel_size, kernel_sigma=kernel_sigma, embed=embed, context=context,
                         kernel_hidden=tuple(kernel_hidden),
                         unet_encoder=unet_encoder, unet_bottleneck=unet_bottleneck, unet_decoder=unet_decoder)
        self.kernel_size, self.embed = kernel_size, embed
        self.reducer = mlp(self.reducer_inputs, (embed, embed), embed, last_act=True)
        self.unet = UNet(embed, context, unet_encoder, unet_bottleneck, unet_decoder)
        self.kernel_gen = mlp(context + embed, kernel_hidden, kernel_size * kernel_size)
        xavier_init(self)
        gaussian_kernel_bias(self.kernel_gen[-1], kernel_size, kernel_sigma)
