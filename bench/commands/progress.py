"""Rich progress bars on stderr: for streaming runs, and for counting done items."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any


def _bar() -> Any:
    """A ``rich.progress.Progress`` on stderr: description, bar, done/total, elapsed time."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=Console(stderr=True),
        transient=False,
    )


@contextmanager
def stream_progress(enabled: bool = True) -> Iterator[Callable[[int, int, int], None]]:
    """Yield ``update(round, done, total)``; one bar per round, drawn on stderr."""
    if not enabled:
        yield lambda _i, _d, _t: None
        return
    bar = _bar()
    tasks: dict[int, int] = {}

    def update(index: int, done: int, total: int) -> None:
        if not tasks:
            bar.start()  # drawn from the first sample on: an early failure prints only its error
        if index not in tasks:
            tasks[index] = bar.add_task(f"streaming round {index}", total=total)
        bar.update(tasks[index], completed=done)

    try:
        yield update
    finally:
        if tasks:
            bar.stop()


@contextmanager
def count_progress(
    description: str | Callable[[int], str], enabled: bool = True
) -> Iterator[Callable[[int, int], None]]:
    """Yield ``update(done, total)`` for one bar, drawn on stderr from the first update on
    (``description`` may be a function of the total)."""
    if not enabled:
        yield lambda _d, _t: None
        return
    bar = _bar()
    tasks: list[int] = []

    def update(done: int, total: int) -> None:
        if not tasks:
            text = description(total) if callable(description) else description
            tasks.append(bar.add_task(text, total=total))
            bar.start()
        bar.update(tasks[0], completed=done, total=total)

    try:
        yield update
    finally:
        if tasks:
            bar.stop()
