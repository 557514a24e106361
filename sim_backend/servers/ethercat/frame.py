"""EtherCAT frames and datagrams as bytes: a pure codec, no I/O (ETG.1000.4).

Ethernet frame (EtherType 0x88A4), all EtherCAT fields little-endian::

    +----------+----------+---------+-----------------+-----------+-----+-----------+---------+
    | dst MAC  | src MAC  | 0x88A4  | EtherCAT header | datagram1 | ... | datagramN | padding |
    | 6 bytes  | 6 bytes  | 2 (BE)  | 2 bytes (LE)    |           |     |           | to 60   |
    +----------+----------+---------+-----------------+-----------+-----+-----------+---------+

    EtherCAT header: bits 0..10 length of the datagrams [bytes], bit 11 reserved,
                     bits 12..15 type (1 = EtherCAT commands)

Datagram::

    +-----+-----+-------------------+-------------------+-----+--------+-----+
    | cmd | idx | address           | len | R | C | M   | IRQ | data   | WKC |
    | 1   | 1   | 4                 | 11b | 3b| 1b| 1b  | 2   | len    | 2   |
    +-----+-----+-------------------+-------------------+-----+--------+-----+

    address: position (ADP, 16 bit) + offset (ADO, 16 bit) for the physical
             commands, one 32-bit logical address for LRD/LWR/LRW;
    C: the datagram has circulated; M: more datagrams follow.

A slave changes a frame only in place: the data of what it reads, the
working counter, ADP of auto-increment and broadcast commands (incremented)
and bit 1 of the first source MAC byte (set, as an ESC's port 0 does).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, replace
from enum import IntEnum

ETHERTYPE_ECAT = 0x88A4
#: EtherCAT header type: the frame carries EtherCAT commands (DLPDU).
TYPE_COMMANDS = 1
ETH_HEADER_BYTES = 14
ECAT_HEADER_BYTES = 2
DATAGRAM_HEADER_BYTES = 10
WKC_BYTES = 2
#: Shortest Ethernet frame without FCS [bytes].
MIN_FRAME_BYTES = 60
#: Locally administered bit the slave sets in the first source MAC byte.
SOURCE_MAC_MARK = 0x02

_LEN_MASK = 0x07FF
_CIRCULATED = 0x4000
_MORE = 0x8000


class Command(IntEnum):
    """Datagram commands (ETG.1000.4 table 9)."""

    NOP = 0
    APRD = 1
    APWR = 2
    APRW = 3
    FPRD = 4
    FPWR = 5
    FPRW = 6
    BRD = 7
    BWR = 8
    BRW = 9
    LRD = 10
    LWR = 11
    LRW = 12
    ARMW = 13
    FRMW = 14

    @property
    def logical(self) -> bool:
        return self in (Command.LRD, Command.LWR, Command.LRW)

    @property
    def reads(self) -> bool:
        return self.name.endswith(("RD", "RW", "RMW"))

    @property
    def writes(self) -> bool:
        return self.name.endswith(("WR", "RW"))


class FrameError(ValueError):
    """Bytes that are no well-formed EtherCAT frame."""


@dataclass(frozen=True)
class Datagram:
    """One EtherCAT datagram.

    ``adp``/``ado`` are the position and offset of the physical commands; a
    logical command keeps its 32-bit address in ``logical_address``
    (``adp`` = low 16 bits, ``ado`` = high 16 bits on the wire).
    """

    command: Command
    index: int
    adp: int
    ado: int
    data: bytes
    wkc: int = 0
    irq: int = 0
    circulated: bool = False

    @property
    def logical_address(self) -> int:
        return self.adp | self.ado << 16

    @classmethod
    def logical(cls, command: Command, index: int, address: int, data: bytes, wkc: int = 0):
        return cls(command, index, address & 0xFFFF, address >> 16 & 0xFFFF, bytes(data), wkc)

    def answered(self, data: bytes, wkc: int, adp: int | None = None) -> Datagram:
        """This datagram as a slave returns it."""
        return replace(self, data=bytes(data), wkc=wkc, adp=self.adp if adp is None else adp)


@dataclass(frozen=True)
class Frame:
    """An EtherCAT frame: Ethernet addresses and its datagrams."""

    dst: bytes
    src: bytes
    datagrams: tuple[Datagram, ...]


def decode_datagrams(payload: bytes) -> tuple[Datagram, ...]:
    """The datagrams after the EtherCAT header (``payload`` starts at the header).

    Raises
    ------
    FrameError
        Not EtherCAT commands, or a length that overruns the frame.
    """
    if len(payload) < ECAT_HEADER_BYTES:
        raise FrameError("no EtherCAT header")
    (header,) = struct.unpack_from("<H", payload)
    if header >> 12 != TYPE_COMMANDS:
        raise FrameError(f"EtherCAT header type {header >> 12} is not 1 (commands)")
    end = ECAT_HEADER_BYTES + (header & _LEN_MASK)
    if end > len(payload):
        raise FrameError(f"EtherCAT header length {header & _LEN_MASK} overruns the frame")
    pos, out, more = ECAT_HEADER_BYTES, [], True
    while more:
        if pos + DATAGRAM_HEADER_BYTES + WKC_BYTES > end:
            raise FrameError("datagram header overruns the EtherCAT length")
        cmd, idx, adp, ado, flags, irq = struct.unpack_from("<BBHHHH", payload, pos)
        n = flags & _LEN_MASK
        data_at = pos + DATAGRAM_HEADER_BYTES
        if data_at + n + WKC_BYTES > end:
            raise FrameError(f"datagram {idx} of {n} bytes overruns the EtherCAT length")
        try:
            command = Command(cmd)
        except ValueError:
            raise FrameError(f"unknown datagram command {cmd}") from None
        (wkc,) = struct.unpack_from("<H", payload, data_at + n)
        out.append(
            Datagram(command, idx, adp, ado, bytes(payload[data_at : data_at + n]), wkc, irq,
                     bool(flags & _CIRCULATED))
        )  # fmt: skip
        more = bool(flags & _MORE)
        pos = data_at + n + WKC_BYTES
    return tuple(out)


def encode_datagrams(datagrams: tuple[Datagram, ...] | list[Datagram]) -> bytes:
    """EtherCAT header and datagrams (the M flag set on all but the last)."""
    body = bytearray()
    for i, d in enumerate(datagrams):
        flags = len(d.data) | (_CIRCULATED if d.circulated else 0)
        if i < len(datagrams) - 1:
            flags |= _MORE
        body += struct.pack("<BBHHHH", d.command, d.index, d.adp, d.ado, flags, d.irq)
        body += d.data + struct.pack("<H", d.wkc & 0xFFFF)
    return struct.pack("<H", len(body) | TYPE_COMMANDS << 12) + bytes(body)


def decode_frame(raw: bytes) -> Frame:
    """An Ethernet frame carrying EtherCAT commands.

    Raises
    ------
    FrameError
        Another EtherType, or a malformed EtherCAT part.
    """
    if len(raw) < ETH_HEADER_BYTES + ECAT_HEADER_BYTES:
        raise FrameError("frame shorter than the Ethernet and EtherCAT headers")
    (ethertype,) = struct.unpack_from(">H", raw, 12)
    if ethertype != ETHERTYPE_ECAT:
        raise FrameError(f"EtherType 0x{ethertype:04X} is not EtherCAT")
    return Frame(bytes(raw[0:6]), bytes(raw[6:12]), decode_datagrams(raw[ETH_HEADER_BYTES:]))


def encode_frame(frame: Frame) -> bytes:
    """The Ethernet frame, padded to 60 bytes."""
    raw = (
        frame.dst
        + frame.src
        + struct.pack(">H", ETHERTYPE_ECAT)
        + encode_datagrams(frame.datagrams)
    )
    return raw + bytes(max(0, MIN_FRAME_BYTES - len(raw)))


def returned_source(src: bytes) -> bytes:
    """The source MAC of a frame as the slave sends it on (locally administered bit set)."""
    return bytes([src[0] | SOURCE_MAC_MARK]) + src[1:]
