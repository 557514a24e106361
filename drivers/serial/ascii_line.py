"""Line framing of ASCII drive protocols: terminators, comments and XOR checksums.

Pure bytes <-> text, no I/O; :mod:`servobench.drivers.serial.dialect` says what the lines mean.

::

    request:  <body>[*<checksum>]<terminator>          e.g. b"f 0*118\\n"
    reply:    <body>[*<checksum>]<reply_terminator>    e.g. b"0.500000 1.250000\\r\\n"

With ``checksum = "xor"`` the checksum is the bitwise XOR of every byte
before the ``*``, written in decimal (GCode style; ODrive's
``r vbus_voltage *93``). The ODrive adds a checksum to its reply if and
only if the request carried one, and silently ignores a request whose
checksum is wrong. Anything after a ``;`` in a request is a comment.
"""

from __future__ import annotations

from dataclasses import dataclass

from servobench.errors import DriveConnectionError, UsageError


class MalformedReplyError(DriveConnectionError):
    """A reply line is garbled, truncated, has a bad checksum or the wrong shape."""


def xor_checksum(data: str | bytes) -> int:
    """Bitwise XOR of all bytes of ``data`` (ODrive/GCode line checksum)."""
    raw = data.encode("ascii") if isinstance(data, str) else data
    out = 0
    for b in raw:
        out ^= b
    return out


def encode_line(body: str, terminator: bytes, checksum: bool) -> bytes:
    """``body`` [+ ``*<xor>``] + ``terminator``, as ASCII bytes."""
    if any(c in body for c in "\r\n"):
        raise UsageError(f"line {body!r} contains a line break")
    try:
        raw = body.encode("ascii")
    except UnicodeEncodeError:
        raise UsageError(f"line {body!r} is not ASCII") from None
    if checksum:
        raw += b"*%d" % xor_checksum(raw)
    return raw + terminator


def decode_reply(raw: bytes, expect_checksum: bool) -> str:
    """The body of one reply line (terminator already split off).

    Raises
    ------
    MalformedReplyError
        On non-ASCII bytes, a missing, malformed or wrong checksum when one is
        expected, or a checksum where none is expected.
    """
    try:
        text = raw.decode("ascii").strip("\r\n")
    except UnicodeDecodeError:
        raise MalformedReplyError(f"reply {raw!r} is not ASCII (wrong baud rate?)") from None
    if any(not c.isprintable() for c in text):
        raise MalformedReplyError(f"reply {raw!r} holds control characters (wrong baud rate?)")
    star = text.rfind("*")
    if not expect_checksum:
        if star >= 0 and text[star + 1 :].isdigit():
            raise MalformedReplyError(f"reply {text!r} carries a checksum nobody asked for")
        return text
    if star < 0 or not text[star + 1 :].isdigit():
        raise MalformedReplyError(f"reply {text!r} has no checksum")
    body, got = text[:star], int(text[star + 1 :])
    want = xor_checksum(body)
    if got != want:
        raise MalformedReplyError(f"reply {text!r}: checksum {got} != {want}")
    return body


@dataclass(frozen=True)
class Request:
    """A request line as the drive sees it: body, whether it carried a checksum, if valid."""

    body: str
    checksummed: bool
    valid: bool


def decode_request(raw: bytes) -> Request:
    """Split a request line (no terminator) into body and checksum, ODrive-style.

    A ``;`` starts a comment. With a ``*`` the XOR of the bytes before it must
    equal the decimal number after it, else the line is not ``valid`` (the
    drive ignores it). Non-ASCII lines are not valid.
    """
    try:
        text = raw.decode("ascii")
    except UnicodeDecodeError:
        return Request(raw.decode("ascii", "replace"), False, False)
    text = text.split(";", 1)[0]
    star = text.find("*")
    if star < 0:
        return Request(text.strip(), False, True)
    body, tail = text[:star], text[star + 1 :].strip()
    valid = tail.isdigit() and int(tail) == xor_checksum(body)
    return Request(body.strip(), True, valid)
