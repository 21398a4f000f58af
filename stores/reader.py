"""Reading a store: frames, metadata, crops, splits and clips (numpy only).

``open_store(path)`` returns a :class:`Store`. Image reads go through a fast path on local stores:
each frame of an image array is one shard file, and a crop reads the shard index and only the inner
chunks it touches (``os.pread`` + Blosc), bypassing zarr-python's per-chunk async machinery (5x
faster on crops; results are identical to zarr's, see tests). Other stores (URLs, unexpected
codecs) fall back to zarr slicing.

Splits are by scene, never by frame: ``split_of_clip(clip_id)`` hashes the clip (scene) id with
BLAKE2b into [0, 1) and compares with the store's split fractions (root ``config['split']``, default
train 0.8 / val 0.1 / test 0.1), so every frame of a scene lands in the same split on every machine.
"""
from __future__ import annotations

import hashlib
import os
import threading

import numpy as np

from stores import chunk_files, fitness, schema
from stores.contract import FRAME_ARRAYS, FRAME_META
from stores.errors import (CorruptChunkError, CropSizeError, FrameIndexError, IncompleteFrameError,
                           MissingShardError, SampleCountError, SplitError, StoreCorruptionError, StoreError,
                           StoreLayoutError, raise_if_unreachable)
from stores.schema import ARRAY_BY_PATH, ARRAY_BY_SOURCE, StoreLayout
from stores.shard_reader import ShardReader

DEFAULT_SPLIT = {"train": 0.8, "val": 0.1, "test": 0.1}


def split_of_clip(clip_id: int, fractions: dict | None = None) -> str:
    """The split (``train``/``val``/``test`` or the keys of ``fractions``, in order) of a clip/scene id."""
    fractions = DEFAULT_SPLIT if fractions is None else fractions
    total = float(sum(fractions.values()))
    if total <= 0 or any(v < 0 for v in fractions.values()):
        raise SplitError(f"split fractions must be >= 0 with a positive sum, got {fractions!r}")
    digest = hashlib.blake2b(str(int(clip_id)).encode(), digest_size=8).digest()
    u = int.from_bytes(digest, "little") / 2.0 ** 64
    acc = 0.0
    names = list(fractions)
    for name in names:
        acc += fractions[name] / total
        if u < acc:
            return name
    return names[-1]


def clip_id_in_split(seed: int, split: str, fractions: dict | None = None, *, stride: int = 2 ** 31,
                     tries: int = 64) -> int | None:
    """The first clip id of ``seed + j * stride`` (j = 0, 1, ... < ``tries``) that :func:`split_of_clip`
    puts in ``split``, None when none does: how a dataset gives a scene the split it wants (distinct
    seeds give distinct ids while ``seed < stride``)."""
    for j in range(int(tries)):
        c = int(seed) + j * int(stride)
        if split_of_clip(c, fractions) == split:
            return c
    return None


class Store:
    """A read-only view of a store. Cheap to pickle (re-opens lazily in each process)."""

    def __init__(self, path, *, fast: bool = True, threads: int = 0, check: bool = True):
        self.path = path
        self.fast = fast
        self.threads = int(threads)
        self._pool = None
        self._local = None
        # check=False: the caller has compared the arrays' metadata with the schema already (validate)
        self.root, self.layout = schema.open_group(path, mode="r", check=check)
        self._specs = dict(schema.ARRAY_BY_PATH)
        self._absent = schema.absent_arrays(self.root)   # frames/* newer than the store
        self._num_frames = None
        self._init_local()

    def _init_local(self):
        self._fast_readers: dict[str, ShardReader] = {}
        self._lock = threading.Lock()
        p = self.path
        if self.fast and isinstance(p, (str, os.PathLike)) and "://" not in os.fspath(p):
            self._local = os.fspath(p)
        self._meta_cache = None
        self._clip_starts = None
        self._scene_texts: dict[int, str] = {}
        self._listed: dict[str, set | None] = {}     # URL stores: an array's chunk keys, from one listing

    def __getstate__(self):
        return {"path": self.path, "fast": self.fast, "threads": self.threads}

    def __setstate__(self, state):
        self.__init__(state["path"], fast=state["fast"], threads=state.get("threads", 0))

    def _get_pool(self):
        if self.threads < 2:
            return None
        if self._pool is None:
            from concurrent.futures import ThreadPoolExecutor
            self._pool = ThreadPoolExecutor(self.threads, thread_name_prefix="stores-read")
        return self._pool

    # ---------------------------------------------------------------- metadata
    @property
    def num_frames(self) -> int:
        # cached: every read checks its index, and a zarr group lookup re-reads zarr.json (0.3 ms)
        if self._num_frames is None:
            self._num_frames = int(self.root["status/complete"].shape[0])
        return self._num_frames

    @property
    def attrs(self) -> dict:
        return dict(self.root.attrs)

    @property
    def config(self) -> dict:
        return self.attrs.get("config", {})

    @property
    def schema_version(self) -> int:
        return int(self.attrs["schema_version"])

    @property
    def split_fractions(self) -> dict:
        cfg = self.config
        split = cfg.get("split") if isinstance(cfg, dict) else None
        return dict(split) if isinstance(split, dict) and split else dict(DEFAULT_SPLIT)

    def _zarr_read(self, path: str, sel, frame: int | None = None) -> np.ndarray:
        """``root[path][sel]`` through zarr-python, with damage (a failed crc32c, a truncated or garbage
        chunk) raised as CorruptChunkError naming the array (and the frame, when one is read)."""
        try:
            return np.asarray(self.root[path][sel])
        except StoreError:
            raise
        except Exception as e:    # noqa: BLE001 - zarr/numcodecs raise ValueError, RuntimeError, ... on bad bytes
            raise_if_unreachable(e, self.path, f"reading {path}")          # a lost endpoint is not damage
            if frame is None:     # a whole column: find the frame whose chunk is bad
                for i in range(self.root[path].shape[0]):
                    try:
                        np.asarray(self.root[path][i])
                    except Exception:   # noqa: BLE001
                        frame = i
                        break
            spec = self._specs.get(path)
            f = chunk_files.chunk_file(self.root, spec, frame)[1] if spec is not None and frame is not None else path
            raise CorruptChunkError(f"{path}: frame {frame}: chunk file {f} is damaged: {type(e).__name__}: {e}",
                                    array=path, frame=frame, path=f) from e

    def _require_chunks(self, paths, frames) -> None:
        """Raise MissingShardError (array, frame, file) for the first chunk or shard file of the arrays
        ``paths`` that is missing for one of ``frames`` (frames marked complete: every chunk is written,
        so a missing one is lost data, not zeros)."""
        if not len(frames):
            return
        if self._local is None and len(paths) == 1 and len(frames) == 1:      # a store at a URL: one listing
            spec, i = self._specs[paths[0]], int(frames[0])                  # an array, not a request a read
            key = chunk_files.chunk_key(spec, i)
            have = self._listed.get(spec.path)
            if have is not None and key in have:
                return
            have = self._listed[spec.path] = chunk_files.chunk_keys(self.root, spec)   # new since? list again
            if have is not None and key in have:
                return
        lost = chunk_files.missing_chunks(self.root, frames, paths=paths)
        if lost:
            raise _missing_error(lost)

    def _meta_columns(self) -> list[tuple[str, str]]:
        """``(table key, array path)`` of the columns of the metadata table: with the camera matrices, whose
        chunks hold many frames, and without the scene JSON, kept once a clip (:meth:`scene_json`)."""
        keys = [k for k in FRAME_META if k != "scene_json"] + ["clip_id"]
        cols = [(key, schema.meta_path(key)) for key in keys]
        cols += [(key, ARRAY_BY_SOURCE[key].path) for key in ("camera_to_world", "world_to_clip")]
        return cols + [("complete", "status/complete"), ("error", "status/error")]

    def _meta(self) -> tuple[dict, dict[int, list[StoreCorruptionError]]]:
        """The per-frame metadata table and the damage found building it, frame -> errors: a chunk that
        does not decode (it reads as the fill value here; a damaged completion flag reads False) and,
        a missing chunk file of a frame marked complete. Read once, then cached."""
        if self._meta_cache is None:
            table: dict = {}
            damage: dict[int, list[StoreCorruptionError]] = {}
            for key, path in self._meta_columns():
                if path in self._absent:       # a FRAME_META key newer than the store: its fill value
                    spec = self._specs[path]
                    table[key] = np.full(self.num_frames, spec.fill)
                    continue
                try:
                    table[key] = self._zarr_read(path, slice(None))
                except CorruptChunkError:
                    table[key] = self._read_column_leniently(path, damage)
            table["frame_in_clip"] = table["frame"]
            table["complete"] = np.asarray(table["complete"], bool)
            done = [int(i) for i in np.nonzero(table["complete"])[0]]
            if done:
                paths = [p for _, p in self._meta_columns() if p not in self._absent]
                for i, lost in chunk_files.missing_chunks(self.root, done, paths=paths).items():
                    damage.setdefault(i, []).extend(_missing_error({i: [x]}) for x in lost)
                for i, (first, f) in self._lost_scene_json(table, done).items():
                    damage.setdefault(i, []).append(MissingShardError(
                        f"frames/scene_json: frame {i} is marked complete but its clip's SceneSpec JSON (kept at "
                        f"the clip's first frame, {first}) has no chunk file {f} (re-render the clip's frames: "
                        "`python -m pipeline validate --mark-damaged`, then `python -m pipeline dataset`)",
                        array="frames/scene_json", frame=i, path=f))
            for i, f in self._lost_flags(table["complete"]).items():
                damage.setdefault(i, []).append(MissingShardError(
                    f"status/complete: frame {i} was written (its status/error chunk is there) but its "
                    f"completion flag's chunk file {f} is missing (re-render the frame: `python -m pipeline "
                    "dataset` resumes it)", array="status/complete", frame=i, path=f))
            self._meta_cache = (table, {i: damage[i] for i in sorted(damage)})
            self._clip_starts = None
        return self._meta_cache

    def _lost_flags(self, complete: np.ndarray) -> dict[int, str]:
        """Frames read as incomplete whose ``status/complete`` chunk file is missing although their
        ``status/error`` chunk (written in the same first step of every frame) is there: a lost flag, not
        a frame never started, frame -> the missing file."""
        todo = [int(i) for i in np.nonzero(~np.asarray(complete, bool))[0]]
        if not todo:
            return {}
        no_flag = chunk_files.missing_chunks(self.root, todo, paths=["status/complete"])
        if not no_flag:
            return {}
        no_error = chunk_files.missing_chunks(self.root, list(no_flag), paths=["status/error"])
        return {i: lost[0][1] for i, lost in no_flag.items() if i not in no_error}

    def _read_column_leniently(self, path: str, damage: dict) -> np.ndarray:
        """Column ``path`` chunk by chunk: every chunk that does not decode reads as the fill value and
        each of its frames goes into ``damage`` (frame -> CorruptChunkError)."""
        arr = self.root[path]
        out = np.full(arr.shape, arr.fill_value, dtype=object if arr.dtype.kind in "OTU" else arr.dtype)
        n = arr.chunks[0]
        for lo in range(0, arr.shape[0], n):
            hi = min(lo + n, arr.shape[0])
            try:
                out[lo:hi] = self._zarr_read(path, slice(lo, hi), lo)
            except CorruptChunkError as e:
                for i in range(lo, hi):
                    damage.setdefault(i, []).append(
                        e if n == 1 else CorruptChunkError(f"{path}: frame {i}: {e}", array=path, frame=i, path=e.path))
        return out.astype(str) if out.dtype == object else out

    def _clip_start(self, table: dict, i: int) -> int:
        """The frame holding frame ``i``'s SceneSpec JSON: its clip's first frame, ``i -
        frame_in_clip`` (a dataset writes a clip's frames one after another, and stores the JSON there
        before any of them), when that frame is of the clip or not committed yet (its ``frames/*`` still
        hold fill values: an interrupted run); else a complete frame of its clip with ``frame_in_clip``
        0, else ``i`` itself."""
        clip, fic, done = table["clip_id"], table["frame"], table["complete"]
        j = i - int(fic[i])
        if 0 <= j < len(fic) and (not done[j] or (int(fic[j]) == 0 and clip[j] == clip[i])):
            return j
        if self._clip_starts is None:
            firsts = np.nonzero((np.asarray(fic) == 0) & np.asarray(done, bool))[0]
            self._clip_starts = {int(clip[k]): int(k) for k in firsts[::-1]}
        return self._clip_starts.get(int(clip[i]), i)

    def _lost_scene_json(self, table: dict, done: list[int]) -> dict[int, tuple[int, str]]:
        """Complete frames whose clip's SceneSpec JSON chunk (at the clip's first frame) is missing,
        frame -> (first frame, file)."""
        spec = self._specs["frames/scene_json"]
        names = chunk_files.chunk_names_1d(self.root, spec)
        out, seen = {}, {}
        for i in done:
            f0 = self._clip_start(table, i)
            if f0 not in seen:
                seen[f0] = ((True, "") if names is not None and str(f0) in names
                            else chunk_files.chunk_file(self.root, spec, f0))
            there, f = seen[f0]
            if not there:
                out[i] = (f0, f)
        return out

    def scene_json(self, i: int) -> str:
        """The SceneSpec JSON of frame ``i``'s scene ('' where none was stored), kept once a clip, at the
        clip's first frame."""
        i = self._check_index(i)
        t = self._frame_row(i)
        f0 = self._clip_start(t, i)
        text = self._scene_texts.get(f0)
        if text is None:                    # a clip's frames share one JSON: read it once per Store
            text = self._scene_texts[f0] = str(self._zarr_read("frames/scene_json", f0, f0))
        return text

    def metadata_damage(self) -> dict[int, list[StoreCorruptionError]]:
        """Frames whose ``frames/*`` or ``status/*`` chunks are damaged or (complete frames) missing,
        frame -> the errors (each names array, frame and file). ``{}`` for a sound store."""
        return {i: list(v) for i, v in self._meta()[1].items()}

    def _meta_table(self) -> dict:
        """The metadata table for whole-store questions (splits, clips, complete frames): raises the
        first metadata damage of any frame (StoreCorruptionError; ``metadata_damage()`` lists it all)."""
        table, damage = self._meta()
        if damage:
            raise _first_of(damage)
        return table

    def _frame_row(self, i: int) -> dict:
        """The metadata table, after checking frame ``i``'s own metadata chunks (damage: raised)."""
        table, damage = self._meta()
        if i in damage:
            raise _first_of({i: damage[i]})
        return table

    def meta_column(self, key: str) -> np.ndarray:
        """One ``frames/*`` column by its ``FRAME_META`` key (or ``clip_id``, ``complete``, ``error``) for
        all frames, from the cache. ``frame`` (= ``frame_in_clip``) is the index in the clip, stored as
        ``frames/frame_in_clip``. ``scene_json``, kept once a clip, is read clip by clip (:meth:`scene_json`
        reads one frame's)."""
        t = self._meta_table()
        if key == "scene_json" and key not in t:     # objects: a clip's frames share its one string (a
            out = np.empty(self.num_frames, dtype=object)      # fixed-width str array of a long clip's
            out[:] = [self.scene_json(i) for i in range(self.num_frames)]    # JSON was GiBs)
            return out
        return t[key].copy()

    def complete_flags(self) -> np.ndarray:
        """``status/complete`` of every frame (bool): a flag whose chunk is damaged reads False
        (:meth:`metadata_damage` lists it); nothing is raised."""
        return self._meta()[0]["complete"].copy()

    def complete_frames(self) -> list[int]:
        return [int(i) for i in np.nonzero(self._meta_table()["complete"])[0]]

    def incomplete_frames(self) -> list[int]:
        return [int(i) for i in np.nonzero(~self._meta_table()["complete"])[0]]

    def _check_index(self, i: int) -> int:
        if not (0 <= int(i) < self.num_frames):
            raise FrameIndexError(f"frame index {i} is outside 0..{self.num_frames - 1}")
        return int(i)

    def _check_complete(self, i: int) -> None:
        """Uses the cached completion flags; a frame cached as incomplete is re-checked on disk (it may
        have been finished since this Store was opened)."""
        if self._frame_row(i)["complete"][i]:
            return
        if bool(self._zarr_read("status/complete", i, i)):
            self._meta_cache = None
            self._frame_row(i)
            return
        err = str(self._zarr_read("status/error", i, i))
        why = f" (last error: {err})" if err else " (never finished, or its writer stopped mid-frame)"
        raise IncompleteFrameError(f"frame {i} of {os.fspath(self.path)!s} is incomplete{why}")

    def frames_meta(self, i: int, *, scene: bool = True) -> dict:
        """``FRAME_META`` of frame ``i`` plus ``clip_id``, ``complete``, ``error`` and the camera matrices
        ``camera_to_world``/``world_to_clip`` (float64, 44). Python scalars. ``scene=False`` leaves out
        ``scene_json`` (a long clip's JSON is long: callers that do not need it do not read it)."""
        i = self._check_index(i)
        t = self._frame_row(i)
        out = {}
        for key, typ in FRAME_META.items():
            if key in t:
                out[key] = typ(t[key][i]) if typ is not bool else bool(t[key][i])
            elif scene:                                 # the scene JSON: once a clip
                out[key] = self.scene_json(i)
        out["clip_id"] = int(t["clip_id"][i])
        out["complete"] = bool(t["complete"][i])
        out["error"] = str(t["error"][i])
        for key in ("camera_to_world", "world_to_clip"):
            out[key] = self._read_matrix(key, i)
        return out

    def _read_matrix(self, key: str, i: int) -> np.ndarray:
        """``frames/<key>`` (float64, 44) of frame ``i``, from the metadata table (checked there)."""
        return np.asarray(self._frame_row(i)[key][i], np.float64)

    # ---------------------------------------------------------------- images
    def _reader(self, path: str):
        if self._local is None:
            return None
        with self._lock:
            r = self._fast_readers.get(path)
            if r is None:
                arr = self.root[path]
                meta = arr.metadata.to_dict()
                if not ShardReader.applicable(meta):
                    self._fast_readers[path] = False
                    return None
                r = ShardReader(os.path.join(self._local, *path.split("/")), meta, ARRAY_BY_PATH[path].dims, path)
                self._fast_readers[path] = r
        return r or None

    def _check_crop(self, crop) -> tuple[int, int, int, int]:
        H, W = self.layout.height, self.layout.width
        if crop is None:
            return 0, 0, H, W
        y, x, h, w = (int(v) for v in crop)
        if h < 1 or w < 1 or h > H or w > W:
            raise CropSizeError(f"crop {h}x{w} does not fit the {H}x{W} frames (need 1 <= h <= {H}, 1 <= w <= {W})")
        if y < 0 or x < 0 or y + h > H or x + w > W:
            raise CropSizeError(f"crop at (y={y}, x={x}) of {h}x{w} leaves the {H}x{W} frame")
        return y, x, h, w

    def read_array(self, path: str, i: int, crop=None, *, samples: int | None = None,
                   check_complete: bool = True) -> np.ndarray:
        """One frame of image array ``path`` in storage layout without the frame axis, e.g.
        ``inputs/radiance -> (float32, sample·rgb·h·w)`` (log16 decoded), cropped to
        ``crop = (y, x, h, w)``, the first ``samples`` samples of per-sample arrays.
        Features come back as stored (float16 unless float32 was chosen)."""
        i = self._check_index(i)
        if check_complete:
            self._check_complete(i)
        spec = ARRAY_BY_PATH[path]
        y, x, h, w = self._check_crop(crop)
        if samples is not None and "sample" in spec.dims:
            samples = self._check_spp(samples)
        else:
            samples = None
        # every shard is written, so a complete frame without one lost it
        strict = bool(self._frame_row(i)["complete"][i])
        r = self._reader(path) if spec.image else None
        if r is not None:
            a = r.read(i, y, y + h, x, x + w, samples, self._get_pool(), strict=strict)
        else:
            if strict:
                self._require_chunks([path], [i])
                f = chunk_files.chunk_file(self.root, spec, i)[1]
                if os.path.isfile(f) and os.path.getsize(f) == 0:      # zarr reads an empty shard as fill
                    raise CorruptChunkError(f"{path}: frame {i}: shard file {f} is damaged: it is empty",
                                            array=path, frame=i, path=f)
            sel = [i] + [slice(None)] * (len(spec.dims) - 1)
            if spec.image:
                sel[spec.dims.index("y")] = slice(y, y + h)
                sel[spec.dims.index("x")] = slice(x, x + w)
            if samples is not None:
                sel[spec.dims.index("sample")] = slice(0, samples)
            a = self._zarr_read(path, tuple(sel), i)
        if path == "inputs/radiance" and self.layout.radiance_encoding == "log16":
            from stores.codecs import decode_log16
            a = decode_log16(a)
        return a

    def read_frame(self, i: int, keys=None, *, crop=None, spp: int | None = None,
                   allow_incomplete: bool = False) -> dict:
        """Frame ``i`` in the renderer's layout (``FRAME_ARRAYS`` names, channel-last, float32 images),
        optionally cropped (``crop = (y, x, h, w)``) and limited to the first ``spp`` samples.
        ``keys`` defaults to every array; ``'meta'`` adds ``frames_meta(i)``."""
        i = self._check_index(i)
        if not allow_incomplete:
            self._check_complete(i)
        keys = list(FRAME_ARRAYS) + ["meta"] if keys is None else list(keys)
        spp = self._check_spp(spp)
        out = {}
        for key in keys:
            if key == "meta":
                out["meta"] = self.frames_meta(i)
                continue
            if key not in ARRAY_BY_SOURCE:
                raise StoreLayoutError(f"unknown frame array {key!r}; known: {', '.join(ARRAY_BY_SOURCE)}")
            spec = ARRAY_BY_SOURCE[key]
            if spec.image:
                a = self.read_array(spec.path, i, crop, samples=spp, check_complete=False)
            else:
                a = self._read_matrix(key, i)
            out[key] = spec.from_store(a, self.layout)
        return out

    def _check_spp(self, spp) -> int:
        S = self.layout.spp
        if spp is None:
            return S
        if int(spp) < 1 or int(spp) > S:
            raise SampleCountError(f"asked for {spp} samples per pixel; the store holds 1..{S}")
        return int(spp)

    # ---------------------------------------------------------------- splits and clips
    def split_of_frame(self, i: int) -> str:
        i = self._check_index(i)
        return split_of_clip(int(self._frame_row(i)["clip_id"][i]), self.split_fractions)

    def frames_in_split(self, split: str | None, *, complete_only: bool = True) -> list[int]:
        """Frame indices of ``split`` (None: all), in index order; complete frames only by default."""
        fr = self.split_fractions
        if split is not None and split not in fr:
            raise SplitError(f"unknown split {split!r}; this store has {list(fr)}")
        t = self._meta_table()
        out = []
        for i in range(self.num_frames):
            if complete_only and not t["complete"][i]:
                continue
            if split is None or split_of_clip(int(t["clip_id"][i]), fr) == split:
                out.append(i)
        return out

    def clips(self, split: str | None = None, *, complete_only: bool = True) -> dict[int, list[int]]:
        """clip id -> frame indices ordered by their index in the clip (``frame_in_clip``)."""
        t = self._meta_table()
        groups: dict[int, list[int]] = {}
        for i in self.frames_in_split(split, complete_only=complete_only):
            groups.setdefault(int(t["clip_id"][i]), []).append(i)
        return {c: sorted(v, key=lambda j: int(t["frame"][j])) for c, v in sorted(groups.items())}


    def missing_data(self, frames=None) -> dict[int, list[tuple[str, str]]]:
        """Complete frames (of ``frames``, default all) whose chunk files are not all there, frame ->
        ``[(array, file)]`` (see ``chunk_files.missing_chunks``)."""
        done = self._meta()[0]["complete"]         # a damaged flag reads False (metadata_damage lists it)
        frames = range(self.num_frames) if frames is None else frames
        return chunk_files.missing_chunks(self.root, [int(i) for i in frames if done[int(i)]])

    def frame_problems(self, i: int) -> list[str]:
        """See :func:`frame_problems`."""
        return fitness.frame_problems(self, i)

    def check_frames(self, frames, *, progress: bool = False) -> dict[int, list[str]]:
        """The unfit frames of ``frames``, frame -> problems (:func:`stores.fitness.check_frames`)."""
        return fitness.check_frames(self, frames, progress=progress)

    missing_features: tuple[str, ...] = ()          # every feature group is stored

    def has_array(self, path: str) -> bool:
        """Whether the store has the array ``path`` (``inputs/radiance``, ``layers/radiance``, ...)."""
        try:
            self.root[path]
            return True
        except KeyError:
            return False


def frame_problems(store, i: int) -> list[str]:
    """Why frame ``i`` of ``store`` (a :class:`Store` or a path) should not be trained, evaluated or
    exported (``[]`` if nothing): :func:`stores.fitness.frame_problems`, the one check ``validate``
    applies too."""
    return fitness.frame_problems(store if isinstance(store, Store) else open_store(store), i)


def _missing_error(lost: dict[int, list[tuple[str, str]]]) -> MissingShardError:
    """The MissingShardError of the first of ``lost`` (frame -> ``[(array, file)]``, as
    ``chunk_files.missing_chunks`` gives it), with a count of the others."""
    i = min(lost)
    array, f = lost[i][0]
    kind = "shard" if ARRAY_BY_PATH.get(array) is not None and ARRAY_BY_PATH[array].image else "chunk"
    more = sum(len(v) for v in lost.values()) - 1
    also = f"; {more} more missing file(s) (`python -m pipeline validate` lists them)" if more else ""
    return MissingShardError(f"{array}: frame {i} is marked complete but its {kind} file {f} is missing "
                             f"(re-render the frame: `python -m pipeline dataset` resumes it){also}",
                             array=array, frame=i, path=f)


def _first_of(damage: dict[int, list[StoreCorruptionError]]) -> StoreCorruptionError:
    """The first error of ``damage`` (frame -> errors), its message noting how many others there are."""
    first = damage[min(damage)][0]
    more = sum(len(v) for v in damage.values()) - 1
    if not more:
        return first
    e = type(first)(f"{first}; and {more} more damaged metadata chunk(s) (`python -m pipeline validate` "
                    f"lists them)", array=first.array, frame=first.frame, path=first.path)
    e.__cause__ = first
    return e


def open_store(path, *, fast: bool = True, threads: int = 0, check: bool = True) -> Store:
    """Open an existing store for reading (``StoreNotFoundError``, ``ForeignStoreError`` and
    ``SchemaVersionError`` otherwise; ``ArrayMetadataError`` when an array's ``zarr.json`` disagrees
    with the schema, unless ``check=False`` because the caller compared them already). ``threads >= 2``
    decodes the tiles of a crop in a thread pool (Blosc and numpy release the GIL); leave 0 inside
    DataLoader workers, which already parallelise."""
    return Store(path, fast=fast, threads=threads, check=check)


__all__ = ["Store", "open_store", "frame_problems", "split_of_clip", "DEFAULT_SPLIT", "StoreLayout"]
