"""CAN wire faults of the served CiA 402 drive (``serve-sim --transport canopen``).

At each SYNC the served drive (:mod:`servobench.sim_backend.servers.canopen.drive`) builds its TPDO
frames and asks :meth:`CanFaultHook.transmissions` what actually goes on the
bus:

``drop``    nothing (the drive was clocked; its answer is lost)
``dup``     the TPDOs twice, back to back
``delay``   the TPDOs ``MS`` ms later, from a timer thread
``emcy``    an EMCY frame, then the TPDOs (the drive stays enabled)
``busoff``  nothing, and the drive's controller goes bus-off for ``MS`` ms:
            :meth:`CanFaultHook.muted` is true, and the network classes of
            :mod:`servobench.sim_backend.servers.canopen.serve_canopen` drop every frame in and out
            (SDO answers, heartbeats and EMCYs included). The drive reacts as
            its abort connection option 0x6007 says (1: fault 0x8140) and
            sends the EMCY once :meth:`CanFaultHook.poll` sees it recovered.
"""

from __future__ import annotations

import struct
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from servobench.sim_backend.faults.injector import FaultInjector
from servobench.sim_backend.faults.spec import FaultSpec

#: CiA 301 EMCY error code "recovered from bus off".
BUSOFF_FAULT = 0x8140
#: Error register sent with an injected warning EMCY (bit 0: generic error).
WARNING_REGISTER = 0x01

Frames = list[tuple[int, bytes]]


@dataclass(frozen=True)
class Transmission:
    """Frames to put on the bus, ``delay_s`` after the SYNC."""

    frames: tuple[tuple[int, bytes], ...]
    delay_s: float = 0.0


def emcy_frame(node_id: int, code: int, register: int) -> tuple[int, bytes]:
    """The EMCY frame of ``node_id``: error code (LE), error register, 5 bytes of zeros."""
    return 0x80 + node_id, struct.pack("<HB5x", code, register)


class CanFaultHook:
    """The CAN-side half of the fault injector for one served node.

    Parameters
    ----------
    injector : FaultInjector
        Counts SYNCs and applies the drive's own faults.
    clock : callable
        Monotonic clock [s] for bus-off timing.
    """

    def __init__(
        self, injector: FaultInjector, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.injector = injector
        self._clock = clock
        self._muted_until = 0.0
        self._busoff_pending = False
        self._timers: list[threading.Timer] = []

    def muted(self) -> bool:
        """True while the controller is bus-off: nothing goes in or out."""
        return self._clock() < self._muted_until

    def bus_off(self, spec: FaultSpec) -> None:
        """Go bus-off for the spec's ``MS`` milliseconds, from now."""
        self._muted_until = self._clock() + (spec.arg or 0) / 1000.0
        self._busoff_pending = True

    def recovered(self) -> bool:
        """True once, the first time it is asked after a bus-off has ended."""
        if self._busoff_pending and not self.muted():
            self._busoff_pending = False
            return True
        return False

    def transmissions(
        self, wire: Sequence[FaultSpec], frames: Frames, node_id: int
    ) -> list[Transmission]:
        """What goes on the bus for this SYNC's TPDOs ``frames`` under the wire faults ``wire``."""
        out = [Transmission(tuple(frames))]
        for spec in wire:
            if spec.kind in ("drop", "busoff"):
                return []
            if spec.kind == "dup":
                out = [Transmission(tuple(frames) * 2)]
            elif spec.kind == "delay":
                out = [Transmission(tuple(frames), (spec.arg or 0) / 1000.0)]
            elif spec.kind == "emcy":
                emcy = emcy_frame(node_id, int(spec.arg or 0), WARNING_REGISTER)
                out = [Transmission((emcy, *frames))]
        return out

    def send_later(self, delay_s: float, send: Callable[[], None]) -> None:
        """Run ``send`` after ``delay_s`` from a timer thread (a late answer)."""
        timer = threading.Timer(delay_s, send)
        timer.daemon = True
        self._timers = [t for t in self._timers if t.is_alive()]
        self._timers.append(timer)
        timer.start()

    def close(self) -> None:
        """Cancel answers not sent yet."""
        for timer in self._timers:
            timer.cancel()
        self._timers = []
