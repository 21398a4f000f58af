"""How a command line prints the project's warnings: one plain line, ``warning: MESSAGE``.

Library code tells of what it left out or changed with ``warnings.warn`` (``stores.fitness``: frames
``--skip-bad-frames`` leaves out; ``training.loop``: training without validation; the Noisebase export:
clips split at a flagged frame), so that a caller can record or silence it. Python prints such a
warning as ``FILE:LINE: UserWarning: MESSAGE`` followed by the source line, which reads as a fault of
the program; within :func:`plain_warnings` (each command line's ``main()``) a warning raised from the
project's own code prints as one line instead. A library's warning (a file outside the project, or
under a ``site-packages`` folder) prints as Python prints it.
"""
from __future__ import annotations

import contextlib
import os
import warnings

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))     # the folder holding core/, stores/, ...


def is_ours(filename: str) -> bool:
    """Whether ``filename`` (a warning's source file) is a file of the project rather than of a library."""
    path = os.path.abspath(filename or "")
    return path.startswith(ROOT + os.sep) and "site-packages" not in path.split(os.sep)


def plain(message, category, filename, lineno, line=None) -> str:
    """``warnings.formatwarning`` for the project's warnings: ``warning: MESSAGE`` on one line."""
    return "warning: " + " ".join(str(message).split()) + "\n"


@contextlib.contextmanager
def plain_warnings():
    """Within the block, the project's warnings print as :func:`plain` lines on stderr (module docstring)."""
    original = warnings.formatwarning

    def formatwarning(message, category, filename, lineno, line=None):
        if is_ours(filename):
            return plain(message, category, filename, lineno, line)
        return original(message, category, filename, lineno, line)
    warnings.formatwarning = formatwarning
    try:
        yield
    finally:
        if warnings.formatwarning is formatwarning:
            warnings.formatwarning = original
