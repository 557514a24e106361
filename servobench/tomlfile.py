"""Read a TOML configuration file (plant, register map, dialect) with one clear error."""

from __future__ import annotations

import sys
from pathlib import Path

from servobench.errors import DriveConfigError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


def read_toml(path: str | Path, what: str) -> dict[str, object]:
    """The parsed TOML file ``path``; ``what`` names the file in errors (``"plant file"``).

    Raises
    ------
    DriveConfigError
        Not a regular file (a folder, or a device such as /dev/zero that would
        never end), unreadable, not UTF-8, or not valid TOML.
    """
    path = Path(path)
    if not path.is_file():
        raise DriveConfigError(f"cannot read {what} {str(path)!r}: not a regular file")
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as err:
        raise DriveConfigError(f"cannot read {what} {path}: {err.strerror}") from None
    except UnicodeDecodeError:
        raise DriveConfigError(f"{what} {path} is not UTF-8 text") from None
    except tomllib.TOMLDecodeError as err:
        raise DriveConfigError(f"{what} {path} is not valid TOML: {err}") from None
