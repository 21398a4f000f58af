"""Strict JSON for every file the training commands write (evaluations, reports, hard cases, benches).

``json.dumps`` writes ``NaN`` and ``Infinity`` for non-finite floats, which is not JSON: other tools'
parsers (JavaScript's ``JSON.parse``, ``jq``, Go, Rust) refuse the whole file. Here a non-finite
number is ``null`` (a perfect PSNR is ``inf`` in Python and ``null`` in the file; the tables in the
Markdown next to it say ``inf``), numpy scalars become numbers, and anything else its ``str``.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np


def plain(v):
    """``v`` with non-finite floats as None, numpy scalars and arrays as Python numbers and lists."""
    if isinstance(v, dict):
        return {str(k): plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [plain(x) for x in v]
    if isinstance(v, np.ndarray):
        return plain(v.tolist())
    if isinstance(v, (np.floating, float)) and not isinstance(v, bool):
        f = float(v)
        return f if math.isfinite(f) else None
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, np.bool_):
        return bool(v)
    if v is None or isinstance(v, (str, int, bool)):
        return v
    return str(v)


def dumps(obj, **kw) -> str:
    """Strict JSON text of ``obj`` (:func:`plain`); never ``NaN`` or ``Infinity``."""
    return json.dumps(plain(obj), allow_nan=False, **kw)


def write(path, obj) -> None:
    """``obj`` as indented strict JSON at ``path`` (its folder made), through a temporary file and a
    rename, so a reader never sees half a file."""
    from core.files import write_atomically
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = dumps(obj, indent=2)
    write_atomically(path, lambda f: f.write(text))
