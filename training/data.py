"""Data for training and evaluation: the model's declared input kind (:mod:`training.inputs`) builds
the dataset; batches come through a ``torch.utils.data.DataLoader`` with worker processes.

The batch order is a pure function of (seed, epoch): epoch e visits the items in
``epoch_order(n, seed, e)`` in batches of ``batch`` (the last partial batch dropped), and every item
is asked for as ``(index, epoch)`` so each worker's copy of the dataset draws that epoch's crop and
augmentation (a function of (seed, epoch, frame), see :mod:`training.datasets`). A run resumed at step k
starts the same sequence at batch k, so it sees exactly the batches an uninterrupted run would,
whatever the number of workers.

Under ``torchrun`` (:mod:`training.distributed`) ``batch`` is the global batch: every rank walks the
same sequence and keeps its ``rank``-th contiguous share of ``batch // world`` items of each step, so
the ranks' crops in a step together are exactly the one-process batch, whatever the number of ranks.
"""
from __future__ import annotations

import sys

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, Sampler, default_collate

from .errors import DataError
from .inputs import check_features

ORDER_SALT = 0x0DE7


def open_store(store):
    """:func:`stores.protocol.open_training_store` (the one opener), its errors as :class:`DataError`."""
    from stores.errors import StoreError
    from stores.protocol import open_training_store
    try:
        return open_training_store(store)
    except (StoreError, FileNotFoundError) as e:
        raise DataError(f"cannot open store {store!s}: {e}") from e


def model_dataset(spec, store, split: str, spp: int, crop, augment: bool, seed: int, full_windows: bool = True,
                  skip_bad_frames: bool = False, progress: bool = False, clips=None):
    """The dataset of input declaration ``spec`` (:class:`training.inputs.InputSpec`) on ``store``'s
    ``split``: checks that the store holds every array the kind needs and the sample count, refuses
    frames that ``validate`` would flag (see :func:`screen_frames`; ``skip_bad_frames`` leaves them out
    with a warning naming them), and turns store errors into :class:`DataError`. ``clips``: keep only
    the items of these clip ids (:func:`keep_clips`; None: every clip of the split)."""
    from stores.errors import StoreError
    st = open_store(store)
    kind = spec.input_kind
    kind.check_store(st)
    check_features(spec, st)
    kind.check_spp(st, spp)
    try:
        ds = kind.dataset(st, split, spp, crop, augment, seed, frames=spec.frames, full_windows=full_windows)
        if clips is not None:
            keep_clips(ds, st, split, clips)
        screen_frames(ds, st, split, skip_bad_frames, progress)
    except StoreError as e:
        raise DataError(f"{split!r} data from {st.path!s}: {e}") from e
    return ds


def keep_clips(ds, store, split: str, clips) -> None:
    """Restrict ``ds`` (a store dataset: ``frames`` or ``windows``) to the items whose frames all belong to
    the clips ``clips`` (ids of ``frames/clip_id``); DataError naming the ids the split does not hold, or
    when no item is left (say, clips shorter than the model's window)."""
    want = {int(c) for c in clips}
    have = set(store.clips(split))
    absent = sorted(want - have)
    if absent:
        more = " ..." if len(absent) > 8 else ""
        raise DataError(f"split {split!r} of {store.path!s} has no clip {absent[:8]}{more} "
                        f"({len(absent)} of the {len(want)} clip ids asked for)")
    clip_of = store.meta_column("clip_id")
    items = list(ds.windows)
    keep = [w for w in items if all(int(clip_of[int(i)]) in want for i in w)]
    if not keep:
        raise DataError(f"none of the {len(items)} items of split {split!r} of {store.path!s} lies in the "
                        f"{len(want)} clip(s) asked for (a model that reads windows needs clips at least that long)")
    ds.windows = keep


def screen_frames(ds, store, split: str, skip: bool, progress: bool = False) -> dict[int, list[str]]:
    """Refuse (or, with ``skip``, drop with one warning naming them) the items of ``ds`` that use a frame
    ``validate`` flags, and every incomplete frame of the store (a frame not yet written, failed, or
    unflagged: the datasets hold complete frames only, so without this a partial store would be used
    without a word): :func:`stores.fitness.screen_items`, the one screen, on the items' frame windows
    (``training.datasets.FrameWindows``). Returns the frames left out, frame -> problems, also kept as
    ``ds.left_out``; an unfit store is a :class:`DataError`."""
    from stores.errors import UnfitFrameError
    from stores.fitness import screen_items
    try:
        keep, bad = screen_items(store, list(ds.windows), skip=skip, what=f"split {split!r} of {store.path!s}",
                                 also=store.incomplete_frames(), progress=progress)
    except UnfitFrameError as e:
        raise DataError(str(e)) from None
    if bad:
        ds.windows = keep
    ds.left_out = bad
    return bad


def epoch_order(n: int, seed: int, epoch: int) -> np.ndarray:
    """Shuffled item order of one epoch (int64, n), a function of (seed, epoch) only."""
    return np.random.default_rng(np.random.SeedSequence([seed, epoch, ORDER_SALT])).permutation(n)


def draws_per_epoch(n: int, batch: int) -> int:
    """How many times an epoch visits each item: 1, or ``ceil(batch / n)`` when a batch holds more crops
    than there are items (a small store), each visit drawing its own crop and augmentation."""
    if n < 1:
        raise DataError("the training split is empty")
    return max(1, -(-batch // n))


def batches_per_epoch(n: int, batch: int) -> int:
    return n * draws_per_epoch(n, batch) // batch


def epoch_keys(n: int, seed: int, epoch: int, draws: int) -> list[tuple[int, int]]:
    """The ``(item, draw)`` sequence of one epoch: with one draw per item, ``epoch_order`` with draw
    ``epoch`` (the crops of that epoch); with ``draws`` > 1, that many shuffled passes, pass ``j``
    drawing its crops as epoch ``epoch * draws + j`` would, so no two visits of an item share a crop."""
    if draws == 1:
        return [(int(i), epoch) for i in epoch_order(n, seed, epoch)]
    out = []
    for j in range(draws):
        token = epoch * draws + j
        out += [(int(i), token) for i in epoch_order(n, seed, token)]
    return out


class EpochBatches(Sampler):
    """Batches ``start .. stop - 1`` of a run as lists of ``(item, draw)`` (:func:`epoch_keys`); with
    ``world`` > 1 only rank ``rank``'s share (items ``rank * b .. (rank + 1) * b - 1``,
    ``b = batch // world``) of each global batch."""

    def __init__(self, n: int, batch: int, seed: int, start: int, stop: int, rank: int = 0, world: int = 1):
        self.n, self.batch, self.seed, self.start, self.stop = n, batch, seed, start, stop
        self.draws = draws_per_epoch(n, batch)
        self.per_epoch = batches_per_epoch(n, batch)
        if world < 1 or not 0 <= rank < world or batch % world:
            raise DataError(f"--batch {batch} (the global batch) must divide evenly over the {world} ranks; "
                            f"use a multiple of {world}")
        self.rank, self.world = rank, world

    def __len__(self) -> int:
        return max(0, self.stop - self.start)

    def __iter__(self):
        keys, have = None, None
        for step in range(self.start, self.stop):
            epoch, pos = divmod(step, self.per_epoch)
            if epoch != have:
                keys, have = epoch_keys(self.n, self.seed, epoch, self.draws), epoch
            batch = keys[pos * self.batch:(pos + 1) * self.batch]
            b = self.batch // self.world
            yield batch[self.rank * b:(self.rank + 1) * b]


class _ByEpoch(Dataset):
    """``dataset[(i, epoch)]``: item i as drawn in that epoch (the dataset's ``set_epoch``)."""

    def __init__(self, dataset):
        self.dataset = dataset

    def __len__(self) -> int:
        return len(self.dataset)

    def __getitem__(self, key):
        i, epoch = key
        if hasattr(self.dataset, "set_epoch"):
            self.dataset.set_epoch(epoch)
        return self.dataset[i]


def _worker_init(_):
    torch.set_num_threads(1)          # the training process owns the cores' math libraries
    import signal
    # A terminal's Ctrl-C reaches the whole process group: the training process stops between steps and
    # shuts its loader down; a worker that died of it mid-transfer left a resource_sharer traceback.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    sys.excepthook = _quiet_broken_transfer


def _quiet_broken_transfer(kind, value, tb) -> None:
    """A loader worker's ``sys.excepthook``, which multiprocessing's resource_sharer thread calls when the
    training process stopped taking a batch from this worker half-way (a second Ctrl-C stops it at once):
    the broken connection (``ConnectionError``) is no news, the worker is being shut down, and its
    traceback came after the command's last line. Anything else is printed as Python prints it."""
    if not issubclass(kind, ConnectionError):
        sys.__excepthook__(kind, value, tb)


def batch_loader(dataset, batch: int, seed: int, start: int, stop: int, workers: int = 0, rank: int = 0,
                 world: int = 1, pin_memory: bool = False) -> DataLoader:
    """DataLoader over batches ``start .. stop - 1`` (see the module docstring): with ``world`` > 1,
    rank ``rank``'s share of each global batch of ``batch`` items. ``pin_memory`` (for CUDA): batches
    in page-locked memory, so :func:`to_device`'s copies overlap the GPU's work."""
    sampler = EpochBatches(len(dataset), batch, seed, start, stop, rank, world)
    store = getattr(dataset, "store", None)
    remote = workers and "://" in str(getattr(store, "path", ""))
    # A store at a URL holds an async client (s3fs's, on zarr's event loop) that a forked worker cannot
    # use: spawned workers open the store anew (``stores.reader.Store`` pickles as its path).
    return DataLoader(_ByEpoch(dataset), batch_sampler=sampler,
                      num_workers=workers, collate_fn=default_collate, worker_init_fn=_worker_init if workers else None,
                      persistent_workers=False, prefetch_factor=2 if workers else None,
                      multiprocessing_context="spawn" if remote else None, pin_memory=pin_memory)


def crops_per_second(dataset, n: int = 4) -> float:
    """Items (crops) a second that one loading process makes: ``n`` items of epoch 0 timed here, after
    one untimed (the store's first reads open its arrays)."""
    import time
    items = _ByEpoch(dataset)
    n = max(1, min(n, len(dataset) - 1)) if len(dataset) > 1 else 1
    items[(0, 0)]
    t0 = time.perf_counter()
    for i in range(n):
        items[((i + 1) % len(dataset), 0)]
    return n / max(time.perf_counter() - t0, 1e-9)


def to_device(batch: dict, device) -> dict:
    return {k: (v.to(device, non_blocking=True) if isinstance(v, torch.Tensor) else v) for k, v in batch.items()}
