"""Errors raised by the pipeline (on :mod:`core.errors`). Command-line ``main()`` turns them into exit codes."""
from core.errors import ProjectError, SettingError


class PipelineError(ProjectError):
    """Base class of every pipeline error."""


class ConfigError(PipelineError, SettingError):
    """A configuration value is invalid; the message names the field and its allowed range."""


class RenderError(PipelineError, RuntimeError):
    """Rendering a frame failed."""


class ClusterError(PipelineError, ConnectionError):
    """The Dask cluster cannot be started or reached."""
