"""``python -m stores upgrade STORE [--out PATH]``: a schema v1 or v2 store into a v3 one holding the same
values (:mod:`stores.upgrade` says what differs and how). In place (a local store): the new store is
written beside it (``<store>.upgrading``), then the old one is moved aside (``<store>.v<N>-old``), the new
one takes its name, and the old one is deleted. A run stopped anywhere is finished by running the same
command again: the copy resumes from the frames it has, and a swap cut short is completed. ``--out``
writes a new store instead and leaves the old one alone (the only way for a store at a URL).
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import time

import numpy as np

from stores.errors import (ForeignStoreError, IncompleteStoreError, StoreExistsError, StoreNotFoundError,
                           StorePathError, store_full)
from stores.upgrade import OLD_VERSIONS, require_current

UPGRADING = ".upgrading"               # in place: the new store's folder beside the old one
OLD = ".v{}-old"                       # in place: the old store's folder while the new one takes its name
BATCH = 256                            # frames a commit (and a progress step)


def _meta_source(key_path: str, version: int) -> str:
    """The path in a schema ``version`` store of the v3 metadata array ``key_path``."""
    if key_path == "frames/frame_in_clip" and version == 1:
        return "frames/frame"
    return key_path


def _open_old(src):
    """``(root, attrs, version)`` of the store at ``src`` as zarr reads it (no schema check: that is
    this module's job). Refuses what is not one of our stores, or one whose creation was cut short."""
    import zarr

    from stores.schema import CREATION_ATTR, STORE_KIND, _zarr_store, store_exists
    if not store_exists(src):
        raise StoreNotFoundError(f"no store at {src!s}")
    root = zarr.open_group(_zarr_store(src), mode="r", use_consolidated=False)
    attrs = dict(root.attrs)
    if attrs.get("kind") != STORE_KIND:
        raise ForeignStoreError(f"{src!s} is not a {STORE_KIND} store (root attribute 'kind' is {attrs.get('kind')!r})")
    if CREATION_ATTR in attrs:
        raise IncompleteStoreError(f"{src!s} was never finished (its creation was cut short): nothing to upgrade; "
                                   "run `python -m pipeline dataset` to make it again", creator={})
    return root, attrs, attrs.get("schema_version")


def _source_id(src, attrs: dict) -> str:
    """What identifies the store being upgraded (its path, version, layout and config), recorded in the
    new store so that a resume continues only the same upgrade."""
    path = os.fspath(src)
    path = path if "://" in path else os.path.realpath(path)
    text = json.dumps([path, attrs.get("schema_version"), attrs.get("layout"), attrs.get("config"),
                       attrs.get("store_id")], sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def _column(arr, n: int) -> tuple[np.ndarray, set[int]]:
    """Every value of a one-value-a-frame array, and the frames whose chunk does not decode (read as fill)."""
    try:
        return np.asarray(arr[:n]), set()
    except Exception:  # noqa: BLE001 - zarr and numcodecs raise many kinds for a damaged chunk
        values, bad = [], set()
        for i in range(n):
            try:
                values.append(arr[i])
            except Exception:  # noqa: BLE001
                values.append(arr.fill_value)
                bad.add(i)
        return np.array(values, dtype=object), bad


def _old_table(root, version: int, n: int) -> tuple[dict, set[int]]:
    """The old store's per-frame values by v3 path (FRAME_META keys newer than it: absent), and the frames
    whose metadata chunks do not decode."""
    from stores.schema import ARRAYS
    table, bad = {}, set()
    for spec in ARRAYS:
        if not spec.per_frame or spec.image:
            continue
        try:
            arr = root[_meta_source(spec.path, version)]
        except KeyError:
            continue                                    # newer than the store: its fill value, as it read
        table[spec.path], lost = _column(arr, n)
        bad |= lost
    return table, bad


def _records(table: dict, frames: list[int]) -> dict[int, dict]:
    """What :meth:`stores.writer.StoreWriter.commit` takes for ``frames``, from the old values."""
    from stores.contract import FRAME_META
    from stores.schema import ARRAY_BY_PATH, meta_path
    columns = [(key, meta_path(key)) for key in FRAME_META if key != "scene_json"] + [("clip_id", meta_path("clip_id"))]
    out = {}
    for i in frames:
        meta = {}
        for key, path in columns:
            v = table[path][i] if path in table else ARRAY_BY_PATH[path].fill
            meta[key] = str(v) if FRAME_META.get(key) is str else v.item() if hasattr(v, "item") else v
        out[i] = {"meta": meta, **{k: np.asarray(table[f"frames/{k}"][i], np.float64).tolist()
                                   for k in ("camera_to_world", "world_to_clip")}}
    return out


def _copy_images(src_root, dst_root, frames: list[int]) -> dict[int, str]:
    """Copy every image array's stored values of ``frames``; frame -> why, for those that do not decode."""
    from stores.schema import ARRAYS
    specs = [s for s in ARRAYS if s.image]
    src = {s.path: src_root[s.path] for s in specs}          # each array's zarr.json read once
    dst = {s.path: dst_root[s.path].with_config({"write_empty_chunks": True}) for s in specs}
    bad = {}
    for i in frames:
        values = {}
        for s in specs:
            try:
                values[s.path] = src[s.path][i]
            except Exception as e:  # noqa: BLE001 - a damaged chunk: the frame is rendered again
                bad[i] = f"{s.path}: {type(e).__name__}: {e}"
                break
        if i not in bad:
            for path, a in values.items():
                dst[path][i] = a
    return bad


def _start(dst, src, attrs: dict, version: int):
    """The new store at ``dst``: made (the old one's layout and config), or resumed if it is this upgrade's."""
    from stores import create, schema
    ident = _source_id(src, attrs)
    if schema.store_exists(dst):
        have = dict(schema.open_group(dst, mode="r", check=False)[0].attrs).get("upgrade") or {}
        if have.get("source") != ident:
            raise StoreExistsError(f"{dst!s} is already a store, not this upgrade's: choose another --out")
        return schema.open_group(dst, mode="r+")[0]
    layout = schema.StoreLayout.of_store(attrs["layout"])
    root = create.create_store(dst, layout, attrs.get("config") or {})
    extra = {k: attrs[k] for k in ("config_history", "package_versions", "git_hash") if k in attrs}
    root.attrs.update({**extra, "upgrade": {"source": ident, "from_path": os.fspath(src), "from_version": version,
                                            "started": time.strftime("%Y-%m-%dT%H:%M:%S"), "finished": None}})
    return root


def copy(src, dst, *, progress: bool = False, say=None) -> dict:
    """Write the v3 store ``dst`` from the v1/v2 store ``src`` (resuming a copy cut short). Returns a
    summary: frames, ``copied`` (complete frames written now), ``kept`` (complete already), ``incomplete``
    (incomplete in the old store too), ``damaged`` (frame -> why: left incomplete for a resume)."""
    from stores import schema
    from stores.writer import StoreWriter, complete_flags
    src_root, attrs, version = _open_old(src)
    dst_root = _start(dst, src, attrs, version)
    n = int(schema.StoreLayout.of_store(attrs["layout"]).num_frames)
    table, bad_meta = _old_table(src_root, version, n)
    done_old = np.asarray(table["status/complete"], bool)
    done_new = complete_flags(dst_root)
    writer = StoreWriter(dst)
    out = {"frames": n, "copied": 0, "kept": int((done_old & done_new).sum()), "incomplete": int((~done_old).sum()),
           "damaged": {}, "from_version": version}
    bar = _bar(n, progress)
    firsts: set[int] = set()
    for lo in range(0, n, BATCH):
        batch = [i for i in range(lo, min(lo + BATCH, n)) if not done_new[i]]
        todo = [i for i in batch if done_old[i] and i not in bad_meta]
        damaged = {i: "its metadata chunks do not decode" for i in batch if done_old[i] and i in bad_meta}
        damaged.update(_copy_images(src_root, dst_root, todo))
        good = [i for i in todo if i not in damaged]
        for i in good:
            first = i - int(table["frames/frame_in_clip"][i])
            if 0 <= first < n and first not in firsts:      # once a clip: its frames share the JSON
                firsts.add(first)
                writer.write_scene_json(first, str(table["frames/scene_json"][i]))
        failures = {i: str(table["status/error"][i]) for i in batch if not done_old[i] and str(table["status/error"][i])}
        failures.update({i: f"damaged in the schema v{version} store ({why}); `python -m pipeline dataset` renders "
                            "it again" for i, why in damaged.items()})
        writer.commit(_records(table, good), failures)
        out["copied"] += len(good)
        out["damaged"].update(damaged)
        if say:
            for i, why in damaged.items():
                say(f"frame {i}: damaged in the old store ({why}); left incomplete for `python -m pipeline dataset`")
        if bar is not None:
            bar.update(min(lo + BATCH, n) - lo)
    if bar is not None:
        bar.close()
    finished = dict(dst_root.attrs.get("upgrade") or {}, finished=time.strftime("%Y-%m-%dT%H:%M:%S"))
    dst_root.attrs["upgrade"] = finished
    schema.consolidate(dst)
    return out


def _bar(n: int, progress: bool):
    if not progress:
        return None
    import sys

    from tqdm import tqdm
    return tqdm(total=n, unit="frame", desc="upgrading", file=sys.stderr, dynamic_ncols=True)


def _finished_copy(path: str) -> bool:
    """Whether ``path`` holds a new store whose copy finished (a swap may follow)."""
    from stores import schema
    if not schema.store_exists(path):
        return False
    up = dict(schema.open_group(path, mode="r", check=False)[0].attrs).get("upgrade") or {}
    return bool(up.get("finished"))


def _swap(store: str, new: str, old: str) -> None:
    """The new store takes the old one's name: old aside, new in, old deleted (each step re-runnable)."""
    if os.path.isdir(store) and not os.path.exists(old):
        os.rename(store, old)
    if os.path.isdir(new):
        os.rename(new, store)
    shutil.rmtree(old, ignore_errors=True)


def _in_place_leftover(store: str) -> str | None:
    """Finish an in-place upgrade whose swap was cut short; the old version it came from, else None."""
    new = store + UPGRADING
    for v in OLD_VERSIONS:
        old = store + OLD.format(v)
        if os.path.isdir(old) and (not os.path.isdir(store) or os.path.isdir(new)) and _finished_copy(new):
            _swap(store, new, old)
            return str(v)
        if os.path.isdir(old) and os.path.isdir(store) and not os.path.isdir(new):
            shutil.rmtree(old, ignore_errors=True)          # the new store has its name: only the deletion was left
            return str(v)
    return None


def upgrade(store, out=None, *, progress: bool = False, say=None) -> dict:
    """Upgrade the store at ``store`` to the current schema: in place (a local store), or into a new store at
    ``out``. A run stopped anywhere is finished by running it again. Returns :func:`copy`'s summary plus
    ``path`` (where the upgraded store is) and ``upgraded`` (False: it was current already)."""
    from stores import schema
    from stores.lock import StoreLock
    store = os.fspath(store)
    local = "://" not in store
    if out is None and local:
        done = _in_place_leftover(store)
        if done is not None:
            return {"path": store, "upgraded": True, "from_version": int(done), "resumed_swap": True}
    _, attrs, version = _open_old(store)
    if version == schema.SCHEMA_VERSION:
        return {"path": store, "upgraded": False, "from_version": version}
    if version not in OLD_VERSIONS:
        require_current(store, attrs, schema.SCHEMA_VERSION)
    if out is None and not local:
        raise StorePathError(f"{store} is at a URL, which cannot be renamed: give --out for the upgraded store")
    dst = os.fspath(out) if out is not None else store + UPGRADING
    try:
        with StoreLock(store, command="upgrade"):         # one upgrade at a time (a dataset run refuses v1/v2)
            summary = copy(store, dst, progress=progress, say=say)
        if out is None:
            _swap(store, dst, store + OLD.format(version))
    except OSError as e:
        from core.errors import is_disk_full
        if is_disk_full(e):
            raise store_full(dst, "writing the upgraded store") from None
        raise
    return {**summary, "path": os.fspath(out) if out is not None else store, "upgraded": True}


def add_arguments(ap) -> None:
    """The ``upgrade`` command's arguments (``python -m stores upgrade``)."""
    ap.add_argument("store", help="the store (a folder, or an s3:// URL with --out)")
    ap.add_argument("--out", default=None,
                    help="write the upgraded store here and leave the old one as it is (default: in place)")


def run(args) -> int:
    """``python -m stores upgrade STORE [--out PATH]``."""
    import sys
    s = upgrade(args.store, args.out, progress=sys.stderr.isatty(),
                say=lambda line: print(line, file=sys.stderr))
    if not s["upgraded"]:
        print(f"{s['path']}: already schema v{s['from_version']}; nothing to do")
        return 0
    if s.get("resumed_swap"):
        print(f"{s['path']}: finished the upgrade from schema v{s['from_version']} that was cut short")
        return 0
    damaged = s["damaged"]
    print(f"{s['path']}: upgraded from schema v{s['from_version']} to v3: {s['frames']} frames, "
          f"{s['copied'] + s['kept']} complete, {s['incomplete']} incomplete as before"
          + (f", {len(damaged)} damaged (left incomplete: {sorted(damaged)[:10]})" if damaged else "")
          + ("; `python -m pipeline dataset` with the same config finishes the incomplete ones"
             if s["incomplete"] or damaged else ""))
    return 1 if damaged else 0
