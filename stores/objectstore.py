"""What every process that reads or writes a store at an ``s3://`` URL needs of the object store.

**Retries.** botocore (boto3, and aiobotocore under s3fs and zarr) retries a request whose connection
fails, times out or is throttled; its ``standard`` mode backs off exponentially with jitter, at most 20 s
between attempts. :func:`retry_defaults` makes that the default in this process and the processes it
starts (Dask workers inherit it; ``pipeline.worker_init`` sets it on workers of other clusters):
``AWS_RETRY_MODE=standard`` and ``AWS_MAX_ATTEMPTS=10``, which rides out an endpoint that is gone for
about a minute (0.5 to 1.9 min of back-off in all). Set either variable to choose another window: the
standard AWS environment always wins. When the window is spent, the command stops with one line
(:class:`stores.errors.StoreUnreachableError`, exit 5) and the store resumes once the endpoint is back.
"""
from __future__ import annotations

import os

RETRY_MODE = "standard"
MAX_ATTEMPTS = 10


def retry_defaults() -> None:
    """botocore's retry settings for this process and its children, unless the environment sets them."""
    os.environ.setdefault("AWS_RETRY_MODE", RETRY_MODE)
    os.environ.setdefault("AWS_MAX_ATTEMPTS", str(MAX_ATTEMPTS))


def endpoint() -> str:
    """The S3 endpoint requests go to, as the environment names it (AWS's own when none is set)."""
    return (os.environ.get("AWS_ENDPOINT_URL_S3") or os.environ.get("AWS_ENDPOINT_URL")
            or f"AWS S3 ({os.environ.get('AWS_REGION') or os.environ.get('AWS_DEFAULT_REGION') or 'default region'})")


def retry_window() -> str:
    """How long botocore tried, in words."""
    return (f"{os.environ.get('AWS_MAX_ATTEMPTS', '?')} attempts in botocore's "
            f"{os.environ.get('AWS_RETRY_MODE', 'legacy')} retry mode")


def cancel_abandoned_requests_at_exit() -> None:
    """At exit, before zarr closes its event loop (``zarr.core.sync.cleanup_resources``, registered when
    zarr was imported: ``atexit`` runs the later first), cancel the requests still pending there and let
    them end: a read or write that found the endpoint gone abandons the others of its batch, some
    waiting out botocore's back-off, and each would print asyncio's "Task was destroyed but it is
    pending!" (and a connection's "Future exception was never retrieved") after the command's one-line
    error. Called where a command learns that the endpoint is gone (``stores.errors.store_unreachable``);
    once a process."""
    global _drain_registered
    if not _drain_registered:
        import atexit
        atexit.register(_cancel_pending)
        _drain_registered = True


_drain_registered = False


def _cancel_pending(timeout: float = 5.0) -> None:
    import asyncio
    import sys

    async def cancel_all():
        tasks = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
        for t in tasks:
            t.cancel()
        if tasks:
            await asyncio.wait(tasks, timeout=timeout)
        for t in tasks:                     # their errors are the one the command printed: retrieved here
            if t.done() and not t.cancelled():
                t.exception()
    for name in ("zarr.core.sync", "fsspec.asyn"):      # zarr's loop; fsspec's, for s3fs used directly
        mod = sys.modules.get(name)
        loop = mod.loop[0] if mod is not None and getattr(mod, "loop", None) else None
        if loop is None or loop.is_closed() or not loop.is_running():
            continue
        try:
            asyncio.run_coroutine_threadsafe(cancel_all(), loop).result(timeout + 1)
        except Exception:  # noqa: BLE001 - at exit: a loop that cannot settle prints what asyncio prints
            pass


def _drop_abandoned(unraisable) -> None:
    code = getattr(unraisable.object, "cr_code", None)
    path = getattr(code, "co_filename", "")
    if not any(f"{os.sep}{pkg}{os.sep}" in path for pkg in ("zarr", "fsspec", "s3fs", "aiobotocore")):
        _previous_hook(unraisable)


_previous_hook = None


def quiet_abandoned_requests() -> None:
    """Leave out the tracebacks of requests that zarr's event loop had in flight when the store became
    unreachable: a failed read or write abandons the others of its batch, and each would print its whole
    traceback ("Exception ignored in: <coroutine object StorePath.get ...>") when the garbage collector
    closes it, around the command's one-line error. Anything else is reported as Python does."""
    import sys
    global _previous_hook
    if _previous_hook is None:
        _previous_hook = sys.unraisablehook
        sys.unraisablehook = _drop_abandoned
