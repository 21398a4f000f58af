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
