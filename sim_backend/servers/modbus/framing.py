"""Modbus framing of the served drive: RTU frames with their CRC, TCP frames with their MBAP header.

Pure bytes in, bytes out, no I/O. The PDU (function code and data) is the
business of :mod:`servobench.sim_backend.servers.modbus.pdu`.

RTU (Modbus over Serial Line v1.02, §2.5.1.2 and Appendix B)::

    | address (1) | function code (1) | data (0..252) | CRC low | CRC high |

    CRC-16/MODBUS: polynomial 0xA001 (reflected 0x8005), initial 0xFFFF,
    sent low byte first. The specification's worked example: the CRC of
    02 07 is 0x1241, sent as 41 12.

TCP (Modbus Messaging on TCP/IP Implementation Guide v1.0b, §3.1.3)::

    | transaction id (2) | protocol id (2) = 0 | length (2) | unit id (1) | PDU |

    length counts the unit id and the PDU; all fields big-endian.

An RTU frame ends with 3.5 character times of silence. The served link
(:class:`~servobench.sim_backend.servers.pty_link.PtyLink`) delivers each
frame whole after that silence, so a read normally holds one frame; when it
holds more (frames queued while the drive was busy), :func:`split_rtu`
separates them by the request lengths the function codes define.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

#: Smallest RTU frame: address, function code, CRC.
RTU_MIN_BYTES = 4
#: Largest RTU frame (Serial Line v1.02 §2.5.1.1): 256 bytes.
RTU_MAX_BYTES = 256
#: MBAP header length [bytes], unit id included.
MBAP_BYTES = 7
#: Largest PDU (Application Protocol v1.1b3 §4.1) [bytes].
MAX_PDU_BYTES = 253


def crc16(data: bytes) -> int:
    """CRC-16/MODBUS of ``data`` (Serial Line v1.02 Appendix B): ``crc16(b"\\x02\\x07") == 0x1241``."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


def rtu_frame(address: int, pdu: bytes) -> bytes:
    """``address`` + ``pdu`` + CRC (low byte first)."""
    body = bytes([address]) + pdu
    return body + struct.pack("<H", crc16(body))


def rtu_crc_ok(frame: bytes) -> bool:
    """True when the last two bytes of ``frame`` are the CRC of the rest."""
    return len(frame) >= RTU_MIN_BYTES and struct.unpack("<H", frame[-2:])[0] == crc16(frame[:-2])


def request_length(frame: bytes) -> int | None:
    """Length [bytes] of the RTU request starting ``frame``, by its function code.

    ``None`` when the function code does not define it (an unknown function)
    or not enough bytes have arrived to tell.
    """
    if len(frame) < 2:
        return None
    fc = frame[1]
    if fc in (1, 2, 3, 4, 5, 6, 8):
        return 8
    if fc in (0x07, 0x0B, 0x0C, 0x11):
        return 4
    if fc in (0x0F, 0x10):
        return 9 + frame[6] if len(frame) > 6 else None
    if fc == 0x17:
        return 13 + frame[10] if len(frame) > 10 else None
    if fc == 0x2B:
        return 7
    return None


def split_rtu(chunk: bytes) -> list[bytes]:
    """The frames of one burst of bytes (see the module doc).

    A frame is cut at the length its function code defines when the CRC
    closes there; otherwise the whole rest of the burst is one frame (an
    unknown function, or a garbled frame the receiver will discard).
    """
    frames: list[bytes] = []
    rest = chunk
    while rest:
        n = request_length(rest)
        if n is not None and n < len(rest) and rtu_crc_ok(rest[:n]):
            frames.append(rest[:n])
            rest = rest[n:]
        else:
            frames.append(rest)
            break
    return frames


@dataclass(frozen=True)
class TcpFrame:
    """One Modbus TCP request or response: MBAP fields and the PDU."""

    transaction: int
    protocol: int
    unit: int
    pdu: bytes

    def encode(self) -> bytes:
        return (
            struct.pack(">HHHB", self.transaction, self.protocol, len(self.pdu) + 1, self.unit)
            + self.pdu
        )


def tcp_frame_length(header: bytes) -> int | None:
    """Total length [bytes] of the TCP frame whose first 6+ bytes are ``header``; None if too few."""
    if len(header) < 6:
        return None
    return 6 + struct.unpack(">H", header[4:6])[0]


def decode_tcp(frame: bytes) -> TcpFrame:
    """Split a whole TCP frame (length from :func:`tcp_frame_length`) into its fields."""
    transaction, protocol, _, unit = struct.unpack(">HHHB", frame[:MBAP_BYTES])
    return TcpFrame(transaction, protocol, unit, frame[MBAP_BYTES:])
