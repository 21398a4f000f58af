"""Making a store: ``create_store`` writes an empty store of the current schema (its root ``zarr.json``
first, carrying a ``creating`` mark, then every array, then the root attributes without the mark), after
making room where it goes (a folder that is not a store is refused, a link is never followed). Also the
folder's own housekeeping: what else is there (:func:`foreign_entries`), zarr's leftover ``*.partial``
files, and the package versions and git commit a store records."""
from __future__ import annotations

import json
import os
import re
import subprocess

from stores import codecs
from stores.contract import FEATURE_NAMES
from stores.errors import ForeignStoreError, StoreExistsError, StoreLayoutError
from stores.procinfo import holder_record
from stores.schema import (ARRAYS, CREATION_ATTR, GROUPS, LOCK_NAME, SCHEMA_VERSION, STORE_KIND, StoreLayout,
                           _is_local, _zarr_store, consolidate, coord_values, create_kwargs, store_exists)


def package_versions() -> dict:
    """Versions of the packages that shape the data (recorded in the root attributes)."""
    out = {}
    import importlib.metadata as md
    for name in ("numpy", "zarr", "numcodecs", "mitsuba", "drjit", "denoise-datagen"):
        try:
            out[name] = md.version(name)
        except md.PackageNotFoundError:
            pass
    return out


def git_hash() -> str | None:
    """The project's git commit (None outside a checkout)."""
    try:
        here = os.path.dirname(os.path.abspath(__file__))
        r = subprocess.run(["git", "-C", here, "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5)
        return r.stdout.strip() or None if r.returncode == 0 else None
    except (OSError, subprocess.SubprocessError):
        return None


def url_fs(url: str):
    """``(filesystem, path)`` of a store URL (``s3://bucket/x.zarr``, any fsspec protocol), with
    credentials and endpoint from the standard environment and config files (``AWS_*`` for S3)."""
    import fsspec
    return fsspec.core.url_to_fs(url)


def foreign_entries(path_or_url) -> list[str] | None:
    """What makes ``path_or_url`` something other than a store or an empty place to make one: None when
    there is nothing (no path, an empty folder or prefix, one holding only our lock file) or a store (a
    root ``zarr.json``); else the names found there (sorted; ``['<file>']`` for a plain file)."""
    p = _zarr_store(path_or_url)
    if store_exists(p):
        return None
    if not _is_local(p):
        fs, root = url_fs(p)
        try:
            names = sorted(e.rstrip("/").rsplit("/", 1)[-1] for e in fs.ls(root, detail=False))
        except FileNotFoundError:
            return None
        names = [n for n in names if n != LOCK_NAME]
        return names or None
    if not os.path.lexists(p):
        return None
    if not os.path.isdir(p):
        return ["<file>"]
    names = sorted(n for n in os.listdir(p) if n != LOCK_NAME)
    return names or None


def refuse_link(path, what: str = "--overwrite") -> None:
    """Raise ForeignStoreError when ``path`` is a symbolic link: deleting "its contents" would delete the
    contents of the folder it points to, which may not be a store at all (or anyone's store)."""
    p = os.fspath(path)
    if _is_local(p) and os.path.islink(p):
        raise ForeignStoreError(f"{p} is a symbolic link to {os.path.realpath(p)}; {what} never deletes through a "
                                "link: give the link's target itself, or remove the link")


PARTIAL_NAME = re.compile(r"\.[0-9a-f]{32}\.partial$")   # zarr's local store: KEY.<uuid4 hex>.partial


def partial_files(path_or_url) -> list[str]:
    """The temporary files a cut-short write left in the local store at ``path_or_url`` (sorted paths
    relative to it): zarr's local store writes a key to ``KEY.<uuid>.partial`` and renames it to ``KEY``,
    so a process killed in between (a SIGKILL mid-commit) leaves one; the key keeps its previous bytes.
    Not store data. Empty at a URL (an object store's put is whole or nothing) or where nothing is."""
    p = _zarr_store(path_or_url)
    if not _is_local(p) or not os.path.isdir(p):
        return []
    p = os.fspath(p)
    return sorted(os.path.relpath(os.path.join(d, n), p) for d, _, names in os.walk(p) for n in names
                  if PARTIAL_NAME.search(n))


def remove_partial_files(path_or_url) -> list[str]:
    """Delete :func:`partial_files` (a resume, holding the store's writer lock: no write is under way);
    the paths removed."""
    found = partial_files(path_or_url)
    for rel in found:
        try:
            os.unlink(os.path.join(os.fspath(_zarr_store(path_or_url)), rel))
        except FileNotFoundError:
            pass
    return found


def _clear(path_or_url) -> None:
    """Remove everything at ``path_or_url`` but our lock file (``--overwrite``). A symbolic link is refused
    (:func:`refuse_link`), and links inside the folder are removed, never followed."""
    import shutil
    p = _zarr_store(path_or_url)
    if not _is_local(p):                        # every object under the store's prefix but the lock
        fs, root = url_fs(p)
        try:
            entries = fs.ls(root, detail=False)
        except FileNotFoundError:
            return
        for e in entries:
            if e.rstrip("/").rsplit("/", 1)[-1] != LOCK_NAME:
                fs.rm(e, recursive=True)
        fs.invalidate_cache()
        return
    refuse_link(p)
    if not os.path.lexists(p):                  # nothing there: nothing to clear
        return
    if not os.path.isdir(p):
        raise ForeignStoreError(f"{p} is a file, not a folder; refusing to replace it with a store")
    for name in os.listdir(p):
        if name == LOCK_NAME:
            continue
        q = os.path.join(p, name)
        if os.path.isdir(q) and not os.path.islink(q):
            shutil.rmtree(q)
        else:
            os.unlink(q)


def _creation_hook() -> None:
    """A seam inside the creation window, doing nothing: a test replaces it (``tests/procs.pause_at``) to
    stop a process there and kill it."""


def create_store(path_or_url, layout: StoreLayout, config: dict | None = None, *, overwrite: bool = False):
    """Create the group, every array (empty, ``status/complete`` all False) and the root attributes
    (schema version, layout, the full generation ``config``, package versions, git hash).
    Returns the ``zarr.Group``.

    Never deletes what it was not asked to: an existing store raises StoreExistsError and a non-empty
    folder that is not a store (a Zarr v2 store, a store without its root metadata, any folder)
    raises ForeignStoreError, unless ``overwrite`` (then its contents go first; our lock file stays).
    The root ``zarr.json`` is written first with a ``creating`` attribute (host, pid, start) that the
    last step removes: a store cut mid-creation is recognised (:class:`IncompleteStoreError` from
    :func:`open_group`) and ``stores.writer.open_or_create`` makes it again."""
    p = _zarr_store(path_or_url)
    layout = layout.resolved()               # an encoding left open is the default for new stores
    try:
        json.dumps(config or {})
    except TypeError as e:
        raise StoreLayoutError(f"config must be JSON-serialisable: {e}") from e
    _make_room(p, overwrite)
    root = _create_root(p)
    _create_arrays(root, layout)
    _describe_lossy_codecs(root, layout)
    # last: the complete root attributes, without the "creating" mark (one atomic zarr.json write)
    root.attrs.put(_root_attrs(layout, config))
    consolidate(p)
    return root


def _make_room(p, overwrite: bool) -> None:
    """Refuse a file, an existing store or a folder that is not a store at ``p``; with ``overwrite``
    delete what is there instead (our lock file stays)."""
    if _is_local(p) and os.path.lexists(p) and not os.path.isdir(p):
        raise ForeignStoreError(f"{p} is a file, not a folder; refusing to replace it with a store")
    if overwrite:
        _clear(p)
        return
    if store_exists(p):
        raise StoreExistsError(f"a store already exists at {p!s}; open it (open_or_create) or pass "
                               "overwrite=True")
    found = foreign_entries(p)
    if found:
        shown = ", ".join(found[:5]) + (f", ... ({len(found)} entries)" if len(found) > 5 else "")
        raise ForeignStoreError(f"{p} is a non-empty folder that is not a store (it holds {shown}); "
                                "refusing to write into it: choose another path, or overwrite it "
                                "(--overwrite) to delete its contents")


def _create_root(p):
    """The root group with the ``creating`` mark (:func:`holder_record`), refusing one that appeared meanwhile."""
    import zarr
    if _is_local(p):
        from zarr.storage import LocalStore
        os.makedirs(p, exist_ok=True)
        target = LocalStore(p)
    else:
        target = p
    # zarr's mode "w-" refuses any non-empty folder (our lock file is in it): create_group with
    # overwrite=False is the same "never replace a node" guarantee on the root.
    try:
        return zarr.create_group(target, overwrite=False, attributes={
            "kind": STORE_KIND, "schema_version": SCHEMA_VERSION, CREATION_ATTR: holder_record()})
    except (zarr.errors.ContainsGroupError, zarr.errors.ContainsArrayError, FileExistsError) as e:
        raise StoreExistsError(f"a store appeared at {p!s} while it was being created: {e}") from e


def _create_arrays(root, layout: StoreLayout) -> None:
    """The groups and every array of the schema, empty except the coordinates (their values written)."""
    for g in GROUPS:
        root.require_group(g)
    for n, spec in enumerate(ARRAYS):
        arr = root.create_array(spec.path, **create_kwargs(spec, layout))
        if spec.coord:
            arr.with_config({"write_empty_chunks": True})[:] = coord_values(spec, layout)
        if n == len(ARRAYS) // 2:
            _creation_hook()


def _describe_lossy_codecs(root, layout: StoreLayout) -> None:
    """Array attributes saying what the lossy codecs cost (xarray shows them): the radiance encoding,
    ``max_rel_error`` of bit-rounded arrays (per feature where each has its own bits), log16's decoding."""
    root["inputs/radiance"].attrs["encoding"] = layout.radiance_encoding
    for spec in ARRAYS:
        ch = spec.chain(layout) if spec.image else None
        if ch is None or ch.keepbits is None:
            continue
        if ch.channel_keepbits is not None:      # compact2's features: each its own bits
            root[spec.path].attrs["feature_precision"] = {
                name: {"keepbits": k, "max_rel_error": 2.0 ** -(k + 1)}
                for name, k in zip(FEATURE_NAMES, ch.channel_keepbits)}
        root[spec.path].attrs["max_rel_error"] = 2.0 ** -(min(ch.channel_keepbits or (ch.keepbits,)) + 1)
    if layout.radiance_encoding == "log16":
        root["inputs/radiance"].attrs["log16"] = {
            "min_exp2": codecs.LOG16_MIN_EXP, "max_exp2": codecs.LOG16_MAX_EXP,
            "decode": "0 -> 0; c >= 1 -> 2 ** (min_exp2 + (c - 1) * (max_exp2 - min_exp2) / 65534)"}


def _root_attrs(layout: StoreLayout, config: dict | None) -> dict:
    """The finished store's root attributes: what it is, its layout, where it came from."""
    import uuid
    return {
        "kind": STORE_KIND, "schema_version": SCHEMA_VERSION, "layout": layout.to_dict(),
        "config": config or {}, "config_history": [], "feature_names": list(FEATURE_NAMES),
        "package_versions": package_versions(), "git_hash": git_hash(),
        "store_id": uuid.uuid4().hex,      # this store, not another made at the same path (writers' caches)
    }

