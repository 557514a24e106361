"""A linter for udev rule files, after udev(7).

A rule is one logical line (a trailing ``\\`` continues it, as udevd reads
it) of comma-separated tokens ``KEY[{attr}] OP "value"``. Match keys take
``==`` and ``!=``; assignment keys ``=``, ``+=``, ``-=`` and ``:=``; a few
(``ATTR``, ``ENV``, ``NAME``, ``SYMLINK``, ``TAG``) are both. Values are in
double quotes (``\\"`` escapes a quote; ``e"..."`` takes C escapes).
Operators udevd accepts only with a warning (``GROUP+=`` read as ``GROUP=``)
are warnings here; everything udevd rejects or ignores is an error, and so is
a missing comma, which newer udev versions warn about.
"""

from __future__ import annotations

import difflib
import re
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

MATCH = frozenset({"==", "!="})
#: operators longest first, so that "==" is not read as "="
OPERATORS = ("==", "!=", "+=", "-=", ":=", "=")
PLACEHOLDER = re.compile(r"@[A-Z_]+@")
KEY_RE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
IFNAMSIZ = 15  # longest network interface name [characters]
ACTIONS = frozenset({"add", "remove", "change", "move", "bind", "unbind", "online", "offline"})
REMOVED_KEYS = frozenset({"BUS", "SYSFS", "ID", "WAIT_FOR", "WAIT_FOR_SYSFS", "IGNORE_DEVICE"})
SUBSTITUTION = re.compile(r"\$(\$|[a-z]+(\{[^}]*\})?)|%(%|[knpbMmcNrSPsE](\{[^}]*\})?)|[$%].?")
_DOLLAR = "devnode tempnode attr sysctl env kernel number driver devpath id major minor result"
DOLLAR_NAMES = frozenset(f"{_DOLLAR} parent name links root sys".split())  # noqa: SIM905


@dataclass(frozen=True)
class KeySpec:
    """What udev accepts for one key.

    ``ops`` are accepted silently; ``lenient`` ones udev accepts with a
    warning and reads as another operator; ``attr`` is "none", "optional"
    or "required", ``attr_values`` limits the ``{attr}`` when given.
    """

    ops: frozenset[str]
    attr: str = "none"
    attr_values: frozenset[str] = frozenset()
    lenient: frozenset[str] = frozenset()


def _k(ops: str, attr: str = "none", values: str = "", lenient: str = "") -> KeySpec:
    return KeySpec(
        frozenset(ops.split()), attr, frozenset(values.split()), frozenset(lenient.split())
    )


_MATCH_ONLY = "ACTION DEVPATH KERNEL KERNELS SUBSYSTEM SUBSYSTEMS DRIVER DRIVERS TAGS RESULT"
KEYS: dict[str, KeySpec] = {k: _k("== !=") for k in _MATCH_ONLY.split()} | {
    "ATTRS": _k("== !=", "required"),
    "CONST": _k("== !=", "required", "arch virt"),
    "TEST": _k("== !=", "optional"),
    "PROGRAM": _k("== != ="),
    "IMPORT": _k("== != =", "required", "program builtin file db cmdline parent"),
    "ATTR": _k("== != =", "required", lenient="+= :="),
    "SYSCTL": _k("== != =", "required", lenient="+= :="),
    "ENV": _k("== != = +=", "required", lenient=":="),
    "TAG": _k("== != = += -=", lenient=":="),
    "NAME": _k("== != = :=", lenient="+="),
    "SYMLINK": _k("== != = += -= :="),
    "OWNER": _k("= :=", lenient="+="),
    "GROUP": _k("= :=", lenient="+="),
    "MODE": _k("= :=", lenient="+="),
    "SECLABEL": _k("= :=", "required", lenient="+="),
    "RUN": _k("= += :=", "optional", "program builtin"),
    "OPTIONS": _k("= += :="),
    "LABEL": _k("="),
    "GOTO": _k("="),
}
#: assignment values udev expands ($name, %k ...) before use
_FORMATTED = "NAME SYMLINK OWNER GROUP MODE ENV ATTR SYSCTL RUN IMPORT PROGRAM SECLABEL"
FORMATTED = frozenset(_FORMATTED.split())
OPTIONS_KNOWN = re.compile(
    r"(link_priority=-?\d+|string_escape=(none|replace)|static_node=\S+|"
    r"watch|nowatch|db_persist|log_level=\w+)$"
)


@dataclass(frozen=True)
class Token:
    """One ``KEY{attr} OP "value"`` of a rule; ``line`` is the physical line [1-based]."""

    key: str
    attr: str | None
    op: str
    value: str
    line: int


@dataclass(frozen=True)
class Rule:
    """One logical line of a rule file, as tokens."""

    line: int
    tokens: tuple[Token, ...]


@dataclass(frozen=True)
class Finding:
    """A lint message; ``level`` is "error" or "warning"."""

    path: str
    line: int
    level: str
    message: str

    def __str__(self) -> str:
        return f"{self.path}:{self.line}: {self.level}: {self.message}"


@dataclass(frozen=True)
class LintResult:
    """Rules parsed from one file and what the linter found in them."""

    path: str
    rules: tuple[Rule, ...]
    findings: tuple[Finding, ...]

    @property
    def errors(self) -> tuple[Finding, ...]:
        return tuple(f for f in self.findings if f.level == "error")

    @property
    def warnings(self) -> tuple[Finding, ...]:
        return tuple(f for f in self.findings if f.level == "warning")


# ----------------------------------------------------------------- parsing
@dataclass(frozen=True)
class LogicalLine:
    """A rule's text with its continuations joined.

    ``marks`` maps offsets in ``text`` to physical line numbers [1-based];
    ``notes`` are (line, level, message) about the joining itself.
    """

    text: str
    marks: tuple[tuple[int, int], ...]
    notes: tuple[tuple[int, str, str], ...] = ()

    @property
    def line(self) -> int:
        return self.marks[0][1]


def logical_lines(text: str) -> Iterable[LogicalLine]:
    """Join continued lines as udevd does: a trailing ``\\`` continues the
    rule, comment lines inside it are skipped, a blank line ends it."""
    parts: list[str] = []
    marks: list[tuple[int, int]] = []
    notes: list[tuple[int, str, str]] = []
    size = 0
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.lstrip(" \t")
        if line.startswith("#"):
            if parts:
                notes.append((number, "warning", "comment inside a continued rule (udev skips it)"))
            continue
        if line.rstrip() != line and line.rstrip().endswith("\\"):
            notes.append((number, "error", "blank after '\\': not a line continuation"))
        marks.append((size, number))
        if line.endswith("\\"):
            parts.append(line[:-1])
            size += len(line) - 1
            continue
        if line.strip() or parts:
            yield LogicalLine("".join(parts) + line, tuple(marks), tuple(notes))
        parts, marks, notes, size = [], [], [], 0
    if parts:
        notes.append((marks[-1][1], "error", "line continuation at the end of the file"))
        yield LogicalLine("".join(parts), tuple(marks), tuple(notes))


def _line_at(marks: list[tuple[int, int]], pos: int) -> int:
    return max((ln for off, ln in marks if off <= pos), default=marks[0][1])


def parse_rule(
    text: str, marks: list[tuple[int, int]]
) -> tuple[list[Token], list[tuple[int, str, str]]]:
    """Tokenize one logical line; return (tokens, [(line, level, message)])."""
    tokens: list[Token] = []
    problems: list[tuple[int, str, str]] = []

    def error(line: int, message: str) -> None:
        problems.append((line, "error", message))

    pos, n = 0, len(text)

    def skip_ws() -> None:
        nonlocal pos
        while pos < n and text[pos] in " \t":
            pos += 1

    while True:
        skip_ws()
        where = _line_at(marks, pos)
        key_m = KEY_RE.match(text, pos)
        if key_m is None:
            error(where, f"expected a key at {text[pos : pos + 20]!r}")
            break
        key, pos, attr = key_m.group(), key_m.end(), None
        if pos < n and text[pos] == "{":
            close = text.find("}", pos)
            if close < 0:
                error(where, f"unbalanced '{{' in {key}{text[pos : pos + 20]}")
                break
            attr, pos = text[pos + 1 : close], close + 1
        skip_ws()
        op = next((o for o in OPERATORS if text.startswith(o, pos)), None)
        if op is None:
            error(where, f"expected an operator (== != = += -= :=) after {key}")
            break
        pos += len(op)
        skip_ws()
        quote = (
            pos + 1 if text.startswith('"', pos) else pos + 2 if text.startswith('e"', pos) else -1
        )
        if quote < 0:
            what = "single-quoted" if text.startswith("'", pos) else "unquoted"
            error(where, f"value of {key} is {what}: values must be in double quotes")
            break
        escaped_c = quote == pos + 2
        end, chars = quote, []
        while end < n and text[end] != '"':
            if text[end] == "\\" and end + 1 < n and (text[end + 1] == '"' or escaped_c):
                end += 1
            chars.append(text[end])
            end += 1
        if end >= n:
            error(where, f"unterminated quoted value of {key}")
            break
        tokens.append(Token(key, attr, op, "".join(chars), where))
        pos = end + 1
        skip_ws()
        if pos >= n:
            break
        if text[pos] == ",":
            pos += 1
            skip_ws()
            if pos >= n:
                problems.append(
                    (_line_at(marks, pos - 1), "warning", "trailing ',' at the end of the rule")
                )
                break
            continue
        nxt = text[pos : pos + 20]
        if nxt.startswith("#"):
            error(where, "comments must be on a line of their own")
            break
        error(_line_at(marks, pos), f"missing ',' between {key} and {nxt.split('=')[0]!r}")
    return tokens, problems


# ----------------------------------------------------------------- checking
def _kind(spec: KeySpec) -> str:
    if spec.ops <= MATCH:
        return "a match key"
    return "an assignment key" if not spec.ops & MATCH else "a key"


def _check_key(t: Token, name: str) -> Iterable[tuple[str, str]]:
    """Key, {attribute} and operator of one token: (level, message) pairs."""
    spec = KEYS.get(t.key)
    if spec is None:
        if t.key in REMOVED_KEYS:
            yield "error", f"{t.key} is no longer supported by udev"
            return
        close = difflib.get_close_matches(t.key.upper(), KEYS, n=1)
        yield "error", f"unknown key {t.key}" + (f" (did you mean {close[0]}?)" if close else "")
        return
    if spec.attr == "none" and t.attr is not None:
        yield "error", f"{t.key} takes no {{attribute}}"
    elif spec.attr == "required" and not t.attr:
        yield "error", f"{t.key} needs an {{attribute}}, e.g. {t.key}{{name}}"
    elif spec.attr_values and t.attr and t.attr not in spec.attr_values:
        allowed = ", ".join(sorted(spec.attr_values))
        yield "error", f"{name}: the attribute must be one of {allowed}"
    if t.op in spec.lenient:
        yield "warning", f"udev reads {name}{t.op} as {name}=; write '='"
    elif t.op not in spec.ops:
        allowed = " ".join(sorted(spec.ops))
        yield "error", f"{name} is {_kind(spec)}: operator {t.op!r} not allowed (use {allowed})"


def _check_value(t: Token, name: str) -> Iterable[tuple[str, str]]:
    """The value of one token with a known key: (level, message) pairs."""
    assigning = t.op not in MATCH
    if t.key in FORMATTED and (assigning or t.key in ("PROGRAM", "IMPORT")):
        for m in SUBSTITUTION.finditer(t.value):
            word = m.group(1) or ""
            if (
                not m.group(1)
                and not m.group(3)
                or (word not in ("", "$") and word.split("{")[0] not in DOLLAR_NAMES)
            ):
                yield "error", f"unknown substitution {m.group()!r} in {name} (write $$ or %%)"
    literal = SUBSTITUTION.search(t.value) is None
    if t.key == "ACTION":
        bad = [a for a in t.value.split("|") if a not in ACTIONS]
        if bad:
            yield "warning", f"ACTION {'|'.join(bad)!r} is not one of {' '.join(sorted(ACTIONS))}"
    elif t.key == "MODE" and literal and not re.fullmatch(r"[0-7]{3,4}", t.value):
        yield "error", f'MODE {t.value!r} is not an octal mode like "0660"'
    elif t.key in ("OWNER", "GROUP") and not re.fullmatch(r"[A-Za-z0-9_][\w.-]*\$?", t.value):
        yield "error", f"{t.key} {t.value!r} is not a user or group name"
    elif t.key == "TEST" and t.attr and not re.fullmatch(r"[0-7]{3,4}", t.attr):
        yield "error", f"{name}: the attribute is an octal mode"
    elif t.key == "NAME" and assigning and literal:
        if len(t.value) > IFNAMSIZ or not re.fullmatch(r"[\w.:-]+", t.value):
            yield "error", f"NAME {t.value!r}: 1-{IFNAMSIZ} characters, no '/' or blanks"
    elif t.key == "OPTIONS":
        for opt in filter(None, (o.strip() for o in t.value.split(","))):
            if not OPTIONS_KNOWN.match(opt):
                yield "warning", f"unknown OPTIONS entry {opt!r}"
    elif t.key == "RUN" and t.attr in (None, "program") and not t.value.startswith("/"):
        yield "warning", "RUN program is not an absolute path (udev looks in /usr/lib/udev)"


def _check_token(t: Token, template: bool) -> Iterable[tuple[str, str]]:
    """Yield (level, message) for one token."""
    name = f"{t.key}{{{t.attr}}}" if t.attr is not None else t.key
    yield from _check_key(t, name)
    placeholder = PLACEHOLDER.search(t.value)
    if placeholder and not template:
        yield "error", f"unfilled template variable {placeholder.group()} in {name}"
    if t.key in KEYS and not placeholder:
        yield from _check_value(t, name)


def lint_text(text: str, path: str = "<text>", *, template: bool = False) -> LintResult:
    """Lint the text of one rule file.

    Parameters
    ----------
    text : str
        File contents.
    path : str
        Name used in the findings.
    template : bool
        Accept ``@VARIABLE@`` placeholders (an uninstalled template).
    """
    rules: list[Rule] = []
    found: list[Finding] = []
    for logical in logical_lines(text):
        found.extend(Finding(path, ln, lvl, msg) for ln, lvl, msg in logical.notes)
        if not logical.text.strip():
            continue
        tokens, problems = parse_rule(logical.text, list(logical.marks))
        found.extend(Finding(path, ln, lvl, msg) for ln, lvl, msg in problems)
        for t in tokens:
            found.extend(Finding(path, t.line, lvl, msg) for lvl, msg in _check_token(t, template))
        if tokens and all(lvl != "error" for _, lvl, _ in problems):
            rules.append(Rule(logical.line, tuple(tokens)))
            effect = any(t.op not in MATCH or t.key in ("PROGRAM", "IMPORT") for t in tokens)
            if not effect:
                found.append(
                    Finding(path, logical.line, "warning", "rule only matches: it has no effect")
                )
    found.extend(_check_labels(rules, path))
    return LintResult(path, tuple(rules), tuple(sorted(found, key=lambda f: f.line)))


def _check_labels(rules: list[Rule], path: str) -> Iterable[Finding]:
    labels: dict[str, int] = {}
    for r in rules:
        for t in r.tokens:
            if t.key == "LABEL":
                if t.value in labels:
                    yield Finding(path, t.line, "warning", f"LABEL {t.value!r} is defined twice")
                labels.setdefault(t.value, t.line)
    for r in rules:
        for t in r.tokens:
            if t.key == "GOTO" and labels.get(t.value, 0) <= t.line:
                yield Finding(
                    path,
                    t.line,
                    "error",
                    f"GOTO {t.value!r} has no LABEL after it in this file (udev jumps forward only)",
                )


def lint_file(path: Path, *, template: bool = False) -> LintResult:
    """Lint a rule file (see :func:`lint_text`)."""
    text = Path(path).read_text(encoding="utf-8", errors="replace")
    return lint_text(text, str(path), template=template)
