"""What scene families share: objects being placed, the layout a family returns, random shapes and
light/probe draws (numpy only).

A family (``scene_gen.families``, one file each) is a function
``layout(rng, r_cam, cfg, fov, res, user_models) -> Layout`` that places objects with these pieces;
``scene_gen.sampling.sample_scene`` turns its Layout into a SceneSpec (camera path, motion, culling,
defocus, triangle budgets).
"""
from __future__ import annotations

import colorsys
import math
from dataclasses import dataclass

import numpy as np

from scene_gen import meshes
from scene_gen.errors import ConfigError
from scene_gen.spec import MaterialSpec, MeshSpec, Transform


# Procedural shape kinds for random objects and their relative frequency.
SHAPE_WEIGHTS = {"sphere": 1.0, "box": 1.2, "cylinder": 1.0, "capsule": 0.7, "cone": 0.7, "torus": 0.7,
                 "revolve": 1.5, "extrude": 1.2, "blob": 1.2, "boolean": 1.0}


def _f(x) -> float:
    return round(float(x), 6)


@dataclass
class Placed:
    """An object being placed (mutable while the scene is assembled; becomes an ObjectSpec).

    ``radius``: bounding-sphere radius in world units; ``keep``: never culled (room, backdrop, lights);
    ``movable``: may get a velocity; ``planar``: moves horizontally (rests on a support)."""
    name: str
    mesh: MeshSpec
    material: MaterialSpec
    transform: Transform
    radius: float
    keep: bool = False
    movable: bool = True
    planar: bool = True
    emitter: tuple | None = None
    budget: bool = True
    velocity: tuple | None = None


# ---------------------------------------------------------------------------------------------
# shapes

def _half_norm(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Canonical half extents after meshes' normalisation (bbox centred, largest half-extent 1)."""
    half = (np.asarray(hi) - np.asarray(lo)) / 2
    return half / half.max()


def _primitive(rng: np.random.Generator, kind: str) -> tuple[dict, np.ndarray, np.ndarray]:
    """params and the (lo, hi) bounding box before normalisation, y up."""
    u = rng.uniform
    if kind == "sphere":
        return {"subdivisions": 3}, -np.ones(3), np.ones(3)
    if kind == "box":
        e = np.array([u(0.3, 1.0), u(0.3, 1.0), u(0.3, 1.0)])
        return {"extents": [_f(x) for x in e]}, -e / 2, e / 2
    if kind in ("cylinder", "cone"):
        r, h = u(0.2, 1.0), u(0.3, 2.0)
        return {"radius": _f(r), "height": _f(h), "sections": 32}, np.array([-r, -h / 2, -r]), np.array([r, h / 2, r])
    if kind == "capsule":
        r, h = u(0.2, 0.6), u(0.0, 1.5)
        y = h / 2 + r
        return {"radius": _f(r), "height": _f(h), "sections": 24}, np.array([-r, -y, -r]), np.array([r, y, r])
    if kind == "torus":
        R, r = 1.0, u(0.15, 0.45)
        return {"major_radius": R, "minor_radius": _f(r)}, np.array([-R - r, -r, -R - r]), np.array([R + r, r, R + r])
    if kind == "revolve":   # a vase/bottle/lamp-like profile
        n = int(rng.integers(5, 9))
        y = np.sort(np.concatenate([[0.0, 1.0], u(0.05, 0.95, n - 2)])) * u(0.8, 2.5)
        r = np.clip(np.cumsum(rng.normal(0, 0.18, n)) + u(0.3, 0.7), 0.08, 1.0)
        prof = [[_f(a), _f(b)] for a, b in zip(r, y)]
        rm = float(r.max())
        return {"profile": prof, "sections": 48}, np.array([-rm, y.min(), -rm]), np.array([rm, y.max(), rm])
    if kind == "extrude":   # a star-shaped outline
        n = int(rng.integers(5, 12))
        gaps = u(0.4, 1.0, n) if rng.uniform() < 0.5 else np.ones(n)   # monotone angles: a simple polygon
        ang = np.cumsum(gaps) / gaps.sum() * 2 * np.pi
        rad = u(0.4, 1.0, n) if rng.uniform() < 0.6 else np.where(np.arange(n) % 2 == 0, 1.0, u(0.35, 0.6))
        xz = np.stack([rad * np.cos(ang), rad * np.sin(ang)], 1)
        h = u(0.15, 1.5)
        params = {"outline": [[_f(a), _f(b)] for a, b in xz], "height": _f(h),
                  "bevel": _f(u(0.05, 0.3)) if rng.uniform() < 0.5 else 0.0}
        xz = np.asarray(params["outline"])
        return params, np.array([xz[:, 0].min(), -h / 2, xz[:, 1].min()]), np.array([xz[:, 0].max(), h / 2, xz[:, 1].max()])
    if kind == "blob":   # a displaced sphere: bounds unknown without building; assume most of the cube
        params = {"bumps": int(rng.integers(3, 10)), "amplitude": _f(u(0.15, 0.45))}
        return params, -0.9 * np.ones(3), 0.9 * np.ones(3)
    raise ConfigError(f"unknown shape kind {kind!r}")


def random_shape(rng: np.random.Generator, user_models: list[str] | None = None,
                 p_user_model: float = 0.0) -> tuple[MeshSpec, np.ndarray]:
    """A random mesh spec and its canonical half extents (float64, 3; after normalisation, y up)."""
    seed = int(rng.integers(0, 2**31 - 1))
    if user_models and rng.uniform() < p_user_model:
        spec = MeshSpec("file", {"path": user_models[int(rng.integers(len(user_models)))]}, seed=seed)
        b = meshes.build(spec).bounds.astype(np.float64)   # user models only: cached per process
        return spec, np.maximum(_half_norm(b[0], b[1]), 0.02)
    kinds = list(SHAPE_WEIGHTS)
    w = np.array([SHAPE_WEIGHTS[k] for k in kinds])
    kind = kinds[int(rng.choice(len(kinds), p=w / w.sum()))]
    if kind != "boolean":
        params, lo, hi = _primitive(rng, kind)
        return MeshSpec(kind, params, seed=seed), np.maximum(_half_norm(lo, hi), 0.02)
    op = ("union", "difference", "intersection")[int(rng.choice(3, p=[0.3, 0.5, 0.2]))]
    ka, kb = (("sphere", "box", "cylinder")[int(i)] for i in rng.integers(0, 3, 2))
    pa, la, ha = _primitive(rng, ka)
    pb, lb, hb = _primitive(rng, kb)
    la, ha = -_half_norm(la, ha), _half_norm(la, ha)          # children are canonical meshes
    lb, hb = -_half_norm(lb, hb), _half_norm(lb, hb)
    scale = rng.uniform(0.9, 1.3) if op == "intersection" else rng.uniform(0.4, 0.9)
    d = rng.normal(size=3)
    off = d / np.linalg.norm(d) * (rng.uniform(0.4, 0.8) if op == "intersection" else rng.uniform(0.2, 0.8))
    lb, hb = lb * scale + off, hb * scale + off
    if op == "union":
        lo, hi = np.minimum(la, lb), np.maximum(ha, hb)
    elif op == "difference":
        lo, hi = la, ha
    else:
        lo, hi = np.maximum(la, lb), np.minimum(ha, hb)
        if (hi <= lo).any():
            lo, hi = la, ha
    params = {"op": op, "b_scale": _f(scale), "b_offset": [_f(x) for x in off]}
    children = (MeshSpec(ka, pa, seed=seed + 1), MeshSpec(kb, pb, seed=seed + 2))
    return MeshSpec("boolean", params, seed=seed, children=children), np.maximum(_half_norm(lo, hi), 0.02)


def upright(rng: np.random.Generator, half: np.ndarray, size: float, *, p_lying: float = 0.25):
    """Scale (3), rotation (XYZ Euler degrees) and resting height of a shape of largest half-extent ``size``.

    Upright shapes turn about y only; lying ones are first turned 90° about x, so their canonical z
    extent becomes the height. Returns (scale, rotate, rest_y, bounding radius)."""
    aspect = np.exp(rng.uniform(-0.25, 0.25, 3))
    scale = size * aspect / aspect.max()
    yaw = rng.uniform(0, 360)
    if rng.uniform() < p_lying:
        rot, vertical = (90.0, yaw, 0.0), scale[2] * half[2]
    else:
        rot, vertical = (0.0, yaw, 0.0), scale[1] * half[1]
    radius = float(np.linalg.norm(scale * half))
    return tuple(_f(s) for s in scale), tuple(_f(a) for a in rot), float(vertical), radius



@dataclass
class Layout:
    """What a scene family returns: placed objects, lights, the first camera and how the camera may move."""
    objects: list
    lights: list
    origin: np.ndarray
    target: np.ndarray
    camera_step: float            # camera path speed, world units per frame
    clamp: object = None          # maps a point back into the allowed region (rooms)


def light_color(rng: np.random.Generator) -> np.ndarray:
    """A light tint: warm to cool white (normalised to max 1), sometimes a saturated colour."""
    if rng.uniform() < 0.85:
        t = rng.uniform(0, 1)
        c = np.array([1.0, 0.85 + 0.15 * t, 0.65 + 0.35 * t]) if rng.uniform() < 0.7 else np.array([0.85 + 0.15 * t, 0.93, 1.0])
    else:
        c = np.array(colorsys.hsv_to_rgb(rng.uniform(), rng.uniform(0.3, 0.7), 1.0))
    return c / c.max()


def probe_params(rng: np.random.Generator, *, sky: float, sun_irradiance: float) -> dict:
    """Parameters of a procedural HDR probe (``scene_gen.probes.make_probe``).

    ``sky`` scales the sky radiance; the sun disc's radiance is set so that it delivers
    ``sun_irradiance`` at normal incidence whatever its random size (radius in degrees)."""
    zen = np.array([0.25, 0.45, 0.9]) * np.exp(rng.normal(0, 0.15, 3))
    hor = np.array([0.85, 0.9, 1.0]) * np.exp(rng.normal(0, 0.08, 3))
    gnd = np.array([0.25, 0.22, 0.2]) * np.exp(rng.normal(0, 0.25, 3))
    size = rng.uniform(0.8, 2.0)
    solid_angle = 2 * math.pi * (1 - math.cos(math.radians(size)))
    return {"seed": int(rng.integers(0, 2**31 - 1)), "sun_elevation": _f(rng.uniform(8, 70)),
            "sun_azimuth": _f(rng.uniform(0, 360)), "sun_radiance": _f(sun_irradiance / solid_angle),
            "sun_size": _f(size), "zenith": [_f(x) for x in np.clip(zen, 0, 1)],
            "horizon": [_f(x) for x in np.clip(hor, 0, 1)], "ground": [_f(x) for x in np.clip(gnd, 0, 1)],
            "sky_radiance": _f(sky), "clouds": _f(rng.uniform(0, 0.7))}
