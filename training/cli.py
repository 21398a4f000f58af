"""The ``python -m training`` command line, built once from the settings' own fields.

``train``'s options are :class:`training.config.TrainConfig`'s fields (``val_every`` -> ``--val-every``),
their types, defaults and ``help`` taken from the dataclass, so a setting added there is an option here
without a second definition. The options every command that runs a model shares (``--device``,
``--precision``, ``--compile``, ``--skip-bad-frames``) are those same fields, added by :func:`add_shared`;
those of the commands that evaluate (``--store``, ``--split``, ``--spp``, ``--frames``, ``--no-flip``,
``--no-oidn``, ``--out``, ``--no-progress``) are :class:`EvalOptions`' fields, added the same way.
"""
from __future__ import annotations

import argparse
import types
import typing
from dataclasses import MISSING, dataclass, field, fields

from .config import TrainConfig

HIDDEN = {"train_clips"}                    # settings of the scaling study, not of a command line
SHARED = ("device", "precision", "compile", "skip_bad_frames")


def _kind(hint):
    """The argparse type of a field's type hint (``int | None`` -> int)."""
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        hint = next(a for a in typing.get_args(hint) if a is not type(None))
    return hint


def add_field(p: argparse.ArgumentParser, cls, name: str, *, help: str | None = None, **kw) -> None:
    """The option ``--name`` of dataclass field ``name`` of ``cls``: a flag for a bool, else typed, with the
    field's default, ``choices`` and ``help`` (``help`` replaces the field's where a command means more)."""
    f = next(f for f in fields(cls) if f.name == name)
    hint = _kind(typing.get_type_hints(cls)[name])
    text = help if help is not None else f.metadata.get("help", "")
    flag = "--" + name.replace("_", "-")
    if hint is bool:
        p.add_argument(flag, action="store_true", help=text, **kw)
        return
    default = f.default if f.default is not MISSING else None
    p.add_argument(flag, type=hint if hint in (int, float, str) else str, default=default, help=text,
                   choices=f.metadata.get("choices"), **kw)


def add_config_options(p: argparse.ArgumentParser, cls=TrainConfig, *, skip=(), **helps: str) -> None:
    """Every field of ``cls`` (but ``skip`` and :data:`HIDDEN`) as an option (``helps``: a field's help as
    this command words it)."""
    for f in fields(cls):
        if f.name not in HIDDEN and f.name not in skip:
            add_field(p, cls, f.name, help=helps.get(f.name), **({"required": True} if f.name == "model" else {}))


def add_shared(p: argparse.ArgumentParser, names=SHARED, **helps: str) -> None:
    """The options a command that runs a model shares with ``train`` (``helps``: a command's own wording)."""
    for name in names:
        add_field(p, TrainConfig, name, help=helps.get(name))


def _opt(default, text: str):
    return field(default=default, metadata={"help": text})


@dataclass(frozen=True)
class EvalOptions:
    """The options of the commands that evaluate models on a store (``evaluate``, ``report``,
    ``hard-cases``, ``bench``, ``denoise``, ``scaling``), defined once; each command takes those it needs
    (:func:`add_eval`), in its own words where it means more."""
    store: str | None = _opt(None, "a Zarr store made by `python -m pipeline dataset`, or a folder of Noisebase "
                                   "sequences")
    split: str = _opt("test", "train, val or test (default test: held-out scenes)")
    spp: int | None = _opt(None, "input samples per pixel; a count the store does not hold is refused")
    frames: int = _opt(0, "at most this many frames (0: all)")
    no_flip: bool = _opt(False, "skip FLIP (the slowest metric)")
    no_oidn: bool = _opt(False, "leave OIDN out")
    out: str | None = _opt(None, "where the command writes")
    no_progress: bool = _opt(False, "no progress bars")


def add_eval(p: argparse.ArgumentParser, names, *, required=(), **helps: str) -> None:
    """The :class:`EvalOptions` fields ``names`` as options (``required``: those a command cannot do
    without; ``helps``: a field's help as this command words it)."""
    for name in names:
        add_field(p, EvalOptions, name, help=helps.get(name), **({"required": True} if name in required else {}))


def config_from(a: argparse.Namespace, model_cfg: dict) -> TrainConfig:
    """The :class:`TrainConfig` of ``train``'s parsed options (``model_cfg``: ``--model-cfg`` decoded)."""
    given = {f.name: getattr(a, f.name) for f in fields(TrainConfig) if hasattr(a, f.name)}
    return TrainConfig(**{**given, "model_cfg": model_cfg})
