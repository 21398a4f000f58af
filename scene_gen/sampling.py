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

The scene kinds are the registered scene families (``scene_gen.families``; a family's layout function
places the room or backdrop, the objects and the lights). All randomness comes from
``np.random.SeedSequence([seed, family.seed_index])`` split into independent streams (layout,
materials, camera, motion, lens), so the same arguments give an identical spec in any process.
"""
from __future__ import annotations

import numpy as np

from scene_gen import cameras as cams
from scene_gen import meshes
from scene_gen.config import ConfigError, SceneGenConfig
from scene_gen.families import family_names, get_family
from scene_gen.layout import Layout, Placed
from scene_gen.materials import random_material
from scene_gen.meshes import triangle_budget
from scene_gen.phenomena import add_phenomena
from scene_gen.spec import MeshSpec, ObjectSpec, SceneSpec

__all__ = ["sample_scene", "scan_models", "Layout", "Placed"]

def scan_models(folder: str | None) -> list[str]:
    """Valid user models in ``folder`` (broken files are skipped with a warning by ``meshes.scan_model_folder``).

    Raises ConfigError naming the folder when none can be used."""
    if folder is None:
        return []
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
    if kind not in family_names():
        raise ConfigError(f"scene kind must be one of {family_names()}, got {kind!r}")
    if isinstance(num_frames, bool) or not isinstance(num_frames, (int, np.integer)) or not 1 <= num_frames <= 100000:
        raise ConfigError(f"num_frames must be an integer in [1, 100000], got {num_frames!r}")
    if isinstance(res, bool) or not isinstance(res, (int, np.integer)) or not 1 <= res <= 65536:
        raise ConfigError(f"res must be an integer in [1, 65536] pixels, got {res!r}")


def sample_scene(seed: int, kind: str, *, num_frames: int = 1, res: int = 256,
                 config: SceneGenConfig | None = None) -> SceneSpec:
    """A random scene of ``kind`` (a scene family: ``indoor``, ``outdoor``, ...) for ``num_frames`` frames at ``res``² pixels.

    Pure function of its arguments (numpy only)."""
    _check_args(seed, kind, num_frames, res)
    cfg = config or SceneGenConfig()
    if not isinstance(cfg, SceneGenConfig):
        raise ConfigError(f"config must be a SceneGenConfig, got {type(cfg).__name__}")
    user_models = scan_models(cfg.model_folder)
    family = get_family(kind)
    ss = np.random.SeedSequence([int(seed), family.seed_index])
    r_flags, r_layout, r_cam, r_motion, r_lens, r_path = (np.random.default_rng(s) for s in ss.spawn(6))
    defocus = bool(r_flags.uniform() < cfg.p_defocus)
    motion = bool(r_flags.uniform() < cfg.p_motion)
    fov = cams.sample_fov(r_cam, cfg.fov_range)
    lay: Layout = family.layout(r_layout, r_cam, cfg, fov, res, user_models)
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
    if defocus:
        frames = _focus(frames, objs, vis, centers, vel, r_lens, cfg)
    rpx = cams.max_projected_radius(frames, centers, radii, vel, (res, res))
    out = [_object_spec(o, rpx[i], motion, cfg) for i, o in enumerate(objs)
           if keep[i] and (cfg.pymeshlab or not meshes.needs_pymeshlab(o.mesh))]
    spec = SceneSpec(kind=kind, seed=int(seed), objects=tuple(out), lights=tuple(lay.lights), cameras=tuple(frames),
                     shutter=float(cfg.shutter), max_depth=int(cfg.max_depth))
    return add_phenomena(spec, cfg, family.seed_index, res)


def _focus(frames: list, objs: list, vis: np.ndarray, centers: np.ndarray, vel: np.ndarray,
           r_lens: np.random.Generator, cfg: SceneGenConfig) -> list:
    """The frames' cameras with a thin lens focused on a random visible content object (its distance in
    each frame; the target's distance when none is visible) and one aperture for the clip."""
    cand = [i for i, o in enumerate(objs) if not o.keep and vis[i]]
    i = cand[int(r_lens.integers(len(cand)))] if cand else None
    dists = []
    for f, cam in enumerate(frames):
        if i is None:
            d = float(np.linalg.norm(np.subtract(cam.target, cam.origin)))
        else:
            d = float(cams.to_camera(cam, centers[i] + vel[i] * f)[0, 2])
        dists.append(max(d, 0.1))
    aperture = cams.sample_aperture(r_lens, dists[0], cfg.aperture_range)
    return [cams.make_camera(c.origin, c.target, c.fov, aperture, d) for c, d in zip(frames, dists)]


def _object_spec(o: Placed, rpx: float, motion: bool, cfg: SceneGenConfig) -> ObjectSpec:
    """A placed object as the SceneSpec holds it: its mesh's triangle budget from its largest projected
    radius over the frames (``rpx``, pixels), its velocity in a scene with motion."""
    mesh = o.mesh
    if o.budget and cfg.pymeshlab:
        b = triangle_budget(float(min(rpx, 1e6)), tris_per_px=cfg.tris_per_px, min=cfg.min_triangles,
                            max=cfg.max_triangles)
        mesh = MeshSpec(mesh.kind, mesh.params, mesh.seed, b, mesh.children)
    v = o.velocity if (motion and o.velocity is not None and any(x != 0 for x in o.velocity)) else None
    return ObjectSpec(o.name, mesh, o.material, o.transform, velocity=v, emitter_radiance=o.emitter)


def _apply_palette(rng: np.random.Generator, objs: list, k: int) -> None:
    """Content objects (movable, not kept structure or furniture, not emitters) take one of ``k`` random
    materials."""
    palette = [random_material(rng) for _ in range(k)]
    for o in objs:
        if o.movable and not o.keep and o.emitter is None:
            o.material = palette[int(rng.integers(k))]
