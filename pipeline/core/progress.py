"""Progress bars for long steps, silenced by ``--quiet`` and when not on a terminal."""

from __future__ import annotations

import contextlib
from typing import Callable, Iterable, Iterator, TypeVar

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

T = TypeVar("T")

console = Console(stderr=True)
_enabled = True


def set_enabled(enabled: bool) -> None:
    global _enabled
    _enabled = enabled


def is_enabled() -> bool:
    """False under ``--quiet``: only warnings and errors are shown."""
    return _enabled


def _bar(*extra) -> Progress:
    """A transient bar: description, bar, steps done of all, time left, ``extra`` columns."""
    columns = (TextColumn("  {task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(), *extra)
    return Progress(*columns, console=console, transient=True)


def track(items: Iterable[T], description: str, total: int | None = None) -> Iterator[T]:
    """Iterate ``items`` with a progress bar on stderr."""
    if not _enabled or not console.is_terminal:
        yield from items
        return
    with _bar() as progress:
        yield from progress.track(items, total=total, description=description)


@contextlib.contextmanager
def steps(total: int, description: str) -> Iterator[Callable[[str], None]]:
    """A progress bar for ``total`` steps on stderr; yields ``advance(status)``, which
    moves it one step and shows ``status`` (a loss, an error) beside it."""
    if not _enabled or not console.is_terminal:
        yield lambda status: None
        return
    with _bar(TextColumn("{task.fields[status]}")) as progress:
        task = progress.add_task(description, total=total, status="")
        yield lambda status: progress.update(task, advance=1, status=status)
