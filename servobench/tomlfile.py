"""The one reader of TOML files: plant files, register maps, dialects, ``bench.toml``.

:func:`read_toml` reads a file into a document with one clear error;
:class:`TomlTable` reads a table of it key by key, checked::

    top = TomlTable(read_toml(path, "register map file"), str(path))
    head = top.table("map")                        # required table
    name = head.get("name", str)                   # required key
    fc23 = head.get("fc23", bool, False)           # typed, with a default
    order = head.choice("word_order", ("big", "little"), "big")
    head.done()                                    # keys never asked for are unknown

Every problem raises one error (a :class:`DriveConfigError` unless told
otherwise) that names the file, the table and the key, in the
:class:`Wording` of its file format.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from servobench.errors import DriveConfigError, ServobenchError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


def read_toml(
    path: str | Path, what: str, error: type[ServobenchError] = DriveConfigError
) -> dict[str, object]:
    """The parsed TOML file ``path``; ``what`` names the file in errors (``"plant file"``).

    Raises
    ------
    error
        Missing, not a regular file (a folder, or a device such as /dev/zero
        that would never end), unreadable, not UTF-8, or not valid TOML.
    """
    path = Path(path)
    if not path.is_file():
        why = "not a regular file" if path.exists() else "no such file"
        raise error(f"cannot read {what} {str(path)!r}: {why}")
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as err:
        raise error(f"cannot read {what} {path}: {err.strerror}") from None
    except UnicodeDecodeError:
        raise error(f"{what} {path} is not UTF-8 text") from None
    except tomllib.TOMLDecodeError as err:
        raise error(f"{what} {path} is not valid TOML: {err}") from None


@dataclass(frozen=True)
class Wording:
    """How a file format words the checks of :class:`TomlTable` (``str.format`` templates).

    Register maps and plant files put the key first (:data:`KEYED`); dialects
    and ``bench.toml`` write a sentence about the table (:data:`SENTENCE`).
    Both wordings are kept because users and tests match on them; the checks
    behind them are one.

    The templates see ``where`` (the table, from ``table`` or ``top``),
    ``key``, ``value`` (its repr), ``kind`` (``"int"``, ``"list of numbers"``
    ...), ``options``, ``what`` (``"key 'x'"`` or ``"table [x]"``), ``keys``,
    ``known``, ``noun`` and ``nouns``.
    """

    table: str
    top: str
    wrong_type: str
    missing: str
    not_one_of: str
    unknown: str


#: ``map.toml: [registers.velocity] address: expected int, got True`` (register maps, plant files).
KEYED = Wording(
    table="{file}: [{table}]",
    top="{file}: [top level]",
    wrong_type="{where} {key}: expected {kind}, got {value}",
    missing="{where} {key}: is required",
    not_one_of="{where} {key}: {value} is not one of {options}",
    unknown="{where} {keys}: unknown {nouns} (known: {known})",
)
#: ``dialect odrive.toml [states]: enabled must be a int, got '8'`` (dialects, ``bench.toml``).
SENTENCE = Wording(
    table="{file} [{table}]",
    top="{file}",
    wrong_type="{where}: {key} must be a {kind}, got {value}",
    missing="{where}: missing {what}",
    not_one_of="{where}: {key} must be one of {options}, got {value}",
    unknown="{where}: unknown {noun}(s) {keys} (known: {known})",
)


class _NoDefault:
    def __repr__(self) -> str:
        return "NO_DEFAULT"


#: The default of a key that must be present.
NO_DEFAULT: Any = _NoDefault()

_KIND_NAMES = {bool: "bool", int: "int", float: "number", str: "string", list: "list",
               dict: "table", object: "value"}  # fmt: skip


def _is(value: object, kind: type) -> bool:
    """Whether ``value`` is a TOML value of ``kind``: a bool is no number, an int is a float."""
    if isinstance(value, bool):
        return kind in (bool, object)
    if kind is float:
        return isinstance(value, (int, float))
    return isinstance(value, kind)


class TomlTable:
    """One table of a TOML document, read key by key.

    Parameters
    ----------
    data : Mapping
        The table, as :func:`read_toml` gives it.
    file : str
        How errors name the file (``"odrive.toml"``, ``"dialect odrive.toml"``).
    name : str
        Dotted name of the table (``"registers.velocity"``); ``""`` for the top level.
    wording : Wording
        How errors are worded (:data:`KEYED` or :data:`SENTENCE`).
    error : type
        The error raised (``DriveConfigError``; ``UsageError`` for ``bench.toml``).

    Unknown keys are found in one of two ways: :meth:`allow` declares the
    known keys up front, or :meth:`done` reports, after reading, every key
    that was never asked for (present or not, a key asked for is known).
    Tables read from this one inherit the file, wording and error.
    """

    def __init__(
        self,
        data: Mapping[str, object],
        file: str,
        name: str = "",
        *,
        wording: Wording = KEYED,
        error: type[ServobenchError] = DriveConfigError,
    ) -> None:
        self.data, self.file, self.name = data, file, name
        self.wording, self.error_type = wording, error
        #: Where errors say the table is (``"map.toml: [registers]"``).
        self.where = (wording.table if name else wording.top).format(file=file, table=name)
        self._seen: set[str] = set()

    def __contains__(self, key: object) -> bool:
        return key in self.data

    # ------------------------------------------------------------ errors
    def error(self, key: str, message: str) -> ServobenchError:
        """The error for ``key``: ``<where> <key>: <message>``."""
        return self.error_type(f"{self.where} {key}: {message}")

    def table_error(self, message: str) -> ServobenchError:
        """The error for the table as a whole: ``<where>: <message>``."""
        return self.error_type(f"{self.where}: {message}")

    def _fail(self, template: str, key: str = "", **fields: str) -> ServobenchError:
        return self.error_type(template.format(where=self.where, key=key, **fields))

    def _wrong_type(self, key: str, kind: str, value: object) -> ServobenchError:
        return self._fail(self.wording.wrong_type, key, kind=kind, value=repr(value))

    def _unknown(self, keys: Sequence[str], known: Collection[str], noun: str) -> ServobenchError:
        nouns = noun if len(keys) == 1 else noun + "s"
        return self._fail(self.wording.unknown, keys=", ".join(keys), noun=noun, nouns=nouns,
                          known=", ".join(sorted(known)) or "none")  # fmt: skip

    # ------------------------------------------------------------ reading
    def _lookup(self, key: str, default: object, what: str) -> tuple[bool, object]:
        self._seen.add(key)
        if key in self.data:
            return True, self.data[key]
        if default is NO_DEFAULT:
            raise self._fail(self.wording.missing, key, what=what)
        return False, default

    def get(self, key: str, kind: type, default: object = NO_DEFAULT) -> Any:
        """The value of ``key``, of type ``kind``; ``default`` when absent.

        ``kind`` is ``bool``, ``int`` (never a bool), ``float`` (any number:
        TOML writes whole ones without a point), ``str``, ``list``, ``dict`` or
        ``object`` (any value).
        """
        present, value = self._lookup(key, default, f"key {key!r}")
        if not present:
            return value
        if not _is(value, kind):
            raise self._wrong_type(key, _KIND_NAMES.get(kind, kind.__name__), value)
        return value

    def number(self, key: str, default: object = NO_DEFAULT, *, allow_inf: bool = False) -> Any:
        """The number ``key`` as a float: finite (or +-inf with ``allow_inf``), never NaN."""
        value = self.get(key, float, default)
        if key not in self.data:
            return value
        if math.isnan(value) or (math.isinf(value) and not allow_inf):
            raise self._wrong_type(key, "number" if allow_inf else "finite number", value)
        return float(value)

    def choice(self, key: str, options: Sequence[str], default: object = NO_DEFAULT) -> Any:
        """The string ``key``, one of ``options``."""
        value = self.get(key, str, default)
        if key in self.data and value not in options:
            options_text = ", ".join(repr(o) for o in options)
            raise self._fail(self.wording.not_one_of, key, value=repr(value), options=options_text)
        return value

    def sequence(self, key: str, kind: type, default: object = NO_DEFAULT) -> Any:
        """The array ``key`` as a tuple, every item of type ``kind`` (as in :meth:`get`)."""
        present, value = self._lookup(key, default, f"key {key!r}")
        if not present:
            return value
        if not isinstance(value, list) or not all(_is(v, kind) for v in value):
            raise self._wrong_type(key, f"list of {_KIND_NAMES.get(kind, kind.__name__)}s", value)
        return tuple(value)

    def table(self, key: str, required: bool = True) -> TomlTable:
        """The sub-table ``key``; an empty one when it is absent and not ``required``."""
        default = NO_DEFAULT if required else {}
        _, value = self._lookup(key, default, f"table [{self._child(key)}]")
        if not isinstance(value, dict):
            raise self._wrong_type(key, "table", value)
        return self._wrap(value, self._child(key))

    def tables(self, key: str, default: object = NO_DEFAULT) -> Any:
        """The array of tables ``key`` (``[[key]]``), each a :class:`TomlTable` named ``key[i]``."""
        items = self.get(key, list, default)
        if key not in self.data:
            return items
        out = []
        for i, item in enumerate(items):
            if not isinstance(item, dict):
                raise self._wrong_type(f"{key}[{i}]", "table", item)
            out.append(self._wrap(item, f"{self._child(key)}[{i}]"))
        return out

    def require(self, keys: Iterable[str]) -> None:
        """Raise for the first of ``keys`` the table lacks."""
        for key in keys:
            self._lookup(key, NO_DEFAULT, f"key {key!r}")

    def allow(self, keys: Collection[str], noun: str = "key") -> list[str]:
        """Declare the keys the table may hold and raise now for any other.

        Returns the keys present, in file order. For tables whose keys are
        names (registers, commands), and for tables whose unknown keys are to
        be reported before any missing one (a misspelled required key).
        """
        unknown = [k for k in self.data if k not in keys]
        if unknown:
            raise self._unknown(unknown, keys, noun)
        self._seen.update(keys)
        return list(self.data)

    def done(self, noun: str = "key") -> None:
        """Raise for the keys of the table that were never asked for."""
        unknown = [k for k in self.data if k not in self._seen]
        if unknown:
            raise self._unknown(unknown, self._seen, noun)

    def _child(self, key: str) -> str:
        return f"{self.name}.{key}" if self.name else key

    def _wrap(self, data: Mapping[str, object], name: str) -> TomlTable:
        return TomlTable(data, self.file, name, wording=self.wording, error=self.error_type)
