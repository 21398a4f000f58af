"""What a denoiser consumes: the input kinds, one declaration per model, and the datasets they build.

Every registered model declares an :class:`InputSpec` (``model.input_spec()``): a kind, the number of
consecutive frames it reads, and its default samples per pixel. ``train``, ``evaluate``, ``report``,
``bench``, ``denoise`` and ``hard-cases`` take from the kind the dataset, how the model is run over an
item (:meth:`InputKind.forward`, the time axis included), the training target, the arrays a store must
hold, the largest sample count a store allows, the baselines' noisy image, the item of a rendered frame
or of EXR images, and a random batch for timing; none of them branches on a kind's or a model's name.
The kinds:

* ``samples``: per-sample frames (the layer family): ``radiance (S,3,h,w)``, ``features (S,17,h,w)``
  plus the per-pixel guides (:class:`training.datasets.SampleFrames`); the model's ``denoise(radiance,
  features)`` gives ``(B,3,h,w)``.
* ``pixels``: per-pixel frames at N spp made from the stored per-sample inputs (nbg, wskpn): the mean
  ``radiance (3,h,w)`` of the first N samples and the per-pixel mean of those same samples' albedo,
  normal and depth (real N-spp features, noisy under defocus and motion; not the 8-spp guides), plus
  the stored per-pixel ``motion`` for reprojection. With ``frames = T > 1`` an item is a window of T
  consecutive frames of one clip (leading T axis) and the target is the last frame's reference.
* ``clips``: T consecutive per-sample frames of one clip (every ``samples`` key with a leading T axis).
  The model is recurrent and sees one frame at a time: it implements ``step(frame, state) -> (output
  (B,3,h,w), state, extra)``, and the kind unrolls it over the window (``forward``: ``(B,T,3,h,w)``,
  trained against every frame's reference) or, in evaluation, over each clip in order. The time axis
  is handled here, once.
* ``sampled-layers``: the sample layers ``layers (L,3,h,w)`` of each frame (or of T frames) with the
  guides, for a model whose sampler chooses per-pixel counts and composes the layers itself; the
  average budget per pixel is ``spp`` (at most the sum of the stored layers).

Items are dicts of float32 tensors, channel-first, with ``index`` (int64: the store frame, or (T,)
for windows) and ``origin`` (int64, 2). Crop origin, augmentation and sample choice are functions of
(seed, epoch, frame) only (see :mod:`training.datasets`), so the data a run sees does not depend on the
number of DataLoader workers or their order.
"""
from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
import torch

from core.checks import need, need_int
from stores.contract import FEATURE_GROUPS, NUM_FEATURES

from .datasets import LayerFrames, PixelFrames, SampleFrames, pixel_item_from_samples
from .errors import ConfigError, DataError

GUIDE_ARRAYS = ("reference/radiance", "reference/stderr", "guides/albedo", "guides/normal", "guides/depth",
                "guides/motion")
SAMPLE_ARRAYS = ("inputs/radiance", "inputs/features")
PIXEL_FEATURES = ("normal", "depth", "albedo", "motion")    # what the pixels kind's items hold


ALL_FEATURES = tuple(FEATURE_GROUPS)


def check_feature_groups(groups, what: str = '"features"') -> tuple[str, ...]:
    """``groups`` as a tuple in ``FEATURE_GROUPS`` order, or ConfigError naming the unknown ones."""
    need(not isinstance(groups, str) and all(isinstance(g, str) for g in groups), what,
         f"a list of feature groups {list(ALL_FEATURES)}", groups, ConfigError)
    unknown = [g for g in groups if g not in FEATURE_GROUPS]
    if unknown:
        raise ConfigError(f"{what}: unknown feature groups {unknown}; the groups are {list(ALL_FEATURES)}")
    return tuple(g for g in ALL_FEATURES if g in set(groups))


@dataclass(frozen=True)
class InputSpec:
    """What a model consumes: ``kind`` (one of :data:`KINDS`), ``frames`` consecutive frames per item
    (1: stills), ``default_spp``, the samples per pixel it is fed unless told otherwise (for
    ``sampled-layers``: the average budget) and ``features``, the per-sample feature groups it reads
    (``stores.contract.FEATURE_GROUPS``; data that lacks one of them is refused, :func:`check_features`)."""

    kind: str
    frames: int = 1
    default_spp: int = 8
    features: tuple[str, ...] = ALL_FEATURES

    def __post_init__(self):
        need(self.kind in KINDS, "input kind", f"one of {sorted(KINDS)}", self.kind, ConfigError)
        need_int('"frames"', self.frames, 1, None, ConfigError)
        object.__setattr__(self, "features", check_feature_groups(self.features))

    @property
    def input_kind(self) -> "InputKind":
        return KINDS[self.kind]


def check_features(spec: InputSpec, store) -> None:
    """Refuse (DataError naming them) a model that reads feature groups the data does not hold (a store's
    ``missing_features``: e.g. a Noisebase folder has no specular, roughness, coc, lens or time)."""
    reads = spec.input_kind.feature_groups(spec)
    lacking = [g for g in reads if g in store.missing_features]
    if lacking:
        have = [g for g in reads if g not in lacking]
        raise DataError(f"the model reads the feature groups {lacking}, which {store.path!s} does not hold; train "
                        f"it on the ones it has: --model-cfg '{{\"features\": {json.dumps(have)}}}' (the others "
                        "reach the network as 0)")


def mask_features(features: torch.Tensor, groups: tuple[str, ...]) -> torch.Tensor:
    """``features (..., 17, h, w)`` with the groups not in ``groups`` set to 0 (the tensor itself when
    every group is read)."""
    if groups == ALL_FEATURES:
        return features
    keep = torch.zeros(NUM_FEATURES, dtype=features.dtype, device=features.device)
    for g in groups:
        keep[FEATURE_GROUPS[g]] = 1
    return features * keep.view(NUM_FEATURES, 1, 1)


# --------------------------------------------------------------------------------------------
# The kinds


class InputKind:
    """One kind of model input. Subclasses set ``name``, ``arrays`` (what a store must hold),
    ``baseline_input`` (the kind whose items the ``input`` and ``oidn`` baselines read beside this kind's
    models; ``baseline_tag`` marks those baselines' labels beside others), ``holds`` (what an item is
    made of, for messages), ``window_key`` (the key whose second axis is time in a window of frames,
    ``frame_dims`` its dimensions in a single frame; ``per_batch`` the keys of a window without the time
    axis) and ``reads_images`` (an item can be made of per-pixel images, e.g. EXR files:
    :meth:`item_from_images`), and implement ``dataset``, ``example_batch`` and ``item_from_render``;
    ``forward``, ``target`` and ``noisy_image`` where the defaults do not fit.

    Time is handled here, once (:meth:`unroll`): a recurrent model (one that defines ``step``) of any
    kind is stepped through a window's frames by its kind, carrying its state."""

    name = "?"
    arrays: tuple[str, ...] = GUIDE_ARRAYS
    baseline_input = "pixels"
    holds = "per-sample inputs"
    window_key: str | None = None
    frame_dims = 5
    per_batch: tuple[str, ...] = ("origin",)
    reads_images = False
    baseline_tag = ""

    def check_store(self, store) -> None:
        """Raise :class:`DataError` naming every array this kind needs that the store lacks."""
        missing = [path for path in self.arrays if not store.has_array(path)]
        if missing:
            raise DataError(f"input kind {self.name!r} needs the arrays {missing}, which the store "
                            f"{store.path!s} does not have")

    def feature_groups(self, spec: InputSpec) -> tuple[str, ...]:
        """The per-sample feature groups a model of this kind with declaration ``spec`` reads."""
        return spec.features

    def max_spp(self, store) -> int:
        return int(store.layout.spp)

    def check_spp(self, store, spp: int) -> int:
        top = self.max_spp(store)
        if not isinstance(spp, (int, np.integer)) or not 1 <= int(spp) <= top:
            raise DataError(f"--spp {spp}: input kind {self.name!r} can be fed 1..{top} samples per pixel "
                            f"from {store.path!s}")
        return int(spp)

    def dataset(self, store, split, spp: int, crop, augment: bool, seed: int, frames: int = 1,
                full_windows: bool = True):
        raise NotImplementedError

    def forward(self, model, batch: dict) -> torch.Tensor:
        """The model's output for ``batch`` (what ``Denoiser.forward`` runs unless a model defines its own):
        a recurrent model unrolled over time (:meth:`unroll`)."""
        if model.stepwise and self.window_key is not None:
            return self.unroll(model, batch)
        raise ConfigError(f"model {model.name!r} reads input kind {self.name!r} and must define forward(batch)"
                          + (" or step(frame, state)" if self.window_key is not None else ""))

    def unroll(self, model, batch: dict) -> torch.Tensor:
        """A recurrent model over time, the one place it is done: a single frame (``batch[window_key]`` of
        ``frame_dims`` dimensions) gives its first step's output ``(B,3,h,w)``; a window (one more, the
        time axis second) gives ``(B,T,3,h,w)``: the model's ``first_frame`` output, then its ``step``
        through the other frames carrying its state (a one-frame window: its first step)."""
        x = batch[self.window_key]
        if x.dim() == self.frame_dims:
            return model.step(batch, None)[0]
        if x.dim() != self.frame_dims + 1:
            raise ConfigError(f"{self.window_key} must have {self.frame_dims} dimensions (a frame) or "
                              f"{self.frame_dims + 1} (a window), got {tuple(x.shape)}")

        def frame(t):
            return {k: (v if k in self.per_batch else v[:, t]) for k, v in batch.items()}
        if x.shape[1] == 1:
            return model.step(frame(0), None)[0].unsqueeze(1)
        out, state = model.first_frame(frame(0))
        outs = [out]
        for t in range(1, x.shape[1]):
            out, state, _ = model.step(frame(t), state)
            outs.append(out)
        return torch.stack(outs, dim=1)

    def stream(self, model, frame: dict, state=None):
        """One frame of a stream at inference (evaluation's clips, ``denoise`` of a sequence), the one
        place both kinds of model are told apart there: a recurrent model's ``step`` carrying ``state``
        (None starts a clip), another's ``forward`` (its ``state`` stays None). ``(output, state, extra)``:
        ``extra`` is what a step returns besides (an adaptive sampler's ``counts``), ``{}`` otherwise."""
        if model.stepwise:
            return model.step(frame, state)
        return model(frame), None, {}

    def target(self, batch: dict) -> torch.Tensor:
        """The reference the model's output is compared with (the same shape)."""
        return batch["reference"]

    def noisy_image(self, item: dict, spp: int) -> dict:
        """What the baselines see of one item (no batch axis; a window's last frame): ``radiance``,
        ``albedo`` and ``normal`` ``(3, h, w)``. Only kinds that are some kind's ``baseline_input``
        define it."""
        raise ConfigError(f"the baselines do not read input kind {self.name!r}; they read {self.baseline_input!r}")

    def item_from_render(self, arrays: dict, spp: int) -> dict:
        """The item (no batch axis) of one rendered frame: ``arrays`` as ``python -m pipeline render-frame``
        writes them (``radiance (H,W,S,3)``, ``features (H,W,S,17)``, ``layers (L,H,W,3)``,
        ``guides_albedo`` ...; channel-last numpy arrays), ``spp`` the samples to feed."""
        raise NotImplementedError

    def item_from_images(self, images: dict) -> dict:
        """The item of per-pixel images (``radiance``, ``albedo``, ``normal``, ``depth`` as (C, H, W)
        tensors, e.g. EXR files), for kinds that ``reads_images``."""
        raise ConfigError(f"input kind {self.name!r} reads {self.holds}, which an image does not hold")

    def example_batch(self, b: int, spp: int, h: int, w: int, frames: int = 1, generator=None) -> dict:
        """A random batch of this kind (for timing and the model contract tests)."""
        raise NotImplementedError


def _rand(*shape, generator=None, scale=1.0):
    return torch.rand(*shape, generator=generator) * scale


def _lead(b: int, frames: int) -> tuple[int, ...]:
    return (b,) if frames == 1 else (b, frames)


def _chw(a) -> torch.Tensor:
    """A channel-last array (H, W, C) as a float32 (C, H, W) tensor."""
    return torch.from_numpy(np.ascontiguousarray(np.moveaxis(np.asarray(a, np.float32), -1, 0)))


def _need(arrays: dict, *keys) -> None:
    missing = [k for k in keys if k not in arrays]
    if missing:
        raise DataError(f"the rendered frame has no {missing} (is it from `python -m pipeline render-frame`?)")


def _render_guides(arrays: dict) -> dict:
    _need(arrays, "guides_albedo", "guides_normal", "guides_depth", "guides_motion")
    dep = np.asarray(arrays["guides_depth"], np.float32)
    return {"albedo": _chw(arrays["guides_albedo"]), "normal": _chw(arrays["guides_normal"]),
            "depth": _chw(dep if dep.ndim == 3 else dep[..., None]), "motion": _chw(arrays["guides_motion"])}


def _render_samples(arrays: dict, spp: int) -> dict:
    """``radiance (S,3,H,W)`` and ``features (S,17,H,W)``: the first ``spp`` samples of a rendered frame."""
    _need(arrays, "radiance", "features")
    rad = np.asarray(arrays["radiance"], np.float32)                     # H W S 3
    S = rad.shape[2]
    if not 1 <= spp <= S:
        raise DataError(f"--spp {spp}: the rendered frame holds {S} samples per pixel")
    feat = np.asarray(arrays["features"], np.float32)
    return {"radiance": torch.from_numpy(np.ascontiguousarray(rad[:, :, :spp].transpose(2, 3, 0, 1))),
            "features": torch.from_numpy(np.ascontiguousarray(feat[:, :, :spp].transpose(2, 3, 0, 1)))}


def _last(t: torch.Tensor, dims: int) -> torch.Tensor:
    """A window's last frame of ``t`` (a single frame has ``dims`` dimensions)."""
    return t[-1] if t.dim() > dims else t


class SamplesKind(InputKind):
    name = "samples"
    arrays = SAMPLE_ARRAYS + GUIDE_ARRAYS

    def dataset(self, store, split, spp, crop, augment, seed, frames=1, full_windows=True):
        if frames != 1:
            raise ConfigError("input kind 'samples' reads single frames; use 'clips' for windows")
        return SampleFrames(store, split, spp=spp, crop=crop, augment=augment, seed=seed)

    def forward(self, model, batch):
        return model.denoise(batch["radiance"], batch["features"])

    def item_from_render(self, arrays, spp):
        return {**_render_samples(arrays, spp), **_render_guides(arrays)}

    def example_batch(self, b, spp, h, w, frames=1, generator=None):
        feat = _rand(b, spp, NUM_FEATURES, h, w, generator=generator)
        feat[:, :, FEATURE_GROUPS["depth"]] *= 50.0                   # depth in scene units
        return {"radiance": _rand(b, spp, 3, h, w, generator=generator, scale=4.0), "features": feat}


class PixelsKind(InputKind):
    name = "pixels"
    arrays = SAMPLE_ARRAYS + GUIDE_ARRAYS
    holds = "per-pixel images"
    reads_images = True

    def feature_groups(self, spec):
        return tuple(g for g in spec.features if g in PIXEL_FEATURES)

    def dataset(self, store, split, spp, crop, augment, seed, frames=1, full_windows=True):
        return PixelFrames(store, split, spp=spp, crop=crop, augment=augment, seed=seed, frames=frames,
                           full_windows=full_windows)

    def target(self, batch):
        ref = batch["reference"]
        return ref[:, -1] if ref.dim() == 5 else ref

    def noisy_image(self, item, spp):
        return {k: _last(item[k], 3) for k in ("radiance", "albedo", "normal") if k in item}

    def item_from_render(self, arrays, spp):
        guides = _render_guides(arrays)
        return {**guides, **pixel_item_from_samples(**_render_samples(arrays, spp))}

    def item_from_images(self, images):
        h, w = images["radiance"].shape[-2:]
        return {**images, "motion": torch.zeros(2, h, w)}        # a single image: no motion

    def example_batch(self, b, spp, h, w, frames=1, generator=None):
        lead = _lead(b, frames)
        g = generator
        normal = torch.nn.functional.normalize(torch.rand(*lead, 3, h, w, generator=g) * 2 - 1, dim=-3)
        return {"radiance": _rand(*lead, 3, h, w, generator=g, scale=4.0 / spp ** 0.5),
                "albedo": _rand(*lead, 3, h, w, generator=g), "normal": normal,
                "depth": _rand(*lead, 1, h, w, generator=g, scale=50.0),
                "motion": _rand(*lead, 2, h, w, generator=g, scale=2.0) - 1.0}


class ClipsKind(InputKind):
    """Windows of per-sample frames for recurrent models (``step``): a window ``radiance
    (B,T,S,3,h,w)`` is unrolled over its frames (:meth:`InputKind.unroll`), a single frame
    ``(B,S,3,h,w)`` is a first step."""
    name = "clips"
    arrays = SAMPLE_ARRAYS + GUIDE_ARRAYS
    window_key = "radiance"

    def dataset(self, store, split, spp, crop, augment, seed, frames=1, full_windows=True):
        return SampleFrames(store, split, spp=spp, crop=crop, augment=augment, seed=seed, frames=frames,
                            full_windows=full_windows)

    def forward(self, model, batch):
        return self.unroll(model, batch)

    def item_from_render(self, arrays, spp):
        return SamplesKind.item_from_render(self, arrays, spp)

    def example_batch(self, b, spp, h, w, frames=1, generator=None):
        batch = SamplesKind().example_batch(b * frames, spp, h, w, generator=generator)
        guides = PixelsKind().example_batch(b * frames, spp, h, w, generator=generator)
        batch.update({k: v for k, v in guides.items() if k != "radiance"})
        return batch if frames == 1 else {k: v.view(b, frames, *v.shape[1:]) for k, v in batch.items()}


class SampledLayersKind(InputKind):
    name = "sampled-layers"
    arrays = ("layers/radiance",) + GUIDE_ARRAYS
    baseline_input = "sampled-layers"
    baseline_tag = " layers"             # "input layers": the baseline composed from the layers
    holds = "sample layers"
    window_key = "layers"                # (B,L,3,h,w) a frame, (B,T,L,3,h,w) a window
    per_batch = ("origin", "layer_spp", "spp")

    def feature_groups(self, spec):
        return ()                        # the layers and the per-pixel guides only

    def max_spp(self, store) -> int:
        return int(sum(store.layout.layer_spp))

    def dataset(self, store, split, spp, crop, augment, seed, frames=1, full_windows=True):
        return LayerFrames(store, split, spp=spp, crop=crop, augment=augment, seed=seed, frames=frames,
                           full_windows=full_windows)

    def noisy_image(self, item, spp):
        """``spp`` samples in every pixel composed from the layers, with the store's guides: the input of
        a sampler's uniform baseline at that budget."""
        from . import adaptive
        layers = adaptive.clean_layers(_last(item["layers"], 4)).unsqueeze(0)
        rad = adaptive.compose(layers, adaptive.uniform_counts(layers[:, 0], spp))[0]
        return {"radiance": rad, "albedo": _last(item["albedo"], 3), "normal": _last(item["normal"], 3)}

    def item_from_render(self, arrays, spp):
        _need(arrays, "layers")
        layers = torch.from_numpy(np.ascontiguousarray(np.asarray(arrays["layers"], np.float32)
                                                       .transpose(0, 3, 1, 2)))     # L H W 3 -> L 3 H W
        L = layers.shape[0]
        top = 2 ** L - 1
        if not 0 < spp <= top:
            raise DataError(f"--spp {spp}: the rendered frame's {L} sample layers hold 1..{top} samples per pixel")
        return {"layers": layers, "layer_spp": torch.tensor([2.0 ** n for n in range(L)]),
                "spp": torch.tensor(float(spp)), **_render_guides(arrays)}

    def example_batch(self, b, spp, h, w, frames=1, generator=None):
        lead = _lead(b, frames)
        layers = torch.stack([_rand(*lead, 3, h, w, generator=generator, scale=4.0 / (2 ** n) ** 0.5)
                              for n in range(6)], dim=-4)
        batch = PixelsKind().example_batch(b, 1, h, w, frames, generator)
        batch.pop("radiance")
        return {"layers": layers, "layer_spp": torch.tensor([2.0 ** n for n in range(6)]).expand(b, 6),
                "spp": torch.full((b,), float(spp)), **batch}

    def target(self, batch):
        return batch["reference"]          # (B, T, 3, h, w) for windows: a recurrent model outputs every frame


KINDS: dict[str, InputKind] = {k.name: k for k in (SamplesKind(), PixelsKind(), ClipsKind(), SampledLayersKind())}
BASELINE_INPUTS = tuple(sorted({k.baseline_input for k in KINDS.values()}))
