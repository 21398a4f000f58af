"""Errors raised by the pipeline. Command-line ``main()`` turns them into exit codes."""
from scene_gen.errors import VariantError  # noqa: F401  (raised by the variant leaf, scene_gen.variant)


class PipelineError(Exception):
    """Base class of every pipeline error."""


class ConfigError(PipelineError, ValueError):
    """A configuration value is invalid; the message names the field and its allowed range."""


class RenderError(PipelineError, RuntimeError):
    """Rendering a frame failed."""
