"""Drive URLs: ``scheme://[host[:port]][/path]?key=value&...``.

The scheme selects the backend (see :mod:`servobench.drivers.registry`); everything after
it is handed to the backend as a :class:`DriveURL`. Query keys are checked
against what the backend declares, so a misspelled option is an error, never
silently ignored.
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from urllib.parse import parse_qsl, unquote, urlsplit

from servobench.errors import DriveConfigError


@dataclass(frozen=True)
class DriveURL:
    """A parsed drive URL.

    Attributes
    ----------
    scheme : str
        Lower-case scheme, e.g. ``"canopen"``, ``"modbus+tcp"``, ``"sim"``.
    host : str
        Network location (``"127.0.0.1"``, ``"can0"``); empty when absent.
    port : int or None
        Port number when given.
    path : str
        Path part, percent-decoded (``"/dev/ttyUSB0"``); empty when absent.
    query : dict[str, str]
        Query parameters; a key may appear once.
    raw : str
        The URL as given.
    """

    scheme: str
    host: str = ""
    port: int | None = None
    path: str = ""
    query: Mapping[str, str] = field(default_factory=dict)
    raw: str = ""

    def check_keys(self, allowed: Iterable[str]) -> None:
        """Raise :class:`DriveConfigError` when the query holds a key not in ``allowed``."""
        allowed = set(allowed)
        unknown = sorted(set(self.query) - allowed)
        if unknown:
            known = ", ".join(sorted(allowed)) or "none"
            guesses = [g for k in unknown for g in difflib.get_close_matches(k, allowed, n=2)]
            hint = f"; did you mean {' or '.join(dict.fromkeys(guesses))}?" if guesses else ""
            raise DriveConfigError(
                f"{self.scheme}:// does not take query key(s) {', '.join(unknown)}{hint} (known: {known})"
            )

    def get_float(self, key: str, default: float | None = None) -> float | None:
        """Query value ``key`` as a finite float, or ``default`` when absent."""
        if key not in self.query:
            return default
        text = self.query[key]
        try:
            value = float(text)
        except ValueError:
            raise DriveConfigError(f"query key {key}={text!r} is not a number") from None
        if value != value or value in (float("inf"), float("-inf")):
            raise DriveConfigError(f"query key {key}={text!r} is not finite")
        return value

    def get_int(self, key: str, default: int | None = None) -> int | None:
        """Query value ``key`` as an int (decimal or ``0x`` hex), or ``default``."""
        if key not in self.query:
            return default
        text = self.query[key]
        try:
            return int(text, 0)
        except ValueError:
            raise DriveConfigError(f"query key {key}={text!r} is not an integer") from None

    def get_str(self, key: str, default: str | None = None) -> str | None:
        """Query value ``key`` as text, or ``default``."""
        return self.query.get(key, default)

    def get_bool(self, key: str, default: bool = False) -> bool:
        """Query value ``key`` as a boolean (1/0, true/false, yes/no, on/off)."""
        if key not in self.query:
            return default
        text = self.query[key].strip().lower()
        if text in ("1", "true", "yes", "on"):
            return True
        if text in ("0", "false", "no", "off"):
            return False
        raise DriveConfigError(f"query key {key}={self.query[key]!r} is not a boolean")


def parse_drive_url(url: str) -> DriveURL:
    """Parse ``url`` into a :class:`DriveURL`.

    Raises
    ------
    DriveConfigError
        When the URL has no scheme, a malformed port, or a repeated query key.
    """
    if not isinstance(url, str) or "://" not in url:
        raise DriveConfigError(f"not a drive URL: {url!r} (expected scheme://..., e.g. sim://)")
    try:
        parts = urlsplit(url.strip())
        port = parts.port
    except ValueError as err:
        raise DriveConfigError(f"malformed drive URL {url!r}: {err}") from None
    scheme = parts.scheme.lower()
    if not scheme:
        raise DriveConfigError(f"drive URL {url!r} has no scheme")
    query: dict[str, str] = {}
    try:
        pairs = parse_qsl(parts.query, keep_blank_values=True, strict_parsing=bool(parts.query))
    except ValueError:
        raise DriveConfigError(f"malformed query in drive URL {url!r}") from None
    for key, value in pairs:
        if key in query:
            raise DriveConfigError(f"query key {key!r} given twice in {url!r}")
        query[key] = value
    return DriveURL(
        scheme=scheme,
        host=unquote(parts.hostname or "") if parts.netloc else "",
        port=port,
        path=unquote(parts.path),
        query=query,
        raw=url,
    )
