"""Denoiser registry: one file per model in ``training/models``, each registering its class by name.

    @register("layer")
    class LayerDenoiser(Denoiser): ...

    model = build("layer", layers=2)       # keyword settings override the paper's defaults

Every module in this package (except ``registry`` and ``common``) is imported on first lookup, so a
new model only needs its own file.
"""
from __future__ import annotations

import importlib
import pkgutil

from core.checks import check_signature

from ..errors import ConfigError, UnknownModelError

MODELS: dict[str, type] = {}
_DISCOVERED = False


def register(name: str):
    """Class decorator: register a :class:`training.models.common.Denoiser` subclass under ``name``."""
    def deco(cls):
        if name in MODELS and MODELS[name] is not cls:
            raise ConfigError(f"model {name!r} is already registered by {MODELS[name].__module__}")
        MODELS[name] = cls
        cls.name = name
        return cls
    return deco


def _discover() -> None:
    global _DISCOVERED
    if _DISCOVERED:
        return
    pkg = importlib.import_module(__package__)
    for info in pkgutil.iter_modules(pkg.__path__):
        if info.name not in ("registry", "common") and not info.name.startswith("_"):
            importlib.import_module(f"{__package__}.{info.name}")
    _DISCOVERED = True


def names() -> list[str]:
    """Names of all registered models, sorted."""
    _discover()
    return sorted(MODELS)


def get(name: str) -> type:
    _discover()
    try:
        return MODELS[name]
    except KeyError:
        raise UnknownModelError(f"unknown model {name!r}; registered: {sorted(MODELS)}") from None


def check_settings(name: str, cfg: dict) -> None:
    """Refuse (ConfigError naming the setting, the value and the type it needs) settings of model
    ``name`` whose JSON type does not fit the model's declaration: ``{"layers": 2.5}`` or ``true`` for
    an integer, NaN for a number (:func:`core.checks.check_signature`). Settings the model takes through
    ``**config`` alone are left to it."""
    check_signature(get(name), cfg, f"model {name!r}: setting", ConfigError)


def build(name: str, **cfg):
    """Instantiate model ``name`` with settings ``cfg`` (unknown keys and values of the wrong type
    raise ConfigError, :func:`check_settings`)."""
    cls = get(name)
    cfg = dict(cfg)
    features = cfg.pop("features", None)        # every model's setting (Denoiser.use_features)
    outliers = cfg.pop("outliers", None)        # every model's setting (Denoiser.use_outliers)
    check_settings(name, cfg)
    try:
        model = cls(**cfg)
    except TypeError as e:
        raise ConfigError(f"bad settings for model {name!r}: {e}") from None
    if outliers is not None:
        model.use_outliers(outliers)
    return model if features is None else model.use_features(features)
