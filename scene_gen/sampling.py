"""Seed → SceneSpec: random indoor and outdoor scenes (numpy only; no meshes are built, nothing renders).

``sample_scene(seed, kind, num_frames=1, res=256, config=None)`` follows Gharbi et al. 2019 as the
layer-embeddings paper (Munkberg & Hasselgren 2020, sec. 4) describes it:

- outdoor: ~75 meshes on a backdrop, lit by Mitsuba's ``sunsky`` or a procedural HDR probe;
- indoor: one of the :data:`scene_gen.rooms.ROOM_TYPES` with ~50 meshes on the floor, tables and
  shelves, four area lights, one point light and an HDR probe seen through the openings;
- random materials (``scene_gen.materials``), random camera (fov 15–65°), thin-lens defocus with
  probability ``p_defocus`` focused on a random visible object (lens radius log-uniform), linear
  object motion with probability ``p_motion``, and for clips a smooth camera path;
- only what the scene needs: objects outside every frame's view frustum (motion sweep included) are
  dropped, triangle budgets follow the projected size, static scenes carry no velocities.

All randomness comes from ``np.random.SeedSequence([seed, kind_id])`` split into independent streams
(layout, materials, camera, motion, lens), so the same arguments give an identical spec in any process.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from scene_gen import cameras as cams
from scene_gen.config import ConfigError, SceneGenConfig
from scene_gen.spec import SCENE_KINDS, MaterialSpec, MeshSpec, ObjectSpec, SceneSpec, Transform

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
        from scene_gen import meshes
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


def scan_models(folder: str | None) -> list[str]:
    """Valid user models in ``folder`` (broken files are skipped with a warning by ``meshes.scan_model_folder``).

    Raises ConfigError naming the folder when none can be used."""
    if folder is None:
        return []
    from scene_gen import meshes
    found = _scan_cache.get(folder)
    if found is None:
        found = meshes.scan_model_folder(folder)
        _scan_cache[folder] = found
    if not found:
        raise ConfigError(f"scene_gen.model_folder {folder!r} holds no loadable OBJ/PLY/GLB/GLTF/STL model")
    return found


_scan_cache: dict[str, list[str]] = {}


# ---------------------------------------------------------------------------------------------
# the scene

def _check_args(seed, kind, num_frames, res) -> None:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ConfigError(f"seed must be an integer >= 0, got {seed!r}")
    if kind not in SCENE_KINDS:
        raise ConfigError(f"scene kind must be one of {SCENE_KINDS}, got {kind!r}")
    if isinstance(num_frames, bool) or not isinstance(num_frames, (int, np.integer)) or not 1 <= num_frames <= 100000:
        raise ConfigError(f"num_frames must be an integer in [1, 100000], got {num_frames!r}")
    if isinstance(res, bool) or not isinstance(res, (int, np.integer)) or not 1 <= res <= 65536:
        raise ConfigError(f"res must be an integer in [1, 65536] pixels, got {res!r}")


def sample_scene(seed: int, kind: str, *, num_frames: int = 1, res: int = 256,
                 config: SceneGenConfig | None = None) -> SceneSpec:
    """A random scene of ``kind`` (``indoor``/``outdoor``) for ``num_frames`` frames at ``res``² pixels.

    Pure function of its arguments (numpy only)."""
    _check_args(seed, kind, num_frames, res)
    cfg = config or SceneGenConfig()
    if not isinstance(cfg, SceneGenConfig):
        raise ConfigError(f"config must be a SceneGenConfig, got {type(cfg).__name__}")
    user_models = scan_models(cfg.model_folder)
    ss = np.random.SeedSequence([int(seed), SCENE_KINDS.index(kind)])
    r_flags, r_layout, r_cam, r_motion, r_lens, r_path = (np.random.default_rng(s) for s in ss.spawn(6))
    defocus = bool(r_flags.uniform() < cfg.p_defocus)
    motion = bool(r_flags.uniform() < cfg.p_motion)
    fov = cams.sample_fov(r_cam, cfg.fov_range)
    if kind == "indoor":
        from scene_gen import rooms
        lay = rooms.layout_indoor(r_layout, r_cam, cfg, fov, res, user_models)
    else:
        from scene_gen import outdoor
        lay = outdoor.layout_outdoor(r_layout, r_cam, cfg, fov, res, user_models)
    path = cams.camera_path(r_path, lay.origin, lay.target, num_frames, step=lay.camera_step, clamp=lay.clamp)
    frames = [cams.make_camera(o, t, fov) for o, t in path]
    objs: list[Placed] = lay.objects
    if cfg.material_palette > 0:
        _apply_palette(np.random.default_rng(ss.spawn(1)[0]), objs, cfg.material_palette)
    # motion: each movable object moves with probability p_object_motion in a scene with motion
    if motion:
        for o in objs:
            if o.movable and r_motion.uniform() < cfg.p_object_motion:
                o.velocity = cams.random_velocity(r_motion, o.radius, cfg.speed_range, planar=o.planar)
    # cull what no frame sees
    centers = np.array([o.transform.translate for o in objs], float).reshape(-1, 3)
    radii = np.array([o.radius for o in objs], float)
    vel = np.array([o.velocity or (0.0, 0.0, 0.0) for o in objs], float).reshape(-1, 3)
    vis = cams.visible_any_frame(frames, centers, radii, vel, (res, res), cfg.shutter if motion else 0.0)
    keep = np.array([o.keep for o in objs], bool) | vis
    # defocus: focus on a random visible content object
    if defocus:
        cand = [i for i, o in enumerate(objs) if not o.keep and vis[i]]
        if cand:
            i = cand[int(r_lens.integers(len(cand)))]
        else:
            i = None
        dists = []
        for f, cam in enumerate(frames):
            if i is None:
                d = float(np.linalg.norm(np.subtract(cam.target, cam.origin)))
            else:
                d = float(cams.to_camera(cam, centers[i] + vel[i] * f)[0, 2])
            dists.append(max(d, 0.1))
        aperture = cams.sample_aperture(r_lens, dists[0], cfg.aperture_range)
        frames = [cams.make_camera(c.origin, c.target, c.fov, aperture, d) for c, d in zip(frames, dists)]
    # triangle budgets from the largest projected radius over the frames
    from scene_gen.meshes import triangle_budget
    rpx = cams.max_projected_radius(frames, centers, radii, vel, (res, res))
    out = []
    for i, o in enumerate(objs):
        if not keep[i]:
            continue
        mesh = o.mesh
        if o.budget:
            b = triangle_budget(float(min(rpx[i], 1e6)), tris_per_px=cfg.tris_per_px, min=cfg.min_triangles,
                                max=cfg.max_triangles)
            mesh = MeshSpec(mesh.kind, mesh.params, mesh.seed, b, mesh.children)
        v = o.velocity if (motion and o.velocity is not None and any(x != 0 for x in o.velocity)) else None
        out.append(ObjectSpec(o.name, mesh, o.material, o.transform, velocity=v, emitter_radiance=o.emitter))
    return SceneSpec(kind=kind, seed=int(seed), objects=tuple(out), lights=tuple(lay.lights), cameras=tuple(frames),
                     shutter=float(cfg.shutter), max_depth=int(cfg.max_depth))


def _apply_palette(rng: np.random.Generator, objs: list, k: int) -> None:
    """Content objects (movable, not kept structure or furniture, not emitters) take one of ``k`` random
    materials."""
    from scene_gen.materials import random_material
    palette = [random_material(rng) for _ in range(k)]
    for o in objs:
        if o.movable and not o.keep and o.emitter is None:
            o.material = palette[int(rng.integers(k))]


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
        import colorsys
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
