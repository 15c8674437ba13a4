"""Command-line options generated from a dataclass: one place for defaults, types,
ranges and help."""

import argparse
from dataclasses import dataclass, field
from typing import Annotated, Literal

import pytest

from pipeline.cli.options import Arg, add_options, parse_options
from pipeline.core.config import Range
from pipeline.core.errors import ConfigError


@dataclass(frozen=True)
class Inner:
    """Nested settings, added in place."""

    steps: Annotated[int, Range(1, None)] = 10
    """How many steps."""


@dataclass(frozen=True)
class Options:
    """A command."""

    path: Annotated[str, Arg(positional=True)]
    """Where to work."""
    extra: Annotated[str | None, Arg(positional=True)] = None
    """An optional second folder."""
    mode: Literal["fast", "slow"] = "fast"
    """How to run."""
    rate: Annotated[float | None, Range(0.0, None, exclusive_lo=True)] = None
    """A positive rate, or none."""
    names: Annotated[tuple[str, ...], Arg(repeat=True, short="-n")] = ()
    """Given several times."""
    sizes: tuple[int, ...] = (1, 2)
    """Several values at once."""
    verbose: bool = False
    """A switch."""
    inner: Inner = field(default_factory=Inner)
    """Nested."""


def _parse(argv: list[str]) -> Options:
    parser = argparse.ArgumentParser()
    add_options(parser, Options)
    return parse_options(Options, parser.parse_args(argv), "test")


def test_defaults_come_from_the_dataclass():
    assert _parse(["here"]) == Options(path="here")


def test_every_kind_of_field_is_parsed():
    options = _parse(
        [
            "here",
            "there",
            "--mode",
            "slow",
            "--rate",
            "0.5",
            "-n",
            "a",
            "--names",
            "b",
            "--sizes",
            "3",
            "4",
            "5",
            "--verbose",
            "--steps",
            "7",
        ]
    )
    assert options == Options("here", "there", "slow", 0.5, ("a", "b"), (3, 4, 5), True, Inner(7))


@pytest.mark.parametrize("argv, key", [(["x", "--rate", "0"], "test.rate"), (["x", "--steps", "0"], "test.steps")])
def test_values_out_of_range_are_refused_with_the_key(argv, key):
    with pytest.raises(ConfigError, match=key):
        _parse(argv)


def test_a_choice_outside_the_literal_is_a_usage_error():
    with pytest.raises(SystemExit):
        _parse(["x", "--mode", "medium"])


def test_help_is_the_field_docstring_with_type_and_default():
    parser = argparse.ArgumentParser()
    add_options(parser, Options)
    text = parser.format_help()
    assert "A positive rate, or none." in text and "How many steps. (int in [1, inf]; default 10)" in text


@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_a_non_finite_number_is_refused(value):
    with pytest.raises(ConfigError, match="not a finite number"):
        _parse(["x", f"--rate={value}"])
