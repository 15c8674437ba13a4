"""JSON that stays JSON: Python's json writes NaN and Infinity, which no JSON parser
but Python's reads. Non-finite numbers are written as null."""

from __future__ import annotations

import json
import math
from typing import Any


def finite(value: Any) -> Any:
    """``value`` with every non-finite float (nested in dicts, lists and tuples) as None."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {key: finite(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite(item) for item in value]
    return value


def dumps(value: Any, **options: Any) -> str:
    """json.dumps with non-finite numbers as null (``allow_nan`` off: nothing else slips through)."""
    return json.dumps(finite(value), allow_nan=False, **options)


__all__ = ["dumps", "finite"]
