"""Zarr v3 stores of per-sample denoiser training data (schema: ``stores/SCHEMA.md``).

Modules: ``contract`` (renderer -> store arrays), ``schema`` (the array table, create/open),
``writer`` (resumable lock-free frame writes), ``reader`` (frames, crops, splits, clips), ``codecs``,
``validate``, ``export`` and ``upgrade`` (CLI sub-commands; ``upgrade`` is the one module that knows
older schema versions), ``bench``, ``errors``. The PyTorch datasets over a store
are ``training.datasets``. Nothing is imported here, so numpy-only users never pay for zarr.
"""
