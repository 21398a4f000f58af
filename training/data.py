"""Data for training and evaluation, from the store package's PyTorch datasets (``stores.datasets``).

The loop needs only a map-style dataset whose items are dicts of channel-first float32 tensors
(``radiance (S,3,h,w)``, ``features (S,17,h,w)``, ``reference (3,h,w)``, guides) with ``set_epoch(e)``;
:class:`stores.datasets.SampleDataset` is one. Batches are built here, in-process, in an order that
is a pure function of (seed, epoch), so a resumed run sees exactly the batches it would have seen.
"""
from __future__ import annotations

import numpy as np
import torch
from torch.utils.data import default_collate

from .errors import DataError

ORDER_SALT = 0x0DE7


def open_store(store):
    """A :class:`stores.reader.Store` from a path (or the store itself)."""
    from stores.errors import StoreError
    from stores.reader import Store, open_store as _open
    if isinstance(store, Store):
        return store
    try:
        return _open(store)
    except (StoreError, FileNotFoundError) as e:
        raise DataError(f"cannot open store {store!s}: {e}") from e


def sample_dataset(store, split: str, spp: int, crop: int | None, augment: bool, seed: int):
    """``stores.datasets.SampleDataset`` with the store errors turned into :class:`DataError`."""
    from stores.datasets import SampleDataset
    from stores.errors import StoreError
    try:
        return SampleDataset(open_store(store), split=split, spp=spp, crop=crop, augment=augment, seed=seed)
    except StoreError as e:
        raise DataError(f"{split!r} data from {getattr(store, 'path', store)!s}: {e}") from e


def epoch_order(n: int, seed: int, epoch: int) -> np.ndarray:
    """Shuffled item order of one epoch (int64, n), a function of (seed, epoch) only."""
    return np.random.default_rng(np.random.SeedSequence([seed, epoch, ORDER_SALT])).permutation(n)


def batches_per_epoch(n: int, batch: int) -> int:
    if n < 1:
        raise DataError("the training split is empty")
    return max(1, n // batch)


def get_batch(dataset, seed: int, step: int, batch: int) -> tuple[dict, int]:
    """Batch number ``step`` of the run (epochs of ``n // batch`` batches, last partial batch dropped)
    and its epoch. Items are dicts of tensors; the batch has a leading B axis."""
    n = len(dataset)
    per_epoch = batches_per_epoch(n, batch)
    epoch, pos = divmod(step, per_epoch)
    order = epoch_order(n, seed, epoch)
    b = min(batch, n)
    idx = order[pos * b:(pos + 1) * b]
    if hasattr(dataset, "set_epoch"):
        dataset.set_epoch(epoch)
    return default_collate([dataset[int(i)] for i in idx]), epoch


def to_device(batch: dict, device) -> dict:
    return {k: (v.to(device, non_blocking=True) if isinstance(v, torch.Tensor) else v) for k, v in batch.items()}
