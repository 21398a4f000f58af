"""Where the frames' chunk files are: the key and file of a frame's chunk or shard of a per-frame array,
and which of them are missing (a complete frame has every one; a missing file is damage). One listing a prefix on an object store, one directory listing a 1-D array on disk."""
from __future__ import annotations

import os

from stores.schema import ARRAYS, ArraySpec, absent_arrays


def chunk_key(spec: ArraySpec, frame: int) -> str:
    """The key (path below the array) of the chunk or shard holding frame ``frame`` of a per-frame array
    (metadata: chunk ``frame // META_CHUNK``)."""
    return "/".join(["c", str(int(frame) // spec.frame_chunk)] + ["0"] * (len(spec.dims) - 1))


def chunk_file(root, spec: ArraySpec, frame: int) -> tuple[bool, str]:
    """``(exists, file)`` of frame ``frame``'s chunk or shard of per-frame array ``spec`` (``file`` is a
    local path, or the store key for other stores)."""
    from zarr.storage import LocalStore
    store = root.store
    key = "/".join(p for p in (root.path.strip("/"), spec.path, chunk_key(spec, frame)) if p)
    if isinstance(store, LocalStore):
        f = os.path.join(str(store.root), *key.split("/"))
        return os.path.isfile(f), f
    from zarr.core.sync import sync
    return bool(sync(store.exists(key))), _object_url(store, key)


def _object_url(store, key: str) -> str:
    """The URL of ``key`` in a store that is not local (``s3://bucket/x.zarr/guides/depth/c/1/0/0``),
    as error messages name it; the key where the store has no URL."""
    fs, path = getattr(store, "fs", None), getattr(store, "path", None)
    if fs is None or path is None:
        return key
    proto = fs.protocol[0] if isinstance(fs.protocol, (tuple, list)) else fs.protocol
    return f"{proto}://{path.rstrip('/')}/{key}"


def chunk_keys(root, spec: ArraySpec) -> set[str] | None:
    """Every chunk key (``c/...``) of ``spec``'s array in a store that is not local, from one listing of
    its prefix (a HEAD request a frame would cost in proportion to the store); None if it cannot list."""
    from zarr.core.sync import sync
    prefix = "/".join(p for p in (root.path.strip("/"), spec.path, "c") if p) + "/"
    try:
        async def keys():
            return [k async for k in root.store.list_prefix(prefix)]
        out = sync(keys())
    except (NotImplementedError, AttributeError):
        return None
    cut = len(prefix) - 2                     # keep "c/..."
    return {k[cut:] for k in out}


def missing_chunks(root, frames, *, paths=None) -> dict[int, list[tuple[str, str]]]:
    """frame -> ``[(array, file), ...]`` of the per-frame arrays (all, or those in ``paths``) whose chunk
    or shard file for that frame does not exist. Meaningful for frames marked complete (every chunk is
    written, even all-zero ones), and for a frame's ``status/*`` chunks, which its commit makes. On a
    local store a one-dimensional array's chunks are one directory listing."""
    absent = absent_arrays(root)
    specs = [s for s in ARRAYS if s.per_frame and (paths is None or s.path in paths)
             and s.path not in absent and not s.clip_first]       # the scene JSON: at clip starts only
    frames = [int(i) for i in frames]
    out: dict[int, list[tuple[str, str]]] = {}
    from zarr.storage import LocalStore
    listed = not isinstance(root.store, LocalStore) and len(frames) > 8
    for spec in specs:
        names = chunk_names_1d(root, spec) if len(frames) > 8 else None
        keys = chunk_keys(root, spec) if listed and names is None else None    # URL image shards: one listing
        seen: dict[int, tuple[bool, str]] = {}            # chunk index -> (exists, file): a chunk holds many frames
        for i in frames:
            c = i // spec.frame_chunk
            if names is not None and str(c) in names:
                continue
            if keys is not None and chunk_key(spec, i) in keys:
                continue
            if c not in seen:
                seen[c] = chunk_file(root, spec, i)
            there, f = seen[c]
            if not there:
                out.setdefault(i, []).append((spec.path, f))
    return {i: out[i] for i in sorted(out)}


def chunk_names_1d(root, spec: ArraySpec) -> set[str] | None:
    """The chunk files of a one-dimensional array (names under ``c/``) from one listing, else None (a
    store that is neither local nor listable). At a URL, :func:`chunk_keys` lists every array."""
    from zarr.storage import LocalStore
    if not isinstance(root.store, LocalStore):
        keys = chunk_keys(root, spec)
        if keys is None or len(spec.dims) != 1:
            return None
        return {k.split("/", 1)[1] for k in keys if k.startswith("c/") and k.count("/") == 1}
    if len(spec.dims) != 1:
        return None
    d = os.path.join(str(root.store.root), *(p for p in (root.path.strip("/"),) if p), *spec.path.split("/"), "c")
    try:
        with os.scandir(d) as it:
            return {e.name for e in it if e.is_file()}
    except FileNotFoundError:
        return set()

