"""Errors a user can cause, each ending the CLI with one clear message.

Anything else that escapes a stage is a bug and keeps its traceback.
"""


class PipelineError(Exception):
    """A problem the user can fix (bad photos, failed registration, ...): exit code 1."""

    exit_code = 1


class ConfigError(PipelineError):
    """Bad usage or configuration, detected before anything runs: exit code 2."""

    exit_code = 2
