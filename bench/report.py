"""Writing benchmark results into docs/benchmarks.md, one marked section per benchmark."""

from __future__ import annotations

from pathlib import Path

BENCHMARKS = Path(__file__).resolve().parents[1] / "docs" / "benchmarks.md"


def write_section(name: str, lines: list[str]) -> str:
    """Replace the section between ``<!-- NAME:begin -->`` and ``<!-- NAME:end -->``
    (new sections go before "## Test suite"); returns the section's text."""
    begin, end = f"<!-- {name}:begin -->", f"<!-- {name}:end -->"
    section = "\n".join([begin, *lines, end])
    text = BENCHMARKS.read_text()
    if begin in text:
        text = text[: text.index(begin)] + section + text[text.index(end) + len(end) :]
    else:
        text = text.replace("\n## Test suite", f"\n{section}\n\n## Test suite")
    BENCHMARKS.write_text(text)
    return section
