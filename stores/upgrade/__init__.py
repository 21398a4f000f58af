"""Older stores through one door. Every open of a store (``stores.schema.open_group``) passes
:func:`require_current`, which refuses an older schema version with a line naming ``python -m stores
upgrade``; :func:`upgrade` turns a schema v1 or v2 store into a v3 one holding the same values. This is
the one module that knows the older versions; everything else reads and writes v3 only.

What the older versions hold differently (``stores/SCHEMA.md`` has the full tables):

- v1: the index of a frame in its clip is ``frames/frame``; no checksums; all-zero chunks were not
  written (they read as zeros); the only coordinates are ``inputs/feature`` and ``layers/spp``.
- v2: ``frames/frame_in_clip``, checksums and coordinates as v3, but one chunk a frame for every
  ``frames/*`` and ``status/*`` value, and the SceneSpec JSON at every frame.

The upgrade reads each array by its path through zarr (whose codecs decode any of them) and writes a new
v3 store through ``stores.create`` and ``stores.writer``: the image arrays' stored values are copied as
they are (the same layout and encoding, so nothing is rounded again), each complete frame's metadata is
committed as a dataset run commits it, and each clip's SceneSpec JSON is kept once, at its first frame.
Incomplete frames stay incomplete (with their error text), so ``python -m pipeline dataset`` finishes
them as before; a complete frame whose chunks do not decode (a v2 checksum) is left incomplete, named,
for the same resume. FRAME_META keys newer than the store read as their fill values, as they did.

``stores.upgrade.migrate`` is the copy and the command; this module is the door every open passes
(it imports nothing of the package but its errors, so the schema below can call it).
"""
from __future__ import annotations

from stores.errors import SchemaVersionError

OLD_VERSIONS = (1, 2)


def require_current(path, attrs: dict, current: int) -> None:
    """Refuse a store whose root attributes name another schema version than ``current`` (this code's,
    ``stores.schema.SCHEMA_VERSION``), with the command that upgrades it (v1, v2) or the reason it cannot
    (a newer or unknown version)."""
    version = attrs.get("schema_version")
    if version == current and not isinstance(version, bool):
        return
    if version in OLD_VERSIONS and not isinstance(version, bool):
        raise SchemaVersionError(
            f"{path!s} is a schema v{version} store; this code reads and writes v{current}: "
            f"`python -m stores upgrade {path!s}` turns it into one, keeping every value (in place and "
            "resumable; --out PATH writes a copy)")
    raise SchemaVersionError(f"{path!s} has schema version {version!r}; this code reads and writes "
                             f"v{current} and upgrades v1 and v2 (a store from a newer release needs that release)")
