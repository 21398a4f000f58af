"""Outdoor scenes: ~75 meshes resting on a backdrop, lit by ``sunsky`` or a procedural HDR probe (numpy only).

The backdrop is a large ground plane (``plane`` mesh, y = 0), half the time bent up behind the
objects like a photo-studio cyclorama. The camera stands 0.8–6 m above the ground and looks at a
point 4–25 m away; objects are dropped where random rays through the image meet the ground (so they
are in view), mostly resting on it (a few float), without overlapping footprints where possible.

Each step below draws from the random streams in turn: reordering the steps, or the draws inside
one, changes every outdoor scene of every dataset (``tests/test_scene_gen_pinned.py`` holds some).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from scene_gen import cameras as cams
from scene_gen.families import Setting, register_family
from scene_gen.layout import Layout, Placed, probe_params, random_shape, upright
from scene_gen.materials import diffuse, random_material, random_texture
from scene_gen.spec import LightSpec, MeshSpec, Transform

# Radiance scales chosen so a 64-spp preview with the fixed log tone map is well exposed.
MAX_SCREEN = 0.3  # largest object radius as a share of the half-width of the view at its distance
SUN_SCALE = 2.0   # Mitsuba sunsky at scale 1: the sun lights a 0.5-albedo ground to ~0.17 (at 45°)
SKY_SCALE = 5.0   # ... the sky alone to ~0.04, and the sky itself is ~0.1 (sunsky turned y-up)
OUTDOOR_PROBE_SCALE = 1.0
OUTDOOR_SUN = 3.0  # probe sun irradiance: a 0.5-albedo ground in full sun ~0.5 (x sin elevation)

SETTINGS = {"outdoor_objects": Setting(75, "int", 0, 10000, "meshes placed on the backdrop"),
            "p_sunsky": Setting(0.5, "probability", doc="Mitsuba sunsky, else a procedural HDR probe"),
            "p_sun_in_view": Setting(0.0, "probability", doc="a sunsky's sun moved into view (scene_gen.phenomena)",
                                     newer=True)}


def _f(x) -> float:
    return round(float(x), 6)


@dataclass
class View:
    """The first camera: its position, target, horizontal forward direction, basis and the tangents
    of its half field of view."""
    origin: np.ndarray
    target: np.ndarray
    ahead: np.ndarray          # horizontal unit vector towards the target
    right: np.ndarray
    up: np.ndarray
    forward: np.ndarray
    tan_x: float
    tan_y: float


@register_family("outdoor", seed_index=1, settings=SETTINGS)
def layout_outdoor(rng: np.random.Generator, r_cam: np.random.Generator, cfg, fov: float, res: int,
                   user_models: list[str]) -> Layout:
    """Backdrop, ~``cfg.outdoor_objects`` meshes on it and a sky (a ``scene_gen.layout.Layout``)."""
    view = random_view(r_cam, fov, res)
    backdrop, curve_line = random_backdrop(rng, view)
    objects = place_objects(rng, view, curve_line, cfg, user_models)
    sky = random_sky(rng, cfg)
    return Layout(objects=[backdrop] + objects, lights=[sky], origin=view.origin, target=view.target,
                  camera_step=_f(rng.uniform(0.05, 0.3)))


def random_view(r_cam: np.random.Generator, fov: float, res: int) -> View:
    """The camera 0.8-6 m above the ground (log-uniform), looking at a point 4-25 m away."""
    height = math.exp(r_cam.uniform(math.log(0.8), math.log(6.0)))
    az = r_cam.uniform(0, 2 * math.pi)
    dist = r_cam.uniform(4.0, 25.0)
    fwd = np.array([math.sin(az), 0.0, math.cos(az)])
    origin = np.array([0.0, height, 0.0])
    target = origin + fwd * dist
    target[1] = r_cam.uniform(0.0, 1.5)
    cam0 = cams.make_camera(origin, target, fov)
    r, u, f = cams.basis(cam0)
    tx, ty = cams.tan_half(cam0, (res, res))
    return View(origin, target, fwd, r, u, f, tx, ty)


def random_backdrop(rng: np.random.Generator, view: View) -> tuple[Placed, tuple | None]:
    """Flat ground or a cyclorama whose curved half rises behind the target, and where the curve
    starts (a point and the direction it rises along; None for flat ground)."""
    bend = rng.uniform() < 0.5
    ground_tex = random_texture(rng, kind=("checker", "noise", "cells", "stripes")[int(rng.integers(4))])
    gmat = diffuse(ground_tex.color0, texture=ground_tex) if rng.uniform() < 0.7 else random_material(
        rng, kind=("roughplastic", "diffuse", "principled")[int(rng.integers(3))])
    if bend:
        behind = rng.uniform(3.0, 15.0)
        size = 60.0
        center = view.target * np.array([1, 0, 1]) + view.ahead * behind
        yaw = math.degrees(math.atan2(-view.ahead[0], -view.ahead[2]))
        params = {"resolution": 32, "bend": _f(rng.uniform(0.25, 0.6))}
        curve_line = (center, view.ahead)
    else:
        size, center, yaw = 400.0, np.zeros(3), 0.0
        params = {"resolution": 1}
        curve_line = None
    backdrop = Placed("backdrop", MeshSpec("plane", params, seed=0), gmat,
                      Transform((_f(center[0]), 0.0, _f(center[2])), (0.0, _f(yaw), 0.0), (size, size, size)),
                      radius=size * 1.5, keep=True, movable=False, budget=False)
    return backdrop, curve_line


def place_objects(rng: np.random.Generator, view: View, curve_line, cfg, user_models: list[str]) -> list[Placed]:
    """``cfg.outdoor_objects`` random meshes (fewer where no spot is found) where random rays through
    the image meet the ground, a tenth anywhere near the target (clips may turn to them), a few floating."""
    out = []
    placed_xz, placed_r = [], []      # footprints so far
    for k in range(cfg.outdoor_objects):
        anywhere = rng.uniform() < 0.1
        size = math.exp(rng.uniform(math.log(0.25), math.log(2.0)))
        spot = _ground_spot(rng, view, curve_line, placed_xz, placed_r, anywhere, size)
        if spot is None:
            continue
        xz, size, bound = spot
        shape, half = random_shape(rng, user_models, cfg.p_user_model)
        scale, rot, rest, radius = upright(rng, half, size)
        floating = rng.uniform() < cfg.p_floating
        y = rest + (rng.uniform(0.3, 3.0) * size if floating else 0.0)
        out.append(Placed(f"obj_{k:03d}", shape, random_material(rng),
                          Transform((_f(xz[0]), _f(y), _f(xz[1])), rot, scale), radius=radius,
                          planar=not floating))
        placed_xz.append(xz)
        placed_r.append(bound * 0.7)
    return out


def _ground_spot(rng, view: View, curve_line, placed_xz: list, placed_r: list, anywhere: bool, size: float):
    """(x-z point, size, bounding radius) of one object, shrunk so it does not fill the view, or None
    when 30 tries find no place (footprints apart for the first 20)."""
    bound = size * 1.2   # typical bounding radius; the exact one follows the shape
    for attempt in range(30):
        if not anywhere:   # in view: a ray through a random image point meets the ground
            px, py = rng.uniform(-1, 1, 2)
            d = view.forward + view.right * px * view.tan_x + view.up * py * view.tan_y
            if d[1] >= -1e-3:
                continue
            p = view.origin + d * (-view.origin[1] / d[1])
        else:
            a, rr = rng.uniform(0, 2 * math.pi), 30 * math.sqrt(rng.uniform())
            p = view.target * np.array([1, 0, 1]) + rr * np.array([math.cos(a), 0, math.sin(a)])
        cam_d = float(np.linalg.norm(p - view.origin))
        if bound > MAX_SCREEN * cam_d * view.tan_x:    # no object fills the view: shrink it
            bound = MAX_SCREEN * cam_d * view.tan_x
            size = bound / 1.2
        if cam_d < 2.5 * bound + 0.5 or cam_d > 70.0:
            continue
        if curve_line is not None and np.dot(p - curve_line[0], curve_line[1]) > -bound:
            continue   # keep objects on the flat part of the cyclorama
        q = p[[0, 2]]
        if placed_xz and attempt < 20:
            dd = np.linalg.norm(np.asarray(placed_xz) - q, axis=1)
            if (dd < np.asarray(placed_r) + bound * 0.7).any():
                continue
        return q, size, bound
    return None


def random_sky(rng: np.random.Generator, cfg) -> LightSpec:
    """Mitsuba's ``sunsky`` (with probability ``cfg.p_sunsky``) or a procedural HDR probe."""
    if rng.uniform() < cfg.p_sunsky:
        el = math.radians(rng.uniform(10, 70))
        saz = rng.uniform(0, 2 * math.pi)
        sun = [_f(math.cos(el) * math.sin(saz)), _f(math.sin(el)), _f(math.cos(el) * math.cos(saz))]
        return LightSpec("sunsky", {"sun_direction": sun, "turbidity": _f(rng.uniform(2, 8)),
                                    "albedo": _f(rng.uniform(0.1, 0.4)),
                                    "sun_scale": _f(SUN_SCALE * rng.uniform(0.6, 1.3)),
                                    "sky_scale": _f(SKY_SCALE * rng.uniform(0.6, 1.3))})
    s = math.exp(rng.uniform(math.log(0.5), math.log(1.5)))
    return LightSpec("envmap", {"probe": probe_params(rng, sky=0.5 * s, sun_irradiance=OUTDOOR_SUN * s),
                                "scale": OUTDOOR_PROBE_SCALE, "rotation": _f(rng.uniform(0, 360))})
