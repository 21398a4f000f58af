"""Errors raised by the pipeline. Command-line ``main()`` turns them into exit codes."""


class PipelineError(Exception):
    """Base class of every pipeline error."""


class VariantError(PipelineError, RuntimeError):
    """The Mitsuba variant cannot start (missing or broken libLLVM, no CUDA, ...)."""


class ConfigError(PipelineError, ValueError):
    """A configuration value is invalid; the message names the field and its allowed range."""


class RenderError(PipelineError, RuntimeError):
    """Rendering a frame failed."""
