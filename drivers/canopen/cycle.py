"""One ``canopen://`` control cycle: RPDOs and a SYNC out, the SYNC's TPDOs in, scaled.

:class:`CycleIO` keeps what the RPDOs carry (controlword, target torque,
torque offset, target position), sends them with the SYNC, waits for the
TPDOs of that SYNC and turns them into a :class:`~servobench.drivers.base.Feedback`
in the drive's SI units. It also keeps the drive clock: the time stamp
0x1013 of each TPDO pair when the layout maps it (unwrapped across its 32-bit
roll-over), else the SYNC count times the cycle period. A pair that began
to arrive before this cycle's SYNC went out (a duplicate, or a late answer
to an earlier SYNC) is dropped. A pair that answers this SYNC with the stamp
of the pair before is a repeated sample: a drive whose control tick is
slower than the SYNC latched nothing new since (it is kept, and the log's
trailer counts it); without 0x1013 repeats cannot be told.

The host instant of each sample (``Feedback.t_host_s``, ``t_unc_s``): the
midpoint and half-width of SYNC out (host clock just before the write) to
the TPDO pair in (host clock in the receive thread). On SocketCAN in a
real-time run (:meth:`CycleIO.start_kernel_sync`) the kernel's broadcast
manager sends the SYNC every period on its own timer and the host sends
only RPDOs: the TPDO pair's kernel receive stamp names the SYNC it answers
(:func:`sync_index`), whose instant is the timer's, uncertain by one CAN
frame (a frame already on the bus delays the SYNC). An RPDO sent later than
the synchronous window after the previous SYNC (:data:`SYNC_WINDOW_SHARE`
of the period, where the drive's 0x1007 is not known) reaches the drive
after its SYNC and is counted late; SYNC slots without an answer taken are
counted missed (:attr:`CycleIO.counts`).
"""

from __future__ import annotations

import math
import struct
import threading
import time
from dataclasses import dataclass, replace

import can

from servobench.drivers.base import Feedback
from servobench.drivers.canopen.link import CounterUnwrap, HeartbeatProducer, TappedNetwork
from servobench.drivers.canopen.mapping import Layout
from servobench.drivers.canopen.options import CanopenOptions
from servobench.drivers.canopen.sdo import SdoAccess
from servobench.drivers.cia402_units import Scaling
from servobench.errors import DriveTimeoutError

#: Cycle period assumed for the SYNC-count clock until the host or 0x1006 tells one [s].
DEFAULT_CYCLE_S = 1e-3
#: After the TPDO wait timed out, this much more [s] for the receiving thread to hand over what
#: is already in the socket: a host stopped past the deadline (a hypervisor's pause, a loaded
#: machine) wakes both threads at once, and the waiting one may look before the receiver has run.
#: The drive answered every SYNC meanwhile; without it, a host stopped 30-150 ms (SIGSTOP) now and
#: then stopped a served CANopen run with "no TPDO within 100 ms" though the TPDOs were there.
RX_GRACE_S = 0.02
#: Share of the period after a SYNC within which RPDOs must leave (the synchronous window).
SYNC_WINDOW_SHARE = 0.5
#: Bits of the longest CAN frame with stuffing (8 data bytes, 11-bit id).
MAX_FRAME_BITS = 135


def sync_index(rx_wall_s: float, first_sync_wall_s: float, period_s: float) -> int:
    """Which kernel-timed SYNC a TPDO received at ``rx_wall_s`` answers [-].

    The SYNCs leave at ``first_sync_wall_s + k period_s``; the drive answers
    within the period, so the answer's SYNC is the last one before it.
    """
    return int(math.floor((rx_wall_s - first_sync_wall_s) / period_s))


@dataclass(frozen=True)
class Cycle:
    """What one SYNC brought back: the statusword and the scaled feedback."""

    statusword: int
    feedback: Feedback


def _wrap_i32(value: int) -> int:
    return (value + 2**31) % 2**32 - 2**31


class CycleIO:
    """The cyclic frames of one node (see the module docstring).

    ``layout``, ``scaling`` and ``max_lsb`` are set by the bring-up before the
    first cycle; ``heartbeat`` once the watchdog is armed.
    """

    def __init__(self, options: CanopenOptions, network: TappedNetwork, sdo: SdoAccess) -> None:
        self.options, self.network, self.sdo = options, network, sdo
        self.layout: Layout | None = None
        self.scaling: Scaling | None = None
        self.max_lsb = 0x7FFF  #: largest |0x6071| / |0x60B2| sent (0x6072, else INTEGER16)
        self.heartbeat: HeartbeatProducer | None = None
        self.values = {0x6040: 0, 0x6071: 0, 0x60B2: 0, 0x607A: 0}  #: RPDO contents
        self.emcy: tuple[int, int] | None = None  #: (error code, error register) pending
        self.period_s: float | None = None  #: cycle period for the SYNC-count clock [s]
        self._rx1: bytes | None = None
        self._rx2: bytes | None = None
        self._rx_event = threading.Event()
        self._last_stamp: int | None = None  # 0x1013 of the last TPDO pair consumed
        self._sent_s = -math.inf  # host clock when this cycle's SYNC went out
        self._rx1_s = math.inf  # host clock when the last TPDO1 came in
        self._position, self._clock = CounterUnwrap(32), CounterUnwrap(32)
        self._sync_time_s = 0.0  # SYNC count x cycle period, when the drive has no 0x1013
        self._rx_host_s = math.nan  # host clock when the last TPDO pair was complete
        self._rx_wall_s = math.nan  # its receive stamp (python-can: time.time() base)
        self._kernel: can.ModifiableCyclicTaskABC | can.CyclicSendTaskABC | None = None
        self._sync0_wall_s = 0.0  # first kernel SYNC (time.time() base)
        self._wall_minus_host_s = 0.0
        self._last_index = -1
        self.counts = {"late_rpdos": 0, "missed_syncs": 0}  #: kernel-timed cycle faults

    # -------------------------------------------------------- kernel SYNC
    @property
    def kernel_sync(self) -> bool:
        """True while the kernel's broadcast manager sends the SYNC."""
        return self._kernel is not None

    def start_kernel_sync(self, period_s: float) -> None:
        """The SYNC every ``period_s`` from the kernel (python-can ``send_periodic``, the
        broadcast manager on SocketCAN); from now on :meth:`cycle` sends RPDOs only."""
        msg = can.Message(arbitration_id=self.options.sync_cob, data=b"", is_extended_id=False)
        self.period_s = period_s
        self._wall_minus_host_s = time.time() - time.monotonic()
        self._sync0_wall_s = time.time()
        self._kernel = self.network.bus.send_periodic(msg, period_s)
        self._last_index = -1
        self.counts = {"late_rpdos": 0, "missed_syncs": 0}

    def stop_kernel_sync(self) -> None:
        task, self._kernel = self._kernel, None
        if task is not None:
            task.stop()

    # ------------------------------------------------------------- commands
    def _lsb(self, u: float) -> int:
        return max(-self.max_lsb, min(self.max_lsb, round(u / self.scaling.u.scale)))

    def representable(self, u: float) -> float:
        """``u`` rounded to the torque object's resolution [command units]."""
        return self._lsb(u) * self.scaling.u.scale

    def set_torque(self, u: float, holding: bool) -> None:
        """The host's command: target torque 0x6071, or the torque offset 0x60B2 in a hold."""
        raw = self._lsb(u)
        self.values[0x6071], self.values[0x60B2] = (0, raw) if holding else (raw, 0)

    def set_target(self, x_ref: float) -> None:
        """Target position 0x607A = ``x_ref`` [position units], by SDO now and by RPDO each cycle."""
        raw = _wrap_i32(round(x_ref / self.scaling.x.scale))
        self.values[0x607A] = raw
        self.sdo.write(0x607A, 0, raw)

    def _frames(self, holding: bool, sync: bool) -> list[tuple[int, bytes]]:
        pdos = self.layout.rpdos if holding else (self.layout.rpdo_command,)
        frames = [(p.cob_id, p.pack(self.values)) for p in pdos]
        return frames + [(self.options.sync_cob, b"")] if sync else frames

    def send_rpdos(self, holding: bool) -> None:
        """The RPDOs alone, without a SYNC (the drive is not clocked)."""
        with self.sdo.translated("RPDO"):
            self.network.send_messages(self._frames(holding, sync=False))

    # ---------------------------------------------------------------- cycle
    def cycle(self, holding: bool) -> Cycle:
        """RPDOs + SYNC, then this SYNC's TPDOs, decoded and scaled."""
        if self.heartbeat is not None:
            self.heartbeat.check()
        n, timeout_s = self.options.node_id, self.options.pdo_timeout_s
        self._rx1 = self._rx2 = None
        self._rx_event.clear()
        t_sync = self._sync_time_s
        self._sync_time_s += self.period_s or DEFAULT_CYCLE_S
        sent = self._sent_s = time.monotonic()
        with self.sdo.translated("RPDO + SYNC"):
            self.network.send_messages(self._frames(holding, sync=not self.kernel_sync))
        if not self._rx_event.wait(timeout_s) and not self._rx_event.wait(RX_GRACE_S):
            raise DriveTimeoutError(
                f"no TPDO from node {n} within {timeout_s * 1e3:.0f} ms of SYNC"
            )
        if self.kernel_sync:
            t_host, t_unc, t_sync = self._kernel_instant(sent)
        else:
            t_host, t_unc = 0.5 * (sent + self._rx_host_s), 0.5 * (self._rx_host_s - sent)
        rx1, rx2 = self._rx1, self._rx2
        state = None if rx1 is None else self.layout.tpdo_state.unpack(rx1)
        motion = None if rx2 is None else self.layout.tpdo_motion.unpack(rx2)
        if state is None or motion is None:
            raise DriveTimeoutError(
                f"incomplete TPDOs from node {n} at this SYNC: {rx1!r}, {rx2!r}"
            )
        if self.layout.has_clock:
            self._last_stamp = state[0x1013]
            t_s = self._clock(state[0x1013]) * 1e-6
        else:
            t_s = t_sync
        feedback = self._feedback(t_s, motion[0x606C], motion[0x6064], state.get(0x6077))
        return Cycle(state[0x6041], replace(feedback, t_host_s=t_host, t_unc_s=t_unc))

    def _kernel_instant(self, sent_host_s: float) -> tuple[float, float, float]:
        """Host instant, uncertainty and SYNC-count time of the kernel SYNC the pair answers;
        counts a late RPDO and skipped SYNC slots."""
        period = self.period_s or DEFAULT_CYCLE_S
        k = sync_index(self._rx_wall_s, self._sync0_wall_s, period)
        sync_wall = self._sync0_wall_s + k * period
        sent_wall = sent_host_s + self._wall_minus_host_s
        if sent_wall - (sync_wall - period) > SYNC_WINDOW_SHARE * period:
            self.counts["late_rpdos"] += 1
        if self._last_index >= 0 and k > self._last_index + 1:
            self.counts["missed_syncs"] += k - self._last_index - 1
        self._last_index = k
        frame_s = MAX_FRAME_BITS / self.options.bitrate
        return sync_wall - self._wall_minus_host_s, frame_s, k * period

    def _feedback(self, t_s: float, velocity: int, position: int, torque: int | None) -> Feedback:
        s = self.scaling
        applied = math.nan if torque is None else torque * s.u.scale
        x = self._position(position) * s.x.scale
        return Feedback(t_s, velocity * s.v.scale, x, applied=applied)

    def read_feedback(self) -> Feedback:
        """One sample over SDO (no SYNC: the drive is not clocked)."""
        if self.layout.has_clock:
            t_s = self._clock(self.sdo.read(0x1013)) * 1e-6
        else:
            t_s = self._sync_time_s
        torque = self.sdo.read(0x6077) if self.layout.has_torque_actual else None
        return self._feedback(t_s, self.sdo.read(0x606C), self.sdo.read(0x6064), torque)

    # ------------------------------------------------------------ reception
    def on_tpdo1(self, can_id: int, data: bytearray, timestamp: float) -> None:
        self._rx1 = bytes(data)
        self._rx1_s = time.monotonic()

    def on_tpdo2(self, can_id: int, data: bytearray, timestamp: float) -> None:
        rx1, layout = self._rx1, self.layout
        if rx1 is not None and layout is not None and layout.has_clock:
            state = layout.tpdo_state.unpack(rx1)
            if state is not None and state[0x1013] == self._last_stamp and self._rx1_s < self._sent_s:
                self._rx1 = None  # a duplicate or a late pair of a SYNC already answered
                return
        self._rx2 = bytes(data)
        self._rx_host_s, self._rx_wall_s = time.monotonic(), timestamp
        self._rx_event.set()

    def on_emcy(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if len(data) >= 3:
            code, register = struct.unpack_from("<HB", data)
            if code:  # 0x0000 is "error reset / no error"
                self.emcy = (code, register)
