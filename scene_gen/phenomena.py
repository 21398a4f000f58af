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
  caustic under it is found only by BSDF sampling;
- ``p_natural_textures`` (every family): the scene's diffuse, plastic and principled surfaces textured
  with 1/f noise, as photographed surfaces are (the procedural textures are flat colours, checks, stripes,
  cells and value noise);
- ``p_panels_in_view`` (indoor): an emissive panel on a wall or the ceiling in view, against the surface it
  lights only indirectly (the family's panels are mostly out of view: its cameras look at the objects).

The last two draw from streams of their own (``Phenomenon.own_stream``).

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
from scene_gen.layout import light_color
from scene_gen.materials import TEXTURED_KINDS
from scene_gen.rooms import room_walls
from scene_gen.spec import MaterialSpec, MeshSpec, ObjectSpec, SceneSpec, TextureSpec, Transform

PHENOMENA = 0xF4E7          # the phenomena's stream: SeedSequence([seed, family.seed_index, PHENOMENA])
MIN_SUN_ELEVATION = math.radians(2.0)


@dataclass(frozen=True)
class Phenomenon:
    """A registered phenomenon: ``add(spec, rng, res) -> SceneSpec`` applied to the share ``setting`` of the
    scenes (a ``SceneGenConfig`` field: every family's when ``shared``, else the setting of the families
    that declare it, ``scene_gen.families``). ``own_stream``: drawn from its own stream
    ``SeedSequence([seed, family.seed_index, PHENOMENA, k])`` (k: its place in the registry) after the first
    three, which share one stream (each of them draws its rate before any is added), so a phenomenon added
    later moves nothing of theirs."""
    setting: str
    add: Callable
    shared: bool = False
    doc: str = ""
    own_stream: bool = False


PHENOMENA_BY_SETTING: dict[str, Phenomenon] = {}      # in registration order: the order of the draws


def register_phenomenon(setting: str, *, shared: bool = False, own_stream: bool = True):
    """Decorator: register ``add(spec, rng, res)`` as the phenomenon of ``setting`` (:class:`Phenomenon`).
    A new one draws from its own stream, after those before it, so the scenes of the others stay as they
    were (``own_stream`` False: the first three's shared stream, kept for the stores made with them)."""
    def deco(fn):
        PHENOMENA_BY_SETTING[setting] = Phenomenon(setting, fn, shared, (fn.__doc__ or "").strip(), own_stream)
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
    first = {n: p for n, p in PHENOMENA_BY_SETTING.items() if not p.own_stream}
    # one draw each, every scene, in registration order; a family's own setting only in that family
    draws = {n: rng.uniform() < getattr(cfg, n, 0.0) and (n in own or p.shared) for n, p in first.items()}
    for n, p in first.items():
        if draws[n]:
            spec = p.add(spec, rng, res)
    for k, (n, p) in enumerate(PHENOMENA_BY_SETTING.items()):
        if p.own_stream:
            r = np.random.default_rng(np.random.SeedSequence([int(spec.seed), int(seed_index), PHENOMENA, k]))
            if r.uniform() < getattr(cfg, n, 0.0) and (n in own or p.shared):
                spec = p.add(spec, r, res)
    return spec


@register_phenomenon("p_sun_in_view", own_stream=False)
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


@register_phenomenon("p_lamps", own_stream=False)
def lamps(spec: SceneSpec, rng: np.random.Generator, res: int) -> SceneSpec:
    """One to three small, very bright spheres in view."""
    v = view_of(spec, res)
    objs = []
    for k in range(int(rng.integers(1, 4))):
        p = v.point(rng.uniform(-0.9, 0.9), rng.uniform(-0.6, 0.9), rng.uniform(0.3, 0.8) * v.D)
        radiance = math.exp(rng.uniform(math.log(200.0), math.log(5000.0)))
        objs.append(sphere_object(f"lamp_{k}", p, rng.uniform(0.01, 0.03), WHITE, (radiance,) * 3))
    return dataclasses.replace(spec, objects=spec.objects + tuple(objs))


@register_phenomenon("p_caustics", shared=True, own_stream=False)
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


@register_phenomenon("p_natural_textures", shared=True)
def natural_textures(spec: SceneSpec, rng: np.random.Generator, res: int) -> SceneSpec:
    """Surfaces textured as photographed ones are: every diffuse, plastic or principled material (blends'
    children too; emitters left alone) takes a ``natural`` texture (1/f noise, ``scene_gen.textures``). A
    procedural texture keeps its colours, scale and seed and changes its pattern; a plain colour becomes a
    texture between 0.35-0.8x and 1-1.4x that colour (a tenth of the way to a second hue), UV scale 0.5-4.
    A material several objects share stays shared."""
    done: dict[int, MaterialSpec] = {}

    def retextured(m: MaterialSpec) -> MaterialSpec:
        if id(m) in done:
            return done[id(m)]
        if m.kind == "blend":
            out = dataclasses.replace(m, children=tuple(retextured(c) for c in m.children))
        elif m.kind not in TEXTURED_KINDS:
            out = m
        elif m.texture is not None:
            out = dataclasses.replace(m, texture=dataclasses.replace(m.texture, kind="natural"))
        else:
            base = np.asarray(m.base_color, float)
            hue = rng.uniform(0.0, 1.0, 3)
            lo = np.clip(0.9 * base * rng.uniform(0.35, 0.8) + 0.1 * hue * base.mean(), 0.0, 1.0)
            hi = np.clip(0.9 * base * rng.uniform(1.0, 1.4) + 0.1 * hue * base.mean(), 0.0, 1.0)
            out = dataclasses.replace(m, texture=TextureSpec(
                "natural", tuple(round(float(x), 4) for x in lo), tuple(round(float(x), 4) for x in hi),
                uv_scale=round(float(np.exp(rng.uniform(np.log(0.5), np.log(4.0)))), 4),
                seed=int(rng.integers(0, 2 ** 31 - 1))))
        done[id(m)] = out
        return out

    objs = tuple(o if o.emitter_radiance is not None else dataclasses.replace(o, material=retextured(o.material))
                 for o in spec.objects)
    return dataclasses.replace(spec, objects=objs)


PANEL_POWER = (1.5, 6.0)      # radiance x area of a panel, as the indoor family's (log-uniform)


@register_phenomenon("p_panels_in_view")
def panel_in_view(spec: SceneSpec, rng: np.random.Generator, res: int) -> SceneSpec:
    """An emissive panel in view on the room's wall or ceiling, seen against the surface it lights only
    indirectly (a Cornell box's light): half extents 8-35 cm, radiance x area 1.5-6, where the first camera's
    ray through a random point of the upper two thirds of the image first leaves the room (its plan's union
    of rectangles, floor to ceiling), at least 0.5 m away, the panel whole on that wall or ceiling and clear
    of its windows, doors and skylights (the ceiling looked for first in half the scenes, a wall in the
    others). The
    camera stays as it is (an object may hide part of the panel, as in a real room). Nothing changes in a
    room without a ceiling or where no such point is found."""
    ceiling = next((o for o in spec.objects if o.name == "room_ceiling" and o.mesh.kind == "room"), None)
    if ceiling is None:
        return spec
    H, rects = float(ceiling.mesh.params["height"]), np.asarray(ceiling.mesh.params["rects"], float)
    v = view_of(spec, res)
    hx, hz = rng.uniform(0.08, 0.35, 2)
    n = 64
    d = (v.f[None] - v.r[None] * (rng.uniform(-0.85, 0.85, n) * v.tx)[:, None]
         + v.u[None] * (rng.uniform(-0.3, 0.95, n) * v.ty)[:, None])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    on_ceiling = rng.uniform() < 0.5                        # looked for first; else whichever is found
    hits = [_room_exit(v.o, d[k], rects, H) for k in range(n)]
    order = sorted(range(n), key=lambda k: hits[k] is None or (hits[k][1][1] < 0) != on_ceiling)
    for k in order:
        if hits[k] is None:
            continue
        p, normal = hits[k]
        if np.linalg.norm(p - v.o) < 0.5:
            continue
        if normal[1] < 0:                                   # the ceiling: the panel faces down
            ok = _fits_ceiling(ceiling.mesh.params, p, math.hypot(hx, hz) + 0.05)
            rotate = (180.0, round(float(rng.uniform(0, 90)), 4), 0.0)
        else:                                               # a wall: the panel faces into the room
            ok = 0.3 + hz <= p[1] and _fits_wall(ceiling.mesh.params, p, normal, hx + 0.05, hz + 0.05)
            rotate = (90.0, round(math.degrees(math.atan2(normal[0], normal[2])), 4), 0.0)
        scale = (hx, 1.0, hz)
        if ok:
            break
    else:
        return spec
    p = p + 0.01 * normal
    radiance = light_color(rng) * math.exp(rng.uniform(*np.log(PANEL_POWER))) / (4 * hx * hz)
    panel = ObjectSpec("panel_in_view", MeshSpec("plane", {"resolution": 1}), WHITE,
                       Transform(tuple(round(float(c), 4) for c in p), rotate, tuple(round(float(c), 4) for c in scale)),
                       emitter_radiance=tuple(round(float(c), 4) for c in radiance))
    return dataclasses.replace(spec, objects=spec.objects + (panel,))


def _fits_ceiling(room: dict, p: np.ndarray, reach: float) -> bool:
    """Whether a ceiling panel at ``p`` turned any way (``reach``: its half diagonal and a margin) lies whole
    inside the plan and clear of every skylight."""
    rects = np.asarray(room["rects"], float)
    if not all(_in_plan(rects, p + np.array([sx * reach, 0.0, sz * reach])) for sx in (-1, 1) for sz in (-1, 1)):
        return False
    return not any(x0 - reach < p[0] < x1 + reach and z0 - reach < p[2] < z1 + reach
                   for x0, z0, x1, z1 in room.get("skylights") or ())


def _fits_wall(room: dict, p: np.ndarray, normal: np.ndarray, half_u: float, half_v: float) -> bool:
    """Whether a wall panel at ``p`` (half extents with margins ``half_u`` along the wall, ``half_v`` up) lies
    whole on one wall of the room (``scene_gen.rooms.room_walls``: a corner ends it), between floor and
    ceiling, and clear of that wall's openings (windows, doors)."""
    H = float(room["height"])
    if not half_v <= p[1] <= H - half_v:
        return False
    q = np.array([p[0], p[2]])
    for w, (a, b, nin) in enumerate(room_walls(room["rects"])):
        a, b, nin = (np.asarray(x, float) for x in (a, b, nin))
        L = float(np.linalg.norm(b - a))
        t = (b - a) / L
        if np.dot(nin, normal[[0, 2]]) < 0.99 or abs(np.dot(q - a, nin)) > 1e-3:
            continue
        u = float(np.dot(q - a, t))
        if not half_u <= u <= L - half_u:
            continue
        return not any(int(o[0]) == w and o[1] < u + half_u and u - half_u < o[2] and o[3] < p[1] + half_v
                       and p[1] - half_v < o[4] for o in room.get("openings") or ())
    return False


def _in_plan(rects: np.ndarray, q) -> bool:
    return bool(((rects[:, 0] <= q[0]) & (q[0] <= rects[:, 2]) & (rects[:, 1] <= q[2]) & (q[2] <= rects[:, 3])).any())


def _room_exit(o: np.ndarray, d: np.ndarray, rects: np.ndarray, H: float, step: float = 0.01, far: float = 40.0):
    """Where the ray ``o + t d`` first leaves the room (the union of ``rects`` (x0, z0, x1, z1) from floor 0 to
    ceiling ``H``), and the inward normal there: ``(point, normal)``, or None where it leaves through the floor
    or the camera is outside. Marched in ``step`` metres, the crossing then solved exactly on the box it left."""
    if not _in_plan(rects, o) or not 0.0 < o[1] < H:
        return None
    t = np.arange(step, far, step)
    q = o[None] + t[:, None] * d[None]
    inside = ((rects[None, :, 0] <= q[:, None, 0]) & (q[:, None, 0] <= rects[None, :, 2]) &
              (rects[None, :, 1] <= q[:, None, 2]) & (q[:, None, 2] <= rects[None, :, 3])).any(1)
    out = ~inside | (q[:, 1] >= H) | (q[:, 1] <= 0.0)
    if not out.any():
        return None
    i = int(np.argmax(out))
    prev = o if i == 0 else q[i - 1]
    box = next(r for r in rects if r[0] <= prev[0] <= r[2] and r[1] <= prev[2] <= r[3])
    exits = {}
    if d[1] > 0:
        exits["y"] = (H - o[1]) / d[1]
    elif d[1] < 0:
        exits["floor"] = -o[1] / d[1]
    for axis, lo, hi in ((0, box[0], box[2]), (2, box[1], box[3])):
        if d[axis] != 0:
            exits[axis] = ((hi if d[axis] > 0 else lo) - o[axis]) / d[axis]
    which = min(exits, key=exits.get)
    if which == "floor":
        return None
    p = o + exits[which] * d
    if which == "y":
        return p, np.array([0.0, -1.0, 0.0])
    normal = np.zeros(3)
    normal[which] = -np.sign(d[which])
    return p, normal
