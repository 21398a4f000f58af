"""SceneSpec → Mitsuba scene dictionary. The only module that speaks Mitsuba's dict syntax.

Conventions (shared with the renderer):
- Each object is a shape under its ``name`` key, so ``shape.id() == object.name``; with ``merge=True``
  static objects sharing a material are one shape ``merged-<k>`` (:func:`shape_groups` says which
  objects each shape holds) and identical materials share one BSDF instance. Meshes are baked
  in world space (scale, rotate XYZ-Euler in degrees, translate, plus ``velocity * tau`` for moving
  objects) and handed to Mitsuba as ``mi.Mesh`` objects; nothing touches the disk.
- ``tau`` is time in frames (see ``scene_gen.spec``); by default the start of the frame's exposure.
- Cameras: ``perspective`` without defocus, ``thinlens`` with it; ``fov`` on the x axis (Mitsuba's
  default ``fov_axis``); the pixel filter of the render settings (``box``: a pixel is the plain mean of
  its samples; ``gaussian``: Mitsuba's, with the border sampled: :func:`film_dict`).
- Integrator: ``path`` with ``max_depth = spec.max_depth + 1`` (``spec.max_depth`` counts bounces)
  and Russian roulette off (``rr_depth`` past ``max_depth``), as in the layer paper.
- Roughness in a MaterialSpec is perceptual; microfacet ``alpha = roughness ** 2``.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from scene_gen import meshes, projection
from scene_gen.cases import nonfinite_expected, scene_hook
from scene_gen.errors import SpecError
from scene_gen.probes import make_probe
from scene_gen.spec import CameraSpec, LightSpec, MaterialSpec, ObjectSpec, SceneSpec, Transform
from scene_gen.textures import make_texture
from core.variant import mitsuba

TEXTURE_SIZE = 256
PROBE_HEIGHT = 256
NEAR_CLIP, FAR_CLIP = projection.NEAR, projection.FAR     # the sensor's clip planes


def _mi():
    return mitsuba()


# ---------------------------------------------------------------------------------------------
# geometry
def rotation_matrix(angles_deg) -> np.ndarray:
    """R = Rz @ Ry @ Rx for XYZ Euler angles in degrees (x applied first)."""
    ax, ay, az = (math.radians(a) for a in angles_deg)
    cx, sx, cy, sy, cz, sz = math.cos(ax), math.sin(ax), math.cos(ay), math.sin(ay), math.cos(az), math.sin(az)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


def object_matrix(t: Transform) -> np.ndarray:
    """4x4 object-to-world matrix (float64) of a Transform at rest (no motion)."""
    m = np.eye(4)
    m[:3, :3] = rotation_matrix(t.rotate) @ np.diag(t.scale)
    m[:3, 3] = t.translate
    return m


def offset_at(obj: ObjectSpec, tau: float) -> np.ndarray:
    """World-space displacement of a moving object at time ``tau`` (frames)."""
    if not obj.moving:
        return np.zeros(3)
    return np.asarray(obj.velocity, np.float64) * float(tau)


def world_mesh(obj: ObjectSpec, tau: float = 0.0):
    """(vertices float32 N×3, faces uint32 M×3, normals float32 N×3 | None, uv float32 N×2 | None) in world space."""
    md = meshes.build(obj.mesh)
    m = object_matrix(obj.transform)
    v = md.vertices.astype(np.float64) @ m[:3, :3].T + m[:3, 3] + offset_at(obj, tau)
    n = None
    if md.normals is not None:
        nt = np.linalg.inv(m[:3, :3]).T
        n = md.normals.astype(np.float64) @ nt.T
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        n = n.astype(np.float32)
    return v.astype(np.float32), md.faces.astype(np.uint32), n, md.uv


def _mesh_object(mi, obj: ObjectSpec, tau: float, bsdf, emitter):
    v, f, n, uv = world_mesh(obj, tau)
    return _make_mesh(mi, obj.name, v, f, n, uv, bsdf, emitter)


def _make_mesh(mi, name: str, v, f, n, uv, bsdf, emitter):
    props = mi.Properties()
    props["bsdf"] = bsdf
    if emitter is not None:
        props["emitter"] = emitter
    mesh = mi.Mesh(name, len(v), len(f), props=props, has_vertex_normals=n is not None,
                   has_vertex_texcoords=uv is not None)
    p = mi.traverse(mesh)
    p["vertex_positions"] = mi.Float(v.ravel())
    p["faces"] = mi.UInt32(f.ravel())
    if n is not None:
        p["vertex_normals"] = mi.Float(n.ravel())
    if uv is not None:
        p["vertex_texcoords"] = mi.Float(np.asarray(uv, np.float32).ravel())
    p.update()
    return mesh


# ---------------------------------------------------------------------------------------------
# materials
def _rgb(c) -> dict:
    return {"type": "rgb", "value": [float(x) for x in c]}


def _base(mi, mat: MaterialSpec):
    """The base/diffuse reflectance slot: a bitmap texture when the material has one."""
    if mat.texture is None:
        return _rgb(mat.base_color)
    tex = make_texture(mat.texture, TEXTURE_SIZE)
    s = float(mat.texture.uv_scale)
    return {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(tex)), "raw": True,
            "filter_type": "bilinear", "wrap_mode": "repeat", "to_uv": mi.ScalarTransform4f().scale([s, s, 1.0])}


def bsdf_dict(mat: MaterialSpec, mi=None) -> dict:
    """Mitsuba BSDF dict of a MaterialSpec (two-sided where the BSDF is opaque)."""
    mi = mi or _mi()
    p = mat.params
    alpha = max(mat.roughness ** 2, 1e-3)
    k = mat.kind
    if k == "diffuse":
        d = {"type": "diffuse", "reflectance": _base(mi, mat)}
    elif k in ("conductor", "roughconductor"):
        d = {"type": k, "material": p.get("material", "none"), "specular_reflectance": _rgb(mat.specular_color)}
        if k == "roughconductor":
            d.update(distribution="ggx", alpha=alpha)
    elif k in ("dielectric", "roughdielectric", "thindielectric"):
        d = {"type": k, "int_ior": float(p.get("int_ior", 1.5)), "ext_ior": 1.0,
             "specular_transmittance": _rgb(p.get("transmittance", (1.0, 1.0, 1.0)))}
        if k == "roughdielectric":
            d.update(distribution="ggx", alpha=alpha)
        return d  # dielectrics are two-sided by nature
    elif k in ("plastic", "roughplastic"):
        d = {"type": k, "diffuse_reflectance": _base(mi, mat), "int_ior": float(p.get("int_ior", 1.5)),
             "nonlinear": bool(p.get("nonlinear", False))}
        if k == "roughplastic":
            d.update(distribution="ggx", alpha=alpha)
    elif k == "principled":
        d = {"type": "principled", "base_color": _base(mi, mat), "roughness": float(mat.roughness),
             "metallic": float(p.get("metallic", 0.0)), "specular": float(p.get("specular", 0.5)),
             "clearcoat": float(p.get("clearcoat", 0.0)), "clearcoat_gloss": float(p.get("clearcoat_gloss", 0.9)),
             "spec_trans": float(p.get("spec_trans", 0.0)), "anisotropic": float(p.get("anisotropic", 0.0)),
             "sheen": float(p.get("sheen", 0.0))}
        return d  # principled handles both sides itself
    elif k == "blend":
        a, b = mat.children
        return {"type": "blendbsdf", "weight": float(p.get("weight", 0.5)),
                "a": bsdf_dict(a, mi), "b": bsdf_dict(b, mi)}
    else:  # pragma: no cover - MaterialSpec validates kinds
        raise ValueError(f"unknown material kind {k!r}")
    return {"type": "twosided", "material": d} if k != "blend" else d


# ---------------------------------------------------------------------------------------------
# lights and camera
def light_dict(light: LightSpec, mi=None) -> dict:
    mi = mi or _mi()
    p = light.params
    if light.kind == "point":
        return {"type": "point", "position": [float(x) for x in p["position"]], "intensity": _rgb(p["intensity"])}
    if light.kind == "constant":
        return {"type": "constant", "radiance": _rgb(p.get("radiance", (1.0, 1.0, 1.0)))}
    if light.kind == "envmap":
        probe = make_probe(dict(p.get("probe", {})), PROBE_HEIGHT)
        return {"type": "envmap", "bitmap": mi.Bitmap(np.ascontiguousarray(probe)), "scale": float(p.get("scale", 1.0)),
                "to_world": mi.ScalarTransform4f().rotate([0, 1, 0], float(p.get("rotation", 0.0)))}
    if light.kind == "sunsky":
        d = {"type": "sunsky", "sun_direction": [float(x) for x in p["sun_direction"]],
             "turbidity": float(p.get("turbidity", 3.0)), "albedo": float(p.get("albedo", 0.3)),
             "sun_scale": float(p.get("sun_scale", 1.0)), "sky_scale": float(p.get("sky_scale", 1.0)),
             # Mitsuba's sunsky is z-up; our world is y-up. With this turn sun_direction is a world direction.
             "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90)}
        return d
    raise ValueError(f"light kind {light.kind!r} is attached to shapes, not a standalone emitter")


def film_dict(res: tuple[int, int], rfilter: str = "box") -> dict:
    """The film: ``res`` (W, H), RGB, the pixel filter ``rfilter`` (``box``, or ``gaussian``: Mitsuba's, with
    its default standard deviation 0.5). A filter wider than the pixel also samples the border around the
    image, so an edge pixel averages its whole filter as an inner one does (the renderer's input loop draws
    film positions from the filter over the whole plane: ``pipeline.render.inputs``)."""
    w, h = res
    return {"type": "hdrfilm", "width": int(w), "height": int(h), "pixel_format": "rgb",
            "rfilter": {"type": rfilter}, "sample_border": rfilter != "box"}


def sensor_dict(cam: CameraSpec, res: tuple[int, int], mi=None, rfilter: str = "box") -> dict:
    mi = mi or _mi()
    d = {"type": "thinlens" if cam.defocus else "perspective", "fov": float(cam.fov), "fov_axis": "x",
         "near_clip": NEAR_CLIP, "far_clip": FAR_CLIP, "to_world": mi.ScalarTransform4f(projection.camera_to_world(cam).tolist()),
         "film": film_dict(res, rfilter), "sampler": {"type": "independent"}}
    if cam.defocus:
        d.update(aperture_radius=float(cam.aperture_radius), focus_distance=float(cam.focus_distance))
    return d


def integrator_dict(spec: SceneSpec) -> dict:
    depth = spec.max_depth + 1
    return {"type": "path", "max_depth": depth, "rr_depth": depth + 1, "hide_emitters": False}


# ---------------------------------------------------------------------------------------------
# shapes: one per object, or merged by material
MERGED_PREFIX = "merged-"


def material_key(mat: MaterialSpec) -> str:
    """A material's identity (its canonical JSON): equal keys render identically and share one BSDF."""
    return json.dumps(mat.to_dict(), sort_keys=True)


def shape_groups(spec: SceneSpec, merge: bool = False) -> list[tuple[str, tuple[ObjectSpec, ...]]]:
    """The shapes of the Mitsuba scene in order: (shape id, the objects it holds).

    Without ``merge`` every object is its own shape, its id the object's name. With ``merge``, static
    objects without an emitter that share a material (and whose meshes carry the same vertex
    attributes: normals, UVs) become one mesh with id ``merged-<k>``, so the renderer pays one shape
    instead of many (the LLVM backend's cost grows with the shape count); moving objects and emitters
    keep their own shape. Objects of one group share a material, so every per-shape feature
    (specular colour, roughness; velocity 0) is the same for all of them.
    """
    if not merge:
        return [(o.name, (o,)) for o in spec.objects]
    out: list[tuple[str, tuple[ObjectSpec, ...]]] = []
    groups: dict[tuple, list[ObjectSpec]] = {}
    slot: dict[tuple, int] = {}
    for o in spec.objects:
        if o.moving or o.emitter_radiance is not None:
            out.append((o.name, (o,)))
            continue
        md = meshes.build(o.mesh)
        key = (material_key(o.material), md.normals is not None, md.uv is not None)
        if key not in groups:
            groups[key] = []
            slot[key] = len(out)
            out.append(("", ()))
        groups[key].append(o)
    names = {o.name for o in spec.objects}
    k = 0
    for key, objs in groups.items():
        if len(objs) == 1:
            out[slot[key]] = (objs[0].name, (objs[0],))
            continue
        while f"{MERGED_PREFIX}{k:03d}" in names:
            k += 1
        out[slot[key]] = (f"{MERGED_PREFIX}{k:03d}", tuple(objs))
        k += 1
    return out


def _merged_mesh(mi, name: str, objs: tuple[ObjectSpec, ...], tau: float, bsdf):
    """One ``mi.Mesh`` holding the world-space triangles of ``objs`` (same vertex attributes)."""
    parts = [world_mesh(o, tau) for o in objs]
    offsets = np.cumsum([0] + [len(p[0]) for p in parts[:-1]])
    v = np.concatenate([p[0] for p in parts])
    f = np.concatenate([p[1] + np.uint32(off) for p, off in zip(parts, offsets)])
    n = None if parts[0][2] is None else np.concatenate([p[2] for p in parts])
    uv = None if parts[0][3] is None else np.concatenate([np.asarray(p[3], np.float32) for p in parts])
    return _make_mesh(mi, name, v, f, n, uv, bsdf, None)


def scene_dict(spec: SceneSpec, frame: int = 0, *, res: tuple[int, int] = (256, 256), tau: float | None = None,
               merge: bool = False, rfilter: str = "box") -> dict:
    """The Mitsuba scene dict of ``spec`` at ``frame`` with objects at time ``tau`` (default: ``frame``).

    ``merge``: objects that share a material share one BSDF instance and static ones are merged into
    one mesh (:func:`shape_groups`); the image's distribution is that of the unmerged scene.
    """
    mi = _mi()
    if isinstance(res, int):
        res = (res, res)
    w, h = int(res[0]), int(res[1])
    if w <= 0 or h <= 0:
        raise SpecError(f"resolution must be positive, got {w}x{h}")
    tau = float(frame if tau is None else tau)
    cam = spec.camera(frame)
    d: dict[str, Any] = {"type": "scene", "integrator": integrator_dict(spec),
                         "sensor": sensor_dict(cam, (w, h), mi, rfilter)}
    bsdfs: dict[str, Any] = {}

    def bsdf_of(mat: MaterialSpec):
        if not merge:
            return mi.load_dict(bsdf_dict(mat, mi))
        key = material_key(mat)
        if key not in bsdfs:
            bsdfs[key] = mi.load_dict(bsdf_dict(mat, mi))
        return bsdfs[key]

    for name, objs in shape_groups(spec, merge):
        if len(objs) > 1:
            d[name] = _merged_mesh(mi, name, objs, tau, bsdf_of(objs[0].material))
            continue
        obj = objs[0]
        emitter = None
        if obj.emitter_radiance is not None:
            emitter = mi.load_dict({"type": "area", "radiance": _rgb(obj.emitter_radiance)})
        d[obj.name] = _mesh_object(mi, obj, tau, bsdf_of(obj.material), emitter)
    for i, light in enumerate(spec.lights):
        d[f"light_{i:02d}_{light.kind}"] = light_dict(light, mi)
    return d


def file_scene_dict(parts: dict, spec: SceneSpec, cam: CameraSpec, res: tuple[int, int], rfilter: str = "box") -> dict:
    """The scene dict of a scene file's frame (``scene_gen.scene_files``): the file's shapes and emitters
    (``parts``: loaded Mitsuba objects by key) under this project's camera, film and ``path`` integrator."""
    return {"type": "scene", "integrator": integrator_dict(spec), "sensor": sensor_dict(cam, res, _mi(), rfilter),
            **parts}


def load(spec: SceneSpec, frame: int = 0, res: tuple[int, int] | int = (256, 256), tau: float | None = None,
         merge: bool = False, rfilter: str = "box"):
    """``mi.load_dict(scene_dict(...))``."""
    return _mi().load_dict(scene_dict(spec, frame, res=res, tau=tau, merge=merge, rfilter=rfilter))


@dataclass(eq=False)
class LoadedScene:
    """One frame of a scene loaded into Mitsuba (:func:`load_frame`; a scene file's: ``scene_gen.scene_files``),
    with everything a renderer asks of its scene besides the Mitsuba ``scene`` itself (whose BSDFs it asks
    for materials), so that it never reads a description again: the scene's ``seed``, ``num_frames``, hard
    ``case``, ``kind`` and ``shutter``; this frame's camera and the previous one's (a clip's first frame:
    its own) with their matrices at the film ``res`` (``scene_gen.projection``); the ``path`` integrator's
    settings; and the motion: each moving shape's velocity (:meth:`velocity`, world units a frame) and
    :meth:`set_time`, which puts the moving objects where they are at a shutter fraction."""

    scene: Any
    seed: int
    frame: int
    num_frames: int
    case: str
    kind: str
    shutter: float
    res: tuple[int, int]
    camera: CameraSpec
    prev_camera: CameraSpec
    integrator: dict
    moving: tuple[ObjectSpec, ...] = ()
    nonfinite_expected: bool = False       # NaN/Inf samples are its hard case's purpose (Case.nonfinite)
    _params: Any = None
    _base: dict = field(default_factory=dict)
    _normals: dict = field(default_factory=dict)
    _time: float = 0.0

    @property
    def has_motion(self) -> bool:
        """Objects move during the exposure (``SceneSpec.has_motion``)."""
        return self.shutter > 0.0 and bool(self.moving)

    def velocity(self, shape_id: str) -> np.ndarray:
        """World-space velocity (float64, 3; units a frame) of the Mitsuba shape ``shape_id``: a moving
        object's own (it is a shape of its own), 0 for every other shape."""
        for o in self.moving:
            if o.name == shape_id:
                return np.asarray(o.velocity, np.float64)
        return np.zeros(3)

    @property
    def has_defocus(self) -> bool:
        return bool(self.camera.defocus)

    @property
    def camera_to_world(self) -> np.ndarray:
        return projection.camera_to_world(self.camera)

    @property
    def world_to_clip(self) -> np.ndarray:
        return projection.world_to_clip(self.camera, self.res)

    @property
    def prev_world_to_clip(self) -> np.ndarray:
        return projection.world_to_clip(self.prev_camera, self.res)

    def _moving_objects(self) -> "LoadedScene":
        """Where the moving objects' vertices are at rest (the shutter's start), read once at load."""
        if self.has_motion:
            self._params = _mi().traverse(self.scene)
            for o in self.moving:
                key = f"{o.name}.vertex_positions"
                if key not in self._params:
                    raise SpecError(f"moving object {o.name!r} has no {key!r} parameter in the Mitsuba scene")
                self._base[o.name] = np.array(self._params[key], np.float64).reshape(-1, 3)
                normals = f"{o.name}.vertex_normals"
                if normals in self._params:
                    self._normals[o.name] = np.array(self._params[normals], np.float32)
        return self

    def shutter_displacement(self) -> float:
        """The largest screen-space distance, in pixels of this frame, that a vertex of a moving object
        travels during the shutter (0.0 for a frame without motion; ``inf`` where a moving vertex
        crosses the camera's near plane). Only paths that touch the image count. Objects move linearly
        in world space; the path's two ends are compared (a projected straight path is straight)."""
        if not self.has_motion:
            return 0.0
        W, H = self.res
        m = self.world_to_clip
        far = 0.0
        for o in self.moving:
            p0 = self._base[o.name]
            p1 = p0 + np.asarray(o.velocity, np.float64) * self.shutter
            a, b = projection.project_pixels(m, p0, self.res), projection.project_pixels(m, p1, self.res)
            ok_a, ok_b = np.isfinite(a).all(-1), np.isfinite(b).all(-1)
            lo, hi = np.minimum(a, b), np.maximum(a, b)
            seen = ok_a & ok_b & (hi[:, 0] >= 0) & (lo[:, 0] <= W) & (hi[:, 1] >= 0) & (lo[:, 1] <= H)
            if np.any(ok_a != ok_b):
                return math.inf
            if seen.any():
                far = max(far, float(np.max(np.hypot(*(b[seen] - a[seen]).T))))
        return far

    def tau(self, t) -> np.ndarray | float:
        """Scene time in frames of shutter fraction(s) ``t``."""
        return self.frame + self.shutter * np.asarray(t, np.float64)

    def set_time(self, t: float) -> None:
        """Put the moving objects where they are at shutter fraction ``t`` (no-op without motion)."""
        if not self.has_motion or t == self._time:
            return
        mi = _mi()
        dtau = self.shutter * float(t)
        for o in self.moving:
            v = self._base[o.name] + np.asarray(o.velocity, np.float64) * dtau
            self._params[f"{o.name}.vertex_positions"] = mi.Float(v.astype(np.float32).ravel())
            if o.name in self._normals:
                # A translation keeps the normals. Given with the positions, Mitsuba keeps them as they are;
                # otherwise it recomputes them with atomic float adds, whose order (and so the last bits of
                # the normals, and of every sample that hits the object) varies from run to run.
                self._params[f"{o.name}.vertex_normals"] = mi.Float(self._normals[o.name])
        self._params.update()
        self._time = float(t)


def load_frame(spec: SceneSpec, frame: int, res: tuple[int, int] | int, *, merge: bool = True,
               on_loaded=None, rfilter: str = "box") -> LoadedScene:
    """Frame ``frame`` of a generated ``spec`` loaded into Mitsuba at film ``res`` (W, H) with the pixel
    filter ``rfilter``: what a renderer needs (:class:`LoadedScene`; ``scene_gen.sources.load_frame`` is the
    one call for every kind of scene). ``merge``: see :func:`scene_dict`. A hard case that edits the loaded
    scene (its ``loaded`` edit, ``scene_gen.cases.scene_hook``) is applied, then ``on_loaded(scene)`` (tests
    inject values with it), before anything renders."""
    res = (res, res) if isinstance(res, int) else (int(res[0]), int(res[1]))
    scene = load(spec, frame, res, merge=merge, rfilter=rfilter)
    hook = scene_hook(spec) if spec.case else None
    if hook is not None:
        hook(scene)
    if on_loaded is not None:
        on_loaded(scene)
    cam = spec.camera(frame)
    return LoadedScene(scene=scene, seed=int(spec.seed), frame=int(frame), num_frames=spec.num_frames,
                       case=spec.case, kind=spec.kind, shutter=float(spec.shutter), res=res, camera=cam,
                       prev_camera=spec.camera(frame - 1) if frame > 0 else cam,
                       integrator=integrator_dict(spec),
                       moving=tuple(o for o in spec.objects if o.moving),
                       nonfinite_expected=nonfinite_expected(spec.case))._moving_objects()
