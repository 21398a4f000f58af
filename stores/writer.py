"""Resumable, lock-free frame writer.

Protocol for one frame ``i`` (one task writes it; tasks never share a chunk, so no locks):

1. ``status/complete[i] = False`` and ``status/error[i] = ''`` (a re-run first invalidates the frame);
2. every image array's shard for frame ``i`` (whole shards: a re-run overwrites cleanly);
3. the camera matrices and ``frames/*`` metadata of frame ``i``;
4. ``status/complete[i] = True``, last.

A crash anywhere before step 4 leaves the frame marked incomplete, never half-valid; readers refuse
incomplete frames (``IncompleteFrameError``) and ``incomplete_frames()`` lists them for a re-run.
Every chunk is written, all-zero ones included, so in a schema v2 store a complete frame has one file
per array; one whose files went missing counts as incomplete too (``frames_with_missing_data``).
"""
from __future__ import annotations

import os
from typing import Callable

import numpy as np

from stores import schema
from stores.contract import FEATURE_NAMES, FRAME_ARRAYS, FRAME_META
from stores.errors import FrameIndexError, StoreLayoutError, StoreValueError
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
        self.version = schema.version_of(self.root)
        # frames/* arrays of FRAME_META keys newer than the store: open_or_create adds them (one
        # process); a writer opened without it skips them, and readers give their fill value
        self.absent = schema.absent_arrays(self.root, self.version)

    def _array(self, path: str):
        """``path`` for writing: every chunk is written, all-zero ones too (zarr skips chunks equal to
        the fill value by default, and a missing file must mean damage, not zeros; SCHEMA.md v2)."""
        return self.root[path].with_config({"write_empty_chunks": True})

    @property
    def num_frames(self) -> int:
        return int(self.root["status/complete"].shape[0])

    def _check_index(self, index: int) -> int:
        if not (0 <= int(index) < self.num_frames):
            raise FrameIndexError(f"frame index {index} is outside 0..{self.num_frames - 1}")
        return int(index)

    def write_frame(self, index: int, arrays: dict, *, on_progress: Callable[[str], None] | None = None) -> None:
        """Write frame ``index`` from the renderer's dict (``FRAME_ARRAYS`` + ``meta``), completion flag
        last. ``on_progress(path)`` is called after each array is written (logging, tests)."""
        index = self._check_index(index)
        check_frame(arrays, self.layout)
        arr = self._array
        arr("status/complete")[index] = False
        arr("status/error")[index] = ""
        for source, spec in ARRAY_BY_SOURCE.items():
            arr(spec.path)[index] = spec.to_store(arrays[source], self.layout)
            if on_progress:
                on_progress(spec.path)
        meta = dict(arrays["meta"])
        meta.setdefault("clip_id", meta["scene_seed"])
        for key in list(FRAME_META) + ["clip_id"]:
            value = meta[key]
            path = schema.meta_path(key, self.version)
            if path in self.absent:
                continue
            arr(path)[index] = str(value) if FRAME_META.get(key) is str else value
        if on_progress:
            on_progress("frames")
        arr("status/complete")[index] = True
        if on_progress:
            on_progress("status/complete")

    def mark_failed(self, index: int, error) -> None:
        """Record that frame ``index`` failed: ``status/complete`` False, ``status/error`` the text
        (an exception becomes ``'TypeName: message'``)."""
        index = self._check_index(index)
        text = f"{type(error).__name__}: {error}" if isinstance(error, BaseException) else str(error)
        self._array("status/complete")[index] = False
        self._array("status/error")[index] = text or "failed"

    def frame_complete(self, index: int) -> bool:
        """Marked complete and (schema v2) every chunk file of the frame is there."""
        index = self._check_index(index)
        return bool(_complete_flags(self.root, [index])[0]) and not schema.missing_chunks(self.root, [index])

    def incomplete_frames(self) -> list[int]:
        """Frames to (re-)render: not marked complete (or with an unreadable completion flag), or
        marked complete but missing chunk files (schema v2; :func:`frames_with_missing_data`)."""
        done = _complete_flags(self.root)
        lost = schema.missing_chunks(self.root, [int(i) for i in np.nonzero(done)[0]])
        return sorted([int(i) for i in np.nonzero(~done)[0]] + list(lost))

    def errors(self) -> dict[int, str]:
        """Frame index -> recorded error text, for frames with one."""
        err = self.root["status/error"][:]
        return {int(i): str(err[i]) for i in range(len(err)) if str(err[i])}


def _complete_flags(root, frames=None) -> np.ndarray:
    """``status/complete`` (bool, F, or of ``frames``); a flag whose chunk is damaged (fails its
    checksum, garbage) reads False, so a resume re-renders that frame and rewrites it."""
    arr = root["status/complete"]
    idx = range(arr.shape[0]) if frames is None else frames
    try:
        if frames is None:
            return np.asarray(arr[:], bool)
        return np.array([bool(arr[int(i)]) for i in idx], bool)
    except Exception:      # noqa: BLE001 - zarr raises ValueError/RuntimeError/... on bad bytes
        out = []
        for i in idx:
            try:
                out.append(bool(arr[int(i)]))
            except Exception:  # noqa: BLE001
                out.append(False)
        return np.array(out, bool)


def frames_with_missing_data(path) -> dict[int, list[tuple[str, str]]]:
    """Frames of the store at ``path`` marked complete but missing chunk or shard files, frame ->
    ``[(array, file), ...]`` (schema v2; ``{}`` for v1, whose writers skipped all-zero chunks).
    ``StoreWriter.incomplete_frames`` includes them, so a resume re-renders them."""
    root, _ = schema.open_group(path, mode="r", check=False)
    done = _complete_flags(root)
    return schema.missing_chunks(root, [int(i) for i in np.nonzero(done)[0]])


def open_or_create(path, layout: StoreLayout, config: dict | None = None, *, overwrite: bool = False) -> StoreWriter:
    """Open the store at ``path`` for writing, creating it if missing. An existing store must have the
    same frame layout (resolution, spp, layers, tile, encodings) and schema version; if ``layout``
    has more frames, every array grows (append). A different ``config`` replaces the recorded one and
    the previous one goes to ``config_history``. Call from one process before tasks start writing
    (``pipeline dataset`` holds the store's ``stores.lock.StoreLock`` around it).

    Nothing that is not ours is deleted: a non-empty folder that is not a store raises
    ForeignStoreError unless ``overwrite`` (which also replaces an existing store). A store whose
    creation was cut short (``IncompleteStoreError``) is made again, unless its creator still runs
    on this host (the same pid and process start time: a later process that reused the pid does not
    count)."""
    from stores.errors import IncompleteStoreError, StoreLockedError
    if overwrite or not schema._exists(path):
        schema.create_store(path, layout, config, overwrite=overwrite)
        return StoreWriter(path)
    # The store keeps its own encoding: ``layout.encoding`` None (a config that does not name it)
    # matches the store's, whatever it is (lz4 for stores made before the field, compact since).
    try:
        root, have = schema.open_group(path, mode="r+")
    except IncompleteStoreError as e:
        c = e.creator
        import socket
        from stores.lock import pid_alive
        if (c.get("host") == socket.gethostname() and c.get("pid") != os.getpid()
                and pid_alive(c.get("pid", -1), c.get("proc_start"))):
            raise StoreLockedError(f"{os.fspath(path)!s} is being created by pid {c.get('pid')} on {c.get('host')} "
                                   f"(started {c.get('started')})", holder=c) from e
        schema.create_store(path, layout, config, overwrite=True)     # ours, and nothing was written yet
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
