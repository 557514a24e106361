"""What the technician sees: step headings, notes, progress bars (rich).

Kept apart from the steps so they stay testable: a :class:`Console` records
every line it prints (``lines``), and :meth:`Console.progress` gives a
``(done, total)`` callback backed by a rich progress bar.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from typing import Any

ProgressCallback = Callable[[int, int], None]


class Console:
    """Messages and progress bars on a :class:`rich.console.Console`.

    Parameters
    ----------
    rich_console : rich.console.Console, optional
        Where to print; a new one on stdout by default.
    """

    def __init__(self, rich_console: Any = None) -> None:
        if rich_console is None:
            from rich.console import Console as RichConsole

            rich_console = RichConsole(highlight=False, soft_wrap=True)  # whole lines: the terminal wraps
        self.rich = rich_console
        self.lines: list[str] = []

    def step(self, number: int, title: str) -> None:
        """A numbered step heading."""
        self.lines.append(f"[{number}] {title}")
        self.rich.print(f"\n[bold]Step {number}: {title}[/bold]")

    def say(self, text: str) -> None:
        """A plain note."""
        self.lines.append(text)
        self.rich.print(f"  {text}", markup=False)

    def ok(self, text: str) -> None:
        self.lines.append(f"ok: {text}")
        self.rich.print(f"  [green]ok[/green] {_escape(text)}")

    def warn(self, text: str) -> None:
        self.lines.append(f"warning: {text}")
        self.rich.print(f"  [yellow]warning[/yellow] {_escape(text)}")

    def verdict(self, status: str, sentence: str) -> None:
        """The verdict, the last line: ``status`` is ``"pass"``, ``"remark"`` or ``"fail"``."""
        self.lines.append(sentence)
        colour = {"pass": "green", "remark": "yellow"}.get(status, "red")
        self.rich.print(f"\n[bold {colour}]{_escape(sentence)}[/bold {colour}]")

    @contextlib.contextmanager
    def progress(self, description: str) -> Iterator[ProgressCallback]:
        """A progress bar; yields ``callback(done, total)``."""
        from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

        self.lines.append(f"progress: {description}")
        with Progress(
            TextColumn("  {task.description}"),
            BarColumn(),
            TextColumn("{task.percentage:>3.0f}%"),
            TimeRemainingColumn(),
            console=self.rich,
            transient=False,
        ) as bar:
            task = bar.add_task(description, total=None)

            def update(done: int, total: int) -> None:
                bar.update(task, completed=done, total=max(total, 1))

            yield update


def _escape(text: str) -> str:
    from rich.markup import escape

    return escape(text)
