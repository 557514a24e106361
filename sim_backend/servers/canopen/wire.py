"""CAN frames and the socketcand ASCII protocol, as pure codecs.

socketcand (https://github.com/linux-can/socketcand) carries CAN over TCP as
ASCII commands in angle brackets. The subset spoken by python-can's
``socketcand`` client and served by :mod:`servobench.sim_backend.servers.canopen.socketcand_server`::

    server -> client   < hi >                         on connect
    client -> server   < open vcan0 >                 pick the bus
    server -> client   < ok >
    client -> server   < rawmode >                    every frame, both ways
    server -> client   < ok >
    client -> server   < send 123 2 a 1f >            ID (3 hex digits standard, 8 extended),
                                                      DLC, then one hex token per byte
    server -> client   < frame 123 1700000000.123456 0A1F >
                                                      ID, seconds.microseconds, bytes as
                                                      one contiguous hex string

An ID of three hex digits is an 11-bit (standard) identifier, eight digits
a 29-bit (extended) one.
"""

from __future__ import annotations

from dataclasses import dataclass

#: Largest 11-bit and 29-bit identifiers.
MAX_STANDARD_ID = 0x7FF
MAX_EXTENDED_ID = 0x1FFFFFFF


class WireError(ValueError):
    """A socketcand command could not be parsed."""


@dataclass(frozen=True)
class CanFrame:
    """One classic CAN data frame.

    Attributes
    ----------
    can_id : int
        Identifier, 11-bit unless ``is_extended``.
    data : bytes
        Payload, 0 to 8 bytes.
    is_extended : bool
        29-bit identifier.
    """

    can_id: int
    data: bytes = b""
    is_extended: bool = False

    def __post_init__(self) -> None:
        limit = MAX_EXTENDED_ID if self.is_extended else MAX_STANDARD_ID
        if not 0 <= self.can_id <= limit:
            raise WireError(f"CAN id 0x{self.can_id:X} out of range (max 0x{limit:X})")
        if len(self.data) > 8:
            raise WireError(f"classic CAN frame carries at most 8 bytes, got {len(self.data)}")

    def id_text(self) -> str:
        return f"{self.can_id:08X}" if self.is_extended else f"{self.can_id:03X}"


def split_commands(buffer: str) -> tuple[list[str], str]:
    """Complete ``< ... >`` commands in ``buffer`` and the unparsed rest.

    Text outside angle brackets is discarded.
    """
    commands: list[str] = []
    pos = 0
    while True:
        start = buffer.find("<", pos)
        if start < 0:
            return commands, ""
        end = buffer.find(">", start)
        if end < 0:
            return commands, buffer[start:]
        commands.append(buffer[start : end + 1])
        pos = end + 1


def command_words(command: str) -> list[str]:
    """The words between the brackets: ``"< open vcan0 >"`` -> ``["open", "vcan0"]``."""
    if not (command.startswith("<") and command.endswith(">")):
        raise WireError(f"not a socketcand command: {command!r}")
    return command[1:-1].split()


def _parse_id(text: str) -> tuple[int, bool]:
    try:
        can_id = int(text, 16)
    except ValueError:
        raise WireError(f"bad CAN id {text!r}") from None
    return can_id, len(text) > 3


def parse_send(command: str) -> CanFrame:
    """The frame of a ``< send ID DLC b0 b1 ... >`` command."""
    words = command_words(command)
    if len(words) < 3 or words[0] != "send":
        raise WireError(f"not a send command: {command!r}")
    can_id, extended = _parse_id(words[1])
    try:
        dlc = int(words[2], 16)
        data = bytes(int(b, 16) for b in words[3:])
    except ValueError:
        raise WireError(f"bad length or data byte in {command!r}") from None
    if dlc != len(data):
        raise WireError(f"DLC {dlc} but {len(data)} data bytes in {command!r}")
    return CanFrame(can_id, data, extended)


def encode_send(frame: CanFrame) -> str:
    """``< send ... >`` for ``frame`` (what a client transmits)."""
    data = "".join(f" {b:x}" for b in frame.data)
    return f"< send {frame.id_text()} {len(frame.data):X}{data} >"


def encode_frame(frame: CanFrame, timestamp_s: float) -> str:
    """``< frame ... >`` for ``frame`` received at ``timestamp_s`` (what the server delivers)."""
    seconds = int(timestamp_s)
    micros = min(int(round((timestamp_s - seconds) * 1e6)), 999_999)
    return f"< frame {frame.id_text()} {seconds}.{micros:06d} {frame.data.hex().upper()} >"


def parse_frame(command: str) -> tuple[CanFrame, float]:
    """The frame and timestamp [s] of a ``< frame ID SEC.USEC HEX >`` command."""
    words = command_words(command)
    if len(words) not in (3, 4) or words[0] != "frame":
        raise WireError(f"not a frame command: {command!r}")
    can_id, extended = _parse_id(words[1])
    try:
        timestamp = float(words[2])
        data = bytes.fromhex(words[3]) if len(words) == 4 else b""
    except ValueError:
        raise WireError(f"bad timestamp or data in {command!r}") from None
    return CanFrame(can_id, data, extended), timestamp
