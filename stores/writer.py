"""Resumable, lock-free frame writer.

A frame is written in two parts.

1. Its **data** (``write_frame_data``, by the task that rendered it, any process): every image array's
   shard of frame ``i`` (whole shards: tasks never share a file, so no locks; a re-run overwrites cleanly),
   and at a clip's first frame the clip's SceneSpec JSON (``frames/scene_json``, one file a clip). It
   returns the frame's **record**: its ``FRAME_META`` values, clip id and camera matrices.
2. Its **commit** (``commit(records)``, by one process: the dataset run's client): the records go into
   the ``frames/*`` arrays, whose chunks hold :data:`stores.schema.META_CHUNK` frames, then
   ``status/error`` and, last, ``status/complete``. One process writes them, so no chunk has two
   writers; many frames share a file, so a frame costs its image shards and a 1/1024 share of each
   metadata file instead of a file a value.

A crash before a frame's commit leaves it incomplete, never half-valid (its shards are rewritten by
the re-run); readers refuse incomplete frames (``IncompleteFrameError``) and ``incomplete_frames()``
lists them. ``write_frame`` does both parts at once (one process writing a store, as tests and
scripts do). Every chunk is written, all-zero ones included, so a complete frame's files are all
there: a missing one is damage (``frames_with_missing_data``). A store of an older schema is refused
on open, naming ``python -m stores upgrade`` (``stores.upgrade``).
"""
from __future__ import annotations

import os
import socket
from typing import Callable

import numpy as np

from stores import chunk_files, create, schema
from stores.contract import FEATURE_NAMES, FRAME_ARRAYS, FRAME_META
from stores.errors import FrameIndexError, StoreLayoutError, StoreValueError, raise_if_unreachable
from stores.procinfo import pid_alive
from stores.schema import ARRAY_BY_SOURCE, StoreLayout


def _expected_shape(tmpl, layout: StoreLayout) -> tuple[int, ...]:
    dims = {"H": layout.height, "W": layout.width, "S": layout.spp, "L": layout.num_layers}
    return tuple(dims.get(d, d) for d in tmpl)


def check_frame(arrays: dict, layout: StoreLayout) -> None:
    """Raise StoreLayoutError/StoreValueError unless ``arrays`` is a storable frame for ``layout``:
    every ``FRAME_ARRAYS`` key with its exact shape, every ``FRAME_META`` key, features within the
    feature dtype's range."""
    missing = [k for k in FRAME_ARRAYS if k not in arrays]
    if missing:
        raise StoreLayoutError(f"frame lacks arrays: {', '.join(missing)}")
    for name, (tmpl, _dtype) in FRAME_ARRAYS.items():
        shape = _expected_shape(tmpl, layout)
        got = tuple(np.shape(arrays[name]))
        if got != shape:
            raise StoreLayoutError(f"array {name!r} has shape {got}, the store expects {shape} "
                                   f"(H={layout.height}, W={layout.width}, S={layout.spp}, L={layout.num_layers})")
    meta = arrays.get("meta")
    if not isinstance(meta, dict):
        raise StoreLayoutError("frame lacks its 'meta' dict (stores.contract.FRAME_META)")
    missing = [k for k in FRAME_META if k not in meta]
    if missing:
        raise StoreLayoutError(f"frame meta lacks: {', '.join(missing)}")
    if layout.feature_dtype == "float16":
        feats = np.asarray(arrays["features"])
        top = np.asarray(layout.feature_limits)
        big = np.isfinite(feats) & (np.abs(feats) > top)
        if big.any():
            bad = sorted({int(c) for c in np.nonzero(big)[-1]})
            limits = ", ".join(f"|{FEATURE_NAMES[c]}| <= {top[c]:g}" for c in bad)
            raise StoreValueError(f"features {[FEATURE_NAMES[c] for c in bad]} exceed float16's range in the "
                                  f"store's {layout.codec_set!r} encoding ({limits}); rescale them in the "
                                  f"renderer or create the store with feature_dtype='float32'")


class StoreWriter:
    """Writes frames into an existing store. Safe to use from many processes at once as long as each
    frame index is written by one of them at a time.

    >>> w = StoreWriter(path); w.write_frame(3, render_frame(...))
    """

    def __init__(self, path):
        self.path = path
        self.root, self.layout = schema.open_group(path, mode="r+")
        # frames/* arrays of FRAME_META keys newer than the store: open_or_create adds them (one
        # process); a writer opened without it skips them, and readers give their fill value
        self.absent = schema.absent_arrays(self.root)
        self._handles: dict = {}

    def _array(self, path: str):
        """``path`` for writing: every chunk is written, all-zero ones too (zarr skips chunks equal to
        the fill value by default, and a missing file must mean damage, not zeros; SCHEMA.md)."""
        a = self._handles.get(path)
        if a is None:           # opened once per writer: each lookup reads the array's zarr.json again
            a = self._handles[path] = self.root[path].with_config({"write_empty_chunks": True})
        return a

    @property
    def num_frames(self) -> int:
        return int(self._array("status/complete").shape[0])

    def _check_index(self, index: int) -> int:
        if not (0 <= int(index) < self.num_frames):
            raise FrameIndexError(f"frame index {index} is outside 0..{self.num_frames - 1}")
        return int(index)

    def write_frame(self, index: int, arrays: dict, *, on_progress: Callable[[str], None] | None = None) -> None:
        """Write frame ``index`` from the renderer's dict (``FRAME_ARRAYS`` + ``meta``), its data and then
        its commit (completion flag last). ``on_progress(path)`` is called after each array is written
        (logging, tests). For one process writing a store; a dataset run splits the two parts."""
        if bool(complete_flags(self.root, [self._check_index(index)])[0]):
            # rewriting a complete frame: invalidate it first, so a crash mid-way leaves it incomplete
            self.commit({}, {index: "being rewritten"})
        record = self.write_frame_data(index, arrays, on_progress=on_progress)
        self.commit({index: record})
        if on_progress:
            on_progress("status/complete")

    def write_frame_data(self, index: int, arrays: dict, *,
                         on_progress: Callable[[str], None] | None = None) -> dict:
        """Write frame ``index``'s image shards (and, at a clip's first frame, its SceneSpec JSON); return
        its record for :meth:`commit` (plain data: picklable, small)."""
        index = self._check_index(index)
        check_frame(arrays, self.layout)
        arr = self._array
        writes = [(spec.path, spec.to_store(arrays[source], self.layout)) for source, spec in ARRAY_BY_SOURCE.items()
                  if spec.image]            # camera matrices are in the record (metadata chunks)
        if on_progress:                      # one array at a time, in order (tests stop a writer between them)
            for path, a in writes:
                arr(path)[index] = a
                on_progress(path)
        else:                                # every shard at once: zarr's event loop writes them together
            _write_all([(arr(path), index, a) for path, a in writes])
        record = frame_record(arrays)
        scene_json = record["meta"].pop("scene_json")    # kept once a clip, never in the record: a
        if int(record["meta"]["frame"]) == 0:             # long clip's JSON is as long as the clip
            self.write_scene_json(index, scene_json)
        return record

    def write_scene_json(self, first: int, scene_json: str) -> None:
        """Store a clip's SceneSpec JSON at its first frame ``first`` (one file a clip), unless
        it is there already: a resume (the same config gives the same bytes) reads it and writes nothing,
        so a complete frame's file is never rewritten and a store at a URL pays a read, not a write. A
        missing or damaged chunk is written."""
        arr, first = self._array("frames/scene_json"), self._check_index(first)
        try:
            if str(arr[first]) == str(scene_json):
                return
        except Exception as e:  # noqa: BLE001 - zarr/numcodecs raise many kinds for a damaged chunk: write it again
            raise_if_unreachable(e, self.path, "reading frames/scene_json")
        arr[first] = str(scene_json)

    def commit(self, records: dict[int, dict], failures: dict[int, str] | None = None) -> None:
        """Make frames complete: each record of ``records`` (frame -> :meth:`write_frame_data`'s
        record) goes into the ``frames/*`` arrays, ``status/error`` is cleared, and ``status/complete`` is
        set last; ``failures`` (frame -> error text) are recorded as failed at the same time. One process
        at a time (the chunks are shared by :data:`stores.schema.META_CHUNK` frames): a dataset run's
        client, or :meth:`write_frame`."""
        failures = dict(failures or {})
        if not records and not failures:
            return
        idx = sorted(int(i) for i in records)
        for i in idx + list(failures):
            self._check_index(i)
        columns = {}
        for key in [k for k in FRAME_META if k != "scene_json"] + ["clip_id"]:
            if schema.meta_path(key) in self.absent:
                continue                    # a key newer than the store: open_or_create adds its array
            columns[schema.meta_path(key)] = [
                (i, str(records[i]["meta"][key]) if FRAME_META.get(key) is str else records[i]["meta"][key])
                for i in idx]
        for key in ("camera_to_world", "world_to_clip"):
            columns[ARRAY_BY_SOURCE[key].path] = [(i, np.asarray(records[i][key], np.float64)) for i in idx]
        lost: set[int] = set()
        for path, values in columns.items():
            lost |= _set_many(self._array(path), values)
        lost -= set(idx) | set(failures)
        failures.update({i: "damaged: a metadata chunk of this frame could not be read and was written "
                            "again; the frame is rendered again" for i in sorted(lost)})
        # The first commit into a chunk of META_CHUNK frames makes its flag chunk (all False) before
        # status/error: a status/error chunk without its flag chunk then only ever means a lost flag
        # (damage), and an interruption inside this commit leaves its frames incomplete, never damaged.
        fresh = chunk_files.missing_chunks(self.root, idx + [int(i) for i in failures], paths=["status/complete"])
        _set_many(self._array("status/complete"), [(i, False) for i in sorted(fresh)])
        lost = _set_many(self._array("status/error"), [(i, "") for i in idx] +
                         [(int(i), text or "failed") for i, text in failures.items()])
        # last: the flags (a damaged flag chunk is rebuilt with its other frames incomplete: fill False)
        _set_many(self._array("status/complete"), [(i, True) for i in idx] + [(int(i), False) for i in failures]
                  + [(i, False) for i in sorted(lost - set(idx) - set(failures))])

    def mark_failed(self, index: int, error) -> None:
        """Record that frame ``index`` failed: ``status/complete`` False, ``status/error`` the text
        (an exception becomes ``'TypeName: message'``)."""
        index = self._check_index(index)
        text = f"{type(error).__name__}: {error}" if isinstance(error, BaseException) else str(error)
        self.commit({}, {index: text})

    def frame_complete(self, index: int) -> bool:
        """Marked complete and every chunk file of the frame is there."""
        index = self._check_index(index)
        return bool(complete_flags(self.root, [index])[0]) and not chunk_files.missing_chunks(self.root, [index])

    def incomplete_frames(self) -> list[int]:
        """Frames to (re-)render: not marked complete (or with an unreadable completion flag), or
        marked complete but missing chunk files (:func:`frames_with_missing_data`)."""
        done = complete_flags(self.root)
        lost = chunk_files.missing_chunks(self.root, [int(i) for i in np.nonzero(done)[0]])
        return sorted([int(i) for i in np.nonzero(~done)[0]] + list(lost))

    def errors(self) -> dict[int, str]:
        """Frame index -> recorded error text, for frames with one."""
        err = self.root["status/error"][:]
        return {int(i): str(err[i]) for i in range(len(err)) if str(err[i])}


def _write_all(items) -> None:
    """``a[index] = value`` for every ``(a, index, value)`` of ``items`` (zarr arrays) in one round on
    zarr's event loop: the writes of a frame's shards overlap instead of waiting for each other
    (9 shards of an 8x8 frame: 20 -> 8 ms)."""
    import asyncio

    from zarr.core.sync import sync

    async def all_():
        await asyncio.gather(*(a.async_array.setitem(index, value) for a, index, value in items))
    sync(all_())


def generation(path) -> str:
    """Names the store at ``path`` as it is now: its ``store_id`` (made at creation) and frame count.
    Processes that keep a writer open (``pipeline.tasks.store_writer``) open a new one when it changes:
    a store made again at the same path, or grown."""
    root, layout = schema.open_group(path, mode="r", check=False)
    return f"{dict(root.attrs).get('store_id', '')}:{layout.num_frames}"


def frame_record(arrays: dict) -> dict:
    """What a frame's commit needs from the renderer's dict: its ``meta`` (``FRAME_META`` + ``clip_id``,
    which defaults to the scene seed) and its camera matrices, as plain data (small, picklable)."""
    meta = dict(arrays["meta"])
    meta.setdefault("clip_id", meta["scene_seed"])
    return {"meta": meta, "camera_to_world": np.asarray(arrays["camera_to_world"], np.float64).tolist(),
            "world_to_clip": np.asarray(arrays["world_to_clip"], np.float64).tolist()}


def _set_many(arr, values) -> set[int]:
    """``arr[i] = v`` for every ``(i, v)`` of ``values``, chunk by chunk: each chunk touched is read once,
    updated and written whole (a chunk holds many frames; one process writes them). A chunk that cannot
    be read (damaged) is written again from the fill value and these values; the other frames it held
    are returned, so the caller marks them incomplete (their metadata is gone: the resume re-renders
    them) rather than leave them complete with fill values."""
    lost: set[int] = set()
    if not values:
        return lost
    n = arr.chunks[0]
    by_chunk: dict[int, list] = {}
    for i, v in values:
        by_chunk.setdefault(int(i) // n, []).append((int(i), v))
    for c, items in sorted(by_chunk.items()):
        lo, hi = c * n, min((c + 1) * n, arr.shape[0])
        try:
            block = np.asarray(arr[lo:hi])
        except Exception as e:  # noqa: BLE001 - zarr raises many types for a damaged chunk
            raise_if_unreachable(e, doing=f"reading {arr.path}")   # not damage: never overwrite it with fills
            block = np.full((hi - lo,) + tuple(arr.shape[1:]), arr.fill_value,
                            dtype=object if arr.dtype.kind in "OTU" else arr.dtype)
            lost |= set(range(lo, hi)) - {i for i, _ in items}
        if block.dtype.kind in "OTU":
            block = block.astype(object)
        for i, v in items:
            block[i - lo] = v
        arr[lo:hi] = block
    return lost


def complete_flags(root, frames=None) -> np.ndarray:
    """``status/complete`` (bool, F, or of ``frames``); a flag whose chunk is damaged (fails its
    checksum, garbage) reads False, so a resume re-renders that frame and rewrites it."""
    arr = root["status/complete"]
    idx = range(arr.shape[0]) if frames is None else frames
    try:
        if frames is None:
            return np.asarray(arr[:], bool)
        return np.array([bool(arr[int(i)]) for i in idx], bool)
    except Exception as e:      # noqa: BLE001 - zarr raises ValueError/RuntimeError/... on bad bytes
        raise_if_unreachable(e, doing="reading status/complete")   # not all frames to render again
        out = []
        for i in idx:
            try:
                out.append(bool(arr[int(i)]))
            except Exception as e:  # noqa: BLE001
                raise_if_unreachable(e, doing="reading status/complete")
                out.append(False)
        return np.array(out, bool)


def frames_with_missing_data(path) -> dict[int, list[tuple[str, str]]]:
    """Frames of the store at ``path`` marked complete but missing chunk or shard files, frame ->
    ``[(array, file), ...]``.
    ``StoreWriter.incomplete_frames`` includes them, so a resume re-renders them."""
    root, _ = schema.open_group(path, mode="r", check=False)
    done = complete_flags(root)
    return chunk_files.missing_chunks(root, [int(i) for i in np.nonzero(done)[0]])


def open_or_create(path, layout: StoreLayout, config: dict | None = None, *, overwrite: bool = False) -> StoreWriter:
    """Open the store at ``path`` for writing, creating it if missing. An existing store must have the
    same frame layout (resolution, spp, layers, tile, encodings) and the current schema version; if ``layout``
    has more frames, every array grows (append). A different ``config`` replaces the recorded one and
    the previous one goes to ``config_history``. Call from one process before tasks start writing
    (``pipeline dataset`` holds the store's ``stores.lock.StoreLock`` around it).

    Nothing that is not ours is deleted: a non-empty folder that is not a store raises
    ForeignStoreError unless ``overwrite`` (which also replaces an existing store). A store whose
    creation was cut short (``IncompleteStoreError``) is made again, unless its creator still runs
    on this host (the same pid and process start time: a later process that reused the pid does not
    count)."""
    from stores.errors import IncompleteStoreError, StoreLockedError
    if overwrite or not schema.store_exists(path):
        create.create_store(path, layout, config, overwrite=overwrite)
        return StoreWriter(path)
    # The store keeps its own encoding: ``layout.encoding`` None (a config that does not name it)
    # matches the store's, whatever it is (lz4 for stores made before the field, compact since).
    try:
        root, have = schema.open_group(path, mode="r+")
    except IncompleteStoreError as e:
        c = e.creator
        if (c.get("host") == socket.gethostname() and c.get("pid") != os.getpid()
                and pid_alive(c.get("pid", -1), c.get("proc_start"))):
            raise StoreLockedError(f"{os.fspath(path)!s} is being created by pid {c.get('pid')} on {c.get('host')} "
                                   f"(started {c.get('started')})", holder=c) from e
        create.create_store(path, layout, config, overwrite=True)     # ours, and nothing was written yet
        return StoreWriter(path)
    if not have.frame_shape_compatible(layout):
        a, b = have.to_dict(), layout.to_dict()
        diff = {k: (a[k], b.get(k)) for k in a if k != "num_frames" and a[k] != b.get(k)}
        raise StoreLayoutError(f"store at {os.fspath(path)!s} has a different frame layout "
                               f"(field: (store, requested)): {diff}")
    schema.add_absent_arrays(root, have)     # frames/* of FRAME_META keys newer than the store
    schema.grow(root, have, layout.num_frames)
    if config is not None:
        attrs = dict(root.attrs)
        if attrs.get("config") != config:
            root.attrs["config_history"] = list(attrs.get("config_history", [])) + [attrs.get("config")]
            root.attrs["config"] = config
            schema.consolidate(path)        # writing the root attributes dropped the consolidated metadata
    return StoreWriter(path)
