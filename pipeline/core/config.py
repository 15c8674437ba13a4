"""Typed, layered configuration.

Every config section is a dataclass whose fields carry a docstring (a string
literal right after the field, as in nerfstudio) and, where a number has limits,
an ``Annotated[..., Range(lo, hi)]`` bound. The layers are, lowest first:

1. the dataclass defaults,
2. ``configs/<preset>.toml`` (``standard`` unless ``--preset`` says otherwise),
3. ``CAPTURE/capture.toml``,
4. ``-s section.key=value`` overrides from the command line.

A string setting annotated ``InputFile()`` names a file (or folder) a stage reads. It is
relative to the capture folder and must lie inside it, unless it was given on
the command line: a capture.toml cannot make the pipeline read
``../../../../etc/passwd``. The file's content is part of the cache key of every
stage whose config holds the setting (pipeline.core.runner).

Everything is validated before any stage runs: unknown sections or keys, wrong
types and out-of-range values raise :class:`ConfigError` naming the key, the
value and what is allowed.
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import inspect
import json
import math
import textwrap
import tomllib
import types
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal, Mapping

from pipeline.core.errors import ConfigError
from pipeline.core.fsutil import special_kind

PRESETS_DIR = Path(__file__).resolve().parents[2] / "configs"
DEFAULT_PRESET = "standard"


@dataclass(frozen=True)
class Range:
    """Inclusive numeric bounds for a config field; ``None`` leaves a side open.

    ``exclusive_lo`` makes the lower bound strict (for quantities that must be
    positive, such as an extinction coefficient).
    """

    lo: float | None = None
    hi: float | None = None
    exclusive_lo: bool = False

    def check(self, value: float) -> bool:
        if self.lo is not None and (value <= self.lo if self.exclusive_lo else value < self.lo):
            return False
        return self.hi is None or value <= self.hi

    def describe(self) -> str:
        lo = "-inf" if self.lo is None else f"{self.lo:g}"
        hi = "inf" if self.hi is None else f"{self.hi:g}"
        return f"{'(' if self.exclusive_lo or self.lo is None else '['}{lo}, {hi}]"


@dataclass(frozen=True)
class InputFile:
    """Marks a string setting as the path of an input file or folder (empty: none),
    checked before anything runs: a file must end in one of ``suffixes`` (any, when
    empty); a folder is accepted only where ``folder_with`` names what it must hold
    (one of them)."""

    suffixes: tuple[str, ...] = ()
    folder_with: tuple[str, ...] = ()

    def problem(self, path: Path) -> str:
        """Why ``path`` (which exists) is not what the setting reads ('' when it is)."""
        if path.is_dir():
            if not self.folder_with:
                return f"is a folder: name a file{self._kinds()}"
            if not any((path / name).exists() for name in self.folder_with):
                return f"is a folder without {' or '.join(self.folder_with)}: name the folder that holds them"
            return ""
        if self.suffixes and path.suffix.lower() not in self.suffixes:
            return f"is not a file this setting reads: name a file{self._kinds()}"
        return ""

    def _kinds(self) -> str:
        return f" ({', '.join(self.suffixes)})" if self.suffixes else ""


def input_file_settings(section: Any) -> dict[str, str]:
    """The non-empty ``InputFile`` settings of a section instance: field -> value."""
    return {name: value for name in _input_file_markers(type(section)) if (value := getattr(section, name))}


def _input_file_markers(cls: type) -> dict[str, InputFile]:
    """The ``InputFile`` settings of a section class: field -> its marker."""
    hints = typing.get_type_hints(cls, include_extras=True)
    return {
        name: marker
        for name, hint in hints.items()
        if typing.get_origin(hint) is Annotated
        for marker in typing.get_args(hint)[1:]
        if isinstance(marker, InputFile)
    }


def input_file_path(capture_dir: Path, value: str) -> Path:
    """Where an ``InputFile`` setting points: absolute as given, else under the capture."""
    return Path(value) if Path(value).is_absolute() else capture_dir / value


def _check_input_files(name: str, section: Any, capture_dir: Path, origins: Mapping[str, str]) -> None:
    markers = _input_file_markers(type(section))
    for key, value in input_file_settings(section).items():
        path = input_file_path(capture_dir, value)
        origin = origins.get(key, "defaults")
        if not origin.startswith("-s ") and not path.resolve().is_relative_to(capture_dir.resolve()):
            raise ConfigError(
                f"{name}.{key} = {value!r} points outside the capture folder {capture_dir}: "
                f"copy the file into the capture folder, or give it on the command line (-s {name}.{key}=PATH)"
            )
        if not path.exists():
            raise ConfigError(
                f'{name}.{key} = {value!r} is not a file or folder (looked for {path}): fix the path or set it to ""'
            )
        special = special_kind(path)
        if special:
            raise ConfigError(f"{name}.{key} = {value!r} is {special}, not a file: name a regular file")
        problem = markers[key].problem(path)
        if problem:
            raise ConfigError(f"{name}.{key} = {value!r} {problem}")


def confine_input_files(
    schema: Mapping[str, type], capture_dir: Path, overrides: list[str] | tuple[str, ...], where: str
) -> None:
    """Refuse an override from ``where`` (not the command line: the studio's page) whose
    ``InputFile`` setting names a file outside the capture folder, as capture.toml's
    may not."""
    for text in overrides:
        section, key, value = parse_override(text)
        cls = schema.get(section)
        if cls is None or not isinstance(value, str) or not value:
            continue  # an unknown key or a wrong type is refused by load_config, with its message
        hint = typing.get_type_hints(cls, include_extras=True).get(key)
        marked = typing.get_origin(hint) is Annotated and any(isinstance(a, InputFile) for a in typing.get_args(hint))
        if marked and not input_file_path(capture_dir, value).resolve().is_relative_to(capture_dir.resolve()):
            raise ConfigError(
                f"{section}.{key} = {value!r} from {where} points outside the capture folder {capture_dir}: "
                "copy the file into the capture folder, or give it on the command line (-s)"
            )


@functools.cache
def field_docs(cls: type) -> dict[str, str]:
    """The docstring written under each field of a dataclass, by field name; fields a
    dataclass inherits carry their base's documentation."""
    docs: dict[str, str] = {}
    for base in reversed(cls.__mro__[1:]):
        if dataclasses.is_dataclass(base):
            docs |= field_docs(base)
    tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    body = tree.body[0].body  # type: ignore[attr-defined]
    for stmt, following in zip(body, body[1:]):
        if (
            isinstance(stmt, ast.AnnAssign)
            and isinstance(stmt.target, ast.Name)
            and isinstance(following, ast.Expr)
            and isinstance(following.value, ast.Constant)
            and isinstance(following.value.value, str)
        ):
            docs[stmt.target.id] = inspect.cleandoc(following.value.value)
    return docs


def describe_type(hint: Any) -> str:
    """A type for people: "int in [1, inf]", "one of 'l2', 'dual'", "list of float"."""
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        return " or ".join("none" if a is type(None) else describe_type(a) for a in typing.get_args(hint))
    if origin is Annotated:
        base, *extra = typing.get_args(hint)
        ranges = [e.describe() for e in extra if isinstance(e, Range)]
        return describe_type(base) + (f" in {ranges[0]}" if ranges else "")
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in typing.get_args(hint))
    if origin in (list, tuple):
        args = [a for a in typing.get_args(hint) if a is not Ellipsis]
        return f"list of {describe_type(args[0])}" if args else "list"
    return getattr(hint, "__name__", str(hint))


def _coerce(key: str, value: Any, hint: Any) -> Any:
    """Check ``value`` against the type ``hint``; return it in canonical form."""
    origin = typing.get_origin(hint)
    if origin is Annotated:
        base, *extra = typing.get_args(hint)
        value = _coerce(key, value, base)
        for bound in extra:
            if isinstance(bound, Range) and value is not None and not bound.check(value):
                raise ConfigError(f"{key} = {value!r} is out of range: allowed {bound.describe()}")
        return value
    if origin is Literal:
        allowed = typing.get_args(hint)
        if value not in allowed:
            raise ConfigError(f"{key} = {value!r} is not allowed: use one of " + ", ".join(repr(a) for a in allowed))
        return value
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{key} = {value!r} has the wrong type: expected {describe_type(hint)}")
        args = typing.get_args(hint)
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise ConfigError(f"{key} = {value!r} needs exactly {len(args)} items")
            return tuple(_coerce(f"{key}[{i}]", v, a) for i, (v, a) in enumerate(zip(value, args)))
        item = args[0] if args else Any
        items = [_coerce(f"{key}[{i}]", v, item) for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in typing.get_args(hint):
            return None
        return _coerce(key, value, next(a for a in typing.get_args(hint) if a is not type(None)))
    if isinstance(hint, type) and dataclasses.is_dataclass(hint) and isinstance(value, hint):
        return value
    if hint is Any:
        return value
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{key} = {value!r} has the wrong type: expected a number")
        if not math.isfinite(value):
            # NaN passes every comparison a range makes, and no setting means infinity.
            raise ConfigError(f"{key} = {value!r} is not a finite number: give a number")
        return float(value)
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{key} = {value!r} has the wrong type: expected an integer")
        return value
    if hint in (bool, str):
        if not isinstance(value, hint):
            raise ConfigError(
                f"{key} = {value!r} has the wrong type: expected {'true/false' if hint is bool else 'a string'}"
            )
        return value
    raise TypeError(f"config field {key} uses unsupported type {hint!r}")


def build_section(name: str, cls: type, values: Mapping[str, Any]) -> Any:
    """Instantiate dataclass ``cls`` from TOML ``values``, rejecting anything invalid."""
    hints = typing.get_type_hints(cls, include_extras=True)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - set(fields))
    if unknown:
        raise ConfigError(f"unknown key {name}.{unknown[0]}: section [{name}] has " + ", ".join(sorted(fields)))
    kwargs = {k: _coerce(f"{name}.{k}", v, hints[k]) for k, v in values.items()}
    instance = cls(**kwargs)
    # Defaults go through the same checks so a bad default cannot slip past.
    for f in dataclasses.fields(cls):
        if f.name not in kwargs:
            _coerce(f"{name}.{f.name}", getattr(instance, f.name), hints[f.name])
    validate = getattr(instance, "validate", None)
    if validate is not None:
        validate(name)
    return instance


def parse_override(text: str) -> tuple[str, str, Any]:
    """Split ``section.key=value``; the value is read as TOML, else as a bare string."""
    if "=" not in text or "." not in text.split("=", 1)[0]:
        raise ConfigError(f"override {text!r} must look like section.key=value")
    path, raw = text.split("=", 1)
    section, key = path.strip().split(".", 1)
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw  # lets users write `-s fit.loss=dual` without quotes
    return section, key, value


def _read_toml(path: Path) -> dict[str, Any]:
    try:
        with path.open("rb") as f:
            return tomllib.load(f)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: invalid TOML: {e}") from e
    except UnicodeDecodeError as e:
        raise ConfigError(
            f"{path}: invalid TOML: not UTF-8 text ({e.reason} at byte {e.start}); save it as UTF-8"
        ) from e


def preset_names(presets_dir: Path | None = None) -> list[str]:
    return sorted(p.stem for p in (presets_dir or PRESETS_DIR).glob("*.toml"))


@dataclass(frozen=True)
class Config:
    """The validated configuration: one dataclass instance per section."""

    sections: Mapping[str, Any]
    preset: str
    sources: tuple[str, ...]
    """Files and overrides that were layered, lowest first."""

    def __getitem__(self, name: str) -> Any:
        return self.sections[name]

    def as_dict(self) -> dict[str, dict[str, Any]]:
        return {name: section_dict(s) for name, s in self.sections.items()}


def section_dict(section: Any) -> dict[str, Any]:
    """A section as plain JSON/TOML-ready values (tuples become lists)."""
    return {
        f.name: (list(v) if isinstance(v := getattr(section, f.name), tuple) else v)
        for f in dataclasses.fields(section)
    }


def load_config(
    schema: Mapping[str, type],
    capture_dir: Path | None = None,
    preset: str = DEFAULT_PRESET,
    overrides: tuple[str, ...] | list[str] = (),
    presets_dir: Path | None = None,
) -> Config:
    """Layer preset, capture.toml and overrides over the defaults of ``schema``."""
    presets_dir = presets_dir or PRESETS_DIR
    preset_file = presets_dir / f"{preset}.toml"
    if not preset_file.is_file():
        raise ConfigError(f"unknown preset {preset!r}: choose one of " + ", ".join(preset_names(presets_dir)))
    layers: list[tuple[str, dict[str, Any]]] = [(str(preset_file), _read_toml(preset_file))]
    capture_file = capture_dir / "capture.toml" if capture_dir is not None else None
    if capture_file is not None and (capture_file.exists() or capture_file.is_symlink()):
        if not capture_file.is_file():
            kind = special_kind(capture_file) if capture_file.exists() else "a broken link"
            raise ConfigError(f"{capture_file} is {kind or 'a folder'}, not a file: make it a TOML file or remove it")
        layers.append((str(capture_file), _read_toml(capture_file)))
    override_layer: dict[str, dict[str, Any]] = {}
    for text in overrides:
        section, key, value = parse_override(text)
        override_layer.setdefault(section, {})[key] = value
    if override_layer:
        layers.append(("-s " + " -s ".join(overrides), override_layer))

    merged: dict[str, dict[str, Any]] = {name: {} for name in schema}
    origins: dict[str, dict[str, str]] = {name: {} for name in schema}
    for source, layer in layers:
        for section, values in layer.items():
            if section not in schema:
                raise ConfigError(
                    f"{source}: unknown section [{section}]: known sections are " + ", ".join(sorted(schema))
                )
            if not isinstance(values, dict):
                raise ConfigError(f"{source}: {section} must be a [section] table")
            merged[section].update(values)
            origins[section].update(dict.fromkeys(values, source))

    sections = {}
    for name, cls in schema.items():
        try:
            sections[name] = build_section(name, cls, merged[name])
            if capture_dir is not None:
                _check_input_files(name, sections[name], capture_dir, origins[name])
                check_capture = getattr(sections[name], "check_capture", None)
                if check_capture is not None:  # what the settings need of the capture folder
                    check_capture(name, capture_dir)
        except ConfigError as e:
            origin = [s for s, layer in layers if name in layer]
            raise ConfigError(f"{e} (set in {', '.join(origin) or 'defaults'})") from None
    return Config(sections=sections, preset=preset, sources=tuple(s for s, _ in layers))


def describe_schema(schema: Mapping[str, type], config: Config | None = None) -> str:
    """Human-readable listing of every section and key with type, value and doc."""
    lines: list[str] = []
    for name, cls in schema.items():
        hints = typing.get_type_hints(cls, include_extras=True)
        docs = field_docs(cls)
        lines.append(f"[{name}]  {inspect.cleandoc(cls.__doc__ or '').splitlines()[0]}")
        for f in dataclasses.fields(cls):
            value = getattr(config[name] if config else cls(), f.name)
            lines.append(f"  {f.name} = {value!r}    ({describe_type(hints[f.name])})")
            for doc_line in docs.get(f.name, "(undocumented)").splitlines():
                lines.append(f"      {doc_line}")
        lines.append("")
    return "\n".join(lines)


def toml_value(value: Any) -> str:
    return json.dumps(list(value) if isinstance(value, tuple) else value)


def toml_section(name: str, section: Any, documented: bool = True, commented: bool = False) -> list[str]:
    """Lines of a TOML table for a config section object, optionally with each field's
    documentation and type as comments, optionally commented out (a template)."""
    cls = type(section)
    hints = typing.get_type_hints(cls, include_extras=True)
    docs = field_docs(cls)
    prefix = "# " if commented else ""
    lines = []
    if documented:
        lines += [f"# {line}".rstrip() for line in inspect.cleandoc(cls.__doc__ or "").splitlines()]
    lines.append(f"{prefix}[{name}]")
    for f in dataclasses.fields(cls):
        if documented:
            lines += [f"# {line}" for line in docs.get(f.name, "").splitlines()]
            lines.append(f"# ({describe_type(hints[f.name])})")
        lines.append(f"{prefix}{f.name} = {toml_value(getattr(section, f.name))}")
    return lines


__all__ = [
    "Config",
    "ConfigError",
    "InputFile",
    "Range",
    "build_section",
    "describe_schema",
    "describe_type",
    "field_docs",
    "input_file_path",
    "input_file_settings",
    "load_config",
    "parse_override",
    "preset_names",
    "section_dict",
]
