"""Noisebase's per-sample format, ``sampleset_v1`` (github balintio/noisebase): its encodings, its
camera, and a reader that trains our ``samples`` and ``clips`` input kinds on Noisebase sequences.

**The format** (Noisebase's "Sample Training Format v1"; :mod:`pipeline.noisebase` writes it): one Zarr
v2 ``ZipStore`` per sequence of ``F`` frames, every array ``[F, C, H, W, S]`` (samples last), Blosc
LZ4HC level 9, chunked per frame and per :data:`CHUNK_SAMPLES` samples:

==================  =====================  =======  ============================================
array               shape                  dtype    what
==================  =====================  =======  ============================================
``color``           ``[F, 4, H, W, S]``    uint8    radiance, RGBE (:func:`rgbe_encode`)
``exposure``        ``[F, 2]``             float32  ``[min, max]`` log radiance of the frame
``reference``       ``[F, 3, H, W]``       float32  clean radiance
``position``        ``[F, 3, H, W, S]``    float32  world-space position of the sample's hit
``motion``          ``[F, 3, H, W, S]``    float32  world position one frame earlier minus now
``normal``          ``[F, 3, H, W, S]``    float16  world-space normal
``diffuse``         ``[F, 3, H, W, S]``    float16  diffuse colour (our ``albedo``)
``camera_position`` ``[F, 3]``             float32  camera centre
``camera_target``   ``[F, 3]``             float32  a point the camera looks at (frame centre)
``camera_up``       ``[F, 3]``             float32  world vector pointing up on screen
``proj_mat``        ``[F, 4, 4]``          float32  camera-to-clip (column vectors, view x right,
                                                    y up, z forward; :func:`view_proj`)
``view_proj_mat``   ``[F, 4, 4]``          float32  world-to-clip, row vectors (``p @ M``)
``crop_offset``     ``[F, 2]``             int32    the frame's window in the rendering (0, 0)
==================  =====================  =======  ============================================

Screen coordinates are Noisebase's (and ours): ``col = (x/w + 1) W / 2``, ``row = (1 - y/w) H / 2``.

**Reading** (:class:`NoisebaseStore`, zarr 3, without Noisebase's loader, which needs zarr 2): a folder of
sequences (``*.zip``, in name order; a ``noisebase.yaml`` beside them, as our export writes, names
them) read as a store of clips, one clip a sequence. Our per-sample ``features`` are made from what
the format holds: ``normal`` (world), ``depth`` (distance from the camera centre to ``position``),
``albedo`` (``diffuse``) and ``motion`` (screen motion in pixels, ``p_prev - p_cur``, x right, y down,
from ``position``, ``motion`` and the two frames' cameras; 0 on a sequence's first frame, as Noisebase
does). Those it does not hold, :data:`MISSING_FEATURES` (specular, roughness, coc, lens, time), are 0
and declared missing: a model that reads them is refused by name
(:func:`training.inputs.check_features`). The per-pixel guides are the samples' means;
``reference/stderr`` is 0 (the format has none). Splits are by sequence: those the folder declares (our
export's ``sequences.json`` gives each sequence file the split of the clip it came from), else ours
(:func:`stores.reader.split_of_clip` of the sequence index: Noisebase's own data declares none);
``split_source`` says which, and a training run records it. A missing file is never zeros here either:
a chunk missing from a sequence's zip (which zarr reads as its fill value) is ``MissingShardError``, and
one that does not decode or fails the zip's CRC ``CorruptChunkError``, each naming the sequence, array,
frame and chunk key; a sequence file that is not a whole zip (cut short: no central directory) and a
sequence missing one of the format's arrays while holding others are ``StoreCorruptionError``, naming
the file (training exits 3 on each, as for a damaged store of ours). A zip holding none of the format's
arrays is not a sequence (NoisebaseError, exit 2).
"""
from __future__ import annotations

import glob
import os

import numpy as np

from stores.contract import FEATURE_GROUPS, NUM_FEATURES
from stores.errors import (CorruptChunkError, MissingShardError, StoreCorruptionError, StoreError,
                           StoreNotFoundError)

FORMAT = "sampleset_v1"
CHUNK_SAMPLES = 4                 # samples a chunk (Noisebase: "chunked for every frame and every 4 samples")
PER_SAMPLE = ("color", "position", "motion", "normal", "diffuse")
PER_FRAME = ("exposure", "reference", "camera_position", "camera_target", "camera_up", "proj_mat",
             "view_proj_mat", "crop_offset")
HELD_FEATURES = ("normal", "depth", "albedo", "motion")
MISSING_FEATURES = tuple(g for g in FEATURE_GROUPS if g not in HELD_FEATURES)
YAML_NAME = "noisebase.yaml"


def compressor():
    """The format's chunk compressor: Blosc LZ4HC level 9 (byte shuffle)."""
    import numcodecs
    return numcodecs.Blosc(cname="lz4hc", clevel=9, shuffle=numcodecs.Blosc.SHUFFLE)


# ------------------------------------------------------------------------------------------------
# RGBE


def rgbe_encode(color: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Noisebase's RGBE encoding of radiance ``color (3, ...)`` (float, >= 0): ``(uint8 (4, ...),
    float32 [min, max])``. The exponent byte ``e`` quantises the log of the brightest channel over the
    frame's ``[min, max]`` log range (rounded up, so the decoded scale ``exp((e + 1) / 256 (max - min) +
    min)`` is at least the channel), the colour bytes are the channels over that scale times 255,
    dithered with ``rng`` (seeded by the caller: the same input gives the same bytes). Decoding
    (:func:`rgbe_decode`) errs by less than one colour step, ``scale / 255``, per channel. Zero (and
    negative) radiance encodes as 0. A frame whose non-zero radiance is one value gets a range of
    ``1e-6`` around it (Noisebase's own encoder divides by zero there)."""
    color = np.maximum(np.asarray(color, np.float32), 0.0)
    pos = color[color > 0]
    shape = (4,) + color.shape[1:]
    if pos.size == 0:
        return np.zeros(shape, np.uint8), np.zeros(2, np.float32)
    logs = np.log(pos.astype(np.float64))
    lo, hi = float(logs.min()), float(logs.max())
    if hi - lo < 1e-6:
        hi = lo + 1e-6
    lo, hi = float(np.float32(lo)), float(np.float32(hi))      # the exposure as stored (float32)
    bright = color.max(axis=0).astype(np.float64)
    with np.errstate(divide="ignore"):
        expo = np.where(bright > 0, np.log(np.where(bright > 0, bright, 1.0)), -np.inf)
    e = np.clip(np.floor((expo - lo) / (hi - lo) * 256), 0, 255)
    e = np.where(bright > 0, e, 0).astype(np.uint8)
    scale = np.exp((e.astype(np.float32) + 1) / 256 * np.float32(hi - lo) + np.float32(lo))   # as decoded
    rgb = color / scale[None] * 255
    q = np.floor(rgb)
    q = q + ((rgb - q) > rng.random(rgb.shape, dtype=np.float32))
    q = np.where(bright[None] > 0, np.clip(q, 0, 255), 0).astype(np.uint8)
    return np.concatenate([q, e[None]]), np.array([lo, hi], np.float32)


def rgbe_decode(rgbe: np.ndarray, exposure) -> np.ndarray:
    """Radiance ``(3, ...)`` float32 of RGBE bytes ``(4, ...)`` and the frame's ``[min, max]`` (Noisebase's
    ``decompress_RGBE``)."""
    lo, hi = float(exposure[0]), float(exposure[1])
    scale = np.exp((rgbe[3].astype(np.float32) + 1) / 256 * np.float32(hi - lo) + np.float32(lo))
    return rgbe[:3].astype(np.float32) / 255 * scale[None]


# ------------------------------------------------------------------------------------------------
# camera


def camera(camera_to_world: np.ndarray, world_to_clip: np.ndarray) -> dict[str, np.ndarray]:
    """Noisebase's camera arrays of a frame from ours (``scene_gen.projection``: Mitsuba's look-at frame, +x
    left, +y up, +z forward; OpenGL-like clip space with the same screen mapping as Noisebase's):
    ``camera_position``, ``camera_target`` (one unit along the view axis), ``camera_up``, ``proj_mat``
    (our ``world_to_clip`` times the inverse of Noisebase's view matrix, which is exact, so Noisebase's
    projection of any world point lands on our pixel) and ``view_proj_mat`` (row vectors, as its loader
    computes it)."""
    c2w = np.asarray(camera_to_world, np.float64)
    pos, up, fwd = c2w[:3, 3], c2w[:3, 1], c2w[:3, 2]
    view = view_matrix(pos + fwd, up, pos)
    proj = np.asarray(world_to_clip, np.float64) @ np.linalg.inv(view)
    return {"camera_position": pos.astype(np.float32), "camera_target": (pos + fwd).astype(np.float32),
            "camera_up": up.astype(np.float32), "proj_mat": proj.astype(np.float32),
            "view_proj_mat": (proj @ view).T.astype(np.float32)}


def view_matrix(target, up, pos) -> np.ndarray:
    """Noisebase's world-to-view matrix (float64 4x4, column vectors): rows right ``U = W x up``, up
    ``V = U x W``, forward ``W`` (normalised), then the translation by ``-pos``."""
    pos = np.asarray(pos, np.float64)
    W = _unit(np.asarray(target, np.float64) - pos)
    U = _unit(np.cross(W, np.asarray(up, np.float64)))
    V = _unit(np.cross(U, W))
    m = np.eye(4)
    m[:3, :3] = np.stack([U, V, W])
    m[:3, 3] = -m[:3, :3] @ pos
    return m


def view_proj(target, up, pos, proj) -> np.ndarray:
    """World-to-clip (float64 4x4, column vectors) of a frame's Noisebase camera arrays (no augmentation)."""
    return np.asarray(proj, np.float64) @ view_matrix(target, up, pos)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def pixels(world_to_clip: np.ndarray, pts: np.ndarray, height: int, width: int) -> np.ndarray:
    """Pixel coordinates ``(2, ...)`` (x right, y down) of world points ``pts (3, ...)``; points at or behind
    the camera plane give NaN."""
    m = np.asarray(world_to_clip, np.float64)
    p = np.asarray(pts, np.float64)
    cx, cy, cw = (m[i, 0] * p[0] + m[i, 1] * p[1] + m[i, 2] * p[2] + m[i, 3] for i in (0, 1, 3))
    with np.errstate(divide="ignore", invalid="ignore"):
        ok = cw > 0
        x = np.where(ok, (cx / cw + 1.0) * 0.5 * width, np.nan)
        y = np.where(ok, (1.0 - cy / cw) * 0.5 * height, np.nan)
    return np.stack([x, y])


def screen_motion(position, motion, m_cur, m_prev, height: int, width: int) -> np.ndarray:
    """Screen motion (float32 ``(2, ...)``, pixels, ``p_prev - p_cur``, x right, y down) of samples at world
    ``position`` that were at ``position + motion`` one frame earlier; NaN (a point behind a camera) -> 0."""
    cur = pixels(m_cur, position, height, width)
    prev = pixels(m_prev, np.asarray(position, np.float64) + np.asarray(motion, np.float64), height, width)
    d = prev - cur
    return np.where(np.isfinite(d), d, 0.0).astype(np.float32)


# ------------------------------------------------------------------------------------------------
# reading


class NoisebaseError(StoreError):
    """A folder that is not a set of readable sampleset_v1 sequences, or a sequence that breaks the format."""


SEQUENCES_JSON = "sequences.json"


def declared_splits(path, files: list[str]) -> list[str] | None:
    """The split of each sequence file that the folder's ``sequences.json`` declares (our export writes
    one: ``{"sequences": [{"file", "split", ...}]}``), in the order of ``files``; None when the folder
    has none (Noisebase's own data). A ``sequences.json`` that does not declare a split for every file
    is NoisebaseError: reading some sequences by their declared split and others by ours could put a
    test clip into training."""
    import json
    j = os.path.join(os.fspath(path), SEQUENCES_JSON)
    if not os.path.isfile(j):
        return None
    try:
        with open(j) as f:
            rows = json.load(f)["sequences"]
        declared = {str(r["file"]): str(r["split"]) for r in rows if "split" in r}
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise NoisebaseError(f"{j} does not list the sequences' splits ({type(e).__name__}: {e})") from None
    names = [os.path.basename(f) for f in files]
    missing = [n for n in names if n not in declared]
    if missing:
        raise NoisebaseError(f"{j} declares no split for {len(missing)} of the {len(names)} sequences, e.g. "
                             f"{missing[0]}: give every sequence its split, or remove the file to use ours")
    return [declared[n] for n in names]


def is_noisebase(path) -> bool:
    """Whether ``path`` is a folder of Noisebase sequences (a ``noisebase.yaml`` or ``*.zip`` files, and no
    Zarr store of ours)."""
    p = os.fspath(path)
    if not os.path.isdir(p) or os.path.exists(os.path.join(p, "zarr.json")):
        return False
    return os.path.isfile(os.path.join(p, YAML_NAME)) or bool(glob.glob(os.path.join(p, "*.zip")))


def sequence_files(path) -> list[str]:
    """The sequence files of a folder: ``noisebase.yaml``'s ``src.files`` pattern over ``src.sequences``
    where the file is there, else every ``*.zip`` in name order."""
    p = os.fspath(path)
    y = os.path.join(p, YAML_NAME)
    if os.path.isfile(y):
        import yaml
        with open(y) as f:
            src = (yaml.safe_load(f) or {}).get("src", {})
        try:
            files = [os.path.join(p, src["files"].format(index=i)) for i in range(int(src["sequences"]))]
        except (KeyError, ValueError, TypeError) as e:
            raise NoisebaseError(f"{y}: src.files and src.sequences do not name the sequences ({e})") from None
        missing = [f for f in files if not os.path.isfile(f)]
        if missing:
            raise NoisebaseError(f"{y} names {len(files)} sequences; {len(missing)} are not there, e.g. {missing[0]}")
        return files
    files = sorted(glob.glob(os.path.join(p, "*.zip")))
    if not files:
        raise StoreNotFoundError(f"{p} holds no Noisebase sequences (*.zip) and no {YAML_NAME}")
    return files


ARRAYS = ("inputs/radiance", "inputs/features", "reference/radiance", "reference/stderr", "guides/albedo",
          "guides/normal", "guides/depth", "guides/motion")


class NoisebaseStore:
    """A folder of Noisebase ``sampleset_v1`` sequences read as a :class:`stores.protocol.TrainingStore`
    (what training, evaluation and the fitness screen use). Frame ``i`` is frame ``i - offset`` of its
    sequence. See the module docstring."""

    schema_version = "noisebase-" + FORMAT
    missing_features = MISSING_FEATURES

    def __init__(self, path):
        from stores.schema import StoreLayout
        self.path = os.fspath(path)
        self.files = sequence_files(self.path)
        self._groups: dict[int, object] = {}
        self._members: dict[int, frozenset] = {}
        self._moves: dict[int, bool] = {}
        self.frames_per_sequence, shapes = [], set()
        for n, f in enumerate(self.files):
            color = self._array(n, "color")
            if color.ndim != 5 or color.shape[1] != 4 or color.dtype != np.uint8:
                raise NoisebaseError(f"{f}: color must be uint8 [F, 4, H, W, S], got {color.dtype} {color.shape}")
            self.frames_per_sequence.append(int(color.shape[0]))
            shapes.add(color.shape[2:])
        if len(shapes) != 1:
            raise NoisebaseError(f"{self.path}: the sequences differ in H, W, S: {sorted(shapes)}")
        H, W, S = shapes.pop()
        self.offsets = np.concatenate([[0], np.cumsum(self.frames_per_sequence)]).astype(int)
        self.layout = StoreLayout(num_frames=int(self.offsets[-1]), height=int(H), width=int(W), spp=int(S),
                                  layer_spp=())
        self.config = {"source": "noisebase", "format": FORMAT, "files": [os.path.basename(f) for f in self.files]}
        self._declared = declared_splits(self.path, self.files)
        self.split_source = (f"declared ({SEQUENCES_JSON})" if self._declared is not None
                             else "ours (a hash of the sequence index)")

    # -- the sequences
    def _group(self, n: int):
        g = self._groups.get(n)
        if g is None:
            import zipfile

            import zarr
            try:
                with zipfile.ZipFile(self.files[n]) as z:          # the members: what a read may rely on
                    self._members[n] = frozenset(z.namelist())
            except (zipfile.BadZipFile, EOFError) as e:            # cut short or overwritten: lost data
                raise StoreCorruptionError(f"{self.files[n]} is not a whole zip file ({e}): the sequence file is "
                                           "truncated or damaged; copy or export it again", path=self.files[n]) from e
            except OSError as e:
                raise NoisebaseError(f"{self.files[n]} cannot be read: {e}") from e
            try:
                g = zarr.open_group(zarr.storage.ZipStore(self.files[n], mode="r"), mode="r", zarr_format=2)
            except Exception as e:                     # zarr raises many kinds for a file that is not a store
                raise NoisebaseError(f"{self.files[n]} is not a readable Zarr v2 zip store: {e}") from e
            self._groups[n] = g
        return g

    def _array(self, n: int, name: str):
        g = self._group(n)
        try:
            return g[name]
        except KeyError:
            needed = PER_SAMPLE + PER_FRAME[:6]
            held = [k for k in PER_SAMPLE + PER_FRAME if k in self._members[n] or
                    any(m.startswith(k + "/") for m in self._members[n])]
            if held:                   # a sequence that lost an array: damage, as a lost chunk is
                raise StoreCorruptionError(f"{self.files[n]} has no array {name!r}, which every sampleset_v1 "
                                           f"sequence holds (it has {', '.join(held)}): the sequence file is "
                                           "damaged; copy or export it again", array=name,
                                           path=self.files[n]) from None
            raise NoisebaseError(f"{self.files[n]} has no array {name!r} (sampleset_v1 needs "
                                 f"{', '.join(needed)})") from None

    def _read(self, n: int, name: str, sel, frame: int) -> np.ndarray:
        """``array[sel]`` of sequence ``n`` (``sel`` within frame ``frame`` of a per-frame array, or the
        whole of a small per-sequence one). Zarr reads a chunk missing from the zip as its fill value; here
        a missing chunk of the frame's row is :class:`MissingShardError` and one that does not decode (or
        fails the zip's CRC) :class:`CorruptChunkError`, each naming the sequence, array and chunk."""
        a = self._array(n, name)
        row = frame // a.chunks[0]
        for key in self._chunk_keys(a, row):
            if key not in self._members[n]:
                raise MissingShardError(f"{self.files[n]}: chunk {key} of {name!r} (frame {frame} of the sequence) "
                                        "is missing from the zip; a missing chunk is lost data, not zeros",
                                        array=name, frame=frame, path=f"{self.files[n]}:{key}")
        try:
            return np.asarray(a[sel])
        except Exception as e:         # noqa: BLE001  Blosc, zipfile (bad CRC), numcodecs raise many kinds
            keys = ", ".join(self._chunk_keys(a, row)[:2])
            raise CorruptChunkError(f"{self.files[n]}: a chunk of {name!r} (frame {frame} of the sequence: {keys}) "
                                    f"does not decode: {type(e).__name__}: {e}", array=name, frame=frame,
                                    path=f"{self.files[n]}:{keys}") from e

    @staticmethod
    def _chunk_keys(a, row: int) -> list[str]:
        """Zarr v2 keys of every chunk of array ``a`` in chunk row ``row`` of its first axis."""
        import itertools
        sep = a.metadata.dimension_separator or "."
        grid = [range(row, row + 1)] + [range(-(-s // c)) for s, c in zip(a.shape[1:], a.chunks[1:])]
        return [f"{a.path}/" + sep.join(map(str, idx)) for idx in itertools.product(*grid)]

    def _where(self, i: int) -> tuple[int, int]:
        if not 0 <= int(i) < self.num_frames:
            raise IndexError(f"frame {i} out of range: {self.path} has {self.num_frames} frames")
        n = int(np.searchsorted(self.offsets, int(i), side="right") - 1)
        return n, int(i) - int(self.offsets[n])

    def _matrix(self, n: int, f: int) -> np.ndarray:
        a = lambda k: np.asarray(self._read(n, k, f, f), np.float64)     # noqa: E731
        return view_proj(a("camera_target"), a("camera_up"), a("camera_position"), a("proj_mat"))

    # -- the Store interface
    @property
    def num_frames(self) -> int:
        return int(self.layout.num_frames)

    @property
    def split_fractions(self) -> dict:
        """Ours (``DEFAULT_SPLIT``), or for declared splits each split's share of the sequences (every
        split of ours named, so that an empty one is empty rather than unknown)."""
        from stores.reader import DEFAULT_SPLIT
        if self._declared is None:
            return dict(DEFAULT_SPLIT)
        names = list(DEFAULT_SPLIT) + sorted(set(self._declared) - set(DEFAULT_SPLIT))
        return {k: self._declared.count(k) / len(self._declared) for k in names}

    def _split_of_sequence(self, n: int) -> str:
        from stores.reader import split_of_clip
        return self._declared[n] if self._declared is not None else split_of_clip(n, self.split_fractions)

    def has_array(self, path: str) -> bool:
        return path in ARRAYS

    def complete_frames(self) -> list[int]:
        return list(range(self.num_frames))

    def incomplete_frames(self) -> list[int]:
        return []

    def meta_column(self, key: str) -> np.ndarray:
        """``clip_id`` (the sequence), ``frame`` (index in it), ``num_frames``; ``has_motion`` (the camera
        moves in the sequence, or its last frame's samples have non-zero world motion: a moving object
        moves in every frame after the first; :meth:`_sequence_moves`), ``has_defocus`` (False: the
        format has no lens), ``scene_json``, ``case`` and ``kind`` ('': the format has no scene family)."""
        seq = np.repeat(np.arange(len(self.files)), self.frames_per_sequence)
        if key == "clip_id":
            return seq.astype(np.int64)
        if key in ("frame", "frame_in_clip"):
            return (np.arange(self.num_frames) - self.offsets[seq]).astype(np.int64)
        if key == "num_frames":
            return np.asarray(self.frames_per_sequence, np.int64)[seq]
        if key == "has_motion":
            return np.array([self._sequence_moves(n) for n in range(len(self.files))], bool)[seq]
        if key == "has_defocus":
            return np.zeros(self.num_frames, bool)
        if key in ("scene_json", "case", "kind"):
            return np.array([""] * self.num_frames)
        raise KeyError(f"{self.path} (Noisebase) has no frame column {key!r}")

    def _sequence_moves(self, n: int) -> bool:
        """Whether sequence ``n`` holds motion: its camera arrays change between frames, or its last
        frame's per-sample world motion is not all zero (read once, then kept)."""
        moves = self._moves.get(n)
        if moves is None:
            last = self.frames_per_sequence[n] - 1
            cams = [np.asarray(self._read(n, k, slice(None), 0))
                    for k in ("camera_position", "camera_target", "camera_up")]
            moves = any(bool((c != c[:1]).any()) for c in cams) or (
                last > 0 and bool(np.any(self._read(n, "motion", last, last))))
            self._moves[n] = moves
        return moves

    def split_of_frame(self, i: int) -> str:
        return self._split_of_sequence(self._where(i)[0])

    def frames_in_split(self, split: str | None, *, complete_only: bool = True) -> list[int]:
        from stores.errors import SplitError
        if split is not None and split not in self.split_fractions:
            raise SplitError(f"unknown split {split!r}; this store has {list(self.split_fractions)}")
        return [i for n in range(len(self.files)) if split is None or self._split_of_sequence(n) == split
                for i in range(self.offsets[n], self.offsets[n + 1])]

    def clips(self, split: str | None = None, *, complete_only: bool = True) -> dict[int, list[int]]:
        out: dict[int, list[int]] = {}
        for i in self.frames_in_split(split):
            out.setdefault(self._where(i)[0], []).append(int(i))
        return out

    def read_array(self, path: str, i: int, crop=None, *, samples: int | None = None,
                   check_complete: bool = True) -> np.ndarray:
        """Frame ``i`` of one of our arrays (:data:`ARRAYS`), in our storage layout (``inputs/*``:
        ``(S, C, h, w)``, images ``(C, h, w)``, ``guides/depth`` ``(h, w)``), float32, cropped to ``crop =
        (y, x, h, w)``, the first ``samples`` samples of per-sample arrays."""
        if path not in ARRAYS:
            raise KeyError(f"{self.path} (Noisebase) has no array {path!r}; it provides {', '.join(ARRAYS)}")
        H, W = self.layout.height, self.layout.width
        y, x, h, w = (0, 0, H, W) if crop is None else (int(v) for v in crop)
        if h < 1 or w < 1 or y < 0 or x < 0 or y + h > H or x + w > W:
            from stores.errors import CropSizeError
            raise CropSizeError(f"crop at (y={y}, x={x}) of {h}x{w} leaves the {H}x{W} frame")
        n, f = self._where(i)
        S = self.layout.spp if samples is None else int(samples)
        if not 1 <= S <= self.layout.spp:
            from stores.errors import SampleCountError
            raise SampleCountError(f"asked for {S} samples per pixel; {self.path} holds 1..{self.layout.spp}")
        win = np.s_[:, y:y + h, x:x + w]
        if path == "reference/radiance":
            return np.asarray(self._read(n, "reference", (f,) + win, f), np.float32)
        if path == "reference/stderr":
            return np.zeros((3, h, w), np.float32)
        sel = np.s_[f, :, y:y + h, x:x + w, :S]
        if path == "inputs/radiance":
            rad = rgbe_decode(self._read(n, "color", sel, f), self._read(n, "exposure", f, f))
            return np.ascontiguousarray(rad.transpose(3, 0, 1, 2))           # (S, 3, h, w)
        feat = self._features(n, f, sel)                                       # (S, 17, h, w)
        g = FEATURE_GROUPS
        if path == "inputs/features":
            return feat
        if path == "guides/depth":
            return feat[:, g["depth"]].mean(axis=0)[0]
        return feat[:, g[path.split("/")[1]]].mean(axis=0)

    def _features(self, n: int, f: int, sel) -> np.ndarray:
        g = FEATURE_GROUPS
        pos = np.asarray(self._read(n, "position", sel, f), np.float64)         # (3, h, w, S)
        S = pos.shape[-1]
        out = np.zeros((S, NUM_FEATURES) + pos.shape[1:3], np.float32)
        T = lambda a: np.moveaxis(np.asarray(a, np.float32), -1, 0)            # noqa: E731  (C,h,w,S)->(S,C,h,w)
        out[:, g["normal"]] = T(self._read(n, "normal", sel, f))
        out[:, g["albedo"]] = T(self._read(n, "diffuse", sel, f))
        cam = np.asarray(self._read(n, "camera_position", f, f), np.float64)
        out[:, g["depth"]] = T(np.linalg.norm(pos - cam[:, None, None, None], axis=0)[None])
        if f > 0:
            H, W = self.layout.height, self.layout.width
            m = screen_motion(pos, self._read(n, "motion", sel, f), self._matrix(n, f), self._matrix(n, f - 1), H, W)
            out[:, g["motion"]] = T(m)
        return out

    def check_frames(self, frames, *, progress: bool = False) -> dict[int, list[str]]:
        """Frames whose radiance or reference is not finite and non-negative, frame -> problems (the
        fitness screen of our stores, on what the format holds)."""
        bad = {}
        for i in frames:
            probs = []
            for path in ("inputs/radiance", "reference/radiance", "inputs/features"):
                a = self.read_array(path, i)
                if not np.isfinite(a).all():
                    probs.append(f"{path} has {int((~np.isfinite(a)).sum())} non-finite values")
                elif path != "inputs/features" and (a < 0).any():
                    probs.append(f"{path} has {int((a < 0).sum())} negative values")
            if probs:
                bad[int(i)] = probs
        return bad

    def close(self) -> None:
        for g in self._groups.values():
            try:
                g.store.close()
            except Exception:           # noqa: BLE001  closing a read-only zip cannot lose data
                pass
        self._groups.clear()

    def __getstate__(self):             # DataLoader workers reopen the zip files
        d = dict(self.__dict__)
        d["_groups"], d["_members"] = {}, {}
        return d
