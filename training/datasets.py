"""PyTorch datasets over a store: the one hierarchy every input kind (:mod:`training.inputs`) builds on.

Every item is a dict of float32 tensors, channel-first, with ``index`` (int64: the store frame, or (T,)
for a window of T frames) and ``origin`` (int64, 2: y, x):

* :class:`SampleFrames` (kinds ``samples`` and ``clips``): ``radiance (S,3,h,w)``, ``features (S,17,h,w)``,
  ``reference (3,h,w)``, ``stderr (3,h,w)``, ``albedo (3,h,w)``, ``normal (3,h,w)``, ``depth (1,h,w)``,
  ``motion (2,h,w)``.
* :class:`PixelFrames` (kind ``pixels``): the per-pixel means of the first N samples
  (:func:`pixel_item_from_samples`) with ``reference``, ``stderr`` and ``motion``.
* :class:`LayerFrames` (kind ``sampled-layers``): the sample layers ``layers (L,3,h,w)`` with the guides.

Each of them gives single frames (``frames = 1``) or windows of ``frames = T`` consecutive frames of one
clip, every key then with a leading T axis, one crop window and one augmentation for the whole window
(:class:`FrameWindows`; the window logic is written once, in :func:`frame_windows`).

Crop origins are uniform over the frame, or multiples of ``crop_align`` (e.g. the store's tile, 32:
no inner chunk is read only in part, ~1.6x fewer bytes decoded for 128-pixel crops).

Determinism: crop origin and augmentation of an item come from
``np.random.SeedSequence([seed, epoch, frame])`` only (``frame``: the last of its window), so they do not
depend on worker count or order; call ``set_epoch(e)`` before each epoch (with
``DataLoader(persistent_workers=True)`` the workers keep their copy: create the iterator after
``set_epoch``). Splits are by scene (``Store.frames_in_split``).

Augmentation (``augment=True``): rotation by ``k * 90`` degrees (``torch.rot90`` over (h, w)), then an
x flip and a y flip, each with probability 1/2, applied to every image of the item. Screen-space 2-D
vectors follow the image: an x flip negates ``motion_x``, a y flip negates ``motion_y``, a 90-degree
rotation maps ``(mx, my) -> (my, -mx)`` (pixel convention x right, y down). The lens position
(``lens_u``, ``lens_v``) is treated the same way (it is a position on the lens in image-aligned axes).
World-space normals are NOT changed: an image flip moves pixels, it does not mirror the world, and a
world-space normal is a property of the surface, not of the screen; a denoiser uses it as a guide
whose discontinuities move with the pixels. (A camera/screen-space normal would need the same sign
changes as motion.) Depth, albedo, specular, roughness, CoC and time are scalars per pixel and only move.
"""
from __future__ import annotations

import numpy as np
import torch

from stores.contract import FEATURE_GROUPS
from stores.errors import CropSizeError, SampleCountError, SplitError
from stores.protocol import TrainingStore, open_training_store

_MOTION = FEATURE_GROUPS["motion"]
_LENS = FEATURE_GROUPS["lens"]


# ---------------------------------------------------------------------------- augmentation
def draw_augment(rng: np.random.Generator) -> tuple[int, bool, bool]:
    """``(k, flip_x, flip_y)``: rotation by k*90 degrees, then flips."""
    return int(rng.integers(4)), bool(rng.integers(2)), bool(rng.integers(2))


def augment_image(t: torch.Tensor, op: tuple[int, bool, bool]) -> torch.Tensor:
    """Move the pixels of ``t (..., h, w)``."""
    k, fx, fy = op
    if k:
        t = torch.rot90(t, k, dims=(-2, -1))
    if fx:
        t = torch.flip(t, dims=(-1,))
    if fy:
        t = torch.flip(t, dims=(-2,))
    return t


def augment_vectors(t: torch.Tensor, op: tuple[int, bool, bool]) -> torch.Tensor:
    """Move the pixels of a screen-space 2-vector image ``t (..., 2, h, w)`` (x right, y down) and
    transform the vectors with them."""
    return _vec_only(augment_image(t, op), op)


def augment_features(t: torch.Tensor, op: tuple[int, bool, bool]) -> torch.Tensor:
    """``t (..., 17, h, w)``: move pixels; transform motion and lens position as 2-vectors."""
    t = augment_image(t, op).clone()
    for g in (_MOTION, _LENS):
        moved = t[..., g, :, :]
        t[..., g, :, :] = _vec_only(moved, op)
    return t


def _vec_only(t: torch.Tensor, op) -> torch.Tensor:
    """Transform the vectors (not the pixels) of ``t (..., 2, h, w)``."""
    k, fx, fy = op
    vx, vy = t[..., 0, :, :], t[..., 1, :, :]
    for _ in range(k):                 # torch.rot90 maps pixel (x, y) -> (y, W-1-x)
        vx, vy = vy, -vx
    if fx:
        vx = -vx
    if fy:
        vy = -vy
    return torch.stack([vx, vy], dim=-3)


def apply_augment(item: dict, op: tuple[int, bool, bool]) -> dict:
    out = {}
    for key, t in item.items():
        if key in ("index", "origin"):
            out[key] = t
        elif key == "motion":
            out[key] = augment_vectors(t, op)
        elif key == "features":
            out[key] = augment_features(t, op)
        else:
            out[key] = augment_image(t, op)
    return out


# ---------------------------------------------------------------------------- datasets
class StoreDataset(torch.utils.data.Dataset):
    """Crops of a store's frames: the crop window, the epoch and the per-frame random draws (module docstring)."""

    def __init__(self, store, split: str | None, crop: int | tuple[int, int] | None, augment: bool, seed: int,
                 crop_align: int = 1):
        self.store: TrainingStore = open_training_store(store)
        if int(crop_align) < 1:
            raise CropSizeError(f"crop_align must be >= 1, got {crop_align}")
        self.crop_align = int(crop_align)
        H, W = self.store.layout.height, self.store.layout.width
        if crop is None:
            self.crop = (H, W)
        else:
            ch, cw = (crop, crop) if np.isscalar(crop) else tuple(crop)
            if ch < 1 or cw < 1 or ch > H or cw > W:
                raise CropSizeError(f"crop {ch}x{cw} does not fit the store's {H}x{W} frames")
            self.crop = (int(ch), int(cw))
        self.split = split
        self.augment = bool(augment)
        self.seed = int(seed)
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def _rng(self, key: int) -> np.random.Generator:
        return np.random.default_rng(np.random.SeedSequence([self.seed, self.epoch, int(key)]))

    def _origin(self, rng) -> tuple[int, int]:
        H, W = self.store.layout.height, self.store.layout.width
        ch, cw = self.crop
        a = self.crop_align
        return a * int(rng.integers(0, (H - ch) // a + 1)), a * int(rng.integers(0, (W - cw) // a + 1))

    def _region(self, oy, ox):
        return (oy, ox, self.crop[0], self.crop[1])

    def _guides(self, i: int, region) -> dict:
        s = self.store
        t = tensor32
        return {
            "reference": t(s.read_array("reference/radiance", i, region)),
            "stderr": t(s.read_array("reference/stderr", i, region)),
            "albedo": t(s.read_array("guides/albedo", i, region)),
            "normal": t(s.read_array("guides/normal", i, region)),
            "depth": t(s.read_array("guides/depth", i, region)[None]),
            "motion": t(s.read_array("guides/motion", i, region)),
        }

    def _samples(self, i: int, region, spp: int) -> dict:
        s = self.store
        rad = s.read_array("inputs/radiance", i, region, samples=spp)     # (S, 3, h, w)
        feat = s.read_array("inputs/features", i, region, samples=spp)    # (S, 17, h, w)
        # float16 -> float32 in torch: about twice as fast as numpy's astype
        return {"radiance": tensor32(rad), "features": tensor32(feat)}


def tensor32(a: np.ndarray) -> torch.Tensor:
    """float32 tensor of ``a`` (no copy when it already is contiguous float32)."""
    return torch.from_numpy(np.ascontiguousarray(a)).to(torch.float32)


def pixel_item_from_samples(radiance: torch.Tensor, features: torch.Tensor) -> dict:
    """``radiance (..., S, 3, h, w)`` and ``features (..., S, 17, h, w)`` -> per-pixel means over the S
    samples: ``radiance (..., 3, h, w)``, ``albedo``, ``normal`` (3), ``depth`` (1). NaN/Inf samples stay
    in (the models clean their inputs); features are finite by the store's contract."""
    g = FEATURE_GROUPS
    mean = features.mean(dim=-4)
    return {"radiance": radiance.mean(dim=-4), "albedo": mean[..., g["albedo"], :, :],
            "normal": mean[..., g["normal"], :, :], "depth": mean[..., g["depth"], :, :]}


class FrameWindows(StoreDataset):
    """Items of one frame, or windows of ``frames = T > 1`` consecutive frames of one clip (same crop
    and augmentation, every key with a leading T axis). ``full_windows=False`` (evaluation) also gives
    each frame near a clip's start, and each still, a shorter window that ends on it, so every frame of
    the split is evaluated once; training batches need equal shapes and use full windows only.
    Subclasses implement ``_frame(i, region) -> dict`` and set ``spp``."""

    def __init__(self, store, split, crop, augment, seed, frames: int, full_windows: bool, crop_align: int):
        super().__init__(store, split, crop, augment, seed, crop_align)
        self.T = int(frames)
        self.windows = frame_windows(self.store, split, self.T, full_windows)

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


class SampleFrames(FrameWindows):
    """Per-sample frames (kinds ``samples`` and ``clips``): the first ``spp`` (<= stored) input samples
    of a random ``crop`` (None: the full frame) with the guides; see the module docstring for the keys."""

    def __init__(self, store, split: str | None = "train", spp: int = 8, crop=128, augment: bool = True,
                 seed: int = 0, frames: int = 1, full_windows: bool = True, crop_align: int = 1):
        super().__init__(store, split, crop, augment, seed, frames, full_windows, crop_align)
        S = self.store.layout.spp
        if not 1 <= int(spp) <= S:
            raise SampleCountError(f"asked for {spp} samples per pixel; the store holds 1..{S}")
        self.spp = int(spp)

    def _frame(self, i, region):
        return {**self._samples(i, region, self.spp), **self._guides(i, region)}


class PixelFrames(SampleFrames):
    """Per-pixel frames at ``spp`` samples from the stored per-sample inputs (kind ``pixels``): see
    :func:`pixel_item_from_samples`, plus ``reference``, ``stderr`` and ``motion``."""

    def _frame(self, i, region):
        item = pixel_item_from_samples(**self._samples(i, region, self.spp))
        g = self._guides(i, region)
        item.update(reference=g["reference"], stderr=g["stderr"], motion=g["motion"])
        return item


class LayerFrames(FrameWindows):
    """The sample layers of each frame with the guides (kind ``sampled-layers``): ``layers (L,3,h,w)``,
    ``layer_spp (L,)``, ``spp`` (the average budget per pixel, a scalar) and the guides (:meth:`StoreDataset._guides`)."""

    def __init__(self, store, split="train", spp: int = 4, crop=128, augment=True, seed=0, frames: int = 1,
                 full_windows: bool = True, crop_align: int = 1):
        super().__init__(store, split, crop, augment, seed, frames, full_windows, crop_align)
        top = int(sum(self.store.layout.layer_spp))
        if not 0 < float(spp) <= top:
            raise SampleCountError(f"asked for an average of {spp} samples per pixel; the layers hold 1..{top}")
        from .adaptive import check_layer_spp
        check_layer_spp(self.store.layout.layer_spp)         # once, here: the sampler's step reads none back
        self.spp = spp

    def _frame(self, i, region):
        item = {"layers": tensor32(self.store.read_array("layers/radiance", i, region))}
        item.update(self._guides(i, region))
        return item

    def __getitem__(self, idx: int) -> dict:
        out = super().__getitem__(idx)
        out["layer_spp"] = torch.tensor(self.store.layout.layer_spp, dtype=torch.float32)
        out["spp"] = torch.tensor(float(self.spp), dtype=torch.float32)     # the average budget per pixel
        return out


def frame_windows(store, split, T: int, full_windows: bool) -> list[tuple[int, ...]]:
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
            done = len(store.complete_frames())
            why = (f"none of the store's {store.num_frames} frames is complete" if not done else
                   f"the store has {store.num_frames} frames, {done} complete, none of them in {split!r}")
            raise SplitError(f"split {split!r} of {store.path!s} has no complete frame ({why})")
        raise SplitError(f"split {split!r} of {store.path!s} has no run of {T} consecutive complete frames in one "
                         f"clip (the longest is {longest}): the model reads windows of {T} frames; train on a "
                         "store with longer clips, or shorten the model's window (e.g. --model-cfg "
                         "'{\"frames\": N}' for temporal)")
    return sorted(out, key=lambda w: w[-1])          # by the frame they end on: store order


__all__ = ["StoreDataset", "FrameWindows", "SampleFrames", "PixelFrames", "LayerFrames", "frame_windows",
           "pixel_item_from_samples", "apply_augment", "augment_image", "augment_vectors", "augment_features",
           "draw_augment", "tensor32"]
