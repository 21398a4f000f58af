"""Checkpoints that resume exactly: model and optimiser state, RNG states, step, the training config,
the model's config and the store's schema version (and path). ``load`` refuses a mismatch with a
named error (:class:`CheckpointError`)."""
from __future__ import annotations

import os
import random
import tempfile
from pathlib import Path

import numpy as np
import torch

from .config import TrainConfig
from .errors import CheckpointError

FORMAT = "denoise-datagen.training-checkpoint/1"


def rng_state() -> dict:
    state = {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def save(path, *, model, optimizer, step: int, cfg: TrainConfig, store_info: dict, extra: dict | None = None) -> None:
    """Write atomically (temp file + rename) so an interrupted save never leaves a broken checkpoint."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "format": FORMAT, "model": cfg.model, "model_config": model.config, "train_config": cfg.to_dict(),
        "state_dict": model.state_dict(), "optimizer": optimizer.state_dict() if optimizer else None,
        "step": int(step), "rng": rng_state(), "store": dict(store_info), "torch_version": torch.__version__,
        **(extra or {}),
    }
    fd, tmp = tempfile.mkstemp(prefix="checkpoint-", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(payload, f)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def load(path, map_location="cpu") -> dict:
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"no checkpoint at {path}")
    try:
        ck = torch.load(path, map_location=map_location, weights_only=False)
    except Exception as e:   # torch raises many types for a corrupt file
        raise CheckpointError(f"cannot read checkpoint {path}: {e}") from e
    if not isinstance(ck, dict) or ck.get("format") != FORMAT:
        raise CheckpointError(f"{path} is not a {FORMAT} checkpoint")
    return ck


def check_store(ck: dict, schema_version: int, path=None) -> None:
    have = ck.get("store", {}).get("schema_version")
    if have != schema_version:
        raise CheckpointError(f"checkpoint {path or ''} was trained on a store of schema version {have}; "
                              f"this store has version {schema_version}")


def build_model(ck: dict, device="cpu"):
    """The checkpoint's model with its weights, in eval mode."""
    from .models import build
    model = build(ck["model"], **ck["model_config"])
    model.load_state_dict(ck["state_dict"])
    return model.to(device).eval()
