"""What a denoiser consumes: the input kinds, one declaration per model, and the datasets they build.

Every registered model declares an :class:`InputSpec` (``model.input_spec()``): a kind, the number of
consecutive frames it reads, and its default samples per pixel. ``train``, ``evaluate``, ``report`` and
``bench`` take from the kind the dataset, the training target, the arrays a store must hold, the
largest sample count a store allows, and a random batch for timing; none of them branches on a model
name. The kinds:

* ``samples``: per-sample frames (the layer family): ``radiance (S,3,h,w)``, ``features (S,17,h,w)``
  plus the per-pixel guides (``stores.datasets.SampleDataset``).
* ``pixels``: per-pixel frames at N spp made from the stored per-sample inputs (nbg, wskpn): the mean
  ``radiance (3,h,w)`` of the first N samples and the per-pixel mean of those same samples' albedo,
  normal and depth (real N-spp features, noisy under defocus and motion; not the 8-spp guides), plus
  the stored per-pixel ``motion`` for reprojection. With ``frames = T > 1`` an item is a window of T
  consecutive frames of one clip (leading T axis) and the target is the last frame's reference.
* ``clips``: T consecutive per-sample frames of one clip (``stores.datasets.ClipDataset``); the target
  is the whole clip's reference ``(T,3,h,w)``.
* ``sampled-layers``: the sample layers ``layers (L,3,h,w)`` of each frame (or of T frames) with the
  guides, for a model whose sampler chooses per-pixel counts and composes the layers itself; the
  average budget per pixel is ``spp`` (at most the sum of the stored layers).

Items are dicts of float32 tensors, channel-first, with ``index`` (int64: the store frame, or (T,)
for windows) and ``origin`` (int64, 2). Crop origin, augmentation and sample choice are functions of
(seed, epoch, frame) only (see ``stores.datasets``), so the data a run sees does not depend on the
number of DataLoader workers or their order.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from stores.contract import FEATURE_GROUPS, NUM_FEATURES
from stores.datasets import (ClipDataset, SampleDataset, _StoreDataset, _tensor32, apply_augment,
                             draw_augment)
from stores.errors import SampleCountError, SplitError

from .errors import ConfigError, DataError

GUIDE_ARRAYS = ("reference/radiance", "reference/stderr", "guides/albedo", "guides/normal", "guides/depth",
                "guides/motion")
SAMPLE_ARRAYS = ("inputs/radiance", "inputs/features")


@dataclass(frozen=True)
class InputSpec:
    """What a model consumes: ``kind`` (one of :data:`KINDS`), ``frames`` consecutive frames per item
    (1: stills) and ``default_spp``, the samples per pixel it is fed unless told otherwise (for
    ``sampled-layers``: the average budget)."""

    kind: str
    frames: int = 1
    default_spp: int = 8

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ConfigError(f'input kind must be one of {sorted(KINDS)}, got {self.kind!r}')
        if not isinstance(self.frames, int) or self.frames < 1:
            raise ConfigError(f'"frames" must be an integer >= 1, got {self.frames!r}')

    @property
    def input_kind(self) -> "InputKind":
        return KINDS[self.kind]


# --------------------------------------------------------------------------------------------
# Per-pixel frames from the per-sample inputs


def pixel_item_from_samples(radiance: torch.Tensor, features: torch.Tensor) -> dict:
    """``radiance (..., S, 3, h, w)`` and ``features (..., S, 17, h, w)`` -> per-pixel means over the S
    samples: ``radiance (..., 3, h, w)``, ``albedo``, ``normal`` (3), ``depth`` (1). NaN/Inf samples stay
    in (the models clean their inputs); features are finite by the store's contract."""
    g = FEATURE_GROUPS
    mean = features.mean(dim=-4)
    return {"radiance": radiance.mean(dim=-4), "albedo": mean[..., g["albedo"], :, :],
            "normal": mean[..., g["normal"], :, :], "depth": mean[..., g["depth"], :, :]}


class _WindowFrames(_StoreDataset):
    """Items of one frame, or windows of ``frames = T > 1`` consecutive frames of one clip (same crop
    and augmentation, every key with a leading T axis). ``full_windows=False`` (evaluation) also gives
    each frame near a clip's start, and each still, a shorter window that ends on it, so every frame of
    the split is evaluated once; training batches need equal shapes and use full windows only.
    Subclasses implement ``_frame(i, region) -> dict`` and set ``spp``."""

    def __init__(self, store, split, crop, augment, seed, frames: int, full_windows: bool, crop_align: int):
        super().__init__(store, split, crop, augment, seed, crop_align)
        self.T = int(frames)
        self.windows = _windows(self.store, split, self.T, full_windows)

    def __len__(self) -> int:
        return len(self.windows)

    def _frame(self, i: int, region) -> dict:
        raise NotImplementedError

    def __getitem__(self, idx: int) -> dict:
        win = self.windows[idx]
        rng = self._rng(win[-1])
        oy, ox = self._origin(rng)
        region = self._region(oy, ox)
        per_t = [self._frame(i, region) for i in win]
        out = per_t[0] if self.T == 1 else {k: torch.stack([d[k] for d in per_t]) for k in per_t[0]}
        if self.augment:
            out = apply_augment(out, draw_augment(rng))
        out["index"] = torch.tensor(win[-1] if self.T == 1 else win, dtype=torch.int64)
        out["origin"] = torch.tensor([oy, ox], dtype=torch.int64)
        return out


class PixelFrames(_WindowFrames):
    """Per-pixel frames at ``spp`` samples from the stored per-sample inputs (kind ``pixels``): see
    :func:`pixel_item_from_samples`, plus ``reference``, ``stderr`` and ``motion``."""

    def __init__(self, store, split="train", spp: int = 1, crop=128, augment=True, seed=0, frames: int = 1,
                 full_windows: bool = True, crop_align: int = 1):
        super().__init__(store, split, crop, augment, seed, frames, full_windows, crop_align)
        S = self.store.layout.spp
        if not 1 <= int(spp) <= S:
            raise SampleCountError(f"asked for {spp} samples per pixel; the store holds 1..{S}")
        self.spp = int(spp)

    def _frame(self, i, region):
        item = pixel_item_from_samples(**self._samples(i, region, self.spp))
        g = self._guides(i, region)
        item.update(reference=g["reference"], stderr=g["stderr"], motion=g["motion"])
        return item


class LayerFrames(_WindowFrames):
    """The sample layers of each frame with the guides (kind ``sampled-layers``): ``layers (L,3,h,w)``,
    ``layer_spp (L,)``, ``spp`` (the average budget per pixel, a scalar) and the :class:`SampleDataset`
    guide keys."""

    def __init__(self, store, split="train", spp: int = 4, crop=128, augment=True, seed=0, frames: int = 1,
                 full_windows: bool = True, crop_align: int = 1):
        super().__init__(store, split, crop, augment, seed, frames, full_windows, crop_align)
        top = int(sum(self.store.layout.layer_spp))
        if not 0 < float(spp) <= top:
            raise SampleCountError(f"asked for an average of {spp} samples per pixel; the layers hold 1..{top}")
        self.spp = spp

    def _frame(self, i, region):
        item = {"layers": _tensor32(self.store.read_array("layers/radiance", i, region))}
        item.update(self._guides(i, region))
        return item

    def __getitem__(self, idx: int) -> dict:
        out = super().__getitem__(idx)
        out["layer_spp"] = torch.tensor(self.store.layout.layer_spp, dtype=torch.float32)
        out["spp"] = torch.tensor(float(self.spp), dtype=torch.float32)     # the average budget per pixel
        return out


def _windows(store, split, T: int, full_windows: bool) -> list[tuple[int, ...]]:
    """Windows of up to ``T`` consecutive frames of one clip, one ending on each frame, ordered by that
    frame's index; only the full ones when ``full_windows``."""
    in_clip = store.meta_column("frame")
    out, longest = [], 0
    for _, idxs in store.clips(split).items():
        for end in range(len(idxs)):
            start = end
            while start > 0 and end - start + 1 < T and int(in_clip[idxs[start - 1]]) + 1 == int(in_clip[idxs[start]]):
                start -= 1
            longest = max(longest, end - start + 1)
            if end - start + 1 == T or not full_windows:
                out.append(tuple(idxs[start:end + 1]))
    if not out:
        if T == 1:
            raise SplitError(f"split {split!r} of {store.path!s} has no complete frame")
        raise SplitError(f"split {split!r} of {store.path!s} has no run of {T} consecutive complete frames in one "
                         f"clip (the longest is {longest}): the model reads windows of {T} frames; train on a "
                         "store with longer clips, or shorten the model's window (e.g. --model-cfg "
                         "'{\"frames\": N}' for temporal)")
    return sorted(out, key=lambda w: w[-1])          # by the frame they end on: store order, as SampleDataset


# --------------------------------------------------------------------------------------------
# The kinds


class InputKind:
    """One kind of model input. Subclasses set ``name`` and ``arrays`` and implement ``dataset``,
    ``max_spp`` and ``example_batch``."""

    name = "?"
    arrays: tuple[str, ...] = GUIDE_ARRAYS

    def check_store(self, store) -> None:
        """Raise :class:`DataError` naming every array this kind needs that the store lacks."""
        missing = []
        for path in self.arrays:
            try:
                store.root[path]
            except KeyError:
                missing.append(path)
        if missing:
            raise DataError(f"input kind {self.name!r} needs the arrays {missing}, which the store "
                            f"{store.path!s} does not have")

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

    def target(self, batch: dict) -> torch.Tensor:
        """The reference the model's output is compared with."""
        return batch["reference"]

    def example_batch(self, b: int, spp: int, h: int, w: int, frames: int = 1, generator=None) -> dict:
        """A random batch of this kind (for timing and the model contract tests)."""
        raise NotImplementedError


def _rand(*shape, generator=None, scale=1.0):
    return torch.rand(*shape, generator=generator) * scale


def _lead(b: int, frames: int) -> tuple[int, ...]:
    return (b,) if frames == 1 else (b, frames)


class SamplesKind(InputKind):
    name = "samples"
    arrays = SAMPLE_ARRAYS + GUIDE_ARRAYS

    def dataset(self, store, split, spp, crop, augment, seed, frames=1, full_windows=True):
        if frames != 1:
            raise ConfigError("input kind 'samples' reads single frames; use 'clips' for windows")
        return SampleDataset(store, split=split, spp=spp, crop=crop, augment=augment, seed=seed)

    def example_batch(self, b, spp, h, w, frames=1, generator=None):
        feat = _rand(b, spp, NUM_FEATURES, h, w, generator=generator)
        feat[:, :, FEATURE_GROUPS["depth"]] *= 50.0                   # depth in scene units
        return {"radiance": _rand(b, spp, 3, h, w, generator=generator, scale=4.0), "features": feat}


class PixelsKind(InputKind):
    name = "pixels"
    arrays = SAMPLE_ARRAYS + GUIDE_ARRAYS

    def dataset(self, store, split, spp, crop, augment, seed, frames=1, full_windows=True):
        return PixelFrames(store, split, spp=spp, crop=crop, augment=augment, seed=seed, frames=frames,
                           full_windows=full_windows)

    def target(self, batch):
        ref = batch["reference"]
        return ref[:, -1] if ref.dim() == 5 else ref

    def example_batch(self, b, spp, h, w, frames=1, generator=None):
        lead = _lead(b, frames)
        g = generator
        normal = torch.nn.functional.normalize(torch.rand(*lead, 3, h, w, generator=g) * 2 - 1, dim=-3)
        return {"radiance": _rand(*lead, 3, h, w, generator=g, scale=4.0 / spp ** 0.5),
                "albedo": _rand(*lead, 3, h, w, generator=g), "normal": normal,
                "depth": _rand(*lead, 1, h, w, generator=g, scale=50.0),
                "motion": _rand(*lead, 2, h, w, generator=g, scale=2.0) - 1.0}


class ClipsKind(InputKind):
    name = "clips"
    arrays = SAMPLE_ARRAYS + GUIDE_ARRAYS

    def dataset(self, store, split, spp, crop, augment, seed, frames=1, full_windows=True):
        return ClipDataset(store, split=split, frames=frames, spp=spp, crop=crop, augment=augment, seed=seed,
                           stride=1 if full_windows else frames)

    def example_batch(self, b, spp, h, w, frames=1, generator=None):
        batch = SamplesKind().example_batch(b * frames, spp, h, w, generator=generator)
        return {k: v.view(b, frames, *v.shape[1:]) for k, v in batch.items()}


class SampledLayersKind(InputKind):
    name = "sampled-layers"
    arrays = ("layers/radiance",) + GUIDE_ARRAYS

    def max_spp(self, store) -> int:
        return int(sum(store.layout.layer_spp))

    def dataset(self, store, split, spp, crop, augment, seed, frames=1, full_windows=True):
        return LayerFrames(store, split, spp=spp, crop=crop, augment=augment, seed=seed, frames=frames,
                           full_windows=full_windows)

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
