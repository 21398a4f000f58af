"""Errors raised by the stores package. Only command-line ``main()`` turns them into exit codes.

Every specific error also inherits the matching built-in exception (as zarr's
``NodeNotFoundError(BaseZarrError, FileNotFoundError)``), so callers may catch either.
"""


from core.errors import DiskFullError, ProjectError, free_bytes, size_text


class StoreError(ProjectError):
    """Base class of every stores error."""


class StoreNotFoundError(StoreError, FileNotFoundError):
    """No store at the given path or URL."""


class ForeignStoreError(StoreError, ValueError):
    """The path holds something (a Zarr group or not) that is not a store written by this package."""


class SchemaVersionError(StoreError, ValueError):
    """The store was written with a schema version this code cannot read or append to."""


class StoreLayoutError(StoreError, ValueError):
    """A layout or frame does not match the store (shape, sample count, resolution, missing array)."""


class StoreValueError(StoreError, ValueError):
    """A value cannot be stored faithfully (e.g. a feature beyond float16's range)."""


class FrameIndexError(StoreError, IndexError):
    """A frame index outside ``0 .. num_frames - 1``."""


class IncompleteFrameError(StoreError, RuntimeError):
    """A frame that was never finished (or whose writer crashed) was asked for."""


class SampleCountError(StoreError, ValueError):
    """More samples (or a larger per-pixel count) than the store holds were asked for."""


class CropSizeError(StoreError, ValueError):
    """A crop larger than the frame (or not positive) was asked for."""


class SplitError(StoreError, ValueError):
    """An unknown split name, bad split fractions, or a split without any complete frame."""


class ExportError(StoreError, RuntimeError):
    """An export could not be written (bad format, frames or output folder)."""


class UnfitFrameError(StoreError, ValueError):
    """Frames that ``validate`` flags (``stores.fitness``: NaN/Inf or out-of-range values, an all-zero
    reference, NaN/Inf the renderer replaced, incomplete) were asked to be used. ``frames`` maps each
    to its problems; ``--skip-bad-frames`` leaves them out instead."""

    def __init__(self, message: str, frames: dict | None = None):
        super().__init__(message)
        self.frames = dict(frames or {})


class StoreCorruptionError(StoreError):
    """The store's files on disk are damaged: a lost shard, a truncated or garbage chunk, a checksum
    mismatch, or array metadata (``zarr.json``) that disagrees with the schema. ``array``, ``frame``
    and ``path`` (the file) name the damage where known. Every command exits 3 on these."""
    exit_code = 3
    lead = "the store is damaged: "      # how a command's one line begins (core.cli.message)

    def __init__(self, message: str, *, array: str | None = None, frame: int | None = None,
                 path: str | None = None):
        super().__init__(message)
        self.array, self.frame, self.path = array, frame, path


class MissingShardError(StoreCorruptionError, FileNotFoundError):
    """A frame marked complete has no file for one of its chunks (schema v2: every chunk is written)."""


class CorruptChunkError(StoreCorruptionError, ValueError):
    """A chunk or shard file is truncated, holds garbage, or fails its crc32c checksum."""


class ArrayMetadataError(StoreCorruptionError, StoreLayoutError):
    """An array's ``zarr.json`` (dtype, shape, chunks, codecs, fill value, dims) disagrees with the schema."""


class StorePathError(StoreError, OSError):
    """The store's path cannot be made or written: a parent is a file, no permission, a read-only
    file system. The message names the path and the system's reason."""


class StoreFullError(StoreError, DiskFullError):
    """The file system (or quota) holding the store is full: ``ENOSPC`` or ``EDQUOT``. Its own exit code
    (``exit_code``, 4): nothing is wrong with the config or the store; free space and re-run (complete
    frames stay, the run resumes)."""
    exit_code = 4


def store_full(path, doing: str, need_bytes: int | None = None) -> StoreFullError:
    """The :class:`StoreFullError` for the store at ``path`` (one line: what was being written, the free
    space there, the space the rest of the run needs when known, and what to do)."""
    import os
    where = os.fspath(path)
    free = free_bytes(where) if "://" not in where else None
    have = f"{size_text(free)} free there" if free is not None else "no space left"
    need = f"; the rest of the run needs about {size_text(need_bytes)} more" if need_bytes else ""
    return StoreFullError(f"no space left on the device of the store {where} ({doing}; {have}{need}): free space "
                          "or choose another --out; complete frames stay, and the same command resumes")


class StoreUnreachableError(StoreError, ConnectionError):
    """The object store holding the store (an ``s3://`` URL's endpoint) could not be reached, after
    botocore's retries (:mod:`stores.objectstore`). Its own exit code (``exit_code``, 5): nothing is wrong
    with the config or the store; what was committed stays, and the same command resumes once the
    endpoint is back."""
    exit_code = 5


# botocore's and aiohttp's errors of a connection that failed, timed out or was cut (not of a request the
# server answered): matched by name so that code without the S3 extras installed needs neither package
_UNREACHABLE = {("botocore.exceptions", "ConnectionError"), ("botocore.exceptions", "HTTPClientError"),
                ("aiohttp.client_exceptions", "ClientConnectionError"), ("aiohttp.client_exceptions",
                                                                         "ServerTimeoutError")}


def unreachable_cause(e: BaseException) -> BaseException | None:
    """The exception in ``e``'s chain (itself, its cause or context) that is a failed connection to an object
    store (botocore ``EndpointConnectionError``, ``ConnectTimeoutError``, ``ReadTimeoutError``,
    ``ConnectionClosedError``; aiohttp's connection errors), else None."""
    seen = set()
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        if isinstance(e, StoreUnreachableError) or any(
                (c.__module__, c.__name__) in _UNREACHABLE for c in type(e).__mro__):
            return e
        e = e.__cause__ or e.__context__
    return None


def raise_if_unreachable(e: BaseException, store=None, doing: str = "") -> None:
    """Raise the :class:`StoreUnreachableError` of ``store`` from ``e`` when ``e`` is a failed connection to
    an object store. For the handlers that read any other failure as damage (a chunk that does not
    decode, a flag that reads False): an endpoint that is gone is not a damaged store."""
    if unreachable_cause(e) is not None:
        raise store_unreachable(store if store is not None else "the store", e, doing) from e


def store_unreachable(store, e: BaseException, doing: str = "") -> StoreUnreachableError:
    """The :class:`StoreUnreachableError` of ``store`` for the failed connection ``e``: one line naming the
    endpoint, the last error and what to do. The requests still pending on zarr's event loop are
    cancelled at exit (:func:`stores.objectstore.cancel_abandoned_requests_at_exit`): the line stays the
    command's last."""
    from stores.objectstore import cancel_abandoned_requests_at_exit, endpoint, retry_window
    cancel_abandoned_requests_at_exit()
    cause = unreachable_cause(e) or e
    if isinstance(cause, StoreUnreachableError):
        return cause
    text = str(cause).split("\n")[0]
    return StoreUnreachableError(
        f"the object store of {store} at {endpoint()} could not be reached{' ' + doing if doing else ''} "
        f"({retry_window()}; last error: {type(cause).__name__}: {text}): what was committed stays; run the same "
        "command again once the endpoint is back and it resumes (an endpoint that comes back empty has lost the "
        "store: the run then builds it again from the start)")


def explain(e: BaseException, store=None) -> StoreUnreachableError | None:
    """``core.cli.Program.explain`` for commands that read or write stores: a failed connection to the
    object store of ``store`` anywhere in ``e``'s chain is that store's :class:`StoreUnreachableError`
    (exit 5, one line naming the endpoint); None otherwise."""
    if unreachable_cause(e) is None:
        return None
    return store_unreachable(store or "the store", e)


class StoreExistsError(StoreError, FileExistsError):
    """A store already exists where a new one was to be created (``overwrite`` not given)."""


class IncompleteStoreError(StoreError, RuntimeError):
    """The store's creation was cut short (its root still carries the ``creating`` mark).
    ``creator`` holds the host, pid and start time of the process that began it."""

    def __init__(self, message: str, creator: dict | None = None):
        super().__init__(message)
        self.creator = dict(creator or {})


class StoreLockedError(StoreError, RuntimeError):
    """Another run holds the store's writer lock (``stores.lock``); ``holder`` has its host, pid, start."""

    def __init__(self, message: str, holder: dict | None = None):
        super().__init__(message)
        self.holder = dict(holder or {})
