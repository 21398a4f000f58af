"""Hard cases: named, deterministic changes to a generated scene that break naive code.

A case is a documented function ``apply(spec, res) -> SceneSpec`` registered under its name, plus
the ``SceneGenConfig`` settings it needs (``scene_gen``: applied before the scene is sampled), what it
does to the loaded Mitsuba scene where it does more than edit the spec (``loaded``), and whether
non-finite samples are its purpose (``nonfinite``) (:class:`Case`). The
random scene of a seed is made first (``scene_gen.sampling.sample_scene`` with those settings), then
the case edits it in a fixed way that uses the camera only (no random draw), so a case never depends on
luck of the seed. ``SceneSpec.case`` records the names (``frames/case`` in the store)::

    spec = sample_scene(seed, kind, num_frames=n, res=res, config=case_config(cfg, "mirror"))
    spec = apply_cases(spec, "mirror", res)

    @register_case("black", scene_gen={...})
    def black(spec, res): ...

Placement uses the first frame's camera: ``D`` is the distance to its look-at target (at most
:data:`MAX_DEPTH`); image points are ``(px, py)`` in [-1, 1], ``px`` to the image's right, ``py``
up; a pixel at depth ``d`` is ``2 d tan(fov/2) / W`` world units wide. Every case also turns off
the random defocus and motion it does not ask for (``p_defocus``/``p_motion`` 0), so a frame shows
its case and nothing else that is hard.

The cases (``configs/hard-cases.yaml`` renders one frame or clip of each; docs/hard-cases.md):

- ``fireflies``: six tiny emitter spheres (0.3 px radius, radiance 2e4) across the view and a glass
  sphere (dielectric, ior 1.5) under a small bright emitter (radiance 1e4): caustics only BSDF
  sampling finds.
- ``sun``: outdoor ``sunsky`` whose sun is in view (camera pitched up to it, fov at most 30 degrees,
  occluders removed), at ``sun_scale`` :data:`SUN_SCALE`: the sun's radiance is ~1.5e6, its pixel's
  mean above 1e5 from 24 px up.
- ``black``: no light at all (lights and emitters removed): every image is exactly 0.
- ``mirror``: a smooth silver mirror (conductor) over the right of the view, the camera panning
  and every content object moving: motion vectors describe the mirror, not what it reflects.
- ``defocus``: a thin lens focused at 0.25 D with a lens radius of 0.05 D (CoC of tens of pixels).
- ``motion``: every content object moves 6-10 of its radii per frame, across the view (along the
  camera's right axis; the generator's random directions can carry an object through the camera
  plane, whose motion vectors then overflow the store's float16 features).
- ``zero-albedo``: every second non-emitting object (in spec order, the backdrop or room first) is a
  black diffuse surface (albedo exactly 0).
- ``nan``: a small emitter (``NAN_EMITTER``) in view whose radiance the renderer sets to NaN once the
  scene is loaded (its ``loaded`` edit, through :func:`scene_hook`): NaN comes out of Mitsuba in every
  stream, and its frames record that this is their purpose (``nonfinite``).
- ``flat``: one uniform grey wall facing the camera fills the view (content objects removed but one
  sphere): large flat regions, empty bilateral-grid cells.
- ``thin``: an emissive bar one pixel wide across the whole image (radiance 20), on the centre of a
  pixel row.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from scene_gen import cameras as cams
from scene_gen.config import ConfigError, SceneGenConfig
from scene_gen.spec import LightSpec, MaterialSpec, MeshSpec, ObjectSpec, SceneSpec, Transform
from core.variant import mitsuba

MAX_DEPTH = 8.0          # D: placement depth cap (world units)
SUN_SCALE = 150.0        # sunsky sun_scale of the sun case (the generator draws 1.2-2.6): sun radiance ~1.5e6
SUN_MAX_FOV = 30.0       # degrees: the sun case's widest view (the sun disc covers >= 10% of a pixel at 24 px)
NAN_EMITTER = "case_nan_emitter"
SEP = ","                # SceneSpec.case joins case names with it


@dataclass(frozen=True)
class Case:
    """A registered hard case: ``apply(spec, res)`` edits the SceneSpec; ``loaded(scene)``, when given, edits
    the ``mi.Scene`` once it is loaded (before anything renders); ``nonfinite``: non-finite samples are the
    case's purpose, so the frames it makes record it (``frames/nonfinite_expected``) and the fitness check
    takes their NaN/Inf the renderer replaced as intended (``stores.fitness``)."""
    name: str
    apply: Callable
    scene_gen: dict = field(default_factory=dict)
    kind: str | None = None      # the scene kind the case needs (None: any)
    doc: str = ""
    loaded: Callable | None = None
    nonfinite: bool = False


CASES: dict[str, Case] = {}
QUIET = {"p_defocus": 0.0, "p_motion": 0.0}     # what every case turns off unless it asks for it


def register_case(name: str, *, scene_gen: dict | None = None, kind: str | None = None,
                  loaded: Callable | None = None, nonfinite: bool = False):
    """Decorator: register ``apply(spec, res) -> SceneSpec`` as hard case ``name`` (:class:`Case`)."""
    def deco(fn):
        if name in CASES and CASES[name].apply is not fn:
            raise ConfigError(f"hard case {name!r} is already registered")
        CASES[name] = Case(name, fn, {**QUIET, **(scene_gen or {})}, kind, (fn.__doc__ or "").strip(), loaded,
                           bool(nonfinite))
        return fn
    return deco


def case_names() -> list[str]:
    return list(CASES)


def parse_cases(case) -> tuple[str, ...]:
    """Case names from ``None``/'' (none), a name, a comma-separated string or a list of names;
    ConfigError naming the unknown ones and listing the known."""
    if case is None or case == "":
        return ()
    if isinstance(case, str):
        names = [c.strip() for c in case.split(SEP)]
    elif isinstance(case, (list, tuple)) and all(isinstance(c, str) for c in case):
        names = [c.strip() for c in case]
    else:
        raise ConfigError(f"a hard case must be a name or a list of names of {case_names()}, got {case!r}")
    unknown = [c for c in names if c not in CASES]
    if unknown or not names:
        raise ConfigError(f"unknown hard case(s) {unknown or names}; known: {case_names()}")
    if len(set(names)) != len(names):
        raise ConfigError(f"hard case listed twice: {names}")
    return tuple(names)


def case_tag(case) -> str:
    """The ``SceneSpec.case`` / ``frames/case`` string of ``case`` ('' for none)."""
    return SEP.join(parse_cases(case))


def check_kind(case, kind: str) -> None:
    for n in parse_cases(case):
        need = CASES[n].kind
        if need is not None and need != kind:
            raise ConfigError(f"hard case {n!r} needs scenes of kind {need!r}, got {kind!r}")


def case_config(cfg: SceneGenConfig | None, case) -> SceneGenConfig:
    """``cfg`` with the settings the cases need (later cases win)."""
    cfg = cfg or SceneGenConfig()
    over: dict = {}
    for n in parse_cases(case):
        over.update(CASES[n].scene_gen)
    return dataclasses.replace(cfg, **over) if over else cfg


def apply_cases(spec: SceneSpec, case, res: int) -> SceneSpec:
    """``spec`` changed by each case in order, with ``case`` recorded in ``spec.case``."""
    names = parse_cases(case)
    check_kind(names, spec.kind)
    for n in names:
        spec = CASES[n].apply(spec, int(res))
    return dataclasses.replace(spec, case=SEP.join(names)) if names else spec


def spec_cases(spec: SceneSpec | str) -> tuple[str, ...]:
    """The case names a spec (or its JSON) records."""
    if isinstance(spec, str):
        spec = SceneSpec.from_json(spec)
    return tuple(c for c in spec.case.split(SEP) if c)


def scene_hook(spec: SceneSpec) -> Callable | None:
    """What the renderer must do to the loaded ``mi.Scene`` of ``spec`` (``scene_gen.to_mitsuba.load_frame``
    calls it before anything renders): the ``loaded`` edits of its cases, in order, or None."""
    edits = [CASES[n].loaded for n in spec_cases(spec) if n in CASES and CASES[n].loaded is not None]
    if not edits:
        return None

    def edit(scene):
        for fn in edits:
            fn(scene)
    return edit


def nonfinite_expected(case: str) -> bool:
    """Whether non-finite samples are the purpose of one of the hard cases ``case`` names (a
    ``SceneSpec.case`` or ``frames/case`` string; ``Case.nonfinite``)."""
    return any(CASES[n].nonfinite for n in str(case or "").split(SEP) if n in CASES)


# ---------------------------------------------------------------------------------------------
# geometry helpers (first camera)

def _f(x) -> float:
    return round(float(x), 6)


def _v(x) -> tuple:
    return tuple(_f(a) for a in x)


@dataclass
class View:
    """The first camera as the edits place things: origin ``o``, basis (``r`` right in Mitsuba's sense,
    the image's left; ``u``; ``f``), the tangents of the half field of view, ``D`` (the look-at distance,
    1 to MAX_DEPTH) and the resolution."""
    o: np.ndarray
    r: np.ndarray
    u: np.ndarray
    f: np.ndarray
    tx: float
    ty: float
    D: float
    res: int

    def point(self, px: float, py: float, d: float) -> np.ndarray:
        """World point at image position (px, py) in [-1, 1] (right, up) and depth ``d`` along the view
        axis (``cameras.basis``'s right axis is the image's left: Mitsuba's camera +x points left)."""
        return self.o + d * (self.f - self.r * px * self.tx + self.u * py * self.ty)

    def pixel(self, d: float) -> float:
        """Width of one pixel at depth ``d`` (world units)."""
        return 2 * d * self.tx / self.res

    def facing(self) -> tuple:
        """XYZ Euler angles (degrees) turning local +z onto the view axis (local +x stays horizontal)."""
        f = self.f
        return _v((math.degrees(-math.asin(float(np.clip(f[1], -1, 1)))), math.degrees(math.atan2(f[0], f[2])), 0.0))


def view_of(spec: SceneSpec, res: int) -> View:
    """The :class:`View` of ``spec``'s first camera at ``res`` pixels."""
    cam = spec.cameras[0]
    r, u, f = cams.basis(cam)
    tx, ty = cams.tan_half(cam, (res, res))
    D = min(float(np.linalg.norm(np.subtract(cam.target, cam.origin))), MAX_DEPTH)
    return View(np.asarray(cam.origin, float), r, u, f, tx, ty, max(D, 1.0), res)


def sphere_object(name: str, center, radius: float, material: MaterialSpec, emitter=None) -> ObjectSpec:
    """A sphere object (an emitter of radiance ``emitter`` when given)."""
    return ObjectSpec(name, MeshSpec("sphere", {"subdivisions": 3}), material,
                      Transform(_v(center), (0.0, 0.0, 0.0), (_f(radius),) * 3),
                      emitter_radiance=None if emitter is None else _v(emitter))


def _box(name: str, center, half, rotate, material: MaterialSpec, emitter=None) -> ObjectSpec:
    """A box of half extents ``half`` (the unit cube mesh spans [-1, 1] after normalisation)."""
    return ObjectSpec(name, MeshSpec("box", {"extents": [1.0, 1.0, 1.0]}), material,
                      Transform(_v(center), rotate, _v(half)),
                      emitter_radiance=None if emitter is None else _v(emitter))


WHITE = MaterialSpec("diffuse", base_color=(0.8, 0.8, 0.8), roughness=1.0)
GLASS = MaterialSpec("dielectric", specular_color=(1.0, 1.0, 1.0), roughness=0.0, params={"int_ior": 1.5})
MIRROR = MaterialSpec("conductor", specular_color=(0.95, 0.95, 0.95), roughness=0.0, params={"material": "none"})
BLACK = MaterialSpec("diffuse", base_color=(0.0, 0.0, 0.0), roughness=1.0)
GREY = MaterialSpec("diffuse", base_color=(0.5, 0.5, 0.5), roughness=1.0)


def _add(spec: SceneSpec, *objs: ObjectSpec, keep=None) -> SceneSpec:
    base = spec.objects if keep is None else tuple(o for o in spec.objects if keep(o))
    return dataclasses.replace(spec, objects=base + tuple(objs))


def _content(o: ObjectSpec) -> bool:
    """Generated content objects (``obj_*``), not the room, backdrop, furniture or lights."""
    return o.name.startswith("obj_")


# ---------------------------------------------------------------------------------------------
# the cases

@register_case("fireflies")
def fireflies(spec: SceneSpec, res: int) -> SceneSpec:
    """Six tiny very bright emitters across the view and caustics through a glass sphere."""
    v = view_of(spec, res)
    objs = []
    d = 0.4 * v.D
    for k, (px, py) in enumerate([(-0.6, 0.5), (0.0, 0.6), (0.6, 0.45), (-0.5, -0.3), (0.3, -0.1), (0.7, -0.5)]):
        objs.append(sphere_object(f"case_firefly_{k}", v.point(px, py, d), 0.3 * v.pixel(d), WHITE, (2e4, 2e4, 2e4)))
    dg = 0.6 * v.D
    rg = 0.12 * dg * v.tx
    g = v.point(0.0, -0.2, dg)
    objs.append(sphere_object("case_glass", g, rg, GLASS))
    objs.append(sphere_object("case_caustic_light", g + np.array([0.0, 3.0 * rg, 0.0]), 0.1 * rg, WHITE, (1e4, 1e4, 1e4)))
    return _add(spec, *objs)


@register_case("sun", kind="outdoor")
def sun(spec: SceneSpec, res: int) -> SceneSpec:
    """The sun in view: a sunsky whose sun sits at 12 degrees elevation in the upper right of the image
    (fov at most 30 degrees), at sun_scale SUN_SCALE; objects in front of it are removed."""
    cam0 = spec.cameras[0]
    fwd = np.subtract(cam0.target, cam0.origin)
    h = np.array([fwd[0], 0.0, fwd[2]])
    h = h / max(np.linalg.norm(h), 1e-9)
    tx, ty = cams.tan_half(dataclasses.replace(cam0, fov=min(cam0.fov, SUN_MAX_FOV)), (res, res))
    elev = math.radians(12.0)
    pitch = elev - 0.5 * math.atan(ty)               # the sun half way between the centre and the top
    right = np.cross([0.0, 1.0, 0.0], h)
    sun_dir = np.cos(elev) * h + np.sin(elev) * np.array([0.0, 1.0, 0.0])
    sun_dir = sun_dir - 0.4 * tx * right * math.cos(elev)          # right of centre (basis right is image left)
    sun_dir = sun_dir / np.linalg.norm(sun_dir)
    cameras = []
    for c in spec.cameras:
        o = np.asarray(c.origin, float)
        t = o + 10.0 * (math.cos(pitch) * h + math.sin(pitch) * np.array([0.0, 1.0, 0.0]))
        cameras.append(cams.make_camera(o, t, min(c.fov, SUN_MAX_FOV), c.aperture_radius, c.focus_distance))
    # remove objects between the camera and the sun
    o = np.asarray(cam0.origin, float)

    def clear(ob: ObjectSpec) -> bool:
        if ob.name == "backdrop":
            return True
        p = np.asarray(ob.transform.translate) - o
        along = float(p @ sun_dir)
        rad = float(max(ob.transform.scale)) * 1.8
        return along < 0 or float(np.linalg.norm(p - along * sun_dir)) > rad
    sky = LightSpec("sunsky", {"sun_direction": list(_v(sun_dir)), "turbidity": 3.0, "albedo": 0.2,
                               "sun_scale": SUN_SCALE, "sky_scale": 5.0})
    return dataclasses.replace(spec, objects=tuple(ob for ob in spec.objects if clear(ob)), lights=(sky,),
                               cameras=tuple(cameras))


@register_case("black")
def black(spec: SceneSpec, res: int) -> SceneSpec:
    """No light at all: every light and emitter removed."""
    return dataclasses.replace(spec, lights=(), objects=tuple(o for o in spec.objects if o.emitter_radiance is None))


@register_case("mirror", scene_gen={"p_motion": 1.0, "p_object_motion": 1.0})
def mirror(spec: SceneSpec, res: int) -> SceneSpec:
    """A smooth mirror over the right 60% of the view at 0.9 D (turned 25 degrees), a panning camera
    and moving objects."""
    v = view_of(spec, res)
    d = 0.9 * v.D
    rot = v.facing()
    rot = (rot[0], _f(rot[1] + 25.0), 0.0)
    m = _box("case_mirror", v.point(0.45, 0.0, d), (0.7 * d * v.tx, 1.2 * d * v.ty, 0.02), rot, MIRROR)
    step = 0.04 * v.D
    cameras = tuple(cams.make_camera(np.asarray(c.origin) + k * step * v.r, np.asarray(c.target) + k * step * v.r,
                                     c.fov, c.aperture_radius, c.focus_distance)
                    for k, c in enumerate(spec.cameras))
    return dataclasses.replace(_add(spec, m), cameras=cameras)


@register_case("defocus")
def defocus(spec: SceneSpec, res: int) -> SceneSpec:
    """Extreme defocus: focus at 0.25 D, lens radius 0.05 D (the generator's largest is 0.02 x focus)."""
    v = view_of(spec, res)
    cameras = tuple(cams.make_camera(c.origin, c.target, c.fov, 0.05 * v.D, 0.25 * v.D) for c in spec.cameras)
    return dataclasses.replace(spec, cameras=cameras)


@register_case("motion", scene_gen={"p_motion": 1.0, "p_object_motion": 1.0, "speed_range": (6.0, 10.0)})
def motion(spec: SceneSpec, res: int) -> SceneSpec:
    """Fast motion across the view: every moving object keeps its speed (6-10 of its radii per frame) but
    moves along the camera's right axis (alternately left and right), parallel to the image plane."""
    v = view_of(spec, res)
    out, k = [], 0
    for o in spec.objects:
        if o.moving:
            speed = float(np.linalg.norm(o.velocity))
            o = dataclasses.replace(o, velocity=_v((1.0 if k % 2 == 0 else -1.0) * speed * v.r))
            k += 1
        out.append(o)
    return dataclasses.replace(spec, objects=tuple(out))


@register_case("zero-albedo")
def zero_albedo(spec: SceneSpec, res: int) -> SceneSpec:
    """Every second non-emitting object (backdrop or room first) gets a black diffuse material (albedo 0)."""
    out, k = [], 0
    for o in spec.objects:
        if o.emitter_radiance is None:
            if k % 2 == 0:
                o = dataclasses.replace(o, material=BLACK)
            k += 1
        out.append(o)
    return dataclasses.replace(spec, objects=tuple(out))


def _poison(scene) -> None:
    """The ``nan`` case's edit of the loaded scene: its emitter's radiance becomes NaN."""
    mi = mitsuba()
    p = mi.traverse(scene)
    keys = [k for k in p.keys() if k.startswith(NAN_EMITTER) and k.endswith("radiance.value")]
    if not keys:
        raise ConfigError(f"hard case 'nan': the scene has no emitter {NAN_EMITTER!r} to poison")
    for k in keys:
        p[k] = mi.Color3f(float("nan"), 1.0, 1.0) if "Color" in type(p[k]).__name__ else float("nan")
    p.update()


@register_case("nan", loaded=_poison, nonfinite=True)
def nan(spec: SceneSpec, res: int) -> SceneSpec:
    """A small emitter in view (2 px radius) whose radiance becomes NaN when the renderer loads the scene."""
    v = view_of(spec, res)
    d = 0.5 * v.D
    return _add(spec, sphere_object(NAN_EMITTER, v.point(0.3, 0.3, d), 2.0 * v.pixel(d), WHITE, (1.0, 1.0, 1.0)))


@register_case("flat")
def flat(spec: SceneSpec, res: int) -> SceneSpec:
    """A uniform grey wall facing the camera fills the view; content objects removed but one small sphere."""
    v = view_of(spec, res)
    d = 0.5 * v.D
    wall = _box("case_wall", v.point(0.0, 0.0, d), (1.5 * d * v.tx, 1.5 * d * v.ty, 0.01), v.facing(), GREY)
    ball = sphere_object("case_ball", v.point(0.3, -0.3, 0.8 * d), 0.08 * d * v.tx, WHITE)
    return _add(spec, wall, ball, keep=lambda o: not _content(o))


@register_case("thin")
def thin(spec: SceneSpec, res: int) -> SceneSpec:
    """An emissive bar one pixel high across the image, centred on a pixel row (radiance 20)."""
    v = view_of(spec, res)
    d = 0.5 * v.D
    px = v.pixel(d)
    py = (1.0 / res) if res % 2 == 0 else 0.0       # image y of the centre of the row just above the middle
    bar = _box("case_thin", v.point(0.0, py, d), (1.3 * d * v.tx, 0.5 * px, 0.5 * px), v.facing(), WHITE,
               (20.0, 20.0, 20.0))
    return _add(spec, bar)
