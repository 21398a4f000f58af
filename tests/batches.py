"""A run's batches built in the test process: the oracle the DataLoader's batches are checked against."""
from __future__ import annotations

from torch.utils.data import default_collate

from training.data import EpochBatches, _ByEpoch


def get_batch(dataset, seed: int, step: int, batch: int, rank: int = 0, world: int = 1) -> tuple[dict, int]:
    """Batch number ``step`` of the run (rank ``rank``'s share of it), built in this process, and its
    epoch (the batches ``training.data.batch_loader`` gives)."""
    keys = next(iter(EpochBatches(len(dataset), batch, seed, step, step + 1, rank, world)))
    return default_collate([_ByEpoch(dataset)[k] for k in keys]), keys[0][1]
