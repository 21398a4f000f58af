"""The training loop: explicit and short (nanoGPT style).

    summary = train(TrainConfig(model="layer", steps=1000), store="data/default.zarr", out="data/runs/layer")

writes ``out/checkpoint.pt`` (every ``checkpoint_every`` steps and at the end) and ``out/metrics.csv``
(``step, epoch, kind, loss, relmse, smape, psnr, seconds``; kind ``train`` or ``val``). If
``out/checkpoint.pt`` exists the run resumes from it and continues exactly as an uninterrupted run
would (same batches, same optimiser state); a checkpoint from different settings or a store of
another schema version is refused.
"""
from __future__ import annotations

import csv
import time
from pathlib import Path

import numpy as np
import torch

from . import checkpoint as ckpt
from . import metrics
from .config import TrainConfig
from .data import get_batch, open_store, sample_dataset, to_device
from .errors import CheckpointError, ConfigError, NonFiniteError
from .losses import build_loss
from .models import build
from .models.common import flush_denormals

CSV_FIELDS = ("step", "epoch", "kind", "loss", "relmse", "smape", "psnr", "seconds")


def pick_device(name: str) -> torch.device:
    dev = torch.device(name)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f'"device" is {name!r} but no CUDA device is available')
    return dev


def warmup_lr(lr: float, warmup: int, step: int) -> float:
    """Learning rate of optimiser step ``step`` (0-based): linear warm-up over ``warmup`` steps."""
    return lr * min(1.0, (step + 1) / warmup) if warmup else lr


def train_step(model, optimizer, loss_fn, batch: dict, clip_norm: float = 0.0, clip_value: float = 0.0,
               lr: float | None = None) -> float:
    """One optimiser step on ``batch``; returns the loss. Raises NonFiniteError on NaN/Inf loss.
    Gradients are clamped first by total norm, then by value (0: off), like NVlabs/layerdenoise.
    ``lr``: this step's learning rate (None: leave the optimiser's)."""
    if lr is not None:
        for group in optimizer.param_groups:
            group["lr"] = lr
    model.train()
    optimizer.zero_grad(set_to_none=True)
    out = model(batch)
    loss = loss_fn(out, batch["reference"])
    if not torch.isfinite(loss):
        raise NonFiniteError(f"loss is {loss.item()} (non-finite)")
    loss.backward()
    if clip_norm:
        torch.nn.utils.clip_grad_norm_(model.parameters(), clip_norm)
    if clip_value:
        torch.nn.utils.clip_grad_value_(model.parameters(), clip_value)
    optimizer.step()
    return float(loss.detach())


@torch.no_grad()
def validate(model, dataset, loss_fn, device, max_frames: int = 0) -> dict:
    """Mean loss, relMSE, SMAPE and PSNR over (up to ``max_frames``) held-out items, fp32."""
    model.eval()
    n = len(dataset) if not max_frames else min(max_frames, len(dataset))
    rows = []
    for i in range(n):
        item = to_device({k: v.unsqueeze(0) for k, v in dataset[i].items()}, device)
        out = model(item).float()
        ref = item["reference"].float()
        d = out[0].permute(1, 2, 0).cpu().numpy()
        r = ref[0].permute(1, 2, 0).cpu().numpy()
        rows.append({"loss": float(loss_fn(out, ref)), "relmse": metrics.relmse(d, r),
                     "smape": metrics.smape(d, r), "psnr": metrics.psnr(d, r)})
    return {k: float(np.mean([r[k] for r in rows])) for k in rows[0]} if rows else {}


class _Log:
    """metrics.csv, truncated to the rows at or before the resumed step."""

    def __init__(self, path: Path, resume_step: int):
        self.path = path
        rows = []
        if resume_step and path.exists():
            with open(path, newline="") as f:
                rows = [r for r in csv.DictReader(f) if int(r["step"]) <= resume_step]
        with open(path, "w", newline="") as f:
            w = csv.DictWriter(f, CSV_FIELDS)
            w.writeheader()
            w.writerows(rows)

    def write(self, **row) -> None:
        with open(self.path, "a", newline="") as f:
            csv.DictWriter(f, CSV_FIELDS).writerow({k: row.get(k, "") for k in CSV_FIELDS})


def train(cfg: TrainConfig, store, out, *, progress: bool = True, stop_after: int | None = None) -> dict:
    """Train ``cfg.model`` on the store's train split; validate on ``cfg.val_split``.

    ``stop_after``: return after this many steps of THIS call (to test and demonstrate resuming).
    Returns ``{"step", "loss", "val": {...}, "seconds", "checkpoint"}``.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    device = pick_device(cfg.device)
    flush_denormals()
    store = open_store(store)
    store_info = {"path": str(store.path), "schema_version": store.schema_version}
    loss_fn = build_loss(cfg.loss)

    torch.manual_seed(cfg.seed)
    model = build(cfg.model, **cfg.model_cfg).to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    step = 0
    ck_path = out / "checkpoint.pt"
    if ck_path.exists():
        ck = ckpt.load(ck_path, map_location=device)
        prev = TrainConfig.from_dict(ck["train_config"])
        if prev.identity() != cfg.identity():
            diff = {k: (prev.identity()[k], v) for k, v in cfg.identity().items() if prev.identity()[k] != v}
            raise CheckpointError(f"{ck_path} was trained with other settings (setting: (checkpoint, now)): {diff}")
        ckpt.check_store(ck, store.schema_version, ck_path)
        model.load_state_dict(ck["state_dict"])
        optimizer.load_state_dict(ck["optimizer"])
        ckpt.set_rng_state(ck["rng"])
        step = int(ck["step"])

    train_ds = sample_dataset(store, "train", cfg.spp, cfg.crop, augment=True, seed=cfg.seed)
    lay = store.layout
    val_crop = min(cfg.val_crop, lay.height, lay.width) if cfg.val_crop else None   # small stores: whole frames
    val_ds = sample_dataset(store, cfg.val_split, cfg.spp, val_crop, augment=False, seed=cfg.seed)
    log = _Log(out / "metrics.csv", step)

    def save():
        ckpt.save(ck_path, model=model, optimizer=optimizer, step=step, cfg=cfg, store_info=store_info)

    t0 = time.perf_counter()
    loss, val = float("nan"), {}
    todo = cfg.steps - step if stop_after is None else min(cfg.steps - step, stop_after)
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=cfg.steps, initial=step, desc=f"train {cfg.model}", unit="step", dynamic_ncols=True)
    try:
        for _ in range(max(todo, 0)):
            batch, epoch = get_batch(train_ds, cfg.seed, step, cfg.batch)
            loss = train_step(model, optimizer, loss_fn, to_device(batch, device), cfg.grad_clip_norm,
                              cfg.grad_clip_value, lr=warmup_lr(cfg.lr, cfg.warmup, step))
            step += 1
            if bar:
                bar.update(1)
                bar.set_postfix(loss=f"{loss:.4f}")
            if step % cfg.log_every == 0 or step == cfg.steps:
                log.write(step=step, epoch=epoch, kind="train", loss=loss, seconds=time.perf_counter() - t0)
            if (cfg.val_every and step % cfg.val_every == 0) or step == cfg.steps:
                val = validate(model, val_ds, loss_fn, device, cfg.val_frames)
                log.write(step=step, epoch=epoch, kind="val", seconds=time.perf_counter() - t0, **val)
            if step % cfg.checkpoint_every == 0 or step == cfg.steps:
                save()
        if todo > 0 and step % cfg.checkpoint_every and step != cfg.steps:
            save()
    finally:
        if bar:
            bar.close()
    return {"step": step, "loss": loss, "val": val, "seconds": time.perf_counter() - t0, "checkpoint": str(ck_path)}
