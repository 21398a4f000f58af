"""The training loop: explicit and short (nanoGPT style).

    summary = train(TrainConfig(model="layer", steps=1000), store="data/default.zarr", out="data/runs/layer")

writes ``out/checkpoint.pt`` (every ``checkpoint_every`` steps and at the end) and ``out/metrics.csv``
(``step, epoch, kind, loss, relmse, smape, psnr, seconds``; kind ``train`` or ``val``). If
``out/checkpoint.pt`` exists the run resumes from it and continues exactly as an uninterrupted run
would (same batches, same optimiser state); a checkpoint from different settings or another store is
refused (the same store upgraded by ``python -m stores upgrade`` is the same store).

Under ``torchrun --nproc_per_node N -m training train ...`` the same function trains with
DistributedDataParallel (:mod:`training.distributed`: gloo on CPU, nccl on CUDA). ``batch`` is the
global batch, split evenly over the ranks, and the ranks' crops in a step are exactly the
one-process batch, so a run gives the weights of a one-process run with that batch (within float
rounding). The logged training loss is the global batch's (averaged over the ranks); validation is
split over the ranks (frame i on rank i mod N) and gathered, so its figures are the one-process
ones. Rank 0 alone writes ``checkpoint.pt`` and ``metrics.csv`` and shows the progress bar; every
rank loads the checkpoint to resume. The RNG state saved is rank 0's, which is every rank's: all
seed alike and no training step draws from the global RNGs (crops and augmentation are functions of
(seed, epoch, frame)), so resuming is exact under any number of ranks.
"""
from __future__ import annotations

import contextlib
import csv
import math
import os
import signal
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from core import interrupts
from core.files import remove_stale_temps
from stores.errors import SplitError

from . import accel, distributed, metrics
from . import checkpoint as ckpt
from .config import TrainConfig
from .data import batch_loader, batches_per_epoch, draws_per_epoch, model_dataset, open_store, to_device
from .errors import CheckpointError, ConfigError, DataError, NonFiniteError
from .losses import build_loss
from .models import build, get
from .models.common import flush_denormals

DEFAULT_CROP = 128
CSV_FIELDS = ("step", "epoch", "kind", "loss", "relmse", "smape", "psnr", "seconds")


def warmup_lr(lr: float, warmup: int, step: int) -> float:
    """Learning rate of optimiser step ``step`` (0-based): linear warm-up over ``warmup`` steps."""
    return lr * min(1.0, (step + 1) / warmup) if warmup else lr


def train_step(model, optimizer, loss_fn, batch: dict, clip_norm: float = 0.0, clip_value: float = 0.0,
               lr: float | None = None, target=None, dist: distributed.Dist = distributed.SINGLE,
               precision: str = "fp32", scaler: torch.amp.GradScaler | None = None) -> float:
    """One optimiser step on ``batch``; returns the loss, read from the device, and raises
    NonFiniteError on a NaN/Inf loss before the weights move. The arguments are
    :func:`device_train_step`'s. Reading the loss waits for the step to finish (a host sync): the
    training loop uses :func:`device_train_step` and reads its losses every ``log_every`` steps."""
    value = device_train_step(model, optimizer, loss_fn, batch, clip_norm, clip_value, lr, target, dist, precision,
                              scaler, check_finite=True)
    return float(value)


def device_train_step(model, optimizer, loss_fn, batch: dict, clip_norm: float = 0.0, clip_value: float = 0.0,
                      lr: float | None = None, target=None, dist: distributed.Dist = distributed.SINGLE,
                      precision: str = "fp32", scaler: torch.amp.GradScaler | None = None, forward_loss=None,
                      check_finite: bool = False) -> torch.Tensor:
    """One optimiser step on ``batch``; returns the loss as a detached 0-d tensor on the device, read by
    nobody here, so the host runs ahead of the device (:class:`LossReader` reads it later).
    Gradients are clamped first by total norm, then by value (0: off), like NVlabs/layerdenoise.
    ``lr``: this step's learning rate (None: leave the optimiser's). ``target``: the reference the
    output is compared with (default ``batch["reference"]``; the input kind's ``target``).
    ``dist``: under torchrun ``model`` is DDP-wrapped and ``batch`` this rank's share; the returned
    loss is the global batch's (the ranks' means averaged), so every rank reads the same value and
    stops on the same non-finite one. ``precision``: the forward pass's (:func:`training.accel.autocast`
    on the batch's device; fp32: none); ``scaler``: fp16's loss scaling (gradients are unscaled before
    clamping; a step whose gradients overflowed is skipped by the scaler; its check reads the device
    every step). ``forward_loss``: ``(batch, target) -> loss`` (:func:`forward_loss_fn`, compiled for
    ``--compile``; default: the eager forward pass and loss). ``check_finite``: read the loss now and
    raise NonFiniteError, before the weights move, if it is NaN/Inf (a host sync)."""
    if lr is not None:
        for group in optimizer.param_groups:
            group["lr"] = lr
    model.train()
    optimizer.zero_grad(set_to_none=True)
    target = batch["reference"] if target is None else target
    if forward_loss is None:
        device = next(v.device for v in batch.values() if isinstance(v, torch.Tensor))
        forward_loss = forward_loss_fn(model, loss_fn, device, precision)
    loss = forward_loss(batch, target)
    value = dist.mean(loss.detach())
    if check_finite and not torch.isfinite(value):
        raise NonFiniteError(f"loss is {value.item()} (non-finite)")
    if scaler is None or not scaler.is_enabled():
        loss.backward()
        _clamp(model, clip_norm, clip_value)
        optimizer.step()
        return value
    scaler.scale(loss).backward()
    scaler.unscale_(optimizer)
    _clamp(model, clip_norm, clip_value)
    scaler.step(optimizer)
    scaler.update()
    return value


def forward_loss_fn(model, loss_fn, device: torch.device, precision: str = "fp32", compiled: bool = False):
    """``(batch, target) -> loss``: ``model``'s forward pass on ``batch`` in ``precision`` and ``loss_fn``
    against ``target``, in fp32. ``compiled``: through ``torch.compile`` (Inductor; the backward pass
    is compiled with it by AOTAutograd). Its first call compiles (tens of seconds on a CPU); a new
    batch shape compiles again."""
    def forward_loss(batch: dict, target: torch.Tensor) -> torch.Tensor:
        with accel.autocast(device, precision):
            out = model(batch)
        check_output(out, target)
        return loss_fn(out.float(), target)
    return torch.compile(forward_loss) if compiled else forward_loss


class LossReader:
    """The training loss, kept on the device step by step and read to the host (one read for all the
    steps since the last) only when :meth:`read` is called: by the loop every ``every`` steps
    (``log_every``) and before it validates or writes a checkpoint. A NaN/Inf loss among them raises
    NonFiniteError naming its step and the steps read together; the steps after it in that range
    have run (their weights are not written: a checkpoint is written only after a read)."""

    def __init__(self, every: int):
        self.every = every
        self.pending: list[torch.Tensor] = []
        self.first = 0
        self.value = float("nan")

    def add(self, step: int, loss: torch.Tensor) -> None:
        """The loss of optimiser step ``step`` (1-based, as logged), a 0-d tensor on the device."""
        if not self.pending:
            self.first = step
        self.pending.append(loss)

    def read(self) -> float:
        """The last step's loss (NaN before any step), after checking every pending one."""
        if not self.pending:
            return self.value
        values = torch.stack(self.pending).tolist()             # one read for every pending step
        first, self.pending = self.first, []
        for i, v in enumerate(values):
            if not math.isfinite(v):
                raise NonFiniteError(f"loss is {v} (non-finite) at step {first + i}; the loss is read from the "
                                     f"device every {self.every} steps (--log-every), here steps "
                                     f"{first}..{first + len(values) - 1}")
        self.value = values[-1]
        return self.value


def check_output(out: torch.Tensor, target: torch.Tensor) -> None:
    """Refuse an output whose shape is not its target's: the loss would broadcast one against the other
    and train on nonsense without a word (e.g. one frame's output against a clip's references)."""
    if out.shape != target.shape:
        raise ConfigError(f"the model's output is {tuple(out.shape)} but the reference it is trained against is "
                          f"{tuple(target.shape)}: a model of its input kind must output the kind's target "
                          "(training.inputs)")


def _clamp(model, clip_norm: float, clip_value: float) -> None:
    if clip_norm:
        torch.nn.utils.clip_grad_norm_(model.parameters(), clip_norm)
    if clip_value:
        torch.nn.utils.clip_grad_value_(model.parameters(), clip_value)


VAL_BATCH = 4          # held-out items a validation forward takes at once


@torch.no_grad()
def validate(model, dataset, loss_fn, device, max_frames: int = 0, kind=None,
             dist: distributed.Dist = distributed.SINGLE, precision: str = "fp32", batch: int = VAL_BATCH) -> dict:
    """Mean loss, relMSE, SMAPE and PSNR over (up to ``max_frames``) held-out items, the model run in
    ``precision`` (as trained) and every figure computed in float64 on the device. ``kind``:
    the model's input kind (its ``target``); default: the item's ``reference``. ``dist``: under
    torchrun item i is judged on rank ``i mod N`` and the rows gathered in item order, so every rank
    returns the one-process figures (``model``: the unwrapped module). Items of one shape run ``batch``
    at a time, and the figures stay on the device until one read at the end (a host read waits for the
    device: one per item kept a GPU idle between items)."""
    from torch.utils.data import default_collate
    model.eval()
    n = len(dataset) if not max_frames else min(max_frames, len(dataset))
    mine = list(range(dist.rank, n, dist.world))
    parts = []
    for group, got in _same_shape_runs(dataset, mine, max(1, int(batch))):
        items = to_device(default_collate(got), device)
        with accel.autocast(torch.device(device), precision):
            out = model(items)
        out = out.float()
        ref = (items["reference"] if kind is None else kind.target(items)).float()
        check_output(out, ref)
        if out.dim() == 5:                           # a recurrent model's window: judge its last frame
            out, ref = out[:, -1], ref[:, -1]
        losses = torch.stack([loss_fn(out[j:j + 1], ref[j:j + 1]).float() for j in range(len(group))])
        parts.append(torch.cat([losses.double()[:, None], image_metrics(out, ref)], dim=1))
    values = torch.cat(parts).cpu().numpy() if parts else np.zeros((0, 4))
    rows = [{"i": i, **dict(zip(("loss", "relmse", "smape", "psnr"), map(float, v)))} for i, v in zip(mine, values)]
    if dist.enabled:
        rows = sorted((r for part in dist.gather(rows) for r in part), key=lambda r: r["i"])
    rows = [{k: v for k, v in r.items() if k != "i"} for r in rows]
    return {k: float(np.mean([r[k] for r in rows])) for k in rows[0]} if rows else {}


def _same_shape_runs(dataset, indices: list[int], size: int):
    """``(indices, items)`` of ``dataset`` in order, in runs of at most ``size`` items whose tensors have
    the same shapes (they stack)."""
    run, items, shape = [], [], None
    for i in indices:
        item = dataset[i]
        s = tuple((k, tuple(v.shape)) for k, v in sorted(item.items()) if isinstance(v, torch.Tensor))
        if run and (len(run) == size or s != shape):
            yield run, items
            run, items = [], []
        run.append(i)
        items.append(item)
        shape = s
    if run:
        yield run, items


def image_metrics(out: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """relMSE, SMAPE and PSNR of each image of a batch (B 3 H W, linear radiance) as ``training.metrics``
    computes them (its numpy functions are the oracle), in float64 on the images' device: (B, 3)."""
    from core.images import tonemap
    d, r = out.double(), ref.double()
    dims = tuple(range(1, d.dim()))
    relmse = ((d - r) ** 2 / (r ** 2 + metrics.RELMSE_EPS)).mean(dim=dims)
    smape = ((d - r).abs() / (d.abs() + r.abs() + metrics.SMAPE_EPS)).mean(dim=dims)
    mse = ((tonemap(d) - tonemap(r)) ** 2).mean(dim=dims)
    psnr = 10.0 * torch.log10(1.0 / mse)
    return torch.stack([relmse, smape, psnr], dim=1)


class _Feed:
    """Whether the loader keeps up: the crops a second its processes can make (one process's rate, timed
    on a few crops, times the workers) against the crops a second the steps consume, measured over the
    first :attr:`STEPS` steps after the first (a starved GPU waits on the loader: raise --workers)."""
    STEPS = 10

    def __init__(self, dataset, batch: int, workers: int):
        from .data import crops_per_second
        self.batch, self.workers = batch, workers
        self.make = crops_per_second(dataset) * max(workers, 1)
        self.n, self.wait, self.busy = -1, 0.0, 0.0
        self.total_n, self.total_wait, self.total_busy = 0, 0.0, 0.0

    def add(self, wait: float, busy: float) -> bool:
        """Count one step (``wait``: seconds waiting for its batch; ``busy``: seconds of the step);
        True once, when the line is due. Every step after the first also counts in :meth:`summary`."""
        self.n += 1
        if self.n == 0:                     # the first batch waits for the workers to start
            return False
        self.total_n, self.total_wait, self.total_busy = self.total_n + 1, self.total_wait + wait, self.total_busy + busy
        if self.n > self.STEPS:
            return False
        self.wait, self.busy = self.wait + wait, self.busy + busy
        return self.n == self.STEPS

    def summary(self) -> dict:
        """Over every step after the first (which waits for the loader's start and, compiled, compiles):
        ``wait_share`` (the time waiting for batches over the steps' wall time), ``steps_per_s`` (wall
        time with the waits), the loader's and the steps' crops a second, the steps counted. The host
        runs ahead of the device between loss reads, so on a GPU a step's time is the device's only
        averaged over the reads (every ``log_every`` steps)."""
        wall = self.total_wait + self.total_busy
        return {"steps": self.total_n, "wait_s": self.total_wait, "step_s": self.total_busy,
                "wait_share": self.total_wait / wall if wall > 0 else None,
                "steps_per_s": self.total_n / wall if wall > 0 else None,
                "loader_crops_per_s": self.make,
                "consumed_crops_per_s": self.total_n * self.batch / self.total_busy if self.total_busy > 0 else None,
                "workers": self.workers}

    def line(self) -> str:
        use = self.n * self.batch / max(self.busy, 1e-9)
        waited = self.wait / max(self.wait + self.busy, 1e-9)
        who = f"{self.workers} worker process(es)" if self.workers else "the training process (--workers 0)"
        msg = (f"data: the loader makes ~{self.make:.0f} crops/s ({who}); the steps consume {use:.0f} crops/s; "
               f"{100 * waited:.0f}% of the time waiting for data")
        if self.make < use:
            msg += f": the steps are starved, raise --workers (about {use / self.make * max(self.workers, 1):.0f})"
        return msg


def store_identity(store) -> dict:
    """What identifies the data a run trains on: the store's real path, schema version, layout and a
    hash of the config that built it. A resumed run must see the same."""
    import hashlib
    import json
    cfg = json.dumps(store.config, sort_keys=True, default=str).encode()
    path = os.fspath(store.path)
    out = {"path": path if "://" in path else os.path.realpath(path), "schema_version": store.schema_version,
           "layout": store.layout.to_dict(), "config_sha256": hashlib.sha256(cfg).hexdigest()}
    if getattr(store, "split_source", None):          # a Noisebase folder: its declared splits, or ours
        out["split_source"] = store.split_source
    return out


def check_same_store(ck: dict, now: dict, path) -> None:
    """Refuse to resume checkpoint ``ck`` on another store, naming the differing fields."""
    from stores.schema import StoreLayout
    was = ck.get("store", {})

    def same(k):
        if k == "layout":          # a store's layout as recorded (a layout from before ``encoding`` is lz4's)
            try:
                return StoreLayout.of_store(was[k]) == StoreLayout.of_store(now[k])
            except Exception:  # noqa: BLE001 - an unreadable old layout is simply different
                return was[k] == now[k]
        return was[k] == now[k]
    # the schema version may differ: ``python -m stores upgrade`` keeps every value of the store it upgrades
    diff = {k: (was[k], now[k]) for k in now if k in was and k not in ("left_out", "schema_version") and not same(k)}
    if diff:
        raise CheckpointError(f"{path} was trained on another store (field: (checkpoint, now)): {diff}; "
                              "resume on the same store, or train into a new --out")


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


def _prepare_out(out, rank: int = 0) -> Path:
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out} is a file; it must be a run folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / (f".write-test-{rank}" if rank else ".write-test")
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise ConfigError(f"cannot write the run folder --out {out}: {e.strerror or e}") from e
    return out


def train(cfg: TrainConfig, store, out, *, progress: bool = True, stop_after: int | None = None,
          seconds: float | None = None) -> dict:
    """Train ``cfg.model`` on the store's train split; validate on ``cfg.val_split`` (a store without
    that split trains without validation, with a warning).

    The model's input declaration (``model.input_spec()``) chooses the dataset and the target.
    ``stop_after``: return after this many steps of THIS call (to test and demonstrate resuming).
    ``seconds``: return once this call has trained that long, counted from its first step's start
    (``train --seconds``; the step under way
    finishes, the checkpoint is written; the same command resumes). Both leave ``cfg.steps`` and the
    run's identity alone.
    Returns ``{"step", "loss", "val": {...}, "seconds", "checkpoint", "feed"}`` (checkpoint None if no
    step ran and none existed; ``feed``: :meth:`_Feed.summary`, the loader's wait as a share of the
    steps' time and the steps a second, None on other ranks or without steps); under torchrun (module
    docstring) every rank returns it, with ``rank`` and ``world`` added.
    """
    with distributed.session(accel.device_name(cfg.device)) as (dist, device_name):
        return _train(cfg, store, out, dist, device_name, progress, stop_after, seconds)


def _train(cfg: TrainConfig, store, out, dist: distributed.Dist, device_name: str, progress: bool,
           stop_after: int | None, seconds: float | None = None) -> dict:
    if seconds is not None and not (isinstance(seconds, (int, float)) and math.isfinite(seconds) and seconds > 0):
        raise ConfigError(f"--seconds must be a number of seconds > 0, got {seconds!r}")
    store = open_store(store)
    refuse_held_out(store)
    out = _prepare_out(out, dist.rank)
    device = accel.pick_device(device_name)
    precision = accel.precision_for(cfg.precision, device)
    flush_denormals()
    if cfg.crop is None:                    # the paper's 128 px, or whole frames of a smaller store
        cfg = cfg.replace(crop=min(DEFAULT_CROP, store.layout.height, store.layout.width))
    if dist.enabled and cfg.batch % dist.world:
        raise ConfigError(f'"batch" {cfg.batch} is the global batch and must divide evenly over the '
                          f"{dist.world} ranks; use a multiple of {dist.world}")
    run = _Run(cfg, store, out, device, precision, dist)
    train_ds, val_ds = _datasets(cfg, run.module.input_spec(), store)
    left_out = {**getattr(val_ds, "left_out", {}), **train_ds.left_out}      # --skip-bad-frames: kept on record
    run.store_info["left_out"] = {str(i): list(p) for i, p in sorted(left_out.items())}
    todo = max(cfg.steps - run.step, 0) if stop_after is None else max(min(cfg.steps - run.step, stop_after), 0)
    t0 = time.perf_counter()
    loss, val, feed = _loop(run, train_ds, val_ds, todo, progress, t0, seconds)
    dist.barrier()                              # rank 0's checkpoint is written before any rank returns
    res = {"step": run.step, "loss": loss, "val": val, "seconds": time.perf_counter() - t0,
           "checkpoint": str(run.ck_path) if run.ck_path.exists() else None,
           "feed": feed.summary() if feed is not None and feed.total_n else None}
    return {**res, "rank": dist.rank, "world": dist.world} if dist.enabled else res


def refuse_held_out(store) -> None:
    """A store made from a held-out dataset config (``held_out: true``: the hard-case suite, whose scene
    seeds no training config draws) is for evaluation only: DataError naming it."""
    cfg = store.config if isinstance(store.config, dict) else {}
    if cfg.get("held_out"):
        raise DataError(f"{store.path} is a held-out store (its config {cfg.get('name', '')!r} says held_out: true): "
                        "it is for evaluation only, never for training")


class _Run:
    """A run's state: the model (``module``; ``model`` DDP-wrapped under torchrun), its optimiser and
    loss scaler resumed from ``out/checkpoint.pt`` if there is one, the step, and the metrics log."""

    def __init__(self, cfg: TrainConfig, store, out: Path, device, precision: str, dist: distributed.Dist):
        self.cfg, self.store, self.device, self.precision, self.dist = cfg, store, device, precision, dist
        self.store_info = store_identity(store)
        self.loss_fn = build_loss(cfg.loss)
        torch.manual_seed(cfg.seed)
        self.module = accel.prepare(build(cfg.model, **cfg.model_cfg), device)
        self.kind = self.module.input_spec().input_kind
        self.optimizer = accel.adam(self.module.parameters(), cfg.lr)
        self.scaler = accel.grad_scaler(device, precision)
        self.ck_path = out / "checkpoint.pt"
        if dist.is_main:                        # a write a SIGKILL cut short left its temporary file
            remove_stale_temps(self.ck_path)
        self.step = self._resume() if self.ck_path.exists() else 0
        self.model = distributed.wrap(self.module, dist, device)    # DDP under torchrun, else the module
        self.forward_loss = forward_loss_fn(self.model, self.loss_fn, device, precision, compiled=cfg.compile)
        self.log = _Log(out / "metrics.csv", self.step) if dist.is_main else None
        self.ctrl_c = _CtrlC(enabled=False)     # the loop's, while it runs: a write is never cut short

    def _resume(self) -> int:
        """Load the checkpoint after checking it was trained with these settings on this store."""
        cfg, path = self.cfg, self.ck_path
        ck = ckpt.load(path, map_location=self.device)
        prev = TrainConfig.from_dict(ck["train_config"])
        if prev.identity() != cfg.identity():
            diff = {k: (prev.identity()[k], v) for k, v in cfg.identity().items() if prev.identity()[k] != v}
            raise CheckpointError(f"{path} was trained with other settings (setting: (checkpoint, now)): {diff}")
        check_same_store(ck, self.store_info, path)
        trained = {**get(cfg.model).legacy_config, **ck["model_config"]}
        if trained != self.module.config:           # begun before a model setting existed: go on as it began
            self.module = accel.prepare(build(cfg.model, **trained), self.device)
            self.optimizer = accel.adam(self.module.parameters(), cfg.lr)
        self.module.load_state_dict(ck["state_dict"])
        accel.load_optimizer_state(self.optimizer, ck["optimizer"])
        ckpt.set_rng_state(ck["rng"])
        if self.scaler.is_enabled() and ck.get("scaler"):
            self.scaler.load_state_dict(ck["scaler"])
        return int(ck["step"])

    def save(self) -> None:
        if self.dist.is_main:
            with self.ctrl_c.deferred():
                ckpt.save(self.ck_path, model=self.module, optimizer=self.optimizer, step=self.step, cfg=self.cfg,
                          store_info=self.store_info,
                          extra={"scaler": self.scaler.state_dict()} if self.scaler.is_enabled() else None)

    def train_step(self, batch: dict) -> torch.Tensor:
        """One optimiser step; its loss stays on the device (:class:`LossReader`)."""
        cfg = self.cfg
        return device_train_step(self.model, self.optimizer, self.loss_fn, batch, cfg.grad_clip_norm,
                                 cfg.grad_clip_value, lr=warmup_lr(cfg.lr, cfg.warmup, self.step),
                                 target=self.kind.target(batch), dist=self.dist, precision=self.precision,
                                 scaler=self.scaler, forward_loss=self.forward_loss)

    def validate(self, val_ds) -> dict:
        return validate(self.module, val_ds, self.loss_fn, self.device, self.cfg.val_frames, self.kind, self.dist,
                        self.precision)


def _datasets(cfg: TrainConfig, spec, store):
    """The training split's dataset (only the clips ``cfg.train_clips`` when set) and the validation
    split's (every frame, whole frames of a small store; None, with a warning, when the store has no
    such split)."""
    train_ds = model_dataset(spec, store, "train", cfg.spp, cfg.crop, augment=True, seed=cfg.seed,
                             skip_bad_frames=cfg.skip_bad_frames, clips=cfg.train_clips)
    lay = store.layout
    val_crop = min(cfg.val_crop, lay.height, lay.width) if cfg.val_crop else None
    try:
        val_ds = model_dataset(spec, store, cfg.val_split, cfg.spp, val_crop, augment=False, seed=cfg.seed,
                               full_windows=False, skip_bad_frames=cfg.skip_bad_frames)
    except DataError as e:
        if not isinstance(e.__cause__, SplitError):
            raise
        warnings.warn(f"training without validation: {e.__cause__} (--val-split chooses another split)",
                      stacklevel=3)
        val_ds = None
    return train_ds, val_ds


def _loop(run: _Run, train_ds, val_ds, todo: int, progress: bool, t0: float,
          seconds: float | None = None) -> tuple[float, dict, "_Feed | None"]:
    """``todo`` steps from ``run.step`` (fewer once ``seconds`` have passed since the loader was started,
    just before the first step, so the loader's own timing and the set-up do not count): log, validate
    and checkpoint on their schedules; returns the last training loss, validation figures and the
    loader's record. The losses stay on the device between reads (:class:`LossReader`: every
    ``log_every`` steps, and before a validation or a checkpoint), so no step waits for the last."""
    cfg, dist = run.cfg, run.dist
    val, losses = {}, LossReader(cfg.log_every)
    per_epoch = batches_per_epoch(len(train_ds), cfg.batch)
    _say_batch(cfg, train_ds, dist)
    say = print if dist.is_main else (lambda *a, **k: None)
    say(f"train {cfg.model}: {accel.describe(run.device, run.precision)}" + (", compiled" if cfg.compile else ""),
        flush=True)
    feed = _Feed(train_ds, cfg.batch // dist.world, cfg.workers) if todo > 0 and dist.is_main else None
    bar = None
    if progress and dist.is_main:
        from tqdm import tqdm
        bar = tqdm(total=cfg.steps, initial=run.step, desc=f"train {cfg.model}", unit="step", dynamic_ncols=True)
    ctrl_c = run.ctrl_c = _CtrlC(enabled=not dist.enabled and todo > 0)
    try:
        t_step = t_run = time.perf_counter()
        with ctrl_c:
            try:
                for batch in batch_loader(train_ds, cfg.batch, cfg.seed, run.step, run.step + todo, cfg.workers,
                                          dist.rank, dist.world, pin_memory=run.device.type == "cuda"):
                    epoch = run.step // per_epoch
                    t_data = time.perf_counter()
                    losses.add(run.step + 1, run.train_step(to_device(batch, run.device)))
                    if feed and feed.add(t_data - t_step, time.perf_counter() - t_data):
                        (bar.write if bar else say)(feed.line())
                    t_step = time.perf_counter()
                    run.step += 1
                    if bar:
                        bar.update(1)
                    done = _after_step(run, losses, val_ds, epoch, bar, t0)
                    val = val if done is None else done
                    if ctrl_c.stop_now():
                        break
                    if seconds is not None and (not dist.enabled or run.step % cfg.log_every == 0) \
                            and _stop_on_time(dist, time.perf_counter() - t_run >= seconds):
                        break
            except Exception:       # the loader's workers got the Ctrl-C too and ended: a stop between steps
                if not ctrl_c.stop_now():
                    raise
            if todo > 0 and run.step % cfg.checkpoint_every and run.step != cfg.steps:
                losses.read()
                run.save()
        if ctrl_c.pressed:
            raise TrainingInterrupted(run.step, run.ck_path if run.ck_path.exists() else None)
    finally:
        if bar:
            bar.close()
    return losses.read(), val, feed


class TrainingInterrupted(KeyboardInterrupt):
    """Ctrl-C stopped a run between two steps: ``step`` steps are done and ``checkpoint`` (None when no
    step ran and none existed) holds them; the same command resumes from it."""

    def __init__(self, step: int, checkpoint: Path | None):
        super().__init__(f"interrupted at step {step}")
        self.step, self.checkpoint = step, checkpoint


class _CtrlC:
    """Ctrl-C (SIGINT) during training, in the main thread of a one-process run. The first press: the step
    under way finishes, the run is checkpointed at it and :class:`TrainingInterrupted` is raised
    (``pressed``, read between steps: an interruption inside an optimiser step would leave the weights half
    updated). A second press before that step has finished stops at once (KeyboardInterrupt, for a step
    that hangs: the steps since the last checkpoint are not kept). Once it has finished (:meth:`stop_now`)
    and during every checkpoint write (:meth:`deferred`), a press only asks for the stop: the loader's
    shut-down and the write are never cut short, and the run stops at the step written. Once the run
    stops, Ctrl-C is ignored (:func:`core.interrupts.stopping`): the command's one line is its last word.
    Under torchrun the ranks must stop at the same step: there Ctrl-C stops at once (the process's
    handler, :mod:`core.interrupts`) and the last checkpoint stays. A process that ignores Ctrl-C leaves
    it to its parent (the scaling study's workers, which the study ends): that stays so."""

    def __init__(self, enabled: bool):
        self.enabled = enabled and threading.current_thread() is threading.main_thread() \
            and signal.getsignal(signal.SIGINT) is not signal.SIG_IGN
        self.pressed, self.stopping, self.writing, self._previous = False, False, 0, None

    def __enter__(self):
        if self.enabled:
            self._previous = signal.signal(signal.SIGINT, self._handle)
        return self

    def _handle(self, signum, frame) -> None:
        if self.pressed and not (self.stopping or self.writing):
            interrupts.stopping()
            raise KeyboardInterrupt
        self.pressed = True

    def stop_now(self) -> bool:
        """Whether Ctrl-C was pressed; if so the run stops here and later presses wait for it."""
        self.stopping = self.stopping or self.pressed
        return self.pressed

    @contextlib.contextmanager
    def deferred(self):
        """A checkpoint write: a press meanwhile only asks for the stop (the write completes)."""
        self.writing += 1
        try:
            yield
        finally:
            self.writing -= 1

    def __exit__(self, *exc) -> None:
        if self.enabled:
            if self.pressed:
                interrupts.stopping()
            else:
                signal.signal(signal.SIGINT, self._previous)


def _stop_on_time(dist: distributed.Dist, due: bool) -> bool:
    """Whether every rank stops now: rank 0's clock decides for all (ranks must run the same steps; under
    torchrun this is asked only every ``log_every`` steps, when the losses are read anyway)."""
    if not dist.enabled:
        return due
    flag = [due] if dist.is_main else [None]
    torch.distributed.broadcast_object_list(flag, src=0)
    return bool(flag[0])


def _after_step(run: _Run, losses: LossReader, val_ds, epoch: int, bar, t0: float) -> dict | None:
    """What is due after step ``run.step``: reading (and checking) the losses, the log row, a validation
    (returned) and a checkpoint."""
    cfg = run.cfg
    last = run.step == cfg.steps
    logged = run.step % cfg.log_every == 0 or last
    validating = val_ds is not None and ((cfg.val_every and run.step % cfg.val_every == 0) or last)
    saving = run.step % cfg.checkpoint_every == 0 or last
    if not (logged or validating or saving):
        return None
    loss = losses.read()                       # a NaN stops the run before it is validated or written
    if bar:
        bar.set_postfix(loss=f"{loss:.4f}")
    if run.log and logged:
        run.log.write(step=run.step, epoch=epoch, kind="train", loss=loss, seconds=time.perf_counter() - t0)
    val = None
    if validating:
        val = run.validate(val_ds)
        if run.log:
            run.log.write(step=run.step, epoch=epoch, kind="val", seconds=time.perf_counter() - t0, **val)
    if saving:
        run.save()
    return val


def _say_batch(cfg: TrainConfig, train_ds, dist) -> None:
    draws = draws_per_epoch(len(train_ds), cfg.batch)
    if draws > 1 and dist.is_main:
        warnings.warn(f"--batch {cfg.batch} is larger than the {len(train_ds)} training items of the store: each "
                      f"epoch visits every item {draws} times, each visit its own crop and augmentation",
                      stacklevel=4)
