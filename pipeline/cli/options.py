"""Command-line options generated from dataclasses, as nerfstudio does with tyro:
each command's options are one frozen dataclass whose fields carry a docstring,
so defaults, types, allowed ranges and ``--help`` live in one place.

A field becomes ``--field-name``; ``Annotated[..., Arg(...)]`` makes it
positional, renames it, adds a short alias or lets it repeat. Types map as
argparse expects: ``bool`` a switch (``--x/--no-x`` when it defaults to true),
``Literal`` a choice, ``tuple[X, ...]`` one or more values (or, with
``repeat``, the option given several times), a fixed ``tuple[X, Y]`` that many
values, ``X | None`` an optional value. A field whose type is itself such a
dataclass adds that dataclass's options in place (``pipeline fit`` takes the
fitting loop's settings this way). Values given are validated like config
values (pipeline.core.config: type, ``Range``, ``Literal``).
"""

from __future__ import annotations

import argparse
import dataclasses
import types
import typing
from dataclasses import dataclass
from typing import Annotated, Any, Literal

from pipeline.core.config import build_section, describe_type, field_docs


@dataclass(frozen=True)
class Arg:
    """How a field becomes an argument where its name and type do not say it all."""

    positional: bool = False
    """A positional argument (optional when the field has a default)."""
    flag: str | None = None
    """The option's name instead of ``--field-name`` (``--from`` for a field ``start``)."""
    short: str | None = None
    """A short alias such as ``-s``."""
    repeat: bool = False
    """The option may be given several times, each adding one value."""
    metavar: str | None = None
    """How the value is shown in ``--help``."""


def _split(hint: Any) -> tuple[Any, Arg]:
    """The field's type without its ``Arg`` (ranges kept), and its ``Arg``."""
    if typing.get_origin(hint) is Annotated:
        base, *extra = typing.get_args(hint)
        arg = next((e for e in extra if isinstance(e, Arg)), Arg())
        rest = [e for e in extra if not isinstance(e, Arg)]
        return (Annotated[(base, *rest)] if rest else base), arg
    return hint, Arg()


def _bare(hint: Any) -> Any:
    """The type without ``Annotated`` and without ``| None``."""
    if typing.get_origin(hint) is Annotated:
        hint = typing.get_args(hint)[0]
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        hint = next(a for a in typing.get_args(hint) if a is not type(None))
    return hint


def _default(field: dataclasses.Field) -> Any:
    if field.default is not dataclasses.MISSING:
        return field.default
    if field.default_factory is not dataclasses.MISSING:
        return field.default_factory()
    return dataclasses.MISSING


def _is_options(hint: Any) -> bool:
    return isinstance(_bare(hint), type) and dataclasses.is_dataclass(_bare(hint))


def add_options(parser: argparse.ArgumentParser, cls: type) -> None:
    """One argument per field of ``cls``, documented by the field's docstring."""
    hints = typing.get_type_hints(cls, include_extras=True)
    docs = field_docs(cls)
    for field in dataclasses.fields(cls):
        hint, arg = _split(hints[field.name])
        if _is_options(hint):
            add_options(parser, _bare(hint))
            continue
        default = _default(field)
        bare = _bare(hint)
        shown = "" if default is dataclasses.MISSING or default is None else f"; default {default!r}"
        kwargs: dict[str, Any] = {"help": f"{docs.get(field.name, '')} ({describe_type(hint)}{shown})"}
        origin = typing.get_origin(bare)
        if origin is Literal:
            kwargs["choices"] = typing.get_args(bare)
        elif origin is tuple:
            items = typing.get_args(bare)
            kwargs["type"] = _bare(items[0])
            if arg.repeat:
                kwargs["action"] = "append"
            else:
                kwargs["nargs"] = "+" if items[-1] is Ellipsis else len(items)
        elif bare is bool:
            kwargs["action"] = argparse.BooleanOptionalAction if default is True else "store_true"
        else:
            kwargs["type"] = bare
        if arg.metavar:
            kwargs["metavar"] = arg.metavar
        if arg.positional:
            if default is not dataclasses.MISSING:
                kwargs["nargs"] = "?"
            parser.add_argument(field.name, **kwargs)
            continue
        names = [arg.flag or "--" + field.name.replace("_", "-")] + ([arg.short] if arg.short else [])
        required = default is dataclasses.MISSING
        if not required and kwargs.get("action") != "store_true":
            kwargs["default"] = None  # not given: the dataclass's default applies
        parser.add_argument(*names, dest=field.name, required=required, **kwargs)


def parse_options(cls: type, args: argparse.Namespace, name: str) -> Any:
    """Build ``cls`` from parsed arguments, validated like config values; ``name``
    prefixes the keys in error messages."""
    hints = typing.get_type_hints(cls, include_extras=True)
    given: dict[str, Any] = {}
    for field in dataclasses.fields(cls):
        hint = hints[field.name]
        if _is_options(hint):
            given[field.name] = parse_options(_bare(hint), args, name)
            continue
        value = getattr(args, field.name, None)
        if value is not None:
            given[field.name] = value
    return build_section(name, cls, given)
