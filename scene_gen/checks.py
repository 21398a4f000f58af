"""Checking settings: the one mechanism behind every config of the project.

Every config (``scene_gen.config.SceneGenConfig``, ``pipeline.render.RenderConfig``,
``pipeline.config.DatasetConfig`` and its sections, ``training.config.TrainConfig``) is a frozen
dataclass that checks itself at construction with these functions and raises its package's
``ConfigError`` with a one-line message naming the setting, its allowed values and what it got::

    need(is_int(v) and 1 <= v <= 4096, "render.spp", "an integer in [1, 4096]", v, ConfigError)
    -> ConfigError: render.spp must be an integer in [1, 4096], got 0

It lives in ``scene_gen``, the package every other one depends on (scene_gen -> stores -> pipeline,
training), and imports nothing but the standard library.

Why not pydantic (2.14, installed): measured here (2 cores, 5 runs each), importing it with
``BaseModel`` took 56-95 ms and building the first model class another 42-59 ms (pydantic-core
compiles its schema), against 9-13 ms for the whole of ``scene_gen.config``, which every Dask worker
and command imports; its messages ("1 validation error for ... Input should be greater than or
equal to 1", over several lines) would need a custom validator per field to keep ours; and the GPU
check machine has no pydantic (``scripts/device_check.py`` would have to carry it).
"""
from __future__ import annotations

import math
import numbers
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
