"""Errors a user can cause, each ending the CLI with one clear message.

Anything else that escapes a stage is a bug and keeps its traceback.
"""

import shutil
from pathlib import Path

import numpy as np


class PipelineError(Exception):
    """A problem the user can fix (bad photos, failed registration, ...): exit code 1."""

    exit_code = 1


class ConfigError(PipelineError):
    """Bad usage or configuration, detected before anything runs: exit code 2."""

    exit_code = 2


class DiskFull(PipelineError):
    """The file system ran out of space (or quota) while the pipeline wrote ``what``."""

    def __init__(self, folder: Path, what: str, kept: str, needed_bytes: int | None = None):
        free = shutil.disk_usage(folder).free if folder.exists() else 0
        need = f"it needs at least {needed_bytes / 1e6:.1f} MB; " if needed_bytes else ""
        super().__init__(
            f"the disk holding {folder} is full ({free / 1e6:.0f} MB free) while {what}: {need}"
            f"{kept}; free some space and run again"
        )


class NonFiniteOutput(ValueError):
    """A NaN or infinity about to be written into a result file. The fits catch them
    at the source (non-finite gradients are dropped, parameters clamped), so this is
    a bug, raised instead of writing the value silently."""


def require_finite(values, where: str) -> None:
    """Raise NonFiniteOutput naming ``where`` when ``values`` (an array, or nested dicts
    and lists of numbers) holds a NaN or infinity."""
    if isinstance(values, dict):
        for key, value in values.items():
            require_finite(value, f"{where}: {key}")
    elif isinstance(values, (list, tuple)) and not all(isinstance(v, (int, float)) for v in values):
        for index, value in enumerate(values):
            require_finite(value, f"{where}[{index}]")
    elif isinstance(values, (int, float, list, tuple)) or hasattr(values, "dtype"):
        array = np.asarray(values, dtype=np.float64)
        if not np.all(np.isfinite(array)):
            raise NonFiniteOutput(f"{where} is not finite ({np.ravel(array)[:6].tolist()})")
