"""The EtherCAT mailbox header and the CoE header: a pure codec (ETG.1000.6 section 5.6).

Mailbox (in SM0 from the master, in SM1 to it), little-endian::

    +--------+---------+-----------------+-------------------+----------------+
    | length | address | channel/prio    | type/counter      | data (length)  |
    | 2      | 2       | 1: 0..5 channel | 1: 0..3 type      |                |
    |        |         |    6..7 prio    |    4..6 counter   |                |
    +--------+---------+-----------------+-------------------+----------------+

    type: 0 mailbox error, 3 CoE (others are not served: answered with a
    mailbox error "unsupported protocol").

CoE data::

    +------------------------------+-----------------------------------+
    | CoE header (2)               | SDO: command (1) index (2) sub (1)|
    | 0..8 number, 12..15 service  |      data (4, or size + data)     |
    +------------------------------+-----------------------------------+

    service: 1 emergency, 2 SDO request, 3 SDO response, 8 SDO information.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

MAILBOX_HEADER_BYTES = 6
TYPE_ERROR = 0x00
TYPE_COE = 0x03
COE_EMERGENCY = 1
COE_SDO_REQUEST = 2
COE_SDO_RESPONSE = 3
COE_SDO_INFO = 8
#: Mailbox error details (ETG.1000.6 table 29).
MBXERR_SYNTAX = 0x0001
MBXERR_UNSUPPORTED_PROTOCOL = 0x0002
MBXERR_INVALID_HEADER = 0x0005
MBXERR_SIZE_TOO_SHORT = 0x0006
MBXERR_SERVICE_NOT_SUPPORTED = 0x0004


@dataclass(frozen=True)
class Mailbox:
    """One mailbox message."""

    kind: int
    counter: int
    data: bytes
    address: int = 0
    channel: int = 0
    priority: int = 0


def decode_mailbox(raw: bytes) -> Mailbox:
    """The message in a mailbox buffer (the buffer may be longer than the message).

    Raises
    ------
    ValueError
        Shorter than its header or its length.
    """
    if len(raw) < MAILBOX_HEADER_BYTES:
        raise ValueError("mailbox shorter than its header")
    length, address, chan, kind = struct.unpack_from("<HHBB", raw)
    if MAILBOX_HEADER_BYTES + length > len(raw):
        raise ValueError(f"mailbox length {length} overruns the buffer")
    return Mailbox(
        kind & 0x0F, kind >> 4 & 0x07, bytes(raw[6 : 6 + length]), address, chan & 0x3F, chan >> 6
    )


def encode_mailbox(message: Mailbox) -> bytes:
    return (
        struct.pack(
            "<HHBB",
            len(message.data),
            message.address,
            message.channel | message.priority << 6,
            message.kind | (message.counter & 0x07) << 4,
        )
        + message.data
    )


def coe_header(service: int, number: int = 0) -> bytes:
    return struct.pack("<H", number & 0x01FF | service << 12)


def coe_service(data: bytes) -> int:
    return struct.unpack_from("<H", data)[0] >> 12 if len(data) >= 2 else -1


def mailbox_error(detail: int, counter: int = 0) -> bytes:
    """A mailbox error reply (type 0: service 0x0001, then the detail)."""
    return encode_mailbox(Mailbox(TYPE_ERROR, counter, struct.pack("<HH", 0x0001, detail)))


def emergency(code: int, register: int, counter: int = 0) -> bytes:
    """A CoE emergency: error code, error register, 5 manufacturer bytes (zero)."""
    data = coe_header(COE_EMERGENCY) + struct.pack("<HB", code, register) + bytes(5)
    return encode_mailbox(Mailbox(TYPE_COE, counter, data))
