"""A rich progress bar on stderr for streaming runs."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager


@contextmanager
def stream_progress(enabled: bool = True) -> Iterator[Callable[[int, int, int], None]]:
    """Yield ``update(round, done, total)``; one bar per round, drawn on stderr."""
    if not enabled:
        yield lambda _i, _d, _t: None
        return
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    console = Console(stderr=True)
    tasks: dict[int, int] = {}
    bar = Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=console,
        transient=False,
    )

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
    description: str, total: int, enabled: bool = True
) -> Iterator[Callable[[int, int], None]]:
    """Yield ``update(done, total)`` for one bar of ``total`` items, drawn on stderr."""
    if not enabled:
        yield lambda _d, _t: None
        return
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    bar = Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=Console(stderr=True),
        transient=False,
    )
    task = bar.add_task(description, total=total)
    bar.start()
    try:
        yield lambda done, all_: bar.update(task, completed=done, total=all_)
    finally:
        bar.stop()
