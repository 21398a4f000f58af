"""Errors raised by scene generation (on :mod:`core.errors`)."""
from core.errors import ProjectError, SettingError


class SceneGenError(ProjectError):
    """Base class of every scene_gen error."""


class SpecError(SceneGenError, ValueError):
    """A SceneSpec (or one of its parts) is invalid; the message names the field."""


class MeshError(SceneGenError, RuntimeError):
    """A mesh could not be built or loaded (the message names the file or mesh kind)."""


class ConfigError(SpecError, SettingError):
    """A SceneGenConfig field is invalid; the message names the field and its allowed range."""


class SceneFileError(SceneGenError, ValueError):
    """A Mitsuba scene file cannot be a scene of the dataset (missing, unreadable, does not load, no sensor
    and no camera, a plugin the variant lacks, changed since its scene was described); one line naming it."""
