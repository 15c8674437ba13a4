"""Typed JSON records: a dataclass read from and written to one JSON file.

A record's fields are what a later stage reads; ``details`` holds the rest of the
file (how the stage got there: for people, the report and benchmarks), written
beside the fields at the top level so that the file reads as one object. A reader
finds every field or says which key of which file is missing.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any, ClassVar, Self

from pipeline.core import jsonio
from pipeline.core.errors import PipelineError, require_finite


@dataclasses.dataclass(kw_only=True)
class JsonRecord:
    """Shared base of the records. A subclass names the fields that hold small frozen
    dataclasses in ``PARTS`` and the fields that map names to them in ``PART_MAPS``
    (None allowed for either)."""

    PARTS: ClassVar[dict[str, type]] = {}
    PART_MAPS: ClassVar[dict[str, type]] = {}

    details: dict[str, Any] = dataclasses.field(default_factory=dict)
    """The file's other keys, kept as they are."""

    @classmethod
    def typed_fields(cls) -> list[str]:
        return [f.name for f in dataclasses.fields(cls) if f.name != "details"]

    @classmethod
    def from_json(cls, data: dict, source: str = "the record") -> Self:
        names = cls.typed_fields()
        missing = [f.name for f in dataclasses.fields(cls) if f.name in names and f.name not in data and _required(f)]
        if missing:
            raise PipelineError(
                f"{source} has no {', '.join(missing)}: another version of the pipeline wrote it; "
                "run the stage that writes it again (pipeline run CAPTURE --force STAGE)"
            )
        values = {name: _part_from_json(cls, name, data[name]) for name in names if name in data}
        return cls(**values, details={k: v for k, v in data.items() if k not in names})

    def to_json(self) -> dict:
        data = dict(self.details)
        for name in self.typed_fields():
            data[name] = _to_json(getattr(self, name))
        return data

    @classmethod
    def read(cls, path: Path) -> Self:
        return cls.from_json(json.loads(Path(path).read_text()), str(path))

    def write(self, path: Path) -> Path:
        """The record as indented JSON; a NaN or infinity is refused (errors.require_finite)."""
        data = self.to_json()
        require_finite(data, str(path))
        Path(path).write_text(jsonio.dumps(data, indent=1))
        return path


def _required(field: dataclasses.Field) -> bool:
    return field.default is dataclasses.MISSING and field.default_factory is dataclasses.MISSING


def _part_from_json(cls: type[JsonRecord], name: str, value: Any) -> Any:
    if value is None:
        return None
    if name in cls.PARTS:
        return cls.PARTS[name](**value)
    if name in cls.PART_MAPS:
        return {key: cls.PART_MAPS[name](**entry) for key, entry in value.items()}
    return value


def _to_json(value: Any) -> Any:
    """JSON of a part: an optional field left at None is not written (readers take the default)."""
    if dataclasses.is_dataclass(value):
        return {
            f.name: _to_json(getattr(value, f.name))
            for f in dataclasses.fields(value)
            if not (getattr(value, f.name) is None and f.default is None)
        }
    if isinstance(value, dict):
        return {k: _to_json(v) for k, v in value.items()}
    if isinstance(value, tuple):
        return [_to_json(v) for v in value]
    return value


__all__ = ["JsonRecord"]
