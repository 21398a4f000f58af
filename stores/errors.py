"""Errors raised by the stores package. Only command-line ``main()`` turns them into exit codes.

Every specific error also inherits the matching built-in exception (as zarr's
``NodeNotFoundError(BaseZarrError, FileNotFoundError)``), so callers may catch either.
"""


class StoreError(Exception):
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
