"""Errors raised by scene generation."""


class SceneGenError(Exception):
    """Base class of every scene_gen error."""


class SpecError(SceneGenError, ValueError):
    """A SceneSpec (or one of its parts) is invalid; the message names the field."""


class MeshError(SceneGenError, RuntimeError):
    """A mesh could not be built or loaded (the message names the file or mesh kind)."""


class ConfigError(SpecError):
    """A SceneGenConfig field is invalid; the message names the field and its allowed range."""


class VariantError(SceneGenError, RuntimeError):
    """The Mitsuba variant cannot start (missing or broken libLLVM, no CUDA, ...); ``scene_gen.variant``."""
