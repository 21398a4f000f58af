"""Procedural textures (numpy only): two colours mixed by a pattern, tileable in UV. The patterns: checker,
stripes, value noise, Worley cells, and ``natural`` (1/f noise, :func:`natural`).

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


def natural(rng: np.random.Generator, size: int) -> np.ndarray:
    """A pattern with the statistics of photographed surfaces, in [0, 1], (size, size), tileable: white noise
    shaped in frequency to a power spectrum 1/f^a, a in [1.6, 2.6] (natural images: about 2; value noise
    (``fbm``) falls off faster and has its octaves' grid), stretched along one axis by 1-6x (grain, fibres),
    through a random contrast curve. numpy's FFT: the torus it works on is what makes the bitmap tile."""
    a = rng.uniform(1.6, 2.6)
    stretch = np.exp(rng.uniform(0.0, np.log(6.0)))
    along_x = rng.uniform() < 0.5
    fy = np.fft.fftfreq(size)[:, None] * (stretch if along_x else 1.0)
    fx = np.fft.fftfreq(size)[None, :] * (1.0 if along_x else stretch)
    f = np.hypot(fx, fy)
    f[0, 0] = np.inf                                    # no mean term: the pattern is normalised below
    spectrum = np.fft.fft2(rng.standard_normal((size, size))) * f ** (-a / 2)
    v = np.fft.ifft2(spectrum).real
    lo, hi = np.percentile(v, [1, 99])
    v = np.clip((v - lo) / max(hi - lo, 1e-12), 0, 1)
    return v ** np.exp(rng.uniform(-0.7, 0.7))


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
    if spec.kind == "natural":
        return natural(rng, size)
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
