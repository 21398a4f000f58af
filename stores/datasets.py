"""PyTorch datasets over a store, used by all training code.

Every item is a dict of float32 tensors, channel-first:

* :class:`SampleDataset` (per-sample denoisers): ``radiance (S,3,h,w)``, ``features (S,17,h,w)``,
  ``reference (3,h,w)``, ``stderr (3,h,w)``, ``albedo (3,h,w)``, ``normal (3,h,w)``, ``depth (1,h,w)``,
  ``motion (2,h,w)``, plus ``index`` (int64 scalar: the store frame) and ``origin`` (int64, 2: y, x).
* :class:`PixelDataset` (per-pixel denoisers, adaptive sampling): ``radiance (3,h,w)`` composed from
  the sample layers for a per-pixel count, ``spp_map (1,h,w)``, ``reference``, guides.
* :class:`ClipDataset` (temporal): the SampleDataset keys with a leading time axis ``(T, ...)``, T
  consecutive frames of one clip, one crop window and one augmentation for the whole clip.

Crop origins are uniform over the frame, or multiples of ``crop_align`` (e.g. the store's tile, 32:
no inner chunk is read only in part, ~1.6x fewer bytes decoded for 128-pixel crops).

Determinism: crop origin and augmentation of item ``i`` come from
``np.random.SeedSequence([seed, epoch, frame])`` only, so they do not depend on worker count or order;
call ``set_epoch(e)`` before each epoch (with ``DataLoader(persistent_workers=True)`` the workers keep
their copy: create the iterator after ``set_epoch``). Splits are by scene (``Store.frames_in_split``).

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

from typing import Callable

import numpy as np
import torch

from stores.contract import FEATURE_GROUPS
from stores.errors import CropSizeError, SampleCountError, SplitError
from stores.reader import Store, open_store

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


# ---------------------------------------------------------------------------- layer composition
def compose_layers(layers: np.ndarray, counts: np.ndarray, layer_spp) -> np.ndarray:
    """Per-pixel mean of ``counts`` samples from sample layers.

    ``layers (float32, L·3·h·w)``: layer n is the mean of ``layer_spp[n] = 2**n`` samples;
    ``counts (int, h·w)`` in ``0 .. sum(layer_spp)``; a count is the sum of the layers of its binary
    digits (13 = 1 + 4 + 8). Returns ``radiance (float32, 3·h·w)``; 0 where the count is 0."""
    spp = np.asarray(layer_spp, np.int64)
    if not np.array_equal(spp, 2 ** np.arange(len(spp))):
        raise SampleCountError(f"per-pixel composition needs layer_spp = 1, 2, 4, ...; got {tuple(spp)}")
    counts = np.asarray(counts, np.int64)
    top = int(spp.sum())
    if counts.min(initial=0) < 0 or counts.max(initial=0) > top:
        raise SampleCountError(f"per-pixel sample counts must be in 0..{top} (sum of the stored layers), "
                               f"got {counts.min()}..{counts.max()}")
    total = np.zeros(layers.shape[1:], np.float64)
    for n, s in enumerate(spp):
        use = ((counts >> n) & 1).astype(np.float64) * float(s)
        total += layers[n].astype(np.float64) * use[None]
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(counts[None] > 0, total / np.maximum(counts, 1)[None], 0.0)
    return out.astype(np.float32)


# ---------------------------------------------------------------------------- datasets
class _StoreDataset(torch.utils.data.Dataset):
    def __init__(self, store, split: str | None, crop: int | tuple[int, int] | None, augment: bool, seed: int,
                 crop_align: int = 1):
        self.store: Store = store if isinstance(store, Store) else open_store(store)
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
        t = _tensor32
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
        return {"radiance": _tensor32(rad), "features": _tensor32(feat)}


def _tensor32(a: np.ndarray) -> torch.Tensor:
    """float32 tensor of ``a`` (no copy when it already is contiguous float32)."""
    return torch.from_numpy(np.ascontiguousarray(a)).to(torch.float32)


def _split_frames(store: Store, split) -> list[int]:
    frames = store.frames_in_split(split)
    if not frames:
        raise SplitError(f"split {split!r} of {store.path!s} has no complete frame "
                         f"({store.num_frames} frames, {len(store.complete_frames())} complete)")
    return frames


class SampleDataset(_StoreDataset):
    """Per-sample frames: ``spp`` (<= stored) input samples of a random ``crop`` (None: full frame).
    See the module docstring for the keys and the augmentation."""

    def __init__(self, store, split: str | None = "train", spp: int = 8, crop: int | None = 128,
                 augment: bool = True, seed: int = 0, crop_align: int = 1):
        super().__init__(store, split, crop, augment, seed, crop_align)
        S = self.store.layout.spp
        if not 1 <= int(spp) <= S:
            raise SampleCountError(f"asked for {spp} samples per pixel; the store holds 1..{S}")
        self.spp = int(spp)
        self.frames = _split_frames(self.store, split)

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, idx: int) -> dict:
        i = self.frames[idx]
        rng = self._rng(i)
        oy, ox = self._origin(rng)
        region = self._region(oy, ox)
        item = {**self._samples(i, region, self.spp), **self._guides(i, region),
                "index": torch.tensor(i, dtype=torch.int64), "origin": torch.tensor([oy, ox], dtype=torch.int64)}
        if self.augment:
            item = apply_augment(item, draw_augment(rng))
        return item


SppSpec = int | np.ndarray | Callable[[np.random.Generator, int, int], np.ndarray]


class PixelDataset(_StoreDataset):
    """Per-pixel frames composed from the sample layers.

    ``spp``: an int (every pixel), an int array ``(H, W)`` of per-pixel counts over the full frame
    (cropped with the frame), or a callable ``(rng, h, w) -> int array (h, w)`` drawing a sample map
    per item (adaptive sampling). Counts are 0..sum(layer_spp) (63 for the default six layers).
    Keys: ``radiance (3,h,w)``, ``spp_map (1,h,w)``, ``reference``, ``stderr``, ``albedo``, ``normal``,
    ``depth``, ``motion``, ``index``, ``origin``."""

    def __init__(self, store, split: str | None = "train", spp: SppSpec = 8, crop: int | None = 128,
                 augment: bool = True, seed: int = 0, crop_align: int = 1):
        super().__init__(store, split, crop, augment, seed, crop_align)
        lay = self.store.layout
        self.max_spp = int(sum(lay.layer_spp))
        if isinstance(spp, (int, np.integer)):
            if not 0 <= int(spp) <= self.max_spp:
                raise SampleCountError(f"asked for {spp} samples per pixel; the layers hold 0..{self.max_spp}")
        elif isinstance(spp, np.ndarray):
            if spp.shape != (lay.height, lay.width):
                raise SampleCountError(f"sample map has shape {spp.shape}, frames are {(lay.height, lay.width)}")
            if spp.min() < 0 or spp.max() > self.max_spp:
                raise SampleCountError(f"sample map counts must be in 0..{self.max_spp}")
        elif not callable(spp):
            raise SampleCountError(f"spp must be an int, an (H, W) int array or a callable, got {type(spp).__name__}")
        self.spp = spp
        self.frames = _split_frames(self.store, split)

    def __len__(self) -> int:
        return len(self.frames)

    def _counts(self, rng, oy, ox) -> np.ndarray:
        h, w = self.crop
        if isinstance(self.spp, (int, np.integer)):
            return np.full((h, w), int(self.spp), np.int64)
        if isinstance(self.spp, np.ndarray):
            return self.spp[oy:oy + h, ox:ox + w].astype(np.int64)
        counts = np.asarray(self.spp(rng, h, w))
        if counts.shape != (h, w):
            raise SampleCountError(f"sample-map callable returned shape {counts.shape}, expected {(h, w)}")
        return counts.astype(np.int64)

    def __getitem__(self, idx: int) -> dict:
        i = self.frames[idx]
        rng = self._rng(i)
        oy, ox = self._origin(rng)
        region = self._region(oy, ox)
        counts = self._counts(rng, oy, ox)
        layers = self.store.read_array("layers/radiance", i, region)     # (L, 3, h, w)
        rad = compose_layers(layers, counts, self.store.layout.layer_spp)
        item = {"radiance": torch.from_numpy(rad),
                "spp_map": torch.from_numpy(counts.astype(np.float32)[None]),
                **self._guides(i, region),
                "index": torch.tensor(i, dtype=torch.int64), "origin": torch.tensor([oy, ox], dtype=torch.int64)}
        if self.augment:
            item = apply_augment(item, draw_augment(rng))
        return item


class ClipDataset(_StoreDataset):
    """``frames`` consecutive frames of one clip (same crop window and augmentation for all): the
    SampleDataset keys with a leading time axis, e.g. ``radiance (T,S,3,h,w)``, ``motion (T,2,h,w)``,
    ``index (T,)``. Windows start every ``stride`` frames; clips shorter than ``frames`` are skipped.
    ``spp=0`` leaves out the per-sample inputs (guides and reference only). ``pixel_spp`` (int
    0..sum(layer_spp)) adds ``pixel_radiance (T,3,h,w)`` composed from the sample layers, for
    per-pixel temporal denoisers."""

    def __init__(self, store, split: str | None = "train", frames: int = 4, spp: int = 8,
                 crop: int | None = 128, augment: bool = True, seed: int = 0, stride: int = 1,
                 crop_align: int = 1, pixel_spp: int | None = None):
        super().__init__(store, split, crop, augment, seed, crop_align)
        S = self.store.layout.spp
        if not 0 <= int(spp) <= S:
            raise SampleCountError(f"asked for {spp} samples per pixel; the store holds 0..{S}")
        top = int(sum(self.store.layout.layer_spp))
        if pixel_spp is not None and not 0 <= int(pixel_spp) <= top:
            raise SampleCountError(f"pixel_spp={pixel_spp}; the layers hold 0..{top}")
        self.pixel_spp = None if pixel_spp is None else int(pixel_spp)
        if frames < 1 or stride < 1:
            raise SplitError(f"frames and stride must be >= 1, got frames={frames}, stride={stride}")
        self.spp, self.T = int(spp), int(frames)
        windows = []
        in_clip = self.store.meta_column("frame")
        for clip, idxs in self.store.clips(split).items():
            pos = [int(in_clip[j]) for j in idxs]
            for a in range(0, len(idxs) - self.T + 1, stride):
                if all(pos[a + t + 1] == pos[a + t] + 1 for t in range(self.T - 1)):
                    windows.append(tuple(idxs[a:a + self.T]))
        if not windows:
            raise SplitError(f"split {split!r} of {self.store.path!s} has no run of {self.T} consecutive "
                             f"complete frames in one clip")
        self.windows = windows

    def __len__(self) -> int:
        return len(self.windows)

    def __getitem__(self, idx: int) -> dict:
        win = self.windows[idx]
        rng = self._rng(win[0])
        oy, ox = self._origin(rng)
        region = self._region(oy, ox)
        per_t = []
        for i in win:
            item = self._samples(i, region, self.spp) if self.spp else {}
            if self.pixel_spp is not None:
                counts = np.full(self.crop, self.pixel_spp, np.int64)
                layers = self.store.read_array("layers/radiance", i, region)
                item["pixel_radiance"] = torch.from_numpy(
                    compose_layers(layers, counts, self.store.layout.layer_spp))
            item.update(self._guides(i, region))
            per_t.append(item)
        out = {k: torch.stack([d[k] for d in per_t]) for k in per_t[0]}
        if self.augment:
            out = apply_augment(out, draw_augment(rng))
        out["index"] = torch.tensor(win, dtype=torch.int64)
        out["origin"] = torch.tensor([oy, ox], dtype=torch.int64)
        return out


__all__ = ["SampleDataset", "PixelDataset", "ClipDataset", "compose_layers", "apply_augment",
           "augment_image", "augment_vectors", "augment_features", "draw_augment"]
