"""Modbus wire faults of the served drive (``serve-sim --transport modbus-tcp|modbus-rtu``).

The register bridge of :mod:`servobench.sim_backend.servers.serve_modbus` calls
:meth:`ModbusFaultHook.before_clock` on every clocking read (a read that
covers the velocity register, FC3/FC4 or the read half of FC23), after
:meth:`~servobench.sim_backend.faults.injector.FaultInjector.next_cycle`:

``exception``  answered with exception code ``C``; the drive is not clocked
``timeout``    not answered at all (pymodbus drops the request); not clocked
``delay``      the answer leaves ``MS`` ms late (the server awaits; it is clocked)
``crc``        clocked and answered, but the RTU link flips a bit of the
               answer's CRC on its way to the host
               (:meth:`servobench.sim_backend.servers.pty_link.PtyLink.tamper_next`)
"""

from __future__ import annotations

import asyncio
from collections.abc import Sequence

from pymodbus.constants import ExcCodes
from pymodbus.exceptions import NoSuchIdException

from servobench.sim_backend.faults.spec import FaultSpec
from servobench.sim_backend.servers.pty_link import PtyLink


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

    async def before_clock(self, wire: Sequence[FaultSpec]) -> ExcCodes | None:
        """Carry out the wire faults of this cycle; an exception code refuses the request.

        Raises
        ------
        NoSuchIdException
            For ``timeout``: pymodbus (``ignore_missing_devices``) then sends nothing.
        """
        for spec in wire:
            if spec.kind == "exception":
                return ExcCodes(int(spec.arg or 4))
            if spec.kind == "timeout":
                raise NoSuchIdException(f"--fault {spec}")
            if spec.kind == "delay":
                await asyncio.sleep((spec.arg or 0) / 1000.0)
            elif spec.kind == "crc" and self.link is not None:
                self.link.tamper_next(corrupt_crc)
        return None
