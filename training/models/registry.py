"""Denoiser registry: one file per model in ``training/models``, each registering its class by name.

    @register("layer")
    class LayerDenoiser(Denoiser): ...

    model = build("layer", layers=2)       # keyword settings override the paper's defaults

Every module in this package (except ``registry`` and ``common``) is imported on first lookup, so a
new model only needs its own file.
"""
from __future__ import annotations

import importlib
import inspect
import math
import pkgutil
import typing

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


def _declared_settings(cls) -> dict[str, tuple[object, object]]:
    """Every named setting of ``cls`` and the classes it passes ``**config`` on to: name -> (type hint
    or None, default), from the ``__init__`` signatures of its MRO (the most derived one wins)."""
    out: dict[str, tuple[object, object]] = {}
    for klass in cls.__mro__:
        init = klass.__dict__.get("__init__")
        if init is None or klass.__module__.startswith("torch"):
            continue
        try:
            hints = typing.get_type_hints(init)
        except Exception:  # noqa: BLE001 - an unresolvable hint: fall back to the default's type
            hints = {}
        for p in list(inspect.signature(init).parameters.values())[1:]:
            if p.kind in (p.VAR_KEYWORD, p.VAR_POSITIONAL) or p.name in out:
                continue
            out[p.name] = (hints.get(p.name), p.default)
    return out


def _kinds(hint, default) -> list:
    """The types a setting takes: its hint's (a ``Union`` split up, ``None`` kept), else its default's."""
    import types
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        return list(typing.get_args(hint))
    if hint is not None:
        return [hint]
    if default is inspect.Parameter.empty:
        return []
    return [type(default)]


def _describe(kind, default) -> str:
    """``an integer``, ``a list of integers``, ``a list of lists of integers``, ... for error messages."""
    if kind in (tuple, list):
        if isinstance(default, (tuple, list)) and default:
            inner = _describe(type(default[0]), default[0])
            return "a list of " + ("lists" + inner[len("a list"):] if inner.startswith("a list") else
                                   {"an integer": "integers", "a number": "numbers", "a string": "strings",
                                    "true or false": "booleans"}.get(inner, inner))
        return "a list"
    return {int: "an integer", float: "a finite number", bool: "true or false", str: "a string",
            type(None): "null"}.get(kind, getattr(kind, "__name__", str(kind)))


def _fits(value, kinds, default) -> bool:
    """Whether ``value`` is of one of ``kinds`` (integers refuse 2.5 and booleans, numbers refuse
    booleans and NaN/Inf; a list is checked element by element against its default's first element)."""
    for k in kinds:
        if k in (None, type(None)) and value is None:
            return True
        if k is bool and isinstance(value, bool):
            return True
        if k is int and isinstance(value, int) and not isinstance(value, bool):
            return True
        if k is float and isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
            return True
        if k is str and isinstance(value, str):
            return True
        if k in (tuple, list) and isinstance(value, (tuple, list)):
            if not (isinstance(default, (tuple, list)) and default):
                return True
            return all(_fits(v, [type(default[0])], default[0]) for v in value)
    return not kinds or (value is None and default is None)


def check_settings(name: str, cfg: dict) -> None:
    """Refuse (ConfigError naming the setting, the value and the type it needs) settings of model
    ``name`` whose JSON type does not fit the model's declaration: ``{"layers": 2.5}`` or ``true`` for
    an integer, NaN for a number. Settings the model takes through ``**config`` alone are left to it."""
    declared = _declared_settings(get(name))
    for key, value in cfg.items():
        if key not in declared:
            continue
        hint, default = declared[key]
        kinds = _kinds(hint, default)
        if not _fits(value, kinds, default):
            want = " or ".join(_describe(k, default) for k in kinds)
            raise ConfigError(f'model {name!r}: setting "{key}" must be {want}, got {value!r}')


def build(name: str, **cfg):
    """Instantiate model ``name`` with settings ``cfg`` (unknown keys and values of the wrong type
    raise ConfigError, :func:`check_settings`)."""
    cls = get(name)
    cfg = dict(cfg)
    features = cfg.pop("features", None)        # every model's setting (Denoiser.use_features)
    check_settings(name, cfg)
    try:
        model = cls(**cfg)
    except TypeError as e:
        raise ConfigError(f"bad settings for model {name!r}: {e}") from None
    return model if features is None else model.use_features(features)
