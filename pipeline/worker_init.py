"""What every Dask worker process needs before its first task. ``pipeline.cluster.connect`` installs it
on every worker through the ``pipeline.cluster.WorkerInit`` plugin (importing this module from the
plugin's setup, in the worker's main thread), so workers need no flag; ``dask worker --preload
pipeline.worker_init`` does the same and still works (LocalClusters use both).

Importing it, in the worker process's main thread:
- imports pymeshlab there: pymeshlab (Qt plugins) imported first from a non-main thread corrupts the
  heap (glibc's ``malloc_consolidate(): unaligned fastbin chunk detected``), and Dask runs tasks in
  executor threads;
- points drjit at a libLLVM >= 16 and keeps BLAS/OpenMP pools at one thread per worker thread.
"""
from __future__ import annotations

import os


def prepare_environment() -> None:
    """drjit's libLLVM and single-threaded BLAS/OpenMP pools (inherited by worker processes)."""
    from scene_gen.variant import VariantError, find_libllvm
    try:
        lib = find_libllvm()
    except VariantError:
        lib = None
    if lib:
        os.environ.setdefault("DRJIT_LIBLLVM_PATH", lib)
    for k in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ.setdefault(k, "1")


prepare_environment()
import pymeshlab  # noqa: E402,F401  (first import in this, the main, thread; see scene_gen.meshes._pymeshlab)


def dask_setup(worker) -> None:  # noqa: D401 - Dask's preload hook
    """Nothing more to do per worker: importing this module did the work."""
