"""Meshes for generated scenes: procedural shapes, decimation to a triangle budget, user models.

``build(spec)`` turns a :class:`scene_gen.spec.MeshSpec` into a :class:`MeshData`. It is a pure
function of the spec (same spec -> identical vertex/face bytes, in any process) and is cached per
process by the spec's JSON. Canonical meshes are centred at the origin and fit the cube
``[-1, 1]^3`` (largest half-extent 1, +Y is "up" for shapes with an axis); the object's
``Transform`` scales and places them. ``room`` meshes come from ``scene_gen.rooms`` as they are.

Shading data is derived the same way for every kind (``_finish``): vertices are split along sharp
edges (dihedral angle above ``crease_deg``, default 40) so boxes stay boxy and spheres stay smooth;
vertex normals are the corner-angle-weighted mean of the face normals of their smooth patch; UVs
are a box (six-axis) projection of the position, split along the projection seams.

Kinds (``spec.MESH_KINDS``) and their ``params`` (all optional unless stated):

=========  ===================================================================================
sphere     ``subdivisions`` (icosphere level, 0..6, default 3)
box        ``extents`` (3 floats, default [2, 2, 2])
cylinder   ``radius`` (1), ``height`` (2), ``sections`` (32)
capsule    ``radius`` (0.5), ``height`` (1, between cap centres), ``sections`` (24)
cone       ``radius`` (1), ``height`` (2), ``sections`` (32)
torus      ``major_radius`` (1), ``minor_radius`` (0.3), ``major_sections`` (48), ``minor_sections`` (24)
revolve    ``profile`` ([[r, y], ...], r >= 0; else random vase-like from the seed), ``sections`` (48)
extrude    ``outline`` ([[x, z], ...] star-shaped around the origin; else random from the seed),
           ``height`` (random), ``bevel`` (0 = none; fraction of the height, < 0.5)
blob       ``subdivisions`` (4), ``bumps`` (number of random bumps, 6), ``amplitude`` (0.35),
           ``smooth_steps`` (Taubin iterations, 10); shape from the seed
boolean    two ``children``; ``op`` in union|difference|intersection (default difference);
           second operand scaled by ``b_scale`` and moved by ``b_offset`` (random from the seed)
plane      ``resolution`` (grid cells per side, 1), ``bend`` (0..1: the back half, z < 0, curves up
           to height ``bend``, a photo-studio backdrop); lies on y = 0 facing +Y, not normalised
room       ``scene_gen.rooms.room_geometry(params)``, returned without normalisation
file       ``path`` (required: OBJ/PLY/GLB/GLTF/STL), ``up`` ('y' or 'z', default 'y')
=========  ===================================================================================

``spec.triangle_budget > 0`` decimates with pymeshlab's quadric edge collapse (topology, normals
and boundaries preserved) to at most that many triangles; :func:`triangle_budget` picks the budget
from an object's projected size.
"""
from __future__ import annotations

import dataclasses
import functools
import json
import logging
import math
import os
import warnings
from pathlib import Path

import numpy as np

from scene_gen import mesh_ops as ops, rooms
from scene_gen.mesh_ops import CREASE_DEG, MeshData
from scene_gen.errors import MeshError, SpecError
from scene_gen.profiles import random_outline, random_revolve_profile
from scene_gen.spec import MESH_KINDS, MeshSpec


PYMESHLAB_KINDS = ("blob", "boolean")     # the kinds pymeshlab makes (smoothing, remeshing); decimation is its too


def needs_pymeshlab(spec: MeshSpec) -> bool:
    """Whether building ``spec`` needs pymeshlab: a kind of :data:`PYMESHLAB_KINDS` in its tree, or a
    triangle budget (decimation)."""
    return spec.kind in PYMESHLAB_KINDS or bool(spec.triangle_budget) or any(needs_pymeshlab(c) for c in spec.children)


def _pymeshlab():
    """pymeshlab, refusing a first import from a non-main thread: its Qt plugins then corrupt the heap
    (glibc's ``malloc_consolidate(): unaligned fastbin chunk detected``). Dask workers import it in
    their main thread through the ``pipeline.worker_init`` preload. A machine without it gets a
    MeshError that names the setting that leaves its meshes out."""
    import importlib.util
    import sys
    import threading
    if "pymeshlab" not in sys.modules and importlib.util.find_spec("pymeshlab") is None:
        raise MeshError("pymeshlab is not installed here, and blob and boolean meshes and decimation need it: "
                        "install it, or set scene_gen.pymeshlab: false to leave those meshes out")
    if "pymeshlab" not in sys.modules and threading.current_thread() is not threading.main_thread():
        raise MeshError("pymeshlab must first be imported in the main thread (it corrupts the heap otherwise): "
                        "`import pymeshlab` there first, or start Dask workers with "
                        "`--preload pipeline.worker_init`")
    import pymeshlab
    return pymeshlab

log = logging.getLogger(__name__)

MODEL_SUFFIXES = (".obj", ".ply", ".glb", ".gltf", ".stl")
CACHE_SIZE = 512


class BrokenModelWarning(UserWarning):
    """A user model file could not be loaded and was skipped (the message names the file)."""


# --------------------------------------------------------------------------------------------
# public API

def build(spec: MeshSpec) -> MeshData:
    """The mesh of ``spec`` (deterministic, cached per process by the spec's JSON).

    Raises ``SpecError`` for parameters out of range (naming ``mesh.params.<name>``) and
    ``MeshError`` when a mesh cannot be made (naming the kind, or the file for ``file``).
    """
    if not isinstance(spec, MeshSpec):
        raise SpecError(f"meshes.build expects a MeshSpec, got {type(spec).__name__}")
    return _build_cached(_spec_key(spec))


def decimate(mesh: MeshData, max_triangles: int, *, crease_deg: float = CREASE_DEG) -> MeshData:
    """``mesh`` reduced to at most ``max_triangles`` triangles by quadric edge collapse.

    Coincident vertices are merged first (seams do not block collapses); normals and UVs are
    derived again as in :func:`build`. Meshes already within budget are returned unchanged.
    """
    if not isinstance(max_triangles, (int, np.integer)) or max_triangles < 1:
        raise SpecError(f"max_triangles must be an integer >= 1, got {max_triangles!r}")
    if mesh.num_triangles <= max_triangles:
        return mesh
    v, f = ops.merge(mesh.vertices.astype(np.float64), mesh.faces.astype(np.int64))
    v, f = _decimate_vf(v, f, int(max_triangles))
    return ops.finish(v, f, crease_deg=crease_deg)


def triangle_budget(projected_radius_px: float, *, tris_per_px: float = 0.5, min: int = 32,
                    max: int = 20000) -> int:
    """Triangle budget for an object whose bounding sphere projects to a disc of that radius (px).

    ``tris_per_px`` triangles per pixel of the disc's area (pi r^2), clamped to [min, max];
    non-decreasing in the radius. A radius of 0 (or an object behind the camera) gets ``min``.
    """
    r = float(projected_radius_px)
    if not math.isfinite(r) or r < 0:
        raise SpecError(f"projected_radius_px must be a finite number >= 0, got {projected_radius_px!r}")
    if not (tris_per_px > 0 and math.isfinite(tris_per_px)):
        raise SpecError(f"tris_per_px must be > 0, got {tris_per_px!r}")
    if not (1 <= min <= max):
        raise SpecError(f"triangle budget bounds need 1 <= min <= max, got min={min}, max={max}")
    n = tris_per_px * math.pi * r * r
    if n >= max:
        return int(max)
    return int(np.clip(math.ceil(n), min, max))


def scan_model_folder(path: str | os.PathLike) -> list[str]:
    """Loadable user models (OBJ/PLY/GLB/GLTF/STL) under ``path``, recursively, sorted.

    Every file is loaded once; a broken one (unreadable, no triangles, non-finite or flat) is
    skipped with a :class:`BrokenModelWarning` naming it. A missing folder raises ``MeshError``.
    """
    root = Path(path)
    if not root.is_dir():
        raise MeshError(f"model folder {str(root)!r} does not exist or is not a folder")
    good = []
    for p in sorted(root.rglob("*")):
        if not p.is_file() or p.suffix.lower() not in MODEL_SUFFIXES:
            continue
        try:
            _load_user_file(str(p), _file_stamp(str(p)))
        except MeshError as e:
            msg = f"skipping broken model file {str(p)!r}: {e}"
            log.info(msg)
            warnings.warn(msg, BrokenModelWarning, stacklevel=2)
            continue
        good.append(str(p))
    return good


def cache_clear() -> None:
    """Empty the per-process mesh caches (tests, long-lived workers that load new files)."""
    _build_cached.cache_clear()
    _geometry_cached.cache_clear()
    _load_user_file.cache_clear()


# --------------------------------------------------------------------------------------------
# build pipeline: geometry (canonical, float64) -> decimation -> shading data

def _spec_key(spec: MeshSpec) -> str:
    return json.dumps(spec.to_dict(), sort_keys=True, allow_nan=False, separators=(",", ":"))


@functools.lru_cache(maxsize=CACHE_SIZE)
def _build_cached(key: str) -> MeshData:
    spec = MeshSpec.from_dict(json.loads(key))
    if spec.kind == "room":
        mesh = _room(spec)
        if spec.triangle_budget and mesh.num_triangles > spec.triangle_budget:
            mesh = decimate(mesh, spec.triangle_budget)
        return mesh
    v, f = _geometry(_coarsest_for_budget(spec)) if spec.triangle_budget else _geometry(spec)
    if spec.triangle_budget and len(f) > spec.triangle_budget:
        v, f = _decimate_vf(v, f, spec.triangle_budget)
    crease = _param(spec, "crease_deg", CREASE_DEG, 0.0, 180.0)
    return ops.finish(v, f, crease_deg=crease)


def _coarsest_for_budget(spec: MeshSpec) -> MeshSpec:
    """The spec with its tessellation lowered towards its triangle budget (decimating a smaller
    input is several times faster), where the resolution was left to the default.

    Icosphere-based kinds (sphere, blob) take the lowest subdivision level with at least 1.5x the
    budget (never below 2 for blobs, whose bumps need the samples); tori scale both section counts.
    """
    budget, p = spec.triangle_budget, spec.params
    if spec.kind in ("sphere", "blob") and "subdivisions" not in p:
        default = 3 if spec.kind == "sphere" else 4
        level = next((s for s in range(default + 1) if 20 * 4 ** s >= 1.5 * budget), default)
        level = max(level, 2 if spec.kind == "blob" else 1)
        if level < default:
            return dataclasses.replace(spec, params={**p, "subdivisions": level})
    if spec.kind == "torus" and "major_sections" not in p and "minor_sections" not in p:
        f = math.sqrt(1.5 * budget / (2 * 48 * 24))
        if f < 1:
            return dataclasses.replace(spec, params={**p, "major_sections": max(8, math.ceil(48 * f)),
                                                     "minor_sections": max(6, math.ceil(24 * f))})
    return spec


def _geometry(spec: MeshSpec) -> tuple[np.ndarray, np.ndarray]:
    """Canonical geometry (float64 N×3, int64 M×3, read-only, cached), merged vertices, outward
    winding; the triangle budget does not enter (decimated variants share it)."""
    return _geometry_cached(_spec_key(dataclasses.replace(spec, triangle_budget=0)))


@functools.lru_cache(maxsize=CACHE_SIZE)
def _geometry_cached(key: str) -> tuple[np.ndarray, np.ndarray]:
    spec = MeshSpec.from_dict(json.loads(key))
    maker = _MAKERS.get(spec.kind)
    if maker is None:  # pragma: no cover - MeshSpec validates the kind
        raise MeshError(f"mesh kind {spec.kind!r} has no builder (known: {MESH_KINDS})")
    try:
        v, f = maker(spec)
    except (MeshError, SpecError):
        raise
    except Exception as e:  # a library failure inside a builder
        raise MeshError(f"building mesh kind {spec.kind!r} failed: {type(e).__name__}: {e}") from e
    v, f = ops.clean(*ops.merge(np.asarray(v, np.float64), np.asarray(f, np.int64)))
    if len(f) == 0:
        raise MeshError(f"mesh kind {spec.kind!r} produced no triangles (params {dict(spec.params)})")
    if spec.kind != "plane":
        v = ops.normalise(v)
        if _signed_volume(v, f) < 0:     # closed meshes wind counter-clockwise seen from outside
            f = f[:, ::-1].copy()
    v.setflags(write=False)
    f.setflags(write=False)
    return v, f


def _signed_volume(v: np.ndarray, f: np.ndarray) -> float:
    t = v[f]
    return float(np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6.0)


def _rng(spec: MeshSpec) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([spec.seed, MESH_KINDS.index(spec.kind)]))


def _param(spec: MeshSpec, name: str, default, lo: float, hi: float, *, integer: bool = False):
    v = spec.params.get(name, default)
    ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
    if integer:
        ok = ok and float(v).is_integer()
    if not ok or not (lo <= v <= hi):
        kind = "an integer" if integer else "a number"
        raise SpecError(f"mesh.params.{name} ({spec.kind}) must be {kind} in [{lo}, {hi}], got {v!r}")
    return int(v) if integer else float(v)


def _points(spec: MeshSpec, name: str, cols: int, min_rows: int) -> np.ndarray | None:
    v = spec.params.get(name)
    if v is None:
        return None
    try:
        a = np.asarray(v, np.float64)
    except (TypeError, ValueError):
        a = np.zeros((0,))
    if a.ndim != 2 or a.shape[1] != cols or len(a) < min_rows or not np.isfinite(a).all():
        raise SpecError(f"mesh.params.{name} ({spec.kind}) must be a list of >= {min_rows} "
                        f"finite [{', '.join('xyz'[:cols])}] points, got {v!r}")
    return a


def _z_up_to_y_up(v: np.ndarray) -> np.ndarray:
    """Rotate -90° about x: the old +Z axis becomes +Y (a proper rotation keeps the winding)."""
    return np.stack([v[:, 0], v[:, 2], -v[:, 1]], axis=1)


# --- primitives ---------------------------------------------------------------------------

def _sphere(spec):
    import trimesh
    m = trimesh.creation.icosphere(subdivisions=_param(spec, "subdivisions", 3, 0, 6, integer=True))
    return m.vertices, m.faces


def _box(spec):
    import trimesh
    ext = np.asarray(spec.params.get("extents", (2.0, 2.0, 2.0)), np.float64)
    if ext.shape != (3,) or not np.isfinite(ext).all() or (ext <= 0).any():
        raise SpecError(f"mesh.params.extents (box) must be 3 numbers > 0, got {spec.params.get('extents')!r}")
    m = trimesh.creation.box(extents=ext)
    return m.vertices, m.faces


def _cylinder(spec):
    import trimesh
    m = trimesh.creation.cylinder(radius=_param(spec, "radius", 1.0, 1e-3, 1e3),
                                  height=_param(spec, "height", 2.0, 1e-3, 1e3),
                                  sections=_param(spec, "sections", 32, 3, 512, integer=True))
    return _z_up_to_y_up(m.vertices), m.faces


def _capsule(spec):
    import trimesh
    n = _param(spec, "sections", 24, 4, 256, integer=True)
    m = trimesh.creation.capsule(height=_param(spec, "height", 1.0, 0.0, 1e3),
                                 radius=_param(spec, "radius", 0.5, 1e-3, 1e3), count=[n, n])
    return _z_up_to_y_up(m.vertices), m.faces


def _cone(spec):
    import trimesh
    m = trimesh.creation.cone(radius=_param(spec, "radius", 1.0, 1e-3, 1e3),
                              height=_param(spec, "height", 2.0, 1e-3, 1e3),
                              sections=_param(spec, "sections", 32, 3, 512, integer=True))
    return _z_up_to_y_up(m.vertices), m.faces


def _torus(spec):
    import trimesh
    R = _param(spec, "major_radius", 1.0, 1e-3, 1e3)
    r = _param(spec, "minor_radius", 0.3, 1e-3, 1e3)
    if r >= R:
        raise SpecError(f"mesh.params.minor_radius (torus) must be < major_radius {R}, got {r}")
    m = trimesh.creation.torus(R, r, major_sections=_param(spec, "major_sections", 48, 3, 512, integer=True),
                               minor_sections=_param(spec, "minor_sections", 24, 3, 512, integer=True))
    return _z_up_to_y_up(m.vertices), m.faces


def _plane(spec):
    n = _param(spec, "resolution", 1, 1, 512, integer=True)
    bend = _param(spec, "bend", 0.0, 0.0, 1.0)
    if bend > 0:
        n = np.maximum(n, 16)
    t = np.linspace(-1.0, 1.0, n + 1)
    x, z = np.meshgrid(t, t, indexing="xy")          # x varies along columns, z along rows
    y = bend * np.maximum(0.0, -z) ** 2
    v = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    i = np.arange(n)[None, :] + (n + 1) * np.arange(n)[:, None]   # lower-left corner per cell
    a, b, c, d = i, i + 1, i + n + 1, i + n + 2      # a=(x0,z0) b=(x1,z0) c=(x0,z1) d=(x1,z1)
    # counter-clockwise seen from +Y: (a, c, b) and (b, c, d)
    f = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    return v, f


_MAKERS = {
    "sphere": _sphere, "box": _box, "cylinder": _cylinder, "capsule": _capsule, "cone": _cone,
    "torus": _torus, "plane": _plane,
}


# --- profiles, outlines, blobs, booleans ----------------------------------------------------

def _revolve(spec):
    import trimesh
    prof = _points(spec, "profile", 2, 2)
    if prof is None:
        prof = random_revolve_profile(_rng(spec))
    elif (prof[:, 0] < 0).any():
        raise SpecError("mesh.params.profile (revolve) radii (first column) must be >= 0")
    else:   # close the surface on the axis at both ends
        if prof[0, 0] > 0:
            prof = np.concatenate([[[0.0, prof[0, 1]]], prof])
        if prof[-1, 0] > 0:
            prof = np.concatenate([prof, [[0.0, prof[-1, 1]]]])
    n = _param(spec, "sections", 48, 3, 512, integer=True)
    m = trimesh.creation.revolve(prof, sections=n)
    return _z_up_to_y_up(m.vertices), m.faces


def _extrude(spec):
    rng = _rng(spec)
    outline = _points(spec, "outline", 2, 3)
    if outline is None:
        outline = random_outline(rng)
    height = _param(spec, "height", float(rng.uniform(0.15, 1.5)), 1e-3, 1e3)
    bevel = _param(spec, "bevel", 0.0, 0.0, 0.49) * height
    outline = ops.dedupe_ring(outline)
    if len(outline) < 3 or abs(ops.polygon_area(outline)) < 1e-9 * max(np.ptp(outline, axis=0).max(), 1e-30) ** 2:
        raise SpecError("mesh.params.outline (extrude) must enclose a non-zero area")
    if ops.polygon_area(outline) < 0:        # counter-clockwise in (x, z)
        outline = outline[::-1].copy()
    if not ops.is_simple(outline):
        raise SpecError("mesh.params.outline (extrude) must be a simple polygon (its edges cross)")
    cap = ops.fan_or_earclip(outline)        # (T, 3) counter-clockwise triangles of the outline
    k = len(outline)
    centre = ops.polygon_centroid(outline)
    if bevel > 0:
        reach = float(np.linalg.norm(outline - centre, axis=1).max())
        s_in = max(1.0 - bevel / reach, 0.5)
        layers = [(-height / 2, s_in), (-height / 2 + bevel, 1.0), (height / 2 - bevel, 1.0), (height / 2, s_in)]
    else:
        layers = [(-height / 2, 1.0), (height / 2, 1.0)]
    ring = []
    for y, sc in layers:                  # insets scale toward the centroid (keeps the polygon simple)
        p = centre + (outline - centre) * sc
        ring.append(np.stack([p[:, 0], np.full(k, y), p[:, 1]], axis=1))
    v = np.concatenate(ring)
    i = np.arange(k)
    j = (i + 1) % k
    faces = []
    for L in range(len(layers) - 1):
        a, b, c, d = L * k + i, L * k + j, (L + 1) * k + i, (L + 1) * k + j
        faces += [np.stack([a, d, b], 1), np.stack([a, c, d], 1)]
    top = (len(layers) - 1) * k
    faces += [cap, top + cap[:, ::-1]]    # bottom faces -y, top faces +y
    return v, np.concatenate(faces)


def _blob(spec):
    pymeshlab = _pymeshlab()
    import trimesh
    rng = _rng(spec)
    sub = _param(spec, "subdivisions", 4, 1, 6, integer=True)
    bumps = _param(spec, "bumps", 6, 0, 64, integer=True)
    amp = _param(spec, "amplitude", 0.35, 0.0, 1.0)
    steps = _param(spec, "smooth_steps", 10, 0, 200, integer=True)
    ico = trimesh.creation.icosphere(subdivisions=sub)
    d = np.asarray(ico.vertices, np.float64)
    r = np.ones(len(d))
    for _ in range(bumps):       # Gaussian bumps (and dents) on the sphere
        c = rng.normal(size=3)
        c /= np.linalg.norm(c)
        kappa = rng.uniform(2.0, 12.0)
        r += amp * rng.uniform(-0.6, 1.0) * np.exp(kappa * (d @ c - 1.0))
    for _ in range(3):           # low-frequency waves
        e = rng.normal(size=3)
        e /= np.linalg.norm(e)
        r += 0.3 * amp * np.sin(rng.uniform(1.0, 4.0) * (d @ e) + rng.uniform(0, 2 * np.pi))
    v = d * np.clip(r, 0.35, None)[:, None]
    f = np.asarray(ico.faces)
    if steps:
        ms = pymeshlab.MeshSet()
        ms.add_mesh(pymeshlab.Mesh(vertex_matrix=v, face_matrix=f.astype(np.int32)))
        ms.apply_coord_taubin_smoothing(stepsmoothnum=steps)
        v = ms.current_mesh().vertex_matrix().astype(np.float64)
    return v, f


BOOLEAN_OPS = ("union", "difference", "intersection")


def _boolean(spec):
    pymeshlab = _pymeshlab()
    import trimesh
    rng = _rng(spec)
    op = spec.params.get("op", "difference")
    if op not in BOOLEAN_OPS:
        raise SpecError(f"mesh.params.op (boolean) must be one of {BOOLEAN_OPS}, got {op!r}")
    for c in spec.children:
        if c.kind in ("plane", "room"):
            raise SpecError(f"boolean children must be closed solids, got {c.kind!r}")
    # defaults: a smaller second operand that overlaps the first (intersections: a larger one
    # shifted further, so that neither operand simply contains the other)
    lo, hi = ((0.9, 1.3), (0.4, 0.8)) if op == "intersection" else ((0.4, 0.9), (0.2, 0.8))
    scale = _param(spec, "b_scale", float(rng.uniform(*lo)), 1e-3, 10.0)
    direction = rng.normal(size=3)
    offset = direction / np.linalg.norm(direction) * rng.uniform(*hi)
    off = spec.params.get("b_offset", offset.tolist())
    off = np.asarray(off, np.float64)
    if off.shape != (3,) or not np.isfinite(off).all():
        raise SpecError(f"mesh.params.b_offset (boolean) must be 3 finite numbers, got {spec.params.get('b_offset')!r}")
    (va, fa), (vb, fb) = (_geometry(c) for c in spec.children)
    a = trimesh.Trimesh(va, fa, process=False)
    b = trimesh.Trimesh(vb * scale + off, fb, process=False)
    fn = {"union": trimesh.boolean.union, "difference": trimesh.boolean.difference,
          "intersection": trimesh.boolean.intersection}[op]
    out = fn([a, b], engine="manifold", check_volume=False)
    v, f = np.asarray(out.vertices, np.float64), np.asarray(out.faces, np.int64)
    if len(f) == 0:
        raise MeshError(f"boolean {op} of {spec.children[0].kind} and {spec.children[1].kind} is empty")
    if spec.params.get("remesh", False):   # isotropic remeshing evens out the slivers of the cut
        ms = pymeshlab.MeshSet()
        ms.add_mesh(pymeshlab.Mesh(vertex_matrix=v, face_matrix=f.astype(np.int32)))
        ms.meshing_isotropic_explicit_remeshing(iterations=3, targetlen=pymeshlab.PercentageValue(2.5))
        m = ms.current_mesh()
        v, f = m.vertex_matrix().astype(np.float64), m.face_matrix().astype(np.int64)
    return v, f


_MAKERS.update({"revolve": _revolve, "extrude": _extrude, "blob": _blob, "boolean": _boolean})


def _room(spec: MeshSpec) -> MeshData:
    v, f, n, uv = rooms.room_geometry(dict(spec.params))
    return MeshData(vertices=v, faces=f, normals=n, uv=uv)


def _decimate_vf(v: np.ndarray, f: np.ndarray, budget: int) -> tuple[np.ndarray, np.ndarray]:
    """Quadric edge collapse to <= budget faces (pymeshlab); falls back to unconstrained topology."""
    pymeshlab = _pymeshlab()
    if len(f) <= budget:
        return v, f
    target = budget
    for attempt in range(4):
        ms = pymeshlab.MeshSet()
        ms.add_mesh(pymeshlab.Mesh(vertex_matrix=v, face_matrix=f.astype(np.int32)))
        ms.meshing_decimation_quadric_edge_collapse(
            targetfacenum=int(target), qualitythr=0.3, preserveboundary=True, boundaryweight=2.0,
            preservenormal=True, preservetopology=attempt < 2, optimalplacement=True,
            planarquadric=True, autoclean=True)
        m = ms.current_mesh()
        nv, nf = m.vertex_matrix().astype(np.float64), m.face_matrix().astype(np.int64)
        nv, nf = ops.clean(nv, nf)
        if len(nf) <= budget and len(nf) > 0:
            return nv, nf
        target = max(1, int(target * budget / max(len(nf), 1) * 0.9))
    raise MeshError(f"decimation could not reach {budget} triangles (from {len(f)}; last {len(nf)})")


# --------------------------------------------------------------------------------------------
# user models

def _file_stamp(path: str) -> tuple[int, int]:
    try:
        st = os.stat(path)
    except OSError as e:
        raise MeshError(f"model file {path!r} cannot be read: {e.strerror}") from e
    return st.st_mtime_ns, st.st_size


@functools.lru_cache(maxsize=64)
def _load_user_file(path: str, stamp: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(vertices float64 N×3, faces int64 M×3) of a model file, scene graphs flattened."""
    import trimesh
    if Path(path).suffix.lower() not in MODEL_SUFFIXES:
        raise MeshError(f"model file {path!r}: unsupported format (use {', '.join(MODEL_SUFFIXES)})")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            loaded = trimesh.load(path, process=False)
    except Exception as e:
        raise MeshError(f"model file {path!r} cannot be loaded: {type(e).__name__}: {e}") from e
    if isinstance(loaded, trimesh.Scene):
        try:
            geoms = loaded.dump(concatenate=False)
        except Exception as e:
            raise MeshError(f"model file {path!r}: its scene graph cannot be flattened: {e}") from e
    else:
        geoms = [loaded]
    parts = [g for g in geoms if isinstance(g, trimesh.Trimesh) and len(g.faces) > 0]
    if not parts:
        raise MeshError(f"model file {path!r} holds no triangles")
    vs, fs, off = [], [], 0
    for g in parts:
        vs.append(np.asarray(g.vertices, np.float64))
        fs.append(np.asarray(g.faces, np.int64) + off)
        off += len(g.vertices)
    v, f = np.concatenate(vs), np.concatenate(fs)
    if not np.isfinite(v).all():
        raise MeshError(f"model file {path!r} has non-finite vertex coordinates")
    if f.min() < 0 or f.max() >= len(v):
        raise MeshError(f"model file {path!r} has faces that index missing vertices")
    v, f = ops.merge(v, f)
    v, f = ops.clean(v, f)
    if len(f) == 0 or float(np.ptp(v, axis=0).max()) <= 0:
        raise MeshError(f"model file {path!r} has only degenerate triangles")
    v.setflags(write=False)
    f.setflags(write=False)
    return v, f


def _file(spec):
    path = spec.params.get("path")
    if not isinstance(path, str) or not path:
        raise SpecError("mesh.params.path (file) must name a model file")
    up = spec.params.get("up", "y")
    if up not in ("y", "z"):
        raise SpecError(f"mesh.params.up (file) must be 'y' or 'z', got {up!r}")
    v, f = _load_user_file(path, _file_stamp(path))
    v = v.copy()
    if up == "z":
        v = _z_up_to_y_up(v)
    return v, f.copy()


_MAKERS["file"] = _file
