"""The held-out real-scene suite: Mitsuba scene files this project writes from what Mitsuba ships, so that
every figure can be checked on scenes the generator did not make, without downloading anything.

``python -m scene_gen real-scenes --out DIR`` writes (the same bytes every time, so their content hashes
and the stores rendered from them stay put):

- ``cornell-box.xml``: Mitsuba's own Cornell box (``mi.cornell_box()``), written out as a file;
- ``metals.xml``: glossy and rough gold, copper and aluminium (Mitsuba's named conductors) and a rough
  metal slab on a grey floor, lit by two tiny, very bright spheres and a faint sky;
- ``envmap-object.xml``: a rough-plastic torus knot (a PLY mesh), a glass sphere and a principled
  sphere on a disk under an HDR environment map (an OpenEXR sky with a sun, ``scene_gen.probes``);
- ``textured-interior.xml``: a room whose floor, walls, rug and table carry bitmap textures with natural
  (1/f) statistics, lit by a window and a small ceiling lamp;
- ``glass.xml``: smooth, rough and thin dielectrics on a fine checker floor under an area light.

Each file has its own sensor (a perspective camera) and a Gaussian-filtered film, as users render; a
dataset config renders it at its own resolution and pixel filter (``configs/real-scenes.yaml``). The
files are written with :func:`to_xml` from Mitsuba's dict form (the one ``mi.load_dict`` takes), so each
file is checked by loading it back (``mi.load_file``) as it is written.
"""
from __future__ import annotations

import math
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from scene_gen.errors import SceneFileError
from scene_gen.probes import make_probe
from scene_gen.projection import camera_to_world
from scene_gen.scene_files import load_file
from scene_gen.spec import CameraSpec
from scene_gen.textures import fbm

SUITE = ("cornell-box", "metals", "envmap-object", "textured-interior", "glass")
FILM_RES = 128
TEXTURE_RES = 256

# the XML tag of a dict-form plugin, by the key it sits under or by its type
_TAG_BY_KEY = {"bsdf": "bsdf", "emitter": "emitter", "film": "film", "rfilter": "rfilter", "sampler": "sampler",
               "sensor": "sensor", "integrator": "integrator", "material": "bsdf", "a": "bsdf", "b": "bsdf"}
_SHAPES = {"rectangle", "cube", "sphere", "disk", "cylinder", "ply", "obj", "serialized"}
_EMITTERS = {"area", "point", "constant", "envmap", "spot", "directional"}
_TEXTURES = {"bitmap", "checkerboard"}


# ------------------------------------------------------------------------------------------------
# Mitsuba's dict form to its XML form
def _tag(key: str, d: dict) -> str:
    t = d["type"]
    if key in _TAG_BY_KEY and t not in _TEXTURES:
        return _TAG_BY_KEY[key]
    if t in _SHAPES:
        return "shape"
    if t in _EMITTERS:
        return "emitter"
    if t in _TEXTURES:
        return "texture"
    return "bsdf"


def _num(x) -> str:
    return repr(float(x)) if isinstance(x, float) else str(x)


def _value(key: str, v, pad: str) -> list[str]:
    """The XML lines of one property ``key`` of a plugin."""
    n = quoteattr(key)
    if isinstance(v, dict) and v.get("type") == "rgb":
        return [f'{pad}<rgb name={n} value="{", ".join(_num(float(c)) for c in v["value"])}"/>']
    if isinstance(v, dict) and v.get("type") == "ref":
        return [f'{pad}<ref name={n} id={quoteattr(v["id"])}/>']
    if isinstance(v, dict):
        return _plugin(key, v, pad, name=key)
    if hasattr(v, "matrix") or (isinstance(v, np.ndarray) and v.shape == (4, 4)):
        m = np.asarray(v.matrix if hasattr(v, "matrix") else v, np.float64).reshape(4, 4)
        vals = " ".join(_num(float(x)) for x in m.ravel())
        return [f"{pad}<transform name={n}><matrix value=\"{vals}\"/></transform>"]
    if isinstance(v, bool):
        return [f'{pad}<boolean name={n} value="{str(v).lower()}"/>']
    if isinstance(v, int):
        return [f'{pad}<integer name={n} value="{v}"/>']
    if isinstance(v, float):
        return [f'{pad}<float name={n} value="{_num(v)}"/>']
    if isinstance(v, str):
        return [f"{pad}<string name={n} value={quoteattr(v)}/>"]
    if isinstance(v, (list, tuple)) and len(v) == 3:
        x, y, z = (_num(float(c)) for c in v)
        return [f'{pad}<point name={n} x="{x}" y="{y}" z="{z}"/>']
    raise SceneFileError(f"cannot write the property {key!r} ({type(v).__name__}) as Mitsuba XML")


def _plugin(key: str, d: dict, pad: str, *, name: str | None = None, ident: str | None = None) -> list[str]:
    tag = _tag(key, d)
    attrs = f' type={quoteattr(d["type"])}' + (f" id={quoteattr(ident)}" if ident else "")
    if name is not None and tag in ("texture", "bsdf") and key not in _TAG_BY_KEY:
        attrs += f" name={quoteattr(name)}"
    body = []
    for k, v in d.items():
        if k != "type":
            body += _value(k, v, pad + "    ")
    if not body:
        return [f"{pad}<{tag}{attrs}/>"]
    return [f"{pad}<{tag}{attrs}>", *body, f"{pad}</{tag}>"]


def to_xml(scene: dict) -> str:
    """Mitsuba XML (version 3) of a scene in dict form: each top-level plugin under its key as id; BSDFs
    first, so the shapes' ``ref``s find them."""
    items = [(k, v) for k, v in scene.items() if k != "type"]
    order = sorted(items, key=lambda kv: (0 if _tag(kv[0], kv[1]) in ("integrator", "sensor") else
                                          1 if _tag(kv[0], kv[1]) == "bsdf" else 2))
    lines = ['<scene version="3.0.0">']
    for k, v in order:
        lines += _plugin(k, v, "    ", ident=None if k in ("integrator", "sensor") else k)
    return "\n".join(lines + ["</scene>", ""])


# ------------------------------------------------------------------------------------------------
# the suite's scenes (dict form); textures and meshes written beside them
def _look(origin, target, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    return camera_to_world(CameraSpec(origin=tuple(origin), target=tuple(target), up=tuple(up)))


def _sensor(origin, target, fov: float) -> dict:
    return {"type": "perspective", "fov": float(fov), "fov_axis": "x", "to_world": _look(origin, target),
            "film": {"type": "hdrfilm", "width": FILM_RES, "height": FILM_RES, "rfilter": {"type": "gaussian"}}}


def _rgb(*c) -> dict:
    return {"type": "rgb", "value": [float(x) for x in c]}


def _trs(translate=(0.0, 0.0, 0.0), scale=(1.0, 1.0, 1.0), rotate_x: float = 0.0, rotate_y: float = 0.0) -> np.ndarray:
    """translate @ rotate_y @ rotate_x @ scale (degrees)."""
    ax, ay = math.radians(rotate_x), math.radians(rotate_y)
    rx = np.array([[1, 0, 0], [0, math.cos(ax), -math.sin(ax)], [0, math.sin(ax), math.cos(ax)]])
    ry = np.array([[math.cos(ay), 0, math.sin(ay)], [0, 1, 0], [-math.sin(ay), 0, math.cos(ay)]])
    m = np.eye(4)
    m[:3, :3] = ry @ rx @ np.diag(np.broadcast_to(np.asarray(scale, np.float64), 3))
    m[:3, 3] = translate
    return m


def _floor(size: float, bsdf: dict | str, y: float = 0.0) -> dict:
    return {"type": "rectangle", "to_world": _trs((0.0, y, 0.0), (size, size, 1.0), rotate_x=-90.0),
            "bsdf": {"type": "ref", "id": bsdf} if isinstance(bsdf, str) else bsdf}


def cornell_box() -> dict:
    """Mitsuba's Cornell box as ``mi.cornell_box()`` gives it (its sensor, film and integrator included)."""
    from core.variant import mitsuba
    d = mitsuba().cornell_box()
    d["sensor"].pop("sampler", None)
    d["sensor"]["focus_distance"] = float(d["sensor"]["focus_distance"])       # a float property (1000 there)
    d["sensor"]["film"] = {"type": "hdrfilm", "width": FILM_RES, "height": FILM_RES, "rfilter": {"type": "gaussian"}}
    return d


def metals() -> dict:
    small = lambda p, r: {"type": "sphere", "center": list(p), "radius": 0.04,    # noqa: E731
                          "emitter": {"type": "area", "radiance": _rgb(r, 0.92 * r, 0.8 * r)}}
    return {"type": "scene", "integrator": {"type": "path", "max_depth": 6},
            "sensor": _sensor((0.0, 1.6, 4.2), (0.0, 0.45, 0.0), 42.0),
            "grey": {"type": "diffuse", "reflectance": _rgb(0.35, 0.35, 0.33)},
            "floor": _floor(6.0, "grey"),
            "gold": {"type": "sphere", "center": [-1.1, 0.5, 0.0], "radius": 0.5,
                     "bsdf": {"type": "roughconductor", "material": "Au", "alpha": 0.03}},
            "copper": {"type": "sphere", "center": [0.0, 0.5, -0.4], "radius": 0.5,
                       "bsdf": {"type": "roughconductor", "material": "Cu", "alpha": 0.25}},
            "aluminium": {"type": "sphere", "center": [1.1, 0.5, 0.0], "radius": 0.5,
                          "bsdf": {"type": "conductor", "material": "Al"}},
            "slab": {"type": "cube", "to_world": _trs((0.2, 0.08, 1.0), (0.7, 0.08, 0.35), rotate_y=20.0),
                     "bsdf": {"type": "roughconductor", "material": "Cr", "alpha": 0.12}},
            "lamp-left": small((-1.6, 2.0, 1.2), 8000.0), "lamp-right": small((1.7, 1.4, -0.8), 5000.0),
            "sky": {"type": "constant", "radiance": _rgb(0.02, 0.025, 0.03)}}


def envmap_object(folder: Path) -> dict:
    """An object under an HDR environment: writes ``textures/sky.exr`` and ``meshes/knot.ply``."""
    from core.images import write_exr
    probe = make_probe({"seed": 5, "sun_elevation": 35.0, "sun_azimuth": 40.0, "sun_radiance": 3000.0,
                        "sky_radiance": 1.2, "clouds": 0.3}, 256)
    (folder / "textures").mkdir(parents=True, exist_ok=True)
    write_exr(folder / "textures" / "sky.exr", probe)
    _write_knot(folder / "meshes" / "knot.ply")
    return {"type": "scene", "integrator": {"type": "path", "max_depth": 6},
            "sensor": _sensor((0.0, 1.2, 4.0), (0.0, 0.6, 0.0), 40.0),
            "sky": {"type": "envmap", "filename": "textures/sky.exr", "scale": 1.0},
            "stone": {"type": "diffuse", "reflectance": _rgb(0.45, 0.42, 0.38)},
            "ground": {"type": "disk", "to_world": _trs((0.0, 0.0, 0.0), (3.0, 3.0, 1.0), rotate_x=-90.0),
                       "bsdf": {"type": "ref", "id": "stone"}},
            "knot": {"type": "ply", "filename": "meshes/knot.ply",
                     "bsdf": {"type": "roughplastic", "diffuse_reflectance": _rgb(0.6, 0.12, 0.08), "alpha": 0.15}},
            "glass-ball": {"type": "sphere", "center": [1.15, 0.35, 0.6], "radius": 0.35,
                           "bsdf": {"type": "dielectric", "int_ior": 1.5}},
            "satin": {"type": "sphere", "center": [-1.2, 0.4, 0.4], "radius": 0.4,
                      "bsdf": {"type": "principled", "base_color": _rgb(0.2, 0.35, 0.7), "roughness": 0.35,
                               "metallic": 0.0, "clearcoat": 0.6}}}


def _write_knot(path: Path) -> None:
    """A (2, 3) torus knot tube as a binary PLY (trimesh), about 0.5 high, just above the ground."""
    import trimesh
    t = np.linspace(0.0, 2.0 * math.pi, 240, endpoint=False)
    curve = np.stack([(2 + np.cos(3 * t)) * np.cos(2 * t), np.sin(3 * t), (2 + np.cos(3 * t)) * np.sin(2 * t)], 1)
    ring = np.linspace(0.0, 2.0 * math.pi, 16, endpoint=False)
    tangent = np.roll(curve, -1, 0) - np.roll(curve, 1, 0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    side = np.cross(tangent, [0.0, 1.0, 0.0])
    side /= np.maximum(np.linalg.norm(side, axis=1, keepdims=True), 1e-9)
    up = np.cross(side, tangent)
    verts = (curve[:, None] + 0.45 * (np.cos(ring)[None, :, None] * side[:, None] + np.sin(ring)[None, :, None] * up[:, None]))
    n, m = len(t), len(ring)
    i, j = np.meshgrid(np.arange(n), np.arange(m), indexing="ij")
    a, b, c, d = i * m + j, ((i + 1) % n) * m + j, ((i + 1) % n) * m + (j + 1) % m, i * m + (j + 1) % m
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    v = verts.reshape(-1, 3) * 0.16 + [0.0, 0.3, 0.0]
    mesh = trimesh.Trimesh(v, faces, process=False)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(trimesh.exchange.ply.export_ply(mesh, encoding="binary", include_attributes=False))


def _natural_texture(seed: int, base, contrast: float, stretch: float = 1.0) -> np.ndarray:
    """A texture with natural (1/f) statistics: fractal noise (``scene_gen.textures.fbm``), stretched along x
    for grain, as linear RGB in [0, 1] (float32, TEXTURE_RES square)."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x7E57]))
    n = fbm(rng, TEXTURE_RES * 2)[:TEXTURE_RES, :TEXTURE_RES]
    if stretch != 1.0:
        k = max(1, int(round(stretch)))
        n = np.repeat(n[:, ::k], k, axis=1)[:, :TEXTURE_RES]
    n = (n - n.mean()) / max(n.std(), 1e-6)
    img = np.asarray(base, np.float64)[None, None] * np.exp(contrast * n)[..., None]
    return np.clip(img, 0.0, 1.0).astype(np.float32)


def textured_interior(folder: Path) -> dict:
    """A room with bitmap textures of natural statistics: writes ``textures/{wood,plaster,rug,oak}.exr``."""
    from core.images import write_exr
    (folder / "textures").mkdir(parents=True, exist_ok=True)
    textures = {"wood": _natural_texture(1, (0.42, 0.25, 0.12), 0.35, stretch=8.0),
                "plaster": _natural_texture(2, (0.75, 0.72, 0.66), 0.08),
                "rug": _natural_texture(3, (0.55, 0.12, 0.1), 0.5),
                "oak": _natural_texture(4, (0.5, 0.34, 0.18), 0.25, stretch=4.0)}
    for name, img in textures.items():
        write_exr(folder / "textures" / f"{name}.exr", img)

    def tex(name, scale=1.0):
        return {"type": "diffuse", "reflectance": {"type": "bitmap", "filename": f"textures/{name}.exr",
                                                   "raw": True, "to_uv": np.diag([scale, scale, 1.0, 1.0])}}
    wall = lambda m: {"type": "rectangle", "to_world": m, "bsdf": {"type": "ref", "id": "plaster"}}  # noqa: E731
    return {"type": "scene", "integrator": {"type": "path", "max_depth": 6},
            "sensor": _sensor((1.6, 1.5, 2.6), (-0.5, 0.8, -0.8), 60.0),
            "wood": tex("wood", 3.0), "plaster": tex("plaster", 2.0), "rug-bsdf": tex("rug"), "oak": tex("oak"),
            "floor": _floor(3.0, "wood"),
            "ceiling": {"type": "rectangle", "to_world": _trs((0.0, 2.6, 0.0), (3.0, 3.0, 1.0), rotate_x=90.0),
                        "bsdf": {"type": "ref", "id": "plaster"}},
            "back-wall": wall(_trs((0.0, 1.3, -3.0), (3.0, 1.3, 1.0))),
            "left-wall": wall(_trs((-3.0, 1.3, 0.0), (3.0, 1.3, 1.0), rotate_y=90.0)),
            "right-wall": wall(_trs((3.0, 1.3, 0.0), (3.0, 1.3, 1.0), rotate_y=-90.0)),
            "front-wall": wall(_trs((0.0, 1.3, 3.0), (3.0, 1.3, 1.0), rotate_y=180.0)),
            "rug": {"type": "rectangle", "to_world": _trs((-0.3, 0.005, -0.4), (1.1, 0.8, 1.0), rotate_x=-90.0),
                    "bsdf": {"type": "ref", "id": "rug-bsdf"}},
            "table-top": {"type": "cube", "to_world": _trs((-0.6, 0.75, -1.2), (0.7, 0.04, 0.45)),
                          "bsdf": {"type": "ref", "id": "oak"}},
            "table-leg": {"type": "cube", "to_world": _trs((-0.6, 0.37, -1.2), (0.06, 0.37, 0.06)),
                          "bsdf": {"type": "ref", "id": "oak"}},
            "vase": {"type": "cylinder", "p0": [-0.4, 0.79, -1.1], "p1": [-0.4, 1.1, -1.1], "radius": 0.08,
                     "bsdf": {"type": "roughplastic", "diffuse_reflectance": _rgb(0.1, 0.3, 0.5), "alpha": 0.1}},
            "window": {"type": "rectangle", "to_world": _trs((-2.99, 1.5, -0.5), (0.9, 0.6, 1.0), rotate_y=90.0),
                       "emitter": {"type": "area", "radiance": _rgb(9.0, 9.5, 11.0)}},
            "lamp": {"type": "sphere", "center": [0.8, 2.35, 0.4], "radius": 0.06,
                     "emitter": {"type": "area", "radiance": _rgb(400.0, 330.0, 240.0)}}}


def glass(folder: Path) -> dict:
    """Smooth, rough and thin dielectrics on a fine checker floor under an area light."""
    return {"type": "scene", "integrator": {"type": "path", "max_depth": 8},
            "sensor": _sensor((0.0, 1.5, 3.8), (0.0, 0.4, 0.0), 45.0),
            "checks": {"type": "diffuse", "reflectance": {"type": "checkerboard", "color0": _rgb(0.8, 0.8, 0.78),
                                                          "color1": _rgb(0.1, 0.1, 0.12),
                                                          "to_uv": np.diag([12.0, 12.0, 1.0, 1.0])}},
            "floor": _floor(4.0, "checks"),
            "back": {"type": "rectangle", "to_world": _trs((0.0, 2.0, -2.0), (4.0, 2.0, 1.0)),
                     "bsdf": {"type": "diffuse", "reflectance": _rgb(0.5, 0.5, 0.55)}},
            "ball": {"type": "sphere", "center": [-0.9, 0.45, 0.2], "radius": 0.45,
                     "bsdf": {"type": "dielectric", "int_ior": 1.5}},
            "frosted": {"type": "cube", "to_world": _trs((0.35, 0.35, -0.3), (0.35, 0.35, 0.35), rotate_y=30.0),
                        "bsdf": {"type": "roughdielectric", "int_ior": 1.5, "alpha": 0.15}},
            "pane": {"type": "rectangle", "to_world": _trs((1.1, 0.5, 0.6), (0.35, 0.5, 1.0), rotate_y=-35.0),
                     "bsdf": {"type": "thindielectric", "int_ior": 1.5}},
            "light": {"type": "rectangle", "to_world": _trs((0.3, 2.4, 0.6), (0.5, 0.5, 1.0), rotate_x=90.0),
                      "emitter": {"type": "area", "radiance": _rgb(14.0, 13.5, 12.0)}},
            "sky": {"type": "constant", "radiance": _rgb(0.05, 0.05, 0.06)}}


def write_suite(out) -> list[Path]:
    """Write the suite's scene files (and their textures and meshes) into ``out``; each is loaded back with
    ``mi.load_file`` (a :class:`SceneFileError` names one that does not load). Returns the XML paths."""
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    builders = {"cornell-box": lambda: cornell_box(), "metals": lambda: metals(),
                "envmap-object": lambda: envmap_object(folder), "textured-interior": lambda: textured_interior(folder),
                "glass": lambda: glass(folder)}
    written = []
    for name in SUITE:
        path = folder / f"{name}.xml"
        text = to_xml(builders[name]())
        if not path.exists() or path.read_text() != text:
            path.write_text(text)
        load_file(path)
        written.append(path)
    return written
