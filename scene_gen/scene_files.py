"""A user's Mitsuba scene files: a scene source beside the generator.

A dataset's scene group may name a scene file (XML, with the meshes and textures it names) or a folder of
them (``pipeline.config``: ``{file: PATH, count: N, frames: F, camera: {...}}``). Each scene of such a
group is one file seen through cameras of its own:

- **The file is the content.** Its shapes, BSDFs, textures and emitters render as the file has them; the
  lights stay the file's. Its sensor, film, sampler and integrator are replaced by the dataset's (the
  render settings' film size and pixel filter, and the ``path`` integrator with the file's own
  ``max_depth`` where its integrator is ``path``, else :data:`DEFAULT_BOUNCES` bounces; Russian roulette
  off, as for generated scenes: ``scene_gen.to_mitsuba.integrator_dict``).
- **Cameras vary around the file's sensor**, drawn from the scene's seed (:func:`file_spec`): the base
  camera is the file's sensor (``perspective`` or ``thinlens``; its horizontal field of view is kept at
  the dataset's aspect ratio), or the group's ``camera:`` where it gives one. A still moves the camera by
  up to ``jitter`` times the distance ``d`` to what the sensor looks at (the first hit of its central
  ray), the point looked at by up to ``turn`` d, and scales the field of view by up to ``exp(zoom)``; a
  clip starts there and travels ``move`` d along a straight path (perpendicular to the view), so its
  frames have camera motion and motion vectors. ``jitter: 0, turn: 0, zoom: 0`` is the file's own view
  (at the dataset's resolution; a sensor that mirrors the image is refused, and so is a scene reaching
  past the far clip plane, ``to_mitsuba.FAR_CLIP``, from its camera).
- **Recorded and checked.** A scene's ``SceneSpec`` names the file (absolute path) and the SHA-256 of its
  content (:func:`content_hash`: the XML and every file it names, in order), and every frame's load
  checks it: a file changed since its scene was described is refused (:class:`SceneFileError`).
- **One-line errors** (:class:`~scene_gen.errors.SceneFileError`): a path that is missing or holds no
  ``.xml``; a file that does not parse or does not load (the loader's message, on one line); a plugin
  the Mitsuba variant lacks; a scene with no sensor and no ``camera:``; a sensor that is not a
  perspective or thin-lens camera.

Not rendered: participating media (the ``path`` integrator ignores them) and the file's own integrator
settings other than ``max_depth``.
"""
from __future__ import annotations

import hashlib
import math
import re
import threading
from contextlib import contextmanager
import xml.etree.ElementTree as ET
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from core.checks import is_number, known_keys, need
from scene_gen import to_mitsuba
from scene_gen.errors import SceneFileError
from scene_gen.spec import CameraSpec, SceneFile, SceneSpec

DEFAULT_BOUNCES = 5            # path bounces where the file's integrator says none (the generator's default)
MAX_BOUNCES = 64
CAMERA_DRAW = 0xF11E           # SeedSequence([scene seed, CAMERA_DRAW]) draws a file scene's cameras
KIND = "file"                  # frames/kind of a scene file's frames


@dataclass(frozen=True)
class CameraSettings:
    """How a scene group's cameras vary around the file's sensor (the module docstring); ``origin``,
    ``target``, ``up``, ``fov``, ``aperture_radius`` and ``focus_distance`` replace the sensor's (a file
    without a sensor needs at least ``origin`` and ``target``)."""
    origin: tuple | None = None
    target: tuple | None = None
    up: tuple | None = None
    fov: float | None = None
    aperture_radius: float | None = None
    focus_distance: float | None = None
    jitter: float = 0.05
    turn: float = 0.03
    zoom: float = 0.1
    move: float = 0.1

    @classmethod
    def from_dict(cls, d, where: str = "camera") -> "CameraSettings":
        d = known_keys(d, cls, where, SceneFileError)
        for k in ("origin", "target", "up"):
            v = d.get(k)
            if v is not None:
                need(isinstance(v, (list, tuple)) and len(v) == 3 and all(is_number(x, finite=True) for x in v),
                     f"{where}.{k}", "three finite numbers", v, SceneFileError)
                d[k] = tuple(float(x) for x in v)
        fov = d.get("fov")
        need(fov is None or (is_number(fov, finite=True) and 0 < fov < 180), f"{where}.fov",
             "a horizontal field of view in degrees, in (0, 180)", fov, SceneFileError)
        for k in ("aperture_radius", "focus_distance", "jitter", "turn", "zoom", "move"):
            v = d.get(k)
            need(v is None or (is_number(v, finite=True) and v >= 0), f"{where}.{k}", "a finite number >= 0", v,
                 SceneFileError)
        if d.get("focus_distance") == 0:
            raise SceneFileError(f"{where}.focus_distance must be > 0, got 0")
        return cls(**d)

    def to_dict(self) -> dict:
        """The settings given (every field that is not None), plain data."""
        return {f.name: (list(v) if isinstance(v, tuple) else v) for f in fields(self)
                if (v := getattr(self, f.name)) is not None}


# ------------------------------------------------------------------------------------------------
# files, their references and their content hash (no Mitsuba)
def scene_list(path) -> list[Path]:
    """The scene files a group names: the file itself, or a folder's ``*.xml`` in name order (absolute)."""
    p = Path(path).expanduser()
    if p.is_dir():
        found = sorted(q.resolve() for q in p.iterdir() if q.suffix.lower() == ".xml" and q.is_file())
        if not found:
            raise SceneFileError(f"scene folder {str(p)!r} holds no Mitsuba scene file (*.xml)")
        return found
    if not p.exists():
        hint = (": the real-scene suite's files are written by `python -m scene_gen real-scenes --out "
                f"{str(p)}` (`make real-scenes` does it first)") if p.name == "real-scenes" else ""
        raise SceneFileError(f"scene file {str(p)!r} does not exist{hint}")
    if not p.is_file():
        raise SceneFileError(f"scene file {str(p)!r} is not a file")
    return [p.resolve()]


def _parse(path: Path) -> ET.Element:
    try:
        return ET.parse(path).getroot()
    except ET.ParseError as e:
        raise SceneFileError(f"scene file {str(path)!r} is not valid XML: {e}") from None
    except OSError as e:
        raise SceneFileError(f"scene file {str(path)!r} cannot be read: {e.strerror or e}") from None


def referenced_files(path) -> list[Path]:
    """The files a scene file names, found as Mitsuba's loader finds them, in document order, each once:
    every ``filename`` (``<string name="filename">``, ``<include filename>``, a ``filename`` attribute), with
    ``$name`` filled from the file's ``<default>`` values, looked for in the main file's folder, then each
    ``<path value>`` folder, then the folder of the file that names it (an included file's); included XML
    files are read in turn. A name found nowhere is an error (:class:`SceneFileError`)."""
    main = Path(path).resolve()
    folders = [main.parent]
    defaults: dict[str, str] = {}
    out: list[Path] = []
    seen: set[Path] = set()

    def find(name: str, here: Path) -> Path:
        name = re.sub(r"\$(\w+)", lambda m: defaults.get(m.group(1), m.group(0)), name)
        if "$" in name:
            raise SceneFileError(f"scene file {str(main)!r} names {name!r}, a parameter without a <default>: "
                                 "give it one in the file")
        for folder in [*folders, here]:
            q = (folder / name).resolve()
            if q.exists():
                return q
        raise SceneFileError(f"scene file {str(main)!r} names {name!r}, which is neither in its folder nor in "
                             f"the folders it adds ({', '.join(str(f) for f in folders)})")

    def visit(p: Path):
        for el in _parse(p).iter():
            if el.tag == "default" and el.get("name"):
                defaults.setdefault(el.get("name"), el.get("value", ""))
            elif el.tag == "path" and el.get("value"):
                folders.append((p.parent / el.get("value")).resolve())
            name = el.get("value") if el.tag == "string" and el.get("name") == "filename" else el.get("filename")
            if not name:
                continue
            q = find(name, p.parent)
            if q in seen:
                continue
            seen.add(q)
            out.append(q)
            if el.tag == "include" and q.suffix.lower() == ".xml":
                visit(q)
    visit(main)
    return out


_hashes: dict = {}          # (path, the stats of it and of every file it names) -> content hash


def content_hash(path) -> str:
    """SHA-256 (hex) of a scene file's content: its bytes, then each file it names (:func:`referenced_files`)
    with its name relative to the scene's folder and its bytes. A named file that is missing is an error.
    Kept per process for files whose sizes and modification times have not changed (a config is built
    several times a run, and every frame's load checks its file)."""
    p = Path(path).resolve()
    refs = referenced_files(p)
    try:
        key = (str(p), *((str(q), q.stat().st_size, q.stat().st_mtime_ns) for q in [p, *refs]))
    except OSError as e:
        raise SceneFileError(f"scene file {str(p)!r}: a file it names cannot be read: {e.strerror or e}") from None
    if key in _hashes:
        return _hashes[key]
    h = hashlib.sha256()
    try:
        h.update(p.read_bytes())
    except OSError as e:
        raise SceneFileError(f"scene file {str(p)!r} cannot be read: {e.strerror or e}") from None
    for q in refs:
        try:
            data = q.read_bytes()
        except OSError as e:
            raise SceneFileError(f"scene file {str(p)!r} names {str(q)!r}, which cannot be read: "
                                 f"{e.strerror or e}") from None
        rel = str(q.relative_to(p.parent)) if q.is_relative_to(p.parent) else str(q)
        h.update(b"\0" + rel.encode() + b"\0" + hashlib.sha256(data).digest())
    _hashes[key] = h.hexdigest()
    return _hashes[key]


def has_sensor(path) -> bool:
    """Whether a scene file (or a file it includes) declares a ``<sensor>``."""
    p = Path(path)
    root = _parse(p)
    if any(el.tag == "sensor" for el in root.iter()):
        return True
    return any(has_sensor(q) for q in referenced_files(p) if q.suffix.lower() == ".xml" and q.is_file())


# ------------------------------------------------------------------------------------------------
# loading (Mitsuba)
def _one_line(path, e: Exception, mi) -> SceneFileError:
    """The loader's error as one line naming the file (Mitsuba's messages span lines and carry source
    locations); a missing plugin says so, with the variant."""
    text = re.sub(r"\[[\w.]+:\d+\]\s*", "", " ".join(str(e).split()))
    m = re.search(r'[Pp]lugin "?([\w-]+)"? (?:not found|is not available|does not exist)', text) or \
        re.search(r'unknown plugin (?:type )?"?([\w-]+)"?', text, re.IGNORECASE)
    if m:
        return SceneFileError(f"scene file {str(path)!r} uses the plugin {m.group(1)!r}, which Mitsuba's "
                              f"{mi.variant()} variant does not have ({text})")
    return SceneFileError(f"scene file {str(path)!r} does not load: {text}")


LOAD_THREADS = 2       # drjit's pool while a file loads (its OpenEXR reader waits on the pool's other thread)


def load_file(path):
    """``mi.load_file(path)`` with its errors as one line (:class:`SceneFileError`), on the calling thread
    (``parallel=False``: the same objects in the same order every time). drjit's thread pool is at least
    :data:`LOAD_THREADS` while it loads: with the one thread a Dask worker gives it, Mitsuba's OpenEXR reader
    (an EXR texture or environment map) hands its lines to the pool and waits forever (measured: the
    real-scene suite's ``envmap-object.xml`` hung every worker; a plain process with ``dr.set_thread_count(1)``
    hangs too). The pool is set back after."""
    from core.variant import mitsuba
    mi = mitsuba()
    with _load_threads():
        try:
            return mi.load_file(str(path), parallel=False)
        except Exception as e:          # Mitsuba raises RuntimeError (and others) for a file it cannot load
            raise _one_line(path, e, mi) from None


_loads = {"count": 0, "before": 0}
_loads_lock = threading.Lock()


@contextmanager
def _load_threads():
    """drjit's pool at :data:`LOAD_THREADS` at least while any thread of the process loads a file (the pool is
    process-wide: the last load to end sets it back, so one ending never shrinks another's)."""
    import drjit as dr
    with _loads_lock:
        if _loads["count"] == 0:
            _loads["before"] = dr.thread_count()
            if _loads["before"] < LOAD_THREADS:
                dr.set_thread_count(LOAD_THREADS)
        _loads["count"] += 1
    try:
        yield
    finally:
        with _loads_lock:
            _loads["count"] -= 1
            if _loads["count"] == 0 and _loads["before"] < LOAD_THREADS:
                dr.set_thread_count(_loads["before"])


def inspect(path, settings: CameraSettings) -> dict:
    """What a file's scenes are made from, asked of the loaded file: ``camera`` (the base ``CameraSpec``:
    the sensor, or ``settings``' values over it), ``distance`` (what the base camera looks at: its
    target's distance) and ``max_depth`` (bounces). Checks what :func:`load_frame` will need (the file
    loads, has a sensor or ``settings`` a camera, the sensor is a perspective or thin-lens camera)."""
    from core.variant import mitsuba
    mi = mitsuba()
    p = Path(path)
    scene = load_file(p)
    sensor = scene.sensors()[0] if has_sensor(p) and scene.sensors() else None
    if sensor is None and (settings.origin is None or settings.target is None):
        raise SceneFileError(f"scene file {str(p)!r} has no sensor: give its scene group a camera (camera: "
                             "{origin: [x, y, z], target: [x, y, z], fov: degrees})")
    base = _sensor_camera(mi, scene, sensor, p) if sensor is not None else None
    cam = _with_settings(base, settings)
    dist = float(np.linalg.norm(np.subtract(cam.target, cam.origin)))
    _check_extent(scene, cam, p)
    return {"camera": cam.to_dict(), "distance": dist, "max_depth": _bounces(scene.integrator())}


def _sensor_camera(mi, scene, sensor, path: Path) -> CameraSpec:
    """The file's sensor as a ``CameraSpec``: its position, view and up axes and horizontal field of view;
    the target is the first hit of its central ray (else its focus distance, else the scene's bounds)."""
    text = str(sensor)
    if not text.startswith(("PerspectiveCamera", "ThinLensCamera")):
        raise SceneFileError(f"scene file {str(path)!r}: its sensor is a {text.split('[')[0]}, not a perspective "
                             "or thinlens camera; give its scene group a camera (camera: {origin, target, fov})")
    params = mi.traverse(sensor)
    m = np.array(sensor.world_transform().matrix, np.float64).reshape(4, 4)
    if np.linalg.det(m[:3, :3]) < 0:
        raise SceneFileError(f"scene file {str(path)!r}: its sensor's to_world mirrors the image (a negative scale); "
                             "the dataset's cameras are look-at cameras: give its scene group a camera (camera: "
                             "{origin, target, up, fov}) or remove the mirroring")
    origin, forward, up = m[:3, 3], m[:3, 2], m[:3, 1]
    forward = forward / np.linalg.norm(forward)
    ray = mi.Ray3f(mi.Point3f(*map(float, origin)), mi.Vector3f(*map(float, forward)))
    t = float(np.ravel(scene.ray_intersect(ray).t)[0])
    aperture = float(np.ravel(params["aperture_radius"])[0]) if "aperture_radius" in params else 0.0
    focus = float(np.ravel(params["focus_distance"])[0]) if "focus_distance" in params else 0.0
    if not (math.isfinite(t) and t > 0):
        bb = scene.bbox()
        t = focus if focus > 0 else max(float(np.linalg.norm(np.subtract(bb.center(), origin))), 1e-3)
    fov = float(np.ravel(params["x_fov"])[0])
    return CameraSpec(origin=tuple(origin), target=tuple(origin + forward * t), up=tuple(up / np.linalg.norm(up)),
                      fov=fov, aperture_radius=aperture, focus_distance=focus if focus > 0 else t)


def _check_extent(scene, cam: CameraSpec, path: Path) -> None:
    """Refuse a scene that reaches past the dataset's far clip plane from its camera (``to_mitsuba.FAR_CLIP``,
    the cameras of every source: a scene modelled in millimetres would lose what lies beyond it)."""
    bb = scene.bbox()
    lo, hi = np.asarray(bb.min, np.float64).ravel(), np.asarray(bb.max, np.float64).ravel()
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    far = float(np.max(np.linalg.norm(corners - np.asarray(cam.origin), axis=1))) if np.isfinite(corners).all() else 0.0
    if far > to_mitsuba.FAR_CLIP:
        raise SceneFileError(f"scene file {str(path)!r} reaches {far:.4g} units from its camera, past the far clip "
                             f"plane at {to_mitsuba.FAR_CLIP:g}: scale the scene down (e.g. millimetres to metres)")


def _with_settings(base: CameraSpec | None, s: CameraSettings) -> CameraSpec:
    """The base camera: ``base`` (the file's sensor) with what ``s`` gives in its place."""
    d = base.to_dict() if base is not None else {"up": (0.0, 1.0, 0.0), "fov": 40.0}
    for k in ("origin", "target", "up", "fov", "aperture_radius", "focus_distance"):
        v = getattr(s, k)
        if v is not None:
            d[k] = v
    if base is None and s.focus_distance is None:
        d["focus_distance"] = float(np.linalg.norm(np.subtract(d["target"], d["origin"])))
    try:
        return CameraSpec.from_dict(d)
    except Exception as e:          # SpecError: the camera's own message
        raise SceneFileError(f"camera: {e}") from None


def _bounces(integrator) -> int:
    """Path bounces of the file's integrator: ``max_depth - 1`` of a ``path`` integrator with a finite depth
    (at most :data:`MAX_BOUNCES`), else :data:`DEFAULT_BOUNCES`."""
    m = re.search(r"max_depth = (-?\d+)", str(integrator)) if str(integrator).startswith("PathIntegrator") else None
    depth = int(m.group(1)) if m else -1
    return min(depth - 1, MAX_BOUNCES) if depth >= 2 else DEFAULT_BOUNCES


# ------------------------------------------------------------------------------------------------
# a scene of the file: its cameras (numpy only) and its frames' loads
def file_spec(path, sha256: str, info: dict, settings: CameraSettings, seed: int, num_frames: int) -> SceneSpec:
    """The ``SceneSpec`` of one scene of a file: ``num_frames`` cameras drawn around ``info``'s base camera
    (:func:`inspect`) from ``SeedSequence([seed, CAMERA_DRAW])`` (the module docstring), no objects, no
    lights, no shutter (nothing in a file moves), the file's bounces and its ``source``."""
    base = CameraSpec.from_dict(info["camera"])
    d = float(info["distance"])
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), CAMERA_DRAW]))
    o0, t0 = np.asarray(base.origin), np.asarray(base.target)
    start_o = o0 + _in_ball(rng) * settings.jitter * d
    start_t = t0 + _in_ball(rng) * settings.turn * d
    fov = float(np.clip(base.fov * math.exp(rng.uniform(-settings.zoom, settings.zoom)), 1.0, 170.0))
    step = _across(rng, t0 - o0) * settings.move * d
    cams = []
    for f in range(num_frames):
        s = f / (num_frames - 1) if num_frames > 1 else 0.0
        cams.append(CameraSpec(origin=tuple(start_o + step * s), target=tuple(start_t + 0.5 * step * s), up=base.up,
                               fov=fov, aperture_radius=base.aperture_radius, focus_distance=base.focus_distance))
    return SceneSpec(kind=KIND, seed=int(seed), objects=(), lights=(), cameras=tuple(cams), shutter=0.0,
                     max_depth=int(info["max_depth"]), source=SceneFile(path=str(Path(path).resolve()), sha256=sha256))


def _in_ball(rng: np.random.Generator) -> np.ndarray:
    """A point uniform in the unit ball."""
    v = rng.standard_normal(3)
    return v / max(np.linalg.norm(v), 1e-12) * rng.uniform() ** (1.0 / 3.0)


def _across(rng: np.random.Generator, view: np.ndarray) -> np.ndarray:
    """A unit direction perpendicular to ``view`` (uniform around it)."""
    view = view / max(np.linalg.norm(view), 1e-12)
    v = rng.standard_normal(3)
    v -= v.dot(view) * view
    n = np.linalg.norm(v)
    return v / n if n > 1e-9 else np.cross(view, [0.0, 1.0, 0.0] if abs(view[1]) < 0.9 else [1.0, 0.0, 0.0])


def load_frame(spec: SceneSpec, frame: int, res: tuple[int, int], *, rfilter: str = "box", on_loaded=None):
    """Frame ``frame`` of a scene file's ``spec`` loaded into Mitsuba (``scene_gen.to_mitsuba.LoadedScene``):
    the file's shapes and emitters under the frame's camera, the film (``res``, ``rfilter``) and the
    ``path`` integrator. The file must still have the content the spec recorded."""
    src = spec.source
    now = content_hash(src.path)
    if now != src.sha256:
        raise SceneFileError(f"scene file {src.path!r} changed since its scene was described (SHA-256 "
                             f"{src.sha256[:12]}... then, {now[:12]}... now): render it into a new store")
    loaded = load_file(src.path)
    parts = {f"shape-{i:05d}": s for i, s in enumerate(loaded.shapes())}
    parts.update({f"emitter-{i:05d}": e for i, e in enumerate(loaded.emitters()) if e.get_shape() is None})
    cam = spec.camera(frame)
    from core.variant import mitsuba
    scene = mitsuba().load_dict(to_mitsuba.file_scene_dict(parts, spec, cam, res, rfilter))
    del loaded, parts
    if on_loaded is not None:
        on_loaded(scene)
    return to_mitsuba.LoadedScene(scene=scene, seed=int(spec.seed), frame=int(frame), num_frames=spec.num_frames,
                                  case=spec.case, kind=spec.kind, shutter=float(spec.shutter), res=res, camera=cam,
                                  prev_camera=spec.camera(frame - 1) if frame > 0 else cam,
                                  integrator=to_mitsuba.integrator_dict(spec))
