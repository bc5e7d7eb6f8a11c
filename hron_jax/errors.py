"""The project's error types: what a user did wrong, reported as one line without a traceback.

UsageError       bad user input (CLI option, config, scene, run directory): exit code 2
ConfigError      a UsageError about one config field; `.field` is its dotted path in the run
                 config ('ppo.lr', 'env.max_steps'), so the CLI can name the option it came from
CheckpointError  a checkpoint that cannot be restored (damaged, or from another config): exit 1
NonFiniteError   training produced NaN / Inf (loss or parameters): exit 1, the last finite
                 checkpoint is kept
"""

from __future__ import annotations


class UsageError(Exception):
    """Bad user input: reported as one line, exit code 2."""


class ConfigError(UsageError, ValueError):
    """A config field with a value outside its valid range (or of the wrong type)."""

    def __init__(self, field: str, message: str):
        self.field = field
        self.message = message
        super().__init__(f'{field}: {message}')

    def under(self, prefix: str) -> ConfigError:
        """The same error with the field's path prefixed (a sub-config inside the run config)."""
        return ConfigError(f'{prefix}.{self.field}', self.message)


class CheckpointError(Exception):
    """A checkpoint that cannot be restored: reported as one line naming the path, exit code 1."""


class NonFiniteError(Exception):
    """NaN or Inf in the loss or the parameters: the run stops, its last finite checkpoint kept."""
