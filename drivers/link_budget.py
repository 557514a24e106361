"""Physical cycle limits of the bench links: how fast one control cycle can be on the wire.

Pure arithmetic. The drivers build :meth:`~servobench.drivers.base.Drive.max_rate_hz`
from it (:func:`modbus_max_rate_hz`, :func:`ascii_max_rate_hz`), the commands
pick their default sample rate from that (:func:`default_rate_hz`), and
``benchmarks/transport_rate.py`` quotes it beside the measured rates.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

from servobench.errors import UsageError

if TYPE_CHECKING:
    from servobench.drivers.base import Drive

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
#: RTU framing around a PDU (address + CRC) and TCP framing (MBAP header) [bytes].
RTU_FRAMING_BYTES, MBAP_BYTES = 3, 7
#: Share of the link's limit a default sample rate may use: the rest absorbs the
#: host's and the drive's turnaround and the jitter of a shared machine.
DEFAULT_RATE_MARGIN = 0.8
#: Mantissas of the sample rates :func:`default_rate_hz` picks from (1, 2, 2.5, 5 x 10^k Hz).
NICE_RATES = (1.0, 2.0, 2.5, 5.0)


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


def rtu_to_tcp_adu(rtu_frame_bytes: int) -> int:
    """Bytes of the Modbus TCP ADU carrying the PDU of an RTU frame of ``rtu_frame_bytes``."""
    return rtu_frame_bytes - RTU_FRAMING_BYTES + MBAP_BYTES


def modbus_max_rate_hz(
    transactions: Sequence[tuple[int, int]],
    *,
    rtu: bool,
    baud: int = 115200,
    bits_per_char: int = 10,
    turnaround_s: float = 0.0,
    ethernet_bitrate: float = 100e6,
) -> float:
    """Highest cycle rate [Hz] of a cycle made of Modbus ``transactions``.

    Parameters
    ----------
    transactions : sequence of (request, response)
        RTU frame sizes [bytes] of each transaction of one cycle
        (:func:`modbus_rtu_frames` gives those of the command and feedback).
    rtu : bool
        RTU line at ``baud`` (a t3.5 after each frame), else TCP on Ethernet.
    turnaround_s : float
        The drive's time from a request to its answer, per transaction [s].
    """
    frames = [n for pair in transactions for n in pair]
    if rtu:
        wire_s = modbus_rtu_cycle_s(frames, baud, bits_per_char)
    else:
        wire_s = modbus_tcp_cycle_s([rtu_to_tcp_adu(n) for n in frames], ethernet_bitrate)
    cycle_s = wire_s + len(transactions) * turnaround_s
    return 1.0 / cycle_s if cycle_s > 0 else math.inf


def ascii_max_rate_hz(
    cycle_bytes: int,
    baud: int = 115200,
    *,
    bits_per_char: int = 10,
    poll_bytes: int = 0,
    poll_s: float = 0.0,
    turnaround_s: float = 0.0,
) -> float:
    """Highest exchange rate [Hz] of a line protocol on a UART.

    ``cycle_bytes`` [bytes] go over the line every cycle (request and reply:
    one lock-step exchange waits for both), ``poll_bytes`` more every
    ``poll_s`` [s] (a fault poll), and the drive takes ``turnaround_s`` [s]
    to answer.
    """
    char_s = bits_per_char / baud
    busy = poll_bytes * char_s / poll_s if poll_s > 0 else 0.0
    return max(0.0, 1.0 - busy) / (cycle_bytes * char_s + turnaround_s)


def default_rate_hz(
    max_rate_hz: float, ceiling_hz: float, margin: float = DEFAULT_RATE_MARGIN
) -> float:
    """The sample rate [Hz] to use when none is given: ``ceiling_hz`` when the link carries it
    with ``margin`` to spare, else the largest 1, 2, 2.5 or 5 x 10^k Hz within ``margin * max_rate_hz``.

    >>> default_rate_hz(147.0, 1000.0), default_rate_hz(353.0, 1000.0), default_rate_hz(1e5, 1000.0)
    (100.0, 250.0, 1000.0)
    """
    budget = margin * max_rate_hz
    if budget >= ceiling_hz:
        return float(ceiling_hz)
    if not budget >= 1.0:
        raise ValueError(f"the link carries {max_rate_hz:.3g} Hz: too slow for a cycle rate")
    decade = 10.0 ** math.floor(math.log10(budget))
    return max(m * decade for m in NICE_RATES if m * decade <= budget)


def sample_rate_hz(
    requested_hz: float | None,
    max_rate_hz: float,
    ceiling_hz: float,
    link: str = "the link",
    option: str = "--fs",
) -> float:
    """The cycle rate to stream at [Hz]: ``requested_hz`` when the link carries it, else refused.

    With ``requested_hz`` None, :func:`default_rate_hz` of the link's limit
    (at most ``ceiling_hz``). ``link`` names the link in the refusal, ``option``
    where the rate was asked for (``--fs``, ``[bump] fs_hz``).

    Raises
    ------
    UsageError
        ``requested_hz`` beyond ``max_rate_hz``, naming the achievable rate.
    """
    if requested_hz is None:
        try:
            return default_rate_hz(max_rate_hz, ceiling_hz)
        except ValueError as err:
            raise UsageError(f"{link}: {err}") from None
    if requested_hz > max_rate_hz:
        suggestion = default_rate_hz(max_rate_hz, ceiling_hz) if max_rate_hz >= 1.25 else 1.0
        raise UsageError(
            f"{option} {requested_hz:g} Hz is beyond {link}: it carries at most {max_rate_hz:.0f} "
            f"cycles/s; use {option} {suggestion:g} (the default there) or less"
        )
    return float(requested_hz)


def drive_rate_hz(
    requested_hz: float | None, drive: Drive, ceiling_hz: float, option: str = "--fs"
) -> float:
    """:func:`sample_rate_hz` on ``drive``'s link (:meth:`Drive.max_rate_hz`, named by its URL scheme)."""
    link = f"the {drive.url.scheme}:// link"
    return sample_rate_hz(requested_hz, drive.max_rate_hz(), ceiling_hz, link, option)


def lowered_rate_note(requested_hz: float | None, chosen_hz: float, drive: Drive, ceiling_hz: float) -> str:
    """One line for the terminal when the default cycle rate was lowered to fit ``drive``'s link
    (``""`` when the rate was asked for or is the default): the rate, the link's limit and why."""
    if requested_hz is not None or chosen_hz >= ceiling_hz:
        return ""
    why = drive.rate_limit_reason()
    return (
        f"cycle rate lowered to {chosen_hz:g} Hz (default {ceiling_hz:g} Hz): the {drive.url.scheme}:// "
        f"link carries {drive.max_rate_hz():.0f} Hz" + (f" ({why})" if why else "")
        + "; give --fs to choose"
    )
