"""One-line error messages, whatever text they quote.

Error messages quote untrusted text (file paths, TOML keys, URL values); the
CLI prints each error as one line, so line breaks in quoted text must not
survive into a message. :func:`one_line` flattens text;
:func:`one_line_errors` flattens the message of any
:class:`~drivers.errors.ServobenchError` a function raises.
"""

from __future__ import annotations

import functools
import re
from collections.abc import Callable
from typing import TypeVar

from drivers.errors import ServobenchError

#: Every character ``str.splitlines`` breaks at.
LINE_BREAKS = re.compile("[\n\r\x0b\x0c\x1c\x1d\x1e\x85\u2028\u2029]+")

F = TypeVar("F", bound=Callable[..., object])


def one_line(text: str) -> str:
    """``text`` with each run of line breaks replaced by one space."""
    return LINE_BREAKS.sub(" ", text)


def one_line_errors(fn: F) -> F:
    """Decorator: a :class:`ServobenchError` leaving ``fn`` has a one-line message."""

    @functools.wraps(fn)
    def wrapper(*args: object, **kwargs: object) -> object:
        try:
            return fn(*args, **kwargs)
        except ServobenchError as err:
            if err.args and isinstance(err.args[0], str) and LINE_BREAKS.search(err.args[0]):
                err.args = (one_line(err.args[0]), *err.args[1:])
            raise

    return wrapper  # type: ignore[return-value]
