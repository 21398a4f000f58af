"""Checking settings: the one mechanism behind every config of the project.

Every config (``scene_gen.config.SceneGenConfig``, ``pipeline.render.RenderConfig``,
``pipeline.config.DatasetConfig`` and its sections, ``training.config.TrainConfig``) is a frozen
dataclass that checks itself at construction with these functions and raises its package's
``ConfigError`` with a one-line message naming the setting, its allowed values and what it got::

    need(is_int(v) and 1 <= v <= 4096, "render.spp", "an integer in [1, 4096]", v, ConfigError)
    -> ConfigError: render.spp must be an integer in [1, 4096], got 0

A model's settings (``--model-cfg``) are checked by the same functions, from the types its constructor
declares (:func:`check_signature`). It lives in ``core``, the package every other one stands on, and
imports nothing but the standard library.

Why not pydantic (2.14, installed): measured here (2 cores, 5 runs each), importing it with
``BaseModel`` took 56-95 ms and building the first model class another 42-59 ms (pydantic-core
compiles its schema), against 9-13 ms for the whole of ``scene_gen.config``, which every Dask worker
and command imports; its messages ("1 validation error for ... Input should be greater than or
equal to 1", over several lines) would need a custom validator per field to keep ours; and the GPU
check machine has no pydantic (``scripts/device_check.py`` would have to carry it).
"""
from __future__ import annotations

import inspect
import math
import numbers
import types
import typing
from dataclasses import fields, is_dataclass
from typing import Any, Iterable


def is_int(v: Any, *, numpy: bool = False) -> bool:
    """Whether ``v`` is an integer and not a bool (``True`` is an ``int`` in Python); ``numpy``:
    numpy integers count too (settings that are converted to ``int`` before they are stored)."""
    if isinstance(v, bool):
        return False
    return isinstance(v, numbers.Integral) if numpy else isinstance(v, int)


def is_number(v: Any, *, finite: bool = False) -> bool:
    """Whether ``v`` is an int or a float and not a bool; ``finite``: and neither NaN nor +-Inf."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return False
    return not finite or math.isfinite(v)


def need(ok: bool, name: str, allowed: str, value: Any, error: type[Exception]) -> None:
    """Raise ``error("<name> must be <allowed>, got <value!r>")`` unless ``ok``."""
    if not ok:
        raise error(f"{name} must be {allowed}, got {value!r}")


def need_int(name: str, value: Any, lo: int, hi: int | None, error: type[Exception], *,
             numpy: bool = False) -> None:
    """``value`` must be an integer in ``[lo, hi]`` (``hi`` None: ``>= lo``); :func:`need`'s message."""
    ok = is_int(value, numpy=numpy) and lo <= value and (hi is None or value <= hi)
    need(ok, name, f"an integer in [{lo}, {hi}]" if hi is not None else f"an integer >= {lo}", value, error)


def known_keys(d: Any, names: Iterable[str] | type, where: str, error: type[Exception], *,
               noun: str = "key(s)") -> dict:
    """``d`` as a new dict once it is a mapping whose keys are all in ``names`` (an iterable, or a
    dataclass whose field names they are); None gives ``{}``. Raises ``error`` with
    ``"<where> must be a mapping, got <type>"`` or ``"<where>: unknown <noun> [...]; known: [...]"``."""
    if d is None:
        return {}
    if not isinstance(d, dict):
        raise error(f"{where} must be a mapping, got {type(d).__name__}")
    allowed = {f.name for f in fields(names)} if is_dataclass(names) else set(names)
    unknown = sorted(set(map(str, d)) - allowed)
    if unknown:
        raise error(f"{where}: unknown {noun} {unknown}; known: {sorted(allowed)}")
    return dict(d)


# ------------------------------------------------------------------------------------------------
# settings of a class, checked against its constructor's signature


def _declared_settings(cls) -> dict[str, tuple[object, object]]:
    """Every named setting of ``cls`` and the classes it passes ``**config`` on to: name -> (type hint
    or None, default), from the ``__init__`` signatures of its MRO (the most derived one wins)."""
    out: dict[str, tuple[object, object]] = {}
    for klass in cls.__mro__:
        init = klass.__dict__.get("__init__")
        if init is None or klass.__module__.startswith("torch") or klass is object:
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


def check_signature(cls: type, cfg: dict, where: str, error: type[Exception]) -> None:
    """Settings ``cfg`` for ``cls(**cfg)`` checked against the types its constructors declare (type hints,
    else the defaults' types, over its MRO): ``{"layers": 2.5}`` or ``true`` for an integer, NaN for a
    number raise ``error('<where> "<key>" must be <type>, got <value>')``. Keys no signature names (taken
    through ``**config`` alone) are left to the class."""
    declared = _declared_settings(cls)
    for key, value in cfg.items():
        if key not in declared:
            continue
        hint, default = declared[key]
        kinds = _kinds(hint, default)
        want = " or ".join(_describe(k, default) for k in kinds)
        need(_fits(value, kinds, default), f'{where} "{key}"', want, value, error)
