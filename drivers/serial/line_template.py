"""Typed line templates: ``"c {axis} {u}"`` formats requests and parses replies.

A template is text with ``{field}`` placeholders, e.g. ``"c {axis} {u}"``.
Field names are fixed and typed (see :data:`FIELD_KINDS`): ``axis``,
``state`` and ``code`` are integers (decimal or ``0x`` hex when parsed),
``u``, ``x``, ``v``, ``timeout_s``, ``period_s`` and ``value`` are finite
floats, ``text`` is any text. A run of spaces in a template matches any run
of whitespace when parsing. Pure: no I/O.
"""

from __future__ import annotations

import math
import re
import string
from dataclasses import dataclass

from servobench.errors import DriveConfigError, UsageError

#: Placeholder name -> type of its value.
FIELD_KINDS: dict[str, type] = {
    "axis": int,
    "state": int,
    "code": int,
    "u": float,
    "x": float,
    "v": float,
    "timeout_s": float,
    "period_s": float,
    "value": float,
    "text": str,
}

_FIELD_REGEX = {
    int: r"[+-]?(?:0[xX][0-9a-fA-F]+|\d+)",
    float: r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?",
    str: r".*?",
}


@dataclass(frozen=True)
class Template:
    """A line with typed ``{field}`` placeholders; formats and parses (see module doc)."""

    where: str
    text: str
    fields: tuple[str, ...]
    regex: re.Pattern[str]

    @classmethod
    def compile(cls, where: str, text: object, allowed: frozenset[str]) -> Template:
        """Check ``text`` (a template from ``where``) and build its parser."""
        if not isinstance(text, str) or not text.strip():
            raise DriveConfigError(f"{where}: must be a non-empty string, got {text!r}")
        pattern, fields = [], []
        try:
            parts = list(string.Formatter().parse(text))
        except ValueError as err:
            raise DriveConfigError(f"{where}: malformed template {text!r}: {err}") from None
        for literal, name, spec, conversion in parts:
            pattern.append(r"\s+".join(re.escape(w) for w in literal.split(" ")))
            if name is None:
                continue
            if name not in allowed:
                known = ", ".join(sorted(allowed)) or "none"
                raise DriveConfigError(f"{where}: unknown field {{{name}}} (allowed: {known})")
            if spec or conversion or name in fields:
                raise DriveConfigError(f"{where}: field {{{name}}} must appear once, bare")
            fields.append(name)
            pattern.append(f"(?P<{name}>{_FIELD_REGEX[FIELD_KINDS[name]]})")
        regex = re.compile(r"\s*" + "".join(pattern) + r"\s*", re.DOTALL)
        return cls(where, text, tuple(fields), regex)

    def format(self, float_format: str, **values: int | float | str) -> str:
        """The template with its fields filled in; floats as ``format(x, float_format)``."""
        missing = [f for f in self.fields if f not in values]
        if missing:
            raise UsageError(f"{self.where}: no value for {', '.join(missing)}")
        out = {}
        for name in self.fields:
            value = values[name]
            kind = FIELD_KINDS[name]
            if kind is float:
                if not math.isfinite(float(value)):
                    raise UsageError(f"{self.where}: {name}={value!r} is not finite")
                out[name] = format(float(value), float_format)
            elif kind is int:
                out[name] = str(int(value))
            else:
                out[name] = str(value)
        return self.text.format(**out)

    def parse(self, line: str) -> dict[str, int | float | str] | None:
        """Typed fields when ``line`` matches the whole template, else ``None``."""
        m = self.regex.fullmatch(line)
        if m is None:
            return None
        out: dict[str, int | float | str] = {}
        for name, text in m.groupdict().items():
            kind = FIELD_KINDS[name]
            if kind is int:
                digits = text.lstrip("+-")
                value = int(digits, 16 if digits[:2].lower() == "0x" else 10)
                out[name] = -value if text.startswith("-") else value
            elif kind is float:
                value = float(text)
                if not math.isfinite(value):  # "1e999": the fields are finite by contract
                    return None
                out[name] = value
            else:
                out[name] = text
        return out
