"""Training settings: a frozen, self-validating dataclass that round-trips through a dict (checked with
``core.checks``, the mechanism every config of the project shares)."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

from core.checks import is_int, is_number, known_keys, need, need_int

from .errors import ConfigError


# The layer family's training settings (see TrainConfig), for models that declare none of their own.
LAYER_FAMILY_DEFAULTS = dict(loss="smape", lr=0.0005, grad_clip_norm=0.001, grad_clip_value=0.25, warmup=50)


@dataclass(frozen=True)
class TrainConfig:
    """One training run. Defaults are the layer paper's (sec. 4: Adam, batch 4, 128 px crops, 8 spp,
    SMAPE loss) with the learning rate and gradient clamping of its public code (NVlabs/layerdenoise
    ``train.py``: lr 0.0005, ``clip_grad_norm_`` 0.001 then ``clip_grad_value_`` 0.25). The paper's
    text says lr 0.005; without clamping that lets the unnormalised U-net's context features grow
    to ~1e31 within 40 steps, which saturates every kernel to one tap (measured on
    ``configs/train-cpu.yaml``). ``steps`` is the budget in optimiser steps; ``model_cfg`` overrides
    the model's (paper) defaults, e.g. ``{"layers": 3}``; a clamp of 0 disables it.

    ``warmup`` ramps the learning rate linearly from lr/warmup to lr over its first steps. Adam's first
    steps move every weight by about lr in a coherent direction; through the unnormalised 512-wide
    U-net that multiplied the context features 2500x within 5 steps at lr 0.0005 (and 5000x within 20
    at lr 0.0001), saturating the kernels and the sample partition. With warm-up they stay near 1-4.

    Settings left at None take the model's own defaults (its class's ``train_defaults``, e.g. NBG's L1
    loss at lr 1e-4 and WSKPN's SMAPE at lr 1e-3, without clamping or warm-up, and ``spp`` from its
    input declaration: 1 for the per-pixel models), else the layer family's values above; the
    resolved values are what a checkpoint records. ``train_clips`` restricts training to those clips
    (scenes) of the train split, kept whole (``training.scaling``'s nested subsets); it is part of the
    run's identity, so a run resumes only on the same frames. ``workers`` is the number of DataLoader worker
    processes (0: load in the training process); it does not change what is trained. ``log_every``:
    the training loss is logged, and read from the device and checked for NaN/Inf, every this many
    steps (between reads no step waits for the device). ``compile``: the forward pass and the loss
    through ``torch.compile``; it changes the arithmetic only within float rounding, and a run may
    resume with or without it. ``device`` and
    ``precision`` (:mod:`training.accel`) may change between a run and its resumption (a run started
    on a GPU in bf16 resumes on a CPU in fp32)."""

    model: str = "layer"
    model_cfg: dict = field(default_factory=dict)
    loss: str | None = None     # None: the model's default (below: the layer family's)
    lr: float | None = None
    grad_clip_norm: float | None = None
    grad_clip_value: float | None = None
    warmup: int | None = None   # optimiser steps of linear learning-rate warm-up (0: off)
    batch: int = 4
    crop: int | None = None     # None: the paper's 128, or the whole frame where frames are smaller
    spp: int | None = None      # None: the model's declared default (8 for the layer family)
    steps: int = 1000
    seed: int = 0
    val_every: int = 100        # optimiser steps between validations (0: only at the end)
    val_frames: int = 8         # held-out frames per validation (0: all of the split)
    val_crop: int = 128         # crop of validation frames (0: full frames)
    val_split: str = "val"
    log_every: int = 10
    checkpoint_every: int = 100
    device: str = "auto"        # auto: CUDA where present, else the CPU (training.accel)
    precision: str = "auto"     # auto: bf16 on a GPU that has it, else fp32; bf16, fp16 or fp32
    workers: int = 1            # DataLoader worker processes (0: in-process)
    skip_bad_frames: bool = False   # leave out frames validate flags (default: refuse them)
    train_clips: list | None = None  # train only on these clip ids of the train split (None: all of it)
    compile: bool = False       # the forward pass and loss through torch.compile (training.loop.forward_loss_fn)

    def __post_init__(self):
        self._resolve_defaults()

        # one line naming the setting, Mitsuba's style: "lr" must be > 0, got 0
        need(is_number(self.lr) and self.lr > 0, '"lr"', "> 0", self.lr, ConfigError)
        for name in ("grad_clip_norm", "grad_clip_value"):
            v = getattr(self, name)
            need(is_number(v) and v >= 0, f'"{name}"', ">= 0 (0: off)", v, ConfigError)
        if self.crop is not None:
            need(is_int(self.crop) and self.crop >= 1, '"crop"', "an integer >= 1 (or None)", self.crop, ConfigError)
        for name in ("batch", "spp", "log_every", "checkpoint_every"):
            need_int(f'"{name}"', getattr(self, name), 1, None, ConfigError)
        for name in ("steps", "warmup", "val_every", "val_frames", "val_crop", "seed", "workers"):
            need_int(f'"{name}"', getattr(self, name), 0, None, ConfigError)
        need(isinstance(self.model_cfg, dict), '"model_cfg"', "a dict of model settings", self.model_cfg, ConfigError)
        if self.train_clips is not None:
            clips = self.train_clips
            need(isinstance(clips, (list, tuple)) and len(clips) > 0 and all(is_int(c, numpy=True) for c in clips),
                 '"train_clips"', "null or a non-empty list of clip ids", clips, ConfigError)
            object.__setattr__(self, "train_clips", sorted({int(c) for c in clips}))
        need(isinstance(self.compile, bool), '"compile"', "true or false", self.compile, ConfigError)
        from .accel import check_device, check_precision
        check_device(self.device)
        check_precision(self.precision)
        from .losses import build_loss
        build_loss(self.loss)

    def _resolve_defaults(self) -> None:
        """Fill the settings left at None from the model's declaration (frozen: set once, here)."""
        from .models import get
        cls = get(self.model)
        for name, value in {**LAYER_FAMILY_DEFAULTS, "spp": cls.inputs.default_spp, **cls.train_defaults}.items():
            if getattr(self, name) is None:
                object.__setattr__(self, name, value)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        return cls(**known_keys(d, cls, "training", ConfigError, noun="setting(s)"))

    def replace(self, **kw) -> "TrainConfig":
        return TrainConfig.from_dict({**self.to_dict(), **kw})

    def identity(self) -> dict:
        """Settings that must match to resume a run (everything except the step budget and logging)."""
        d = self.to_dict()
        for k in ("steps", "val_every", "val_frames", "log_every", "checkpoint_every", "device", "precision",
                  "workers", "compile"):
            d.pop(k)
        return d
