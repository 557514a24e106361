"""Sphinx extension: ``servobench-help COMMAND`` inserts that command's ``--help``, from the parser itself.

The CLI reference cannot drift from the code: every build formats the help of
``servobench.bench.cli.build_parser`` (at a fixed width of 88 columns).
"""

from __future__ import annotations

import os
from typing import Any

from docutils import nodes
from sphinx.application import Sphinx
from sphinx.util.docutils import SphinxDirective

WIDTH = "88"


def help_text(command: str) -> str:
    """``servobench COMMAND --help`` as the terminal shows it, ``servobench --help`` for ""."""
    from servobench.bench.cli import COMMANDS, build_parser

    before = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = WIDTH
    try:
        parser = build_parser(command or "")
        if not command:
            return parser.format_help()
        if command not in COMMANDS:
            raise KeyError(command)
        sub = next(a for a in parser._subparsers._group_actions if hasattr(a, "choices"))  # noqa: SLF001
        return sub.choices[command].format_help()
    finally:
        if before is None:
            os.environ.pop("COLUMNS", None)
        else:
            os.environ["COLUMNS"] = before


class ServobenchHelp(SphinxDirective):
    """``servobench-help [COMMAND]``: the command's help as a literal block."""

    optional_arguments = 1

    def run(self) -> list[nodes.Node]:
        command = self.arguments[0] if self.arguments else ""
        try:
            text = help_text(command)
        except KeyError:
            raise self.error(f"servobench has no command {command!r}") from None
        block = nodes.literal_block(text, text, language="text")
        self.set_source_info(block)
        return [block]


def setup(app: Sphinx) -> dict[str, Any]:
    app.add_directive("servobench-help", ServobenchHelp)
    return {"version": "1", "parallel_read_safe": True, "parallel_write_safe": True}
