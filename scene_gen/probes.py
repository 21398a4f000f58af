"""Procedural HDR environment probes (numpy only), in lat-long layout as Mitsuba's ``envmap`` reads it.

A probe is a sky gradient (horizon to zenith colours), a sun disc with a glow, optional fbm clouds
and a ground colour below the horizon. ``params`` (all optional; JSON scalars/lists):
``seed``, ``sun_elevation`` / ``sun_azimuth`` (degrees), ``sun_radiance`` (peak, e.g. 1e3..1e5),
``sun_size`` (degrees), ``zenith``, ``horizon``, ``ground`` (RGB), ``sky_radiance`` (scale),
``clouds`` (coverage in [0, 1]).

Mitsuba's envmap maps image u to azimuth and v to the polar angle from +Y (the up axis): row 0 is
the zenith, the middle row the horizon.
"""
from __future__ import annotations

import json
from functools import lru_cache

import numpy as np

from scene_gen.textures import fbm

DEFAULTS = {
    "seed": 0, "sun_elevation": 35.0, "sun_azimuth": 40.0, "sun_radiance": 2.0e4, "sun_size": 1.2,
    "zenith": [0.25, 0.45, 0.9], "horizon": [0.85, 0.9, 1.0], "ground": [0.25, 0.22, 0.2],
    "sky_radiance": 1.0, "clouds": 0.3,
}


def _direction_grid(height: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    w = 2 * height
    u = (np.arange(w) + 0.5) / w
    v = (np.arange(height) + 0.5) / height
    phi = 2 * np.pi * u[None, :]
    theta = np.pi * v[:, None]
    # Mitsuba envmap: direction = (sin(theta) sin(phi), cos(theta), -sin(theta) cos(phi)) in local frame
    x = np.sin(theta) * np.sin(phi)
    y = np.cos(theta) * np.ones_like(phi)
    z = -np.sin(theta) * np.cos(phi)
    return x, y, z


def sun_direction(params: dict) -> np.ndarray:
    p = {**DEFAULTS, **params}
    el, az = np.radians(p["sun_elevation"]), np.radians(p["sun_azimuth"])
    return np.array([np.cos(el) * np.sin(az), np.sin(el), -np.cos(el) * np.cos(az)])


def make_probe(params: dict, height: int = 128) -> np.ndarray:
    """float32 (height, 2*height, 3) HDR radiance. Deterministic in ``params``."""
    return _make_probe(json.dumps(params, sort_keys=True), height).copy()


@lru_cache(maxsize=32)
def _make_probe(params_json: str, height: int) -> np.ndarray:
    p = {**DEFAULTS, **json.loads(params_json)}
    x, y, z = _direction_grid(height)
    zen, hor, gnd = (np.asarray(p[k], np.float64) for k in ("zenith", "horizon", "ground"))
    up = np.clip(y, 0, 1)[..., None]
    sky = hor * (1 - up) ** 3 + zen * (1 - (1 - up) ** 3)
    below = (y < 0)[..., None]
    ground = gnd * (0.6 + 0.4 * np.clip(-y, 0, 1))[..., None]
    img = np.where(below, ground, sky) * p["sky_radiance"]
    if p["clouds"] > 0:
        rng = np.random.default_rng(np.random.SeedSequence([int(p["seed"]), 0xC10D]))
        n = fbm(rng, 2 * height)[:height, :]
        cover = np.clip((n - (1 - p["clouds"])) * 4, 0, 1) * (y > 0.02)
        img = img * (1 - cover[..., None]) + (0.9 * p["sky_radiance"]) * cover[..., None] * np.clip(y, 0.2, 1)[..., None]
    s = sun_direction(p)
    cosang = x * s[0] + y * s[1] + z * s[2]
    ang = np.degrees(np.arccos(np.clip(cosang, -1, 1)))
    size = max(float(p["sun_size"]), 180.0 / height)  # at least about a pixel wide
    disc = (ang < size)[..., None] * float(p["sun_radiance"]) * np.array([1.0, 0.95, 0.85])
    glow = np.exp(-ang / 8.0)[..., None] * 0.02 * float(p["sun_radiance"]) ** 0.5 * np.array([1.0, 0.9, 0.7])
    img = img + disc + glow * (y > -0.05)[..., None]
    out = img.astype(np.float32)
    out.setflags(write=False)
    return out
