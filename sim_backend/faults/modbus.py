"""Modbus wire faults of the served drive (``serve-sim --transport modbus-tcp|modbus-rtu``).

The register bridge of :mod:`servobench.sim_backend.servers.modbus.pdu` calls
:meth:`ModbusFaultHook.before_clock` on every clocking read (a read that
covers the velocity register, FC3/FC4 or the read half of FC23), after
:meth:`~servobench.sim_backend.faults.injector.FaultInjector.next_cycle`:

``exception``  answered with exception code ``C``; the drive is not clocked
``timeout``    not answered at all (:class:`NoAnswer`: the server sends nothing); not clocked
``delay``      the answer leaves ``MS`` ms late (the server waits; it is clocked)
``crc``        clocked and answered, but the RTU link flips a bit of the
               answer's CRC on its way to the host
               (:meth:`servobench.sim_backend.servers.pty_link.PtyLink.tamper_next`)
"""

from __future__ import annotations

import time
from collections.abc import Sequence

from servobench.sim_backend.faults.spec import FaultSpec
from servobench.sim_backend.servers.pty_link import PtyLink


class NoAnswer(Exception):
    """The served drive sends nothing in answer to this request (an injected ``timeout``)."""


def corrupt_crc(frame: bytes) -> bytes:
    """``frame`` with the low bit of its last byte (the CRC's high byte) flipped."""
    if not frame:
        return frame
    return frame[:-1] + bytes([frame[-1] ^ 0x01])


class ModbusFaultHook:
    """The Modbus-side half of the fault injector.

    Parameters
    ----------
    link : PtyLink or None
        The RTU link the answers travel on (``None`` for TCP).
    """

    def __init__(self, link: PtyLink | None = None) -> None:
        self.link = link

    def before_clock(self, wire: Sequence[FaultSpec]) -> int | None:
        """Carry out the wire faults of this cycle; an exception code refuses the request.

        Raises
        ------
        NoAnswer
            For ``timeout``: the server then sends nothing.
        """
        for spec in wire:
            if spec.kind == "exception":
                return int(spec.arg or 4)
            if spec.kind == "timeout":
                raise NoAnswer(f"--fault {spec}")
            if spec.kind == "delay":
                time.sleep((spec.arg or 0) / 1000.0)
            elif spec.kind == "crc" and self.link is not None:
                self.link.tamper_next(corrupt_crc)
        return None
