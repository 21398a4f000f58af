"""SceneGenConfig: the knobs of random scene synthesis (pure data, validated at construction).

Units are metres and degrees. Every field is checked when the config is built and a bad value raises
:class:`ConfigError` naming the field and its allowed range, e.g.
``scene_gen.indoor_objects must be an integer in [0, 10000], got -3``.

The fields are the settings every scene family shares (:class:`SharedSettings`) followed by each
family's own (``scene_gen.families.Setting``: ``indoor_objects``; ``outdoor_objects``, ``p_sunsky``),
so a family brings its settings in its own file. All of them are plain keys of the config's
``scene_gen`` section.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, make_dataclass
from pathlib import Path
from typing import ClassVar

from core.checks import is_number, known_keys, need, need_int
from scene_gen.errors import ConfigError
from scene_gen.families import Setting, family_settings


PROBABILITY = {"probability": True}     # a field checked as a probability (a number in [0, 1])
NEWER = {"newer": True}                 # a field added after stores were made without it (SharedSettings.to_dict)


def _int_in(name: str, v, lo: int, hi: int) -> None:
    need_int(f"scene_gen.{name}", v, lo, hi, ConfigError)


def _prob(name: str, v) -> None:
    need(is_number(v) and 0.0 <= v <= 1.0, f"scene_gen.{name}", "a probability in [0, 1]", v, ConfigError)


def _range(name: str, v, lo: float, hi: float, *, open_lo: bool = False, open_hi: bool = False) -> tuple:
    ok = isinstance(v, (tuple, list)) and len(v) == 2 and all(is_number(x, finite=True) for x in v)
    if ok:
        a, b = float(v[0]), float(v[1])
        ok = a <= b and (a > lo if open_lo else a >= lo) and (b < hi if open_hi else b <= hi)
    lb, rb = "(" if open_lo else "[", ")" if open_hi else "]"
    need(ok, f"scene_gen.{name}", f"a pair (min, max) with min <= max inside {lb}{lo}, {hi}{rb}", v, ConfigError)
    return (float(v[0]), float(v[1]))


def _check_setting(name: str, s: Setting, v) -> None:
    if s.kind == "int":
        _int_in(name, v, s.lo, s.hi)
    else:
        _prob(name, v)


@dataclass(frozen=True)
class SharedSettings:
    """Random scene synthesis settings (Gharbi et al. 2019 as summarised by Munkberg et al. 2020, sec. 4).

    Counts are the meshes *placed*; objects outside every frame's view frustum are dropped afterwards,
    so a scene usually holds fewer. ``aperture_range`` is the lens radius as a fraction of the focus
    distance (log-uniform), so defocus looks alike at every scene scale.

    ``material_palette`` K > 0: each scene draws K random materials and every content object (not
    the room, backdrop, furniture or light panels) takes one of them, so objects share BSDFs and the renderer
    merges static ones into K meshes (1.1x the samples per second, each scene timed alone; make bench); 0: every object draws
    its own. The layout is the same for every K (the palette has its own random stream).

    ``pymeshlab`` false: scenes made without pymeshlab (a machine that cannot have it, such as a GPU
    machine that only receives carried wheels): the objects whose meshes pymeshlab makes (the ``blob``
    and ``boolean`` kinds, :data:`scene_gen.meshes.PYMESHLAB_KINDS`) are left out after the layout
    (every other object, light and camera draw is the same as with it) and no mesh is decimated (no
    triangle budgets: every procedural mesh at its full resolution).

    These are the settings every scene family shares; :class:`SceneGenConfig` adds the families' own.
    """
    _families: ClassVar[dict] = {}        # the families' settings (name -> Setting) of SceneGenConfig
    p_defocus: float = field(default=0.5, metadata=PROBABILITY)
    p_motion: float = field(default=0.5, metadata=PROBABILITY)
    p_object_motion: float = field(default=0.5, metadata=PROBABILITY)   # share of objects that move
    fov_range: tuple = (15.0, 65.0)       # degrees, within (0, 180)
    aperture_range: tuple = (0.001, 0.02)  # lens radius / focus distance, log-uniform
    speed_range: tuple = (0.1, 1.5)       # object speed in object radii per frame
    p_floating: float = field(default=0.1, metadata=PROBABILITY)        # share floating above the ground
    model_folder: str | None = None       # user OBJ/PLY/GLB models (optional)
    p_user_model: float = field(default=0.5, metadata=PROBABILITY)      # share of meshes from model_folder
    max_triangles: int = 20000            # per-object triangle budget ceiling
    min_triangles: int = 64               # per-object triangle budget floor
    tris_per_px: float = 1.0              # triangles per pixel of the projected bounding disc (meshes.triangle_budget)
    max_depth: int = 5                    # path bounces
    shutter: float = field(default=0.5, metadata=PROBABILITY)   # exposure, a fraction of the frame interval
    material_palette: int = field(default=0, metadata=NEWER)   # > 0: content objects draw from K materials
    pymeshlab: bool = field(default=True, metadata=NEWER)      # false: no blob or boolean meshes (above)
    p_caustics: float = field(default=0.0, metadata={**PROBABILITY, **NEWER})   # scene_gen.phenomena
    p_natural_textures: float = field(default=0.0, metadata={**PROBABILITY, **NEWER})   # scene_gen.phenomena

    def __post_init__(self):
        for n, s in self._families.items():
            _check_setting(n, s, getattr(self, n))
        for f in fields(SharedSettings):
            if f.metadata.get("probability"):
                _prob(f.name, getattr(self, f.name))
        object.__setattr__(self, "fov_range", _range("fov_range", self.fov_range, 0.0, 180.0,
                                                     open_lo=True, open_hi=True))
        object.__setattr__(self, "aperture_range", _range("aperture_range", self.aperture_range, 0.0, 1.0,
                                                          open_lo=True))
        object.__setattr__(self, "speed_range", _range("speed_range", self.speed_range, 0.0, 100.0))
        _int_in("max_triangles", self.max_triangles, 12, 10_000_000)
        _int_in("min_triangles", self.min_triangles, 12, 10_000_000)
        if self.min_triangles > self.max_triangles:
            raise ConfigError(f"scene_gen.min_triangles ({self.min_triangles}) must be <= "
                              f"scene_gen.max_triangles ({self.max_triangles})")
        need(is_number(self.tris_per_px) and 0 < self.tris_per_px <= 1e6, "scene_gen.tris_per_px",
             "a number in (0, 1e6]", self.tris_per_px, ConfigError)
        _int_in("max_depth", self.max_depth, 1, 1000)
        _int_in("material_palette", self.material_palette, 0, 10000)
        need(isinstance(self.pymeshlab, bool), "scene_gen.pymeshlab", "true or false", self.pymeshlab, ConfigError)
        if self.model_folder is not None:
            need(isinstance(self.model_folder, (str, Path)) and str(self.model_folder) != "", "scene_gen.model_folder",
                 "a folder path or null", self.model_folder, ConfigError)
            p = Path(self.model_folder)
            if not p.is_dir():
                raise ConfigError(f"scene_gen.model_folder {str(p)!r} is not an existing folder")
            object.__setattr__(self, "model_folder", str(p))

    def to_dict(self) -> dict:
        """Plain data; a setting added after stores were made without it (``NEWER``, a family's
        ``Setting.newer``: the palette, pymeshlab, the phenomena's rates) only when not its default, so those
        stores still resume."""
        d = asdict(self)
        for k, v in d.items():
            if isinstance(v, tuple):
                d[k] = list(v)
        newer = {f.name: f.default for f in fields(SharedSettings) if f.metadata.get("newer")}
        newer.update({n: s.default for n, s in self._families.items() if s.newer})
        for k, default in newer.items():
            if d.get(k) == default:
                del d[k]
        return d

    @classmethod
    def from_dict(cls, d: dict | None) -> "SceneGenConfig":
        if d is None:
            return cls()
        d = known_keys(d, cls, "scene_gen", ConfigError, noun="field(s)")
        kw = {k: (tuple(v) if isinstance(v, list) else v) for k, v in d.items()}
        return cls(**kw)


def _with_family_settings(base: type) -> type:
    """``base`` with every registered family's settings as more fields (families in seed order)."""
    settings = family_settings()
    clash = sorted({f.name for f in fields(base)} & set(settings))
    if clash:
        raise ConfigError(f"scene family setting(s) {clash} are already settings every family shares")
    doc = "\n".join(f"    - ``{n}`` ({s.kind}, default {s.default!r}): {s.doc}" for n, s in settings.items())
    return make_dataclass(
        "SceneGenConfig", [(n, type(s.default), field(default=s.default)) for n, s in settings.items()],
        bases=(base,), frozen=True,
        namespace={"__module__": __name__, "_families": settings,
                   "__doc__": f"{base.__doc__.rstrip()}\n\n    The families' own settings:\n\n{doc}\n"})


SceneGenConfig = _with_family_settings(SharedSettings)
