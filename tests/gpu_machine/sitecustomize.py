"""On this interpreter's path (tests/test_device_check.py), a process sees only the distributions the GPU
check machine has or receives: a module of any other installed distribution (pymeshlab, bokeh, ...) is
not found, as there. ``$DENOISE_TEST_ALLOWED_DISTS`` lists the allowed distributions (comma-separated,
normalised names); modules of no distribution (the standard library, the checkout) are always found.
Every Python process started with this folder on ``PYTHONPATH`` inherits it: the check, its children
and the Dask workers of the dataset run."""
import importlib.abc
import importlib.machinery
import importlib.metadata
import os
import re
import sys

_ALLOWED = {d for d in os.environ.get("DENOISE_TEST_ALLOWED_DISTS", "").split(",") if d}


def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


class _Absent(importlib.abc.Loader):
    """Importing the module fails as a missing module does (``except ImportError`` takes it)."""

    def create_module(self, spec):
        raise ModuleNotFoundError(f"No module named {spec.name!r} (not on the GPU check machine)", name=spec.name)

    def exec_module(self, module):  # pragma: no cover - create_module raised
        pass


class _OnlyTheMachines(importlib.abc.MetaPathFinder):
    def __init__(self):
        self.owners = importlib.metadata.packages_distributions()

    def find_spec(self, name, path=None, target=None):
        owners = self.owners.get(name.partition(".")[0])
        if owners and not any(_norm(d) in _ALLOWED for d in owners):
            return importlib.machinery.ModuleSpec(name, _Absent())
        return None


if _ALLOWED:
    sys.meta_path.insert(0, _OnlyTheMachines())
