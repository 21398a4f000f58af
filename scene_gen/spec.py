"""SceneSpec: the one persistent description of a generated scene (pure data, numpy-free).

A spec is a tree of frozen dataclasses. It validates itself at construction, round-trips exactly
through JSON (``SceneSpec.from_json(spec.to_json()) == spec``) and is everything the renderer needs
to rebuild the Mitsuba scene (``scene_gen.to_mitsuba``); the generator's random draws are not.

Time convention: ``tau`` is continuous time measured in frames. Frame ``f`` is exposed over
``tau in [f, f + shutter)``; a still has one frame (``num_frames == 1``). Objects move linearly:
``position(tau) = transform.translate + velocity * tau``. Cameras are per frame (``cameras[f]``)
and static within a frame's exposure.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar

from scene_gen.errors import SpecError

SPEC_VERSION = 1

MESH_KINDS = ("sphere", "box", "cylinder", "capsule", "cone", "torus", "revolve", "extrude", "blob",
              "boolean", "plane", "room", "file")
MATERIAL_KINDS = ("diffuse", "conductor", "roughconductor", "dielectric", "roughdielectric",
                  "thindielectric", "plastic", "roughplastic", "principled", "blend")
PROCEDURAL_TEXTURE_KINDS = ("checker", "noise", "stripes", "cells")     # what random materials draw from
# "natural": 1/f noise with the statistics of photographed surfaces (scene_gen.textures), given by the
# p_natural_textures phenomenon (scene_gen.phenomena), never drawn by random_texture (its draws stay as they were)
TEXTURE_KINDS = PROCEDURAL_TEXTURE_KINDS + ("natural",)
LIGHT_KINDS = ("area", "point", "envmap", "sunsky", "constant")

Vec3 = tuple[float, float, float]


def _check(cond: bool, msg: str) -> None:
    if not cond:
        raise SpecError(msg)


def _finite(v, name: str) -> None:
    vals = v if isinstance(v, (tuple, list)) else (v,)
    for x in vals:
        _check(isinstance(x, (int, float)) and math.isfinite(x), f"{name} must be finite numbers, got {v!r}")


def _vec(v, n: int, name: str) -> tuple:
    _check(isinstance(v, (tuple, list)) and len(v) == n, f"{name} must have {n} components, got {v!r}")
    _finite(v, name)
    return tuple(float(x) for x in v)


class _Spec:
    """Mixin: exact dict/JSON round trip for frozen dataclasses (tuples restored from lists)."""

    _nested: ClassVar[dict[str, Any]] = {}

    def to_dict(self) -> dict:
        out = {}
        for f in fields(self):
            out[f.name] = _to_plain(getattr(self, f.name))
        return out

    @classmethod
    def from_dict(cls, d: dict):
        if not isinstance(d, dict):
            raise SpecError(f"{cls.__name__}: expected an object, got {type(d).__name__}")
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        _check(not unknown, f"{cls.__name__}: unknown field(s) {sorted(unknown)}")
        kw = {}
        for f in fields(cls):
            if f.name not in d:
                continue
            kw[f.name] = _from_plain(d[f.name], cls._nested.get(f.name))
        return cls(**kw)


def _to_plain(v):
    if isinstance(v, _Spec):
        return v.to_dict()
    if isinstance(v, tuple):
        return [_to_plain(x) for x in v]
    if isinstance(v, dict):
        return {k: _to_plain(x) for k, x in sorted(v.items())}
    return v


def _from_plain(v, nested):
    """nested: None (plain), a _Spec class, or ('tuple', cls) for a tuple of specs."""
    if nested is None:
        return _freeze(v)
    if isinstance(nested, tuple) and nested[0] == "tuple":
        return tuple(nested[1].from_dict(x) for x in v)
    if isinstance(nested, tuple) and nested[0] == "optional":
        return None if v is None else nested[1].from_dict(v)
    return nested.from_dict(v)


def _freeze(v):
    if isinstance(v, list):
        return tuple(_freeze(x) for x in v)
    if isinstance(v, dict):
        return {k: _freeze(x) for k, x in v.items()}
    return v


@dataclass(frozen=True)
class Transform(_Spec):
    """Scale, then rotate (XYZ Euler angles in degrees), then translate."""
    translate: Vec3 = (0.0, 0.0, 0.0)
    rotate: Vec3 = (0.0, 0.0, 0.0)
    scale: Vec3 = (1.0, 1.0, 1.0)

    def __post_init__(self):
        object.__setattr__(self, "translate", _vec(self.translate, 3, "transform.translate"))
        object.__setattr__(self, "rotate", _vec(self.rotate, 3, "transform.rotate"))
        object.__setattr__(self, "scale", _vec(self.scale, 3, "transform.scale"))
        _check(all(s > 0 for s in self.scale), f"transform.scale must be > 0, got {self.scale}")


@dataclass(frozen=True)
class MeshSpec(_Spec):
    """How to build one mesh (``scene_gen.meshes.build``). ``params`` are JSON scalars/lists."""
    kind: str
    params: dict = field(default_factory=dict)
    seed: int = 0
    triangle_budget: int = 0          # 0 = keep full resolution; else decimate to at most this many
    children: tuple["MeshSpec", ...] = ()   # operands of 'boolean'

    def __post_init__(self):
        _check(self.kind in MESH_KINDS, f"mesh.kind must be one of {MESH_KINDS}, got {self.kind!r}")
        _check(isinstance(self.triangle_budget, int) and self.triangle_budget >= 0,
               f"mesh.triangle_budget must be an integer >= 0, got {self.triangle_budget!r}")
        _check(isinstance(self.seed, int) and self.seed >= 0, f"mesh.seed must be an integer >= 0, got {self.seed!r}")
        if self.kind == "boolean":
            _check(len(self.children) == 2, "mesh 'boolean' needs exactly two children")
        object.__setattr__(self, "params", _freeze(dict(self.params)))


MeshSpec._nested = {"children": ("tuple", MeshSpec)}


@dataclass(frozen=True)
class TextureSpec(_Spec):
    """A procedural texture: two colours mixed by a pattern, with a UV scale."""
    kind: str
    color0: Vec3
    color1: Vec3
    uv_scale: float = 1.0
    seed: int = 0

    def __post_init__(self):
        _check(self.kind in TEXTURE_KINDS, f"texture.kind must be one of {TEXTURE_KINDS}, got {self.kind!r}")
        for n in ("color0", "color1"):
            c = _vec(getattr(self, n), 3, f"texture.{n}")
            _check(all(0.0 <= x <= 1.0 for x in c), f"texture.{n} must lie in [0, 1], got {c}")
            object.__setattr__(self, n, c)
        _check(self.uv_scale > 0 and math.isfinite(self.uv_scale), f"texture.uv_scale must be > 0, got {self.uv_scale}")


@dataclass(frozen=True)
class MaterialSpec(_Spec):
    """A BSDF. ``params`` are kind-specific (e.g. ``alpha``, ``int_ior``, ``specular``).

    ``base_color`` is the diffuse/base reflectance (replaced by ``texture`` where given);
    ``specular_color`` and ``roughness`` are the values recorded as per-sample features.
    ``blend`` materials have two ``children`` and ``params['weight']``.
    """
    kind: str
    base_color: Vec3 = (0.5, 0.5, 0.5)
    specular_color: Vec3 = (0.04, 0.04, 0.04)
    roughness: float = 1.0
    params: dict = field(default_factory=dict)
    texture: TextureSpec | None = None
    children: tuple["MaterialSpec", ...] = ()

    def __post_init__(self):
        _check(self.kind in MATERIAL_KINDS, f"material.kind must be one of {MATERIAL_KINDS}, got {self.kind!r}")
        for n in ("base_color", "specular_color"):
            c = _vec(getattr(self, n), 3, f"material.{n}")
            _check(all(0.0 <= x <= 1.0 for x in c), f"material.{n} must lie in [0, 1], got {c}")
            object.__setattr__(self, n, c)
        _finite(self.roughness, "material.roughness")
        _check(0.0 <= self.roughness <= 1.0, f"material.roughness must lie in [0, 1], got {self.roughness}")
        if self.kind == "blend":
            _check(len(self.children) == 2, "material 'blend' needs exactly two children")
            w = self.params.get("weight", 0.5)
            _check(0.0 <= w <= 1.0, f"material.params.weight must lie in [0, 1], got {w}")
        object.__setattr__(self, "params", _freeze(dict(self.params)))


MaterialSpec._nested = {"texture": ("optional", TextureSpec), "children": ("tuple", MaterialSpec)}


@dataclass(frozen=True)
class ObjectSpec(_Spec):
    """A mesh instance with material, placement and optional linear motion (world units per frame)."""
    name: str
    mesh: MeshSpec
    material: MaterialSpec
    transform: Transform = Transform()
    velocity: Vec3 | None = None
    emitter_radiance: Vec3 | None = None   # area emitter attached to this shape (indoor lights)

    def __post_init__(self):
        _check(isinstance(self.name, str) and self.name != "", "object.name must be a non-empty string")
        if self.velocity is not None:
            object.__setattr__(self, "velocity", _vec(self.velocity, 3, f"object {self.name}.velocity"))
        if self.emitter_radiance is not None:
            r = _vec(self.emitter_radiance, 3, f"object {self.name}.emitter_radiance")
            _check(all(x >= 0 for x in r), f"object {self.name}.emitter_radiance must be >= 0, got {r}")
            object.__setattr__(self, "emitter_radiance", r)

    @property
    def moving(self) -> bool:
        return self.velocity is not None and any(v != 0.0 for v in self.velocity)


ObjectSpec._nested = {"mesh": MeshSpec, "material": MaterialSpec, "transform": Transform}


@dataclass(frozen=True)
class LightSpec(_Spec):
    """A light that is not a shape: ``point`` (position, intensity), ``envmap`` (procedural HDR probe
    with ``params``: seed, sun direction, sky colours, scale), ``sunsky`` (sun direction, turbidity,
    albedo, scale) or ``constant`` (radiance)."""
    kind: str
    params: dict = field(default_factory=dict)

    def __post_init__(self):
        _check(self.kind in LIGHT_KINDS, f"light.kind must be one of {LIGHT_KINDS}, got {self.kind!r}")
        object.__setattr__(self, "params", _freeze(dict(self.params)))


@dataclass(frozen=True)
class CameraSpec(_Spec):
    """A look-at camera with vertical-ish field of view in degrees (Mitsuba's ``fov`` on the x axis).

    ``aperture_radius == 0`` is a pinhole (no lens samples); otherwise a thin lens focused at
    ``focus_distance`` (world units along the view axis).
    """
    origin: Vec3
    target: Vec3
    up: Vec3 = (0.0, 1.0, 0.0)
    fov: float = 45.0
    aperture_radius: float = 0.0
    focus_distance: float = 1.0

    def __post_init__(self):
        for n in ("origin", "target", "up"):
            object.__setattr__(self, n, _vec(getattr(self, n), 3, f"camera.{n}"))
        _finite(self.fov, "camera.fov")
        _check(0.0 < self.fov < 180.0, f"camera.fov must lie in (0, 180) degrees, got {self.fov}")
        _check(self.aperture_radius >= 0.0, f"camera.aperture_radius must be >= 0, got {self.aperture_radius}")
        _check(self.focus_distance > 0.0, f"camera.focus_distance must be > 0, got {self.focus_distance}")
        d = [t - o for t, o in zip(self.target, self.origin)]
        _check(sum(x * x for x in d) > 1e-12, "camera.target must differ from camera.origin")

    @property
    def defocus(self) -> bool:
        return self.aperture_radius > 0.0


@dataclass(frozen=True)
class SceneFile(_Spec):
    """A Mitsuba scene file a scene is made of (``scene_gen.scene_files``): its ``path`` (absolute) and the
    SHA-256 of its content (``scene_gen.scene_files.content_hash``: the file and every file it names), so
    a frame is never rendered from a file that changed since its scene was described."""
    path: str
    sha256: str

    def __post_init__(self):
        _check(isinstance(self.path, str) and self.path != "", f"source.path must be a file path, got {self.path!r}")
        _check(isinstance(self.sha256, str) and len(self.sha256) == 64, f"source.sha256 must be a SHA-256 hex "
               f"digest, got {self.sha256!r}")


@dataclass(frozen=True)
class SceneSpec(_Spec):
    """A whole scene: objects, lights, one camera per frame, and render-relevant settings.

    ``kind`` names the scene family that drew it, checked here as a family's name is (a lower-case
    identifier), not against the registry: a spec holds all it needs to render, whatever families this
    install has, and this module sits below the families (they build specs). Where a family is used,
    the registry checks the name (``scene_gen.families.get_family``: sampling, the dataset config, the
    command lines).

    ``source`` (a :class:`SceneFile`): the scene is a user's Mitsuba scene file (``kind`` ``file``, no
    ``objects`` or ``lights``: they are the file's); its cameras are the spec's own, drawn around the
    file's sensor (``scene_gen.scene_files``). None: a generated scene."""
    kind: str
    seed: int
    objects: tuple[ObjectSpec, ...]
    lights: tuple[LightSpec, ...]
    cameras: tuple[CameraSpec, ...]
    shutter: float = 0.5              # exposure as a fraction of the frame interval
    max_depth: int = 5                # path bounces (the layer paper: five)
    version: int = SPEC_VERSION
    case: str = ""                    # hard cases applied (scene_gen.cases), comma-separated; '' = none
    source: SceneFile | None = None   # a scene file's scene (scene_gen.scene_files); None: generated

    def __post_init__(self):
        _check(isinstance(self.kind, str) and self.kind.isidentifier() and self.kind == self.kind.lower(),
               f"scene.kind must be a scene family's name (a lower-case identifier), got {self.kind!r}")
        _check(isinstance(self.seed, int) and self.seed >= 0, f"scene.seed must be an integer >= 0, got {self.seed!r}")
        _check(len(self.cameras) >= 1, "scene.cameras needs at least one camera (one per frame)")
        _check(0.0 <= self.shutter <= 1.0, f"scene.shutter must lie in [0, 1], got {self.shutter}")
        _check(isinstance(self.max_depth, int) and self.max_depth >= 1, f"scene.max_depth must be >= 1, got {self.max_depth}")
        _check(self.version == SPEC_VERSION, f"SceneSpec version {self.version} is not supported (expected {SPEC_VERSION})")
        _check(isinstance(self.case, str), f"scene.case must be a string of hard-case names, got {self.case!r}")
        if self.source is not None:
            _check(not self.objects and not self.lights, "a scene file's spec holds no objects or lights (the file's)")
        names = [o.name for o in self.objects]
        _check(len(set(names)) == len(names), "object names must be unique")
        object.__setattr__(self, "objects", tuple(self.objects))
        object.__setattr__(self, "lights", tuple(self.lights))
        object.__setattr__(self, "cameras", tuple(self.cameras))

    @property
    def num_frames(self) -> int:
        return len(self.cameras)

    @property
    def has_motion(self) -> bool:
        """Objects move during exposure (motion blur); camera paths alone do not blur (static per frame)."""
        return self.shutter > 0.0 and any(o.moving for o in self.objects)

    @property
    def has_defocus(self) -> bool:
        return any(c.defocus for c in self.cameras)

    def to_dict(self) -> dict:
        """Plain data; ``case`` and ``source`` only when set, so specs (and stores) made before they existed
        are unchanged."""
        d = super().to_dict()
        for k in ("case", "source"):
            if not d[k]:
                del d[k]
        return d

    def camera(self, frame: int) -> CameraSpec:
        if not 0 <= frame < self.num_frames:
            raise SpecError(f"frame {frame} out of range: the scene has {self.num_frames} frame(s)")
        return self.cameras[frame]

    def to_json(self, indent: int | None = None) -> str:
        return json.dumps(self.to_dict(), indent=indent, sort_keys=True, allow_nan=False)

    @classmethod
    def from_json(cls, text: str) -> "SceneSpec":
        try:
            d = json.loads(text)
        except json.JSONDecodeError as e:
            raise SpecError(f"SceneSpec JSON is malformed: {e}") from e
        return cls.from_dict(d)


SceneSpec._nested = {"objects": ("tuple", ObjectSpec), "lights": ("tuple", LightSpec), "cameras": ("tuple", CameraSpec),
                     "source": ("optional", SceneFile)}
