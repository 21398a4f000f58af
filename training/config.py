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
    (scenes) of the train split, kept whole (``studies.scaling``'s nested subsets); it is part of the
    run's identity, so a run resumes only on the same frames. ``workers`` is the number of DataLoader worker
    processes (0: load in the training process); it does not change what is trained. ``log_every``:
    the training loss is logged, and read from the device and checked for NaN/Inf, every this many
    steps (between reads no step waits for the device). ``compile``: the forward pass and the loss
    through ``torch.compile``; it changes the arithmetic only within float rounding, and a run may
    resume with or without it. ``device`` and
    ``precision`` (:mod:`training.accel`) may change between a run and its resumption (a run started
    on a GPU in bf16 resumes on a CPU in fp32)."""

    # Each field's ``help`` is its command-line option's (``training.cli``: ``train`` builds its options from
    # these fields, and the other commands take --device, --precision, --compile and --skip-bad-frames
    # from here too).
    model: str = field(default="layer", metadata={"help": "a registered model"})
    model_cfg: dict = field(default_factory=dict, metadata={"help": "JSON model settings, e.g. '{\"layers\": 3}'"})
    loss: str | None = field(default=None, metadata={"help": (
        "smape (eq. 9, linear radiance), l2-tonemap or l1 (tone-mapped, eq. 7), l1-temporal (Hasselgren et al. "
        "eq. 4, clips); default: the model's (smape; nbg: l1; temporal: l1-temporal)")})
    lr: float | None = field(default=None, metadata={"help": (
        "Adam learning rate (default: the model's; layer family 0.0005, NVlabs/layerdenoise's; nbg 1e-4, wskpn "
        "1e-3, their papers')")})
    grad_clip_norm: float | None = field(default=None, metadata={"help": (
        "clip the gradients' norm to this (0: off; default: the model's, 0.001 for the layer family)")})
    grad_clip_value: float | None = field(default=None, metadata={"help": (
        "then clamp every gradient to +-this (0: off; default: the model's, 0.25 for the layer family)")})
    warmup: int | None = field(default=None, metadata={"help": (
        "steps of linear learning-rate warm-up (default: 50 for the layer family, 0 otherwise)")})
    batch: int = field(default=4, metadata={"help": "crops per step (default 4, the paper's)"})
    crop: int | None = field(default=None, metadata={"help": (
        "square training crop in pixels (default 128, the paper's, or the whole frame of a store with smaller "
        "frames; a crop larger than the frames is refused)")})
    spp: int | None = field(default=None, metadata={"help": (
        "samples per pixel fed to the model (default: the model's, 8 for the layer family, 1 for nbg and wskpn; "
        "for temporal the average budget per pixel, default 4, at most the sum of the store's layers; at most "
        "what the store holds)")})
    steps: int = field(default=1000, metadata={"help": "optimiser steps (default 1000)"})
    seed: int = field(default=0, metadata={"help": "seeds weights, crops and augmentation"})
    val_every: int = field(default=100, metadata={"help": "validate on held-out scenes every N steps (0: at the end)"})
    val_frames: int = field(default=8, metadata={"help": "validation frames (from the --val-split split; 0: all)"})
    val_crop: int = field(default=128, metadata={"help": "crop of validation frames in pixels (0: whole frames)"})
    val_split: str = field(default="val", metadata={"help": (
        "split to validate on (default val; a store without it trains without validation)")})
    log_every: int = field(default=10, metadata={"help": (
        "write the training loss to metrics.csv, and read it from the device and check it for NaN/Inf, every N "
        "steps (default 10; between reads no step waits for the device)")})
    checkpoint_every: int = field(default=100, metadata={"help": "write checkpoint.pt every N steps"})
    device: str = field(default="auto", metadata={"help": (
        "auto, cpu, cuda, cuda:1, ... (default auto: CUDA where PyTorch sees a GPU, else the CPU)")})
    precision: str = field(default="auto", metadata={"choices": ("auto", "bf16", "fp16", "fp32"), "help": (
        "autocast precision of the forward pass, weights kept in fp32; fp16 scales the loss (default auto: bf16 "
        "on a GPU that has it, else fp32)")})
    workers: int = field(default=1, metadata={"help": (
        "DataLoader worker processes (default 1; 0 loads in the training process)")})
    skip_bad_frames: bool = field(default=False, metadata={"help": (
        "leave out frames validate flags (incomplete, NaN the renderer replaced, negative or all-zero "
        "references), naming them in one line and in the run's record; default: refuse them")})
    train_clips: list | None = None  # train only on these clip ids of the train split (None: all of it)
    compile: bool = field(default=False, metadata={"help": (
        "run the forward pass and loss through torch.compile (the first step compiles: tens of seconds on a "
        "CPU, a minute or more on a GPU)")})

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
