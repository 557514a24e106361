"""Physical cycle limits of the bench links: how fast one control cycle can be on the wire.

Pure arithmetic, quoted beside the measured rates by ``transport_rate.py``.
"""

from __future__ import annotations

from collections.abc import Sequence

#: CAN 2.0A frame without data: SOF, 11-bit id, RTR, IDE, r0, DLC, CRC(15)+del, ACK(2), EOF(7), IFS(3) [bits].
CAN_FRAME_OVERHEAD_BITS = 47
#: Bits exposed to stuffing in a base frame with no data (SOF to CRC) [bits].
CAN_STUFFED_OVERHEAD_BITS = 34
#: Modbus RTU inter-frame silence above 19200 baud [s].
RTU_T35_FAST_S = 1.75e-3
#: Ethernet + IPv4 + TCP framing around a Modbus TCP ADU: preamble 8, header 14, FCS 4, IFG 12, IP 20, TCP 20 [bytes].
TCP_FRAMING_BYTES = 8 + 14 + 4 + 12 + 20 + 20
#: Smallest Ethernet frame (header to FCS) [bytes].
ETH_MIN_FRAME_BYTES = 64


def can_frame_bits(data_bytes: int, worst_case_stuffing: bool = False) -> int:
    """Bits of one CAN 2.0A data frame with ``data_bytes`` of data (with the worst-case stuff bits)."""
    bits = CAN_FRAME_OVERHEAD_BITS + 8 * data_bytes
    if worst_case_stuffing:
        bits += (CAN_STUFFED_OVERHEAD_BITS + 8 * data_bytes - 1) // 4
    return bits


def canopen_cycle_s(frame_bytes: Sequence[int], bitrate: float = 1e6) -> tuple[float, float]:
    """Best and worst wire time [s] of one cycle made of frames with these data lengths."""
    best = sum(can_frame_bits(n) for n in frame_bytes) / bitrate
    worst = sum(can_frame_bits(n, True) for n in frame_bytes) / bitrate
    return best, worst


def rtu_gap_s(baud: int) -> float:
    """Modbus RTU t3.5 [s]: 3.5 characters of 11 bits, or 1.75 ms above 19200 baud."""
    return RTU_T35_FAST_S if baud > 19200 else 3.5 * 11 / baud


def modbus_rtu_cycle_s(
    frame_bytes: Sequence[int], baud: int = 115200, bits_per_char: int = 10
) -> float:
    """Wire time [s] of RTU frames (address + PDU + CRC bytes each), a t3.5 after each."""
    return sum(frame_bytes) * bits_per_char / baud + len(frame_bytes) * rtu_gap_s(baud)


def modbus_rtu_frames(write_registers: int, read_registers: int, fc23: bool) -> list[int]:
    """RTU frame sizes [bytes] of one cycle: FC23, or FC06/FC16 write then FC03 read."""
    w, r = write_registers, read_registers
    if fc23:
        return [13 + 2 * w, 5 + 2 * r]
    write = [8, 8] if w == 1 else [9 + 2 * w, 8]
    return [*write, 8, 5 + 2 * r]


def modbus_tcp_cycle_s(adu_bytes: Sequence[int], bitrate: float = 100e6) -> float:
    """Wire time [s] of Modbus TCP ADUs (MBAP + PDU) on Ethernet at ``bitrate`` [bit/s]."""
    total = 0
    for adu in adu_bytes:
        frame = max(ETH_MIN_FRAME_BYTES, 14 + 20 + 20 + adu + 4)
        total += frame + 8 + 12  # + preamble/SFD and inter-frame gap
    return total * 8 / bitrate


def uart_cycle_s(bytes_per_cycle: float, baud: int = 115200, bits_per_char: int = 10) -> float:
    """Wire time [s] of a line-based ASCII exchange on a UART (8N1: 10 bits per byte)."""
    return bytes_per_cycle * bits_per_char / baud
