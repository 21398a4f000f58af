"""Zarr v3 stores of per-sample denoiser training data (schema: ``stores/SCHEMA.md``).

Modules: ``contract`` (renderer -> store arrays), ``schema`` (versioned array table, create/open),
``writer`` (resumable lock-free frame writes), ``reader`` (frames, crops, splits, clips), ``codecs``,
``validate`` and ``export`` (CLI sub-commands), ``bench``, ``errors``. The PyTorch datasets over a store
are ``training.datasets``. Nothing is imported here, so numpy-only users never pay for zarr.
"""
