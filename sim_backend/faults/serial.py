"""Serial wire faults of the served drive (``serve-sim --transport serial``).

The served dialect (:mod:`servobench.sim_backend.servers.serial.serve_serial`) clocks the drive for
each feedback query, formats the reply and hands it to
:meth:`SerialFaultHook.reply`, which returns what goes on the wire and when:

``drop``        nothing
``delay``       the reply, ``MS`` ms late
``dup``         the reply twice, in one write
``garble``      one byte in the middle of the reply XOR 0x5A (a digit becomes a letter)
``truncate``    the first half of the reply, then the line end
``interleave``  the first half of the reply, an unsolicited line of the drive's
                own, then the rest: the host reads a mixed line, then half a reply
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from servobench.sim_backend.faults.spec import FaultSpec

#: Unsolicited text interleaved into a reply (what a drive's debug print might say).
STRAY_LINE = b"warning: encoder check"


@dataclass(frozen=True)
class Reply:
    """Bytes to write, ``delay_s`` after the reply was ready."""

    data: bytes
    delay_s: float = 0.0


class SerialFaultHook:
    """The serial-side half of the fault injector (stateless)."""

    def reply(self, wire: Sequence[FaultSpec], raw: bytes, terminator: bytes) -> Reply:
        """What goes on the wire for the reply ``raw`` (terminator included) under ``wire``."""
        body = raw[: len(raw) - len(terminator)] if raw.endswith(terminator) else raw
        out = Reply(raw)
        for spec in wire:
            if spec.kind == "drop":
                return Reply(b"")
            if spec.kind == "delay":
                out = Reply(out.data, (spec.arg or 0) / 1000.0)
            elif spec.kind == "dup":
                out = Reply(raw * 2, out.delay_s)
            elif spec.kind == "garble":
                mangled = bytearray(body)
                if mangled:
                    mangled[len(mangled) // 2] ^= 0x5A
                out = Reply(bytes(mangled) + terminator, out.delay_s)
            elif spec.kind == "truncate":
                out = Reply(body[: len(body) // 2] + terminator, out.delay_s)
            elif spec.kind == "interleave":
                half = len(body) // 2
                mixed = body[:half] + STRAY_LINE + terminator + body[half:] + terminator
                out = Reply(mixed, out.delay_s)
        return out
