"""Progress of long steps: bars on a terminal, a line every 10 s elsewhere; silenced by ``--quiet``."""

from __future__ import annotations

import contextlib
import time
from typing import Callable, Iterable, Iterator, TypeVar

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from pipeline import logger

T = TypeVar("T")
LINE_EVERY_S = 10.0
"""Off a terminal, how often a long step says how far it is."""

console = Console(stderr=True, soft_wrap=True)
if not console.is_terminal:
    # A log file or a pipe has no width: rich's default of 80 columns would wrap lines
    # and cut a table's names short.
    console.width = 10_000
_enabled = True
_stage = ""
"""The stage running now, named in the lines off a terminal (a batch log interleaves)."""


def set_enabled(enabled: bool) -> None:
    global _enabled
    _enabled = enabled


@contextlib.contextmanager
def in_stage(name: str) -> Iterator[None]:
    """Name ``name`` in the progress lines of the work inside."""
    global _stage
    previous, _stage = _stage, name
    try:
        yield
    finally:
        _stage = previous


def is_enabled() -> bool:
    """False under ``--quiet``: only warnings and errors are shown."""
    return _enabled


def _bar(*extra) -> Progress:
    """A transient bar: description, bar, steps done of all, time left, ``extra`` columns."""
    columns = (TextColumn("  {task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(), *extra)
    return Progress(*columns, console=console, transient=True)


class _Lines:
    """Progress off a terminal (a log file, CI, a batch worker): a line every LINE_EVERY_S
    seconds, with the steps done, the time taken and the time left."""

    def __init__(self, description: str, total: int | None):
        self.description, self.total, self.done = description, total, 0
        self.started = self.last = time.monotonic()

    def advance(self, status: str = "") -> None:
        self.done += 1
        now = time.monotonic()
        if now - self.last < LINE_EVERY_S and self.done != self.total:
            return
        self.last = now
        elapsed = now - self.started
        of = f"/{self.total}" if self.total else ""
        left = f", about {elapsed / self.done * (self.total - self.done):.0f} s left" if self.total else ""
        where = f"{_stage}: " if _stage else ""
        logger.info(
            "%s%s: %d%s in %.0f s%s%s",
            where,
            self.description,
            self.done,
            of,
            elapsed,
            left,
            f" ({status})" if status else "",
        )


def track(items: Iterable[T], description: str, total: int | None = None) -> Iterator[T]:
    """Iterate ``items`` with a progress bar on stderr (off a terminal, a line now and then)."""
    if not _enabled:
        yield from items
        return
    if not console.is_terminal:
        lines = _Lines(description, total if total is not None else _length(items))
        for item in items:
            yield item
            lines.advance()
        return
    with _bar() as progress:
        yield from progress.track(items, total=total, description=description)


def _length(items: Iterable) -> int | None:
    return len(items) if hasattr(items, "__len__") else None  # type: ignore[arg-type]


@contextlib.contextmanager
def steps(total: int, description: str) -> Iterator[Callable[[str], None]]:
    """A progress bar for ``total`` steps on stderr; yields ``advance(status)``, which
    moves it one step and shows ``status`` (a loss, an error) beside it. Off a terminal,
    a line now and then."""
    if not _enabled:
        yield lambda status: None
        return
    if not console.is_terminal:
        yield _Lines(description, total).advance
        return
    with _bar(TextColumn("{task.fields[status]}")) as progress:
        task = progress.add_task(description, total=total, status="")
        yield lambda status: progress.update(task, advance=1, status=status)
