"""Denoisers. ``build(name, **cfg)`` / ``names()``; one file per model on :mod:`.common`."""
from .registry import build, get, names, register

__all__ = ["build", "get", "names", "register"]
