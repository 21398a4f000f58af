"""Random 1D profiles and 2D outlines for revolved and extruded meshes (numpy only).

Every function takes a ``np.random.Generator`` and is a pure function of its state.
"""
from __future__ import annotations

import numpy as np

REVOLVE_STYLES = ("vase", "bottle", "goblet", "stack", "bowl")
OUTLINE_STYLES = ("smooth", "star", "gear", "polygon")


def _smooth_curve(y_knots: np.ndarray, r_knots: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Monotone cubic (PCHIP) interpolation of knots -> n samples (no overshoot below zero)."""
    from scipy.interpolate import PchipInterpolator
    y = np.linspace(y_knots[0], y_knots[-1], n)
    return y, PchipInterpolator(y_knots, r_knots)(y)


def random_revolve_profile(rng: np.random.Generator, *, samples: int = 24) -> np.ndarray:
    """A closed profile for a surface of revolution: (float64, K×2) rows ``[r, y]``.

    Starts and ends on the axis (``r == 0``) with a flat base at ``y = -1`` and a top at
    ``y = 1``, radii in (0, 1]; styles: vase, bottle, goblet, stack, bowl.
    """
    style = REVOLVE_STYLES[int(rng.integers(len(REVOLVE_STYLES)))]
    if style == "vase":
        k = int(rng.integers(4, 7))
        yk = np.linspace(-1, 1, k)
        rk = rng.uniform(0.35, 1.0, k)
        y, r = _smooth_curve(yk, rk, samples)
    elif style == "bottle":
        body, neck = rng.uniform(0.7, 1.0), rng.uniform(0.15, 0.35)
        y_sh = rng.uniform(-0.1, 0.4)
        yk = np.array([-1.0, y_sh - 0.3, y_sh, y_sh + 0.35, 1.0])
        rk = np.array([body * 0.95, body, body * 0.9, neck, neck * rng.uniform(1.0, 1.3)])
        y, r = _smooth_curve(yk, rk, samples)
    elif style == "goblet":
        foot, stem, cup = rng.uniform(0.5, 0.8), rng.uniform(0.06, 0.15), rng.uniform(0.6, 1.0)
        y_cup = rng.uniform(-0.2, 0.3)
        yk = np.array([-1.0, -0.92, -0.8, y_cup - 0.15, y_cup, 0.5 * (y_cup + 1), 1.0])
        rk = np.array([foot, foot * 0.6, stem, stem, cup * 0.6, cup * 0.95, cup])
        y, r = _smooth_curve(yk, rk, samples)
    elif style == "stack":
        k = int(rng.integers(2, 5))
        edges = np.sort(np.concatenate([[-1.0, 1.0], rng.uniform(-0.9, 0.9, k - 1)]))
        radii = rng.uniform(0.3, 1.0, k)
        y = np.repeat(edges, 2)[1:-1]
        r = np.repeat(radii, 2)
    else:  # bowl: a rounded shell from a narrow foot to a wide rim
        rim, foot = rng.uniform(0.8, 1.0), rng.uniform(0.2, 0.45)
        t = np.linspace(0, 1, samples)
        y = -1 + 2 * t
        r = foot + (rim - foot) * np.sin(0.5 * np.pi * t) ** rng.uniform(0.5, 1.5)
    r = np.clip(r, 0.03, 1.0)
    prof = np.concatenate([[[0.0, y[0]]], np.stack([r, y], axis=1), [[0.0, y[-1]]]])
    return prof


def random_outline(rng: np.random.Generator, *, samples: int = 64) -> np.ndarray:
    """A simple closed polygon, star-shaped around the origin, counter-clockwise in (x, z):
    (float64, K×2) rows ``[x, z]`` at strictly increasing angles, radii in [0.25, 1]."""
    style = OUTLINE_STYLES[int(rng.integers(len(OUTLINE_STYLES)))]
    if style == "smooth":
        theta = np.linspace(0, 2 * np.pi, samples, endpoint=False)
        r = np.ones_like(theta)
        for freq in range(1, 5):
            r += rng.normal(0, 0.25 / freq) * np.cos(freq * theta + rng.uniform(0, 2 * np.pi))
    elif style == "star":
        k = int(rng.integers(4, 9))
        theta = np.linspace(0, 2 * np.pi, 2 * k, endpoint=False)
        r = np.where(np.arange(2 * k) % 2 == 0, 1.0, rng.uniform(0.35, 0.7))
    elif style == "gear":
        k = int(rng.integers(6, 16))
        base = np.linspace(0, 2 * np.pi, k, endpoint=False)
        w = np.pi / k
        theta = (base[:, None] + np.array([0.0, 0.45 * w, 1.0 * w, 1.45 * w])[None, :]).ravel()
        r = np.tile([1.0, 1.0, 0.8, 0.8], k)
    else:  # polygon: a jittered regular n-gon
        k = int(rng.integers(3, 9))
        theta = np.linspace(0, 2 * np.pi, k, endpoint=False) + rng.uniform(-0.15, 0.15, k) * np.pi / k
        r = rng.uniform(0.8, 1.0, k)
    r = np.clip(r / np.max(r), 0.25, 1.0)
    theta = theta + rng.uniform(0, 2 * np.pi)
    return np.stack([r * np.cos(theta), r * np.sin(theta)], axis=1)
