"""Exceptions of servobench, in one tree.

::

    ServobenchError
    ├── DriveError                       a drive or its link misbehaved
    │   ├── DriveUnavailableError        unknown URL scheme, backend library missing
    │   ├── DriveConfigError(ValueError) malformed URL, unknown query key, bad map/dialect file
    │   ├── DriveConnectionError(ConnectionError)
    │   ├── DriveTimeoutError(TimeoutError)  the drive stopped answering
    │   ├── DriveFaultError              the drive reports a fault (``code`` holds it)
    │   ├── StateTransitionError         a state machine did not reach the requested state
    │   └── LimitExceededError           feedback left the configured safe envelope
    ├── IdentificationError(ValueError)  the data cannot yield a model (no motion, too short ...)
    ├── LogFormatError(ValueError)       a log file is malformed
    └── UsageError(ValueError)           an argument is out of range

    DriveWarning(UserWarning)            a drive works, but with less than asked for

Drivers raise these and never log-and-continue; the runner decides what to
tolerate, and the CLI turns any ``ServobenchError`` into one line on stderr
and a non-zero exit status.
"""

from __future__ import annotations

import contextlib
import re

#: Every character ``str.splitlines`` breaks at.
LINE_BREAKS = re.compile("[\n\r\x0b\x0c\x1c\x1d\x1e\x85\u2028\u2029]+")


def one_line(text: str) -> str:
    """``text`` with each run of line breaks replaced by one space."""
    return LINE_BREAKS.sub(" ", text)


class ServobenchError(Exception):
    """Root of every error servobench raises on purpose.

    The message is kept to one line whatever text it quotes (file paths, TOML
    keys, URL values), so the CLI can always print an error as one line.
    """

    def __init__(self, *args: object) -> None:
        if args and isinstance(args[0], str):
            args = (one_line(args[0]), *args[1:])
        super().__init__(*args)


class DriveError(ServobenchError):
    """A drive, or the link to it, did not do what was asked."""


class DriveUnavailableError(DriveError):
    """The drive backend cannot be used: unknown scheme or missing library."""


class DriveConfigError(DriveError, ValueError):
    """A drive URL, register map or dialect file is malformed."""


class DriveConnectionError(DriveError, ConnectionError):
    """The link to the drive could not be opened or was lost."""


class DriveTimeoutError(DriveError, TimeoutError):
    """The drive did not answer within its deadline."""


class DriveFaultError(DriveError):
    """The drive reports a fault.

    Parameters
    ----------
    message : str
        Human-readable description.
    code : int
        Transport-specific fault code (CiA 402 error code 0x603F, a fault
        register value, ...); 0 when the transport gives none.
    """

    def __init__(self, message: str, code: int = 0) -> None:
        super().__init__(message)
        self.code = int(code)


class StateTransitionError(DriveError):
    """A drive state machine did not reach the requested state in time."""


class LimitExceededError(DriveError):
    """Feedback left the configured envelope (velocity or travel); the axis was stopped.

    ``partial`` holds, for a block exchange, the cycles taken up to and
    including the one that breached, so that no sample taken is lost.
    """

    def __init__(self, message: str, partial: object | None = None) -> None:
        super().__init__(message)
        self.partial = partial


class IdentificationError(ServobenchError, ValueError):
    """The data cannot yield a model: no motion, too few samples, singular fit."""


class LogFormatError(ServobenchError, ValueError):
    """A log file is missing, malformed or lacks a required column."""


class UsageError(ServobenchError, ValueError):
    """An argument is out of its allowed range."""


class DriveWarning(UserWarning):
    """A drive can be used, but lacks something the user should know about (one line).

    Issued with :func:`warnings.warn`; the CLI prints it as
    ``servobench: warning: <message>`` on stderr.
    """

    def __init__(self, message: str) -> None:
        super().__init__(one_line(message))


class SessionWarning(DriveWarning):
    """A :class:`DriveWarning` about the set-up, not the run (a Modbus map that feeds the watchdog
    with any request): the same words need saying once per terminal session, not on every command.
    """


def add_note(err: BaseException, note: str) -> None:
    """Attach a one-line note to ``err`` (PEP 678 ``__notes__``), e.g. where the partial log is.

    The CLI prints the notes after the message, on the same line.
    """
    note = one_line(note)
    if hasattr(err, "add_note"):  # Python >= 3.11
        err.add_note(note)
        return
    with contextlib.suppress(AttributeError):  # an exception type that takes no attributes
        err.__notes__ = [*getattr(err, "__notes__", []), note]  # type: ignore[attr-defined]


def notes_of(err: BaseException) -> list[str]:
    """The notes of ``err`` and of the errors it was raised from, outermost first, each once."""
    out: list[str] = []
    seen: set[int] = set()
    cur: BaseException | None = err
    while cur is not None and id(cur) not in seen:
        seen.add(id(cur))
        out.extend(n for n in getattr(cur, "__notes__", ()) if isinstance(n, str) and n not in out)
        cur = cur.__cause__ or cur.__context__
    return out
