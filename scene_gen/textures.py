"""Procedural textures (numpy only): two colours mixed by a pattern, tileable in UV.

``make_texture(spec, size)`` returns float32 (H, W, 3) linear reflectance in [0, 1]; the UV scale is
applied by the renderer (``to_uv``), so the bitmap itself tiles seamlessly over [0, 1]^2.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

from scene_gen.spec import TextureSpec


def _value_noise(rng: np.random.Generator, size: int, cells: int) -> np.ndarray:
    """Tileable smooth value noise in [0, 1], (size, size)."""
    grid = rng.random((cells, cells))
    t = np.arange(size) * cells / size
    i0 = np.floor(t).astype(int) % cells
    i1 = (i0 + 1) % cells
    f = t - np.floor(t)
    f = f * f * (3 - 2 * f)
    a = grid[i0][:, i0] * (1 - f)[None, :] + grid[i0][:, i1] * f[None, :]
    b = grid[i1][:, i0] * (1 - f)[None, :] + grid[i1][:, i1] * f[None, :]
    return a * (1 - f)[:, None] + b * f[:, None]


def fbm(rng: np.random.Generator, size: int, octaves: int = 5) -> np.ndarray:
    out = np.zeros((size, size))
    amp, total = 1.0, 0.0
    for o in range(octaves):
        out += amp * _value_noise(rng, size, 4 * 2 ** o)
        total += amp
        amp *= 0.5
    return out / total


def _pattern(spec: TextureSpec, size: int) -> np.ndarray:
    rng = np.random.default_rng(np.random.SeedSequence([spec.seed, 0x7E47]))
    y, x = np.mgrid[0:size, 0:size] / size
    if spec.kind == "checker":
        n = int(rng.integers(2, 9))
        return ((np.floor(x * n) + np.floor(y * n)) % 2).astype(np.float64)
    if spec.kind == "stripes":
        n = int(rng.integers(2, 12))
        angle = int(rng.integers(0, 4))            # 0: vertical, 1: horizontal, 2/3: diagonals (tileable)
        u = [x, y, (x + y), (x - y)][angle]
        duty = rng.uniform(0.2, 0.8)
        return ((u * n) % 1.0 < duty).astype(np.float64)
    if spec.kind == "noise":
        v = fbm(rng, size)
        lo, hi = np.percentile(v, [2, 98])
        return np.clip((v - lo) / max(hi - lo, 1e-6), 0, 1)
    if spec.kind == "cells":
        # Worley (cellular) noise on a torus: distance to the nearest of n random points.
        n = int(rng.integers(6, 40))
        pts = rng.random((n, 2))
        d = np.full((size, size), np.inf)
        for px, py in pts:
            dx = np.abs(x - px); dx = np.minimum(dx, 1 - dx)
            dy = np.abs(y - py); dy = np.minimum(dy, 1 - dy)
            d = np.minimum(d, np.sqrt(dx * dx + dy * dy))
        d = d / d.max()
        return np.clip(d * rng.uniform(1.0, 2.0), 0, 1)
    raise ValueError(f"unknown texture kind {spec.kind!r}")  # spec validation makes this unreachable


@lru_cache(maxsize=256)
def make_texture(spec: TextureSpec, size: int = 256) -> np.ndarray:
    """The texture of ``spec`` as float32 (H, W, 3) linear RGB in [0, 1]. Deterministic."""
    t = _pattern(spec, size)[..., None]
    c0 = np.asarray(spec.color0)[None, None]
    c1 = np.asarray(spec.color1)[None, None]
    out = (1 - t) * c0 + t * c1
    out.setflags(write=False)
    return out.astype(np.float32)
