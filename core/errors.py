"""The base classes of every error of the project. Each stage's ``errors.py`` derives its own from
these (``stores.errors.StoreError``, ``pipeline.errors.PipelineError``, ...), and every specific error
also inherits the matching built-in exception, as zarr's ``NodeNotFoundError(BaseZarrError,
FileNotFoundError)``. Only a command-line ``main()`` turns them into exit codes."""


class ProjectError(Exception):
    """Base class of every error this project raises."""


class SettingError(ProjectError, ValueError):
    """A setting (of a config, a model or a command) is invalid; the message names it, its allowed values
    and what it got (``core.checks``). Each stage's ``ConfigError`` is one."""


class VariantError(ProjectError, RuntimeError):
    """The Mitsuba variant cannot start (missing or broken libLLVM, no CUDA, ...); ``core.variant``."""


class DiskFullError(ProjectError, OSError):
    """The file system (or quota) being written is full: ``ENOSPC`` or ``EDQUOT``. Exit code 4 in every
    command (``core.cli``): nothing is wrong with the input; free space and run again. A store's is
    ``stores.errors.StoreFullError``."""
    exit_code = 4


DISK_FULL_ERRNOS = (28, 122)      # ENOSPC, EDQUOT (Linux)
DISK_FULL_HINT = "free space and run it again"


def disk_full_cause(e: BaseException) -> OSError | None:
    """The exception in ``e``'s chain (itself, its cause or context) that is a full file system or quota,
    else None."""
    seen = set()
    while e is not None and id(e) not in seen:
        seen.add(id(e))
        if isinstance(e, OSError) and e.errno in DISK_FULL_ERRNOS:
            return e
        e = e.__cause__ or e.__context__
    return None


def is_disk_full(e: BaseException) -> bool:
    """Whether ``e`` (or an exception it was raised from) is a full file system or quota."""
    return disk_full_cause(e) is not None


def free_bytes(path: str) -> int | None:
    """Free bytes on the file system holding ``path`` (or its nearest existing parent); None if unknown."""
    import os
    import shutil
    p = os.path.abspath(path)
    while p and not os.path.exists(p):
        p = os.path.dirname(p)
    try:
        return shutil.disk_usage(p).free
    except OSError:
        return None


def size_text(n: float) -> str:
    """A byte count as people read it: ``812 bytes``, ``3.4 MB``."""
    for unit in ("bytes", "KB", "MB", "GB", "TB"):
        if abs(n) < 1024 or unit == "TB":
            return f"{n:.0f} {unit}" if unit == "bytes" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} TB"


def disk_full(e: BaseException, out=None, again: str = DISK_FULL_HINT) -> DiskFullError:
    """The :class:`DiskFullError` for the full-disk error in ``e``'s chain: one line naming the file (else
    ``out``, the command's output), the free space on its device and what to do (``again``). A
    :class:`DiskFullError` already in the chain (a store's, with its own message) is returned as it is."""
    import os
    cause = disk_full_cause(e)
    seen, x = set(), e
    while x is not None and id(x) not in seen:
        seen.add(id(x))
        if isinstance(x, DiskFullError):
            return x
        x = x.__cause__ or x.__context__
    where = os.fspath(cause.filename) if cause is not None and getattr(cause, "filename", None) else None
    where = where or (os.fspath(out) if out is not None else None)
    free = free_bytes(os.path.dirname(os.path.abspath(where))) if where and "://" not in where else None
    at = f" writing {where}" if where else ""
    have = f"; {size_text(free)} free there" if free is not None else ""
    why = os.strerror(cause.errno) if cause is not None else "no space left"
    return DiskFullError(f"no space left on the device{at} ({why}{have}): {again}")
