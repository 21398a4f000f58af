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
