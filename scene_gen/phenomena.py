"""Phenomena the scene families rarely or never make by themselves, added at each family's own rate (numpy only).

The random families (``scene_gen.families``) almost never show the sun itself (an outdoor camera looks
down at its objects), small very bright emitters (indoor lights are large panels and a point light) or
caustics through glass (no glass object sits near a light). Denoisers trained on them fail on exactly
those (docs/hard-cases.md). These settings add them to a share of the scenes, drawn from each scene's
own stream ``SeedSequence([seed, family.seed_index, PHENOMENA])``, after the scene is laid out, so a
scene's layout, materials, camera and motion are those it has without them, and every setting at 0 (the
default) leaves every scene exactly as before:

- ``p_sun_in_view`` (outdoor): a ``sunsky`` scene's sun moves into the first camera's view: the direction
  through a random image point in the upper part of the frame, at least 2 degrees above the horizon; a
  camera whose frame shows no sky is first pitched up until the frame's top is 5-15 degrees above the
  horizon, and a cyclorama backdrop (whose curve hides the sky) is laid flat; the sun is drawn among the
  points of a random image column that lie above that; the objects stay where they are (the sun may
  stand behind one). Scenes lit by a probe are left alone: about half of the outdoor
  scenes (``p_sunsky``) can show the sun;
- ``p_lamps`` (indoor): one to three lamps, spheres of 1-3 cm radius and radiance 200-5000 (a bulb),
  floating in view at 30-80% of the way to the camera's look-at point;
- ``p_caustics`` (every family): a glass sphere (dielectric, ior 1.5) in view at 50-80% of the way to the
  look-at point, a small emitter (a tenth of its radius, radiance 2000-20000) three radii above it: the
  caustic under it is found only by BSDF sampling.

Unlike a hard case (``scene_gen.cases``: a forced, documented edit recorded in ``frames/case``), a
phenomenon is part of the family's distribution: its scenes are ordinary frames.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from scene_gen.cameras import make_camera
from scene_gen.cases import GLASS, WHITE, sphere_object, view_of
from scene_gen.families import get_family
from scene_gen.spec import MeshSpec, SceneSpec, Transform

PHENOMENA = 0xF4E7          # the phenomena's stream: SeedSequence([seed, family.seed_index, PHENOMENA])
MIN_SUN_ELEVATION = math.radians(2.0)


@dataclass(frozen=True)
class Phenomenon:
    """A registered phenomenon: ``add(spec, rng, res) -> SceneSpec`` applied to the share ``setting`` of the
    scenes (a ``SceneGenConfig`` field: every family's when ``shared``, else the setting of the families
    that declare it, ``scene_gen.families``)."""
    setting: str
    add: Callable
    shared: bool = False
    doc: str = ""


PHENOMENA_BY_SETTING: dict[str, Phenomenon] = {}      # in registration order: the order of the draws


def register_phenomenon(setting: str, *, shared: bool = False):
    """Decorator: register ``add(spec, rng, res)`` as the phenomenon of ``setting`` (:class:`Phenomenon`).
    A new one draws after those before it, so the scenes of the others stay as they were."""
    def deco(fn):
        PHENOMENA_BY_SETTING[setting] = Phenomenon(setting, fn, shared, (fn.__doc__ or "").strip())
        return fn
    return deco


def wanted(cfg) -> bool:
    """Whether ``cfg`` asks for any phenomenon (otherwise nothing is drawn)."""
    return any(getattr(cfg, n, 0.0) > 0 for n in PHENOMENA_BY_SETTING)


def add_phenomena(spec: SceneSpec, cfg, seed_index: int, res: int) -> SceneSpec:
    """``spec`` with the phenomena its stream draws at ``cfg``'s rates (module docstring)."""
    if not wanted(cfg):
        return spec
    own = get_family(spec.kind).settings
    rng = np.random.default_rng(np.random.SeedSequence([int(spec.seed), int(seed_index), PHENOMENA]))
    # one draw each, every scene, in registration order; a family's own setting only in that family
    draws = {n: rng.uniform() < getattr(cfg, n, 0.0) and (n in own or p.shared)
             for n, p in PHENOMENA_BY_SETTING.items()}
    for n, p in PHENOMENA_BY_SETTING.items():
        if draws[n]:
            spec = p.add(spec, rng, res)
    return spec


@register_phenomenon("p_sun_in_view")
def sun_in_view(spec: SceneSpec, rng: np.random.Generator, res: int) -> SceneSpec:
    """A sunsky's sun moved to a random point of the upper image (nothing without a sunsky). A cyclorama is
    laid flat, and a camera whose frame shows no sky (an outdoor camera mostly looks down at its objects) is
    first pitched up, every frame alike, until the top of its frame is 5-15 degrees above the horizon."""
    lights = list(spec.lights)
    k = next((i for i, lt in enumerate(lights) if lt.kind == "sunsky"), None)
    if k is None:
        return spec
    out = flat_ground(spec)
    v = view_of(out, res)
    top = math.asin(float(np.clip(v.f[1], -1, 1))) + math.atan(v.ty)        # elevation of the frame's top
    want = math.radians(rng.uniform(5.0, 15.0))
    if top < want:
        out = pitched(out, want - top)
        v = view_of(out, res)
    px = rng.uniform(-0.85, 0.85)
    py = np.linspace(0.0, 0.95, 96)
    d = v.f[None] - v.r[None] * px * v.tx + v.u[None] * py[:, None] * v.ty      # the column at px, rows py
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    above = np.nonzero(d[:, 1] >= math.sin(MIN_SUN_ELEVATION))[0]
    if above.size == 0:                       # no sky in this column: the scene stays as it was
        return spec
    sun = d[above[int(rng.integers(above.size))]]
    lights[k] = dataclasses.replace(lights[k], params={**lights[k].params,
                                                       "sun_direction": [round(float(x), 6) for x in sun]})
    return dataclasses.replace(out, lights=tuple(lights))


def flat_ground(spec: SceneSpec) -> SceneSpec:
    """``spec`` with a cyclorama backdrop (its curve rises behind the objects and hides the sky) laid flat:
    the ground plane of the family's flat backdrops, same material (the objects stand on its flat part)."""
    out = []
    for o in spec.objects:
        if o.name == "backdrop" and "bend" in o.mesh.params:
            o = dataclasses.replace(o, mesh=MeshSpec("plane", {"resolution": 1}, o.mesh.seed),
                                    transform=Transform((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (400.0, 400.0, 400.0)))
        out.append(o)
    return dataclasses.replace(spec, objects=tuple(out))


def pitched(spec: SceneSpec, angle: float) -> SceneSpec:
    """Every camera of ``spec`` turned up by ``angle`` radians about its own position (its target keeps its
    distance and its heading)."""
    out = []
    for c in spec.cameras:
        o = np.asarray(c.origin, float)
        fwd = np.asarray(c.target, float) - o
        dist = float(np.linalg.norm(fwd))
        h = np.array([fwd[0], 0.0, fwd[2]])
        h = h / max(float(np.linalg.norm(h)), 1e-9)
        e = min(math.asin(float(np.clip(fwd[1] / dist, -1, 1))) + angle, math.radians(80.0))
        t = o + dist * (math.cos(e) * h + math.sin(e) * np.array([0.0, 1.0, 0.0]))
        out.append(make_camera(o, t, c.fov, c.aperture_radius, c.focus_distance))
    return dataclasses.replace(spec, cameras=tuple(out))


@register_phenomenon("p_lamps")
def lamps(spec: SceneSpec, rng: np.random.Generator, res: int) -> SceneSpec:
    """One to three small, very bright spheres in view."""
    v = view_of(spec, res)
    objs = []
    for k in range(int(rng.integers(1, 4))):
        p = v.point(rng.uniform(-0.9, 0.9), rng.uniform(-0.6, 0.9), rng.uniform(0.3, 0.8) * v.D)
        radiance = math.exp(rng.uniform(math.log(200.0), math.log(5000.0)))
        objs.append(sphere_object(f"lamp_{k}", p, rng.uniform(0.01, 0.03), WHITE, (radiance,) * 3))
    return dataclasses.replace(spec, objects=spec.objects + tuple(objs))


@register_phenomenon("p_caustics", shared=True)
def caustic(spec: SceneSpec, rng: np.random.Generator, res: int) -> SceneSpec:
    """A glass sphere in view under a small bright emitter."""
    v = view_of(spec, res)
    d = rng.uniform(0.5, 0.8) * v.D
    r = rng.uniform(0.04, 0.1) * d * v.tx
    g = v.point(rng.uniform(-0.7, 0.7), rng.uniform(-0.7, 0.3), d)
    radiance = math.exp(rng.uniform(math.log(2e3), math.log(2e4)))
    return dataclasses.replace(spec, objects=spec.objects + (
        sphere_object("caustic_glass", g, r, GLASS),
        sphere_object("caustic_light", g + np.array([0.0, 3.0 * r, 0.0]), 0.1 * r, WHITE, (radiance,) * 3)))
