"""Errors raised by the training package (on :mod:`core.errors`). Only ``training.__main__.main`` turns them
into exit codes."""
from core.errors import ProjectError, SettingError


class TrainingError(ProjectError):
    """Base class of every training error."""


class ConfigError(TrainingError, SettingError):
    """A model or training setting is invalid; the message names the setting and its allowed range."""


class UnknownModelError(TrainingError, KeyError):
    """No model is registered under the requested name."""

    def __str__(self) -> str:           # KeyError's own quotes its message: "'unknown model ...'"
        return str(self.args[0]) if len(self.args) == 1 else super().__str__()


class CheckpointError(TrainingError, RuntimeError):
    """A checkpoint cannot be read or does not match (model, config or store)."""


class DataError(TrainingError, RuntimeError):
    """Training data is missing or has an unexpected layout (shapes, channels, splits)."""


class NonFiniteError(TrainingError, FloatingPointError):
    """A loss or gradient became NaN/Inf during training. Its own exit code (``exit_code``, 1): the run
    failed, no setting was wrong."""
    exit_code = 1


class TargetBelowFloorError(ConfigError):
    """A quality target lies beyond what the fitted scaling curve can reach with any number of frames (its
    floor, or for PSNR its ceiling); the message names the limit and its interval."""
