"""PDOs and the SYNC of the served CiA 402 drive.

canopen's :class:`~canopen.LocalNode` stores PDO parameters but neither sends
TPDOs nor applies received RPDOs. :class:`SyncEngine` compiles the maps the
host wrote (:mod:`servobench.sim_backend.servers.canopen.pdo`) when the node enters
OPERATIONAL or a PDO parameter changed, writes received RPDO payloads into
the object dictionary (controlword, target torque, torque offset, target
position -> the drive's callbacks), and on each SYNC:

1. counts the cycle with the fault injector (drive faults applied);
2. in cyclic synchronous position, runs the drive's position loop on the
   feedback sampled at this SYNC and latches its torque;
3. clocks the device once (``injector.step()``: feedback sampled at the SYNC,
   then the latched command held for one cycle; a ``clock="real"`` device
   samples the axis as it stands in wall-clock time when the SYNC is handled);
4. packs the synchronous TPDOs from that sample, 0x6077 being the command
   that acted over the cycle before this SYNC, and hands them to the CAN
   fault hook, which sends, drops, repeats or delays them.

A ``clock="real"`` drive handles each SYNC at one instant
(:meth:`~servobench.sim_backend.device.SimulatedDevice.instant`), and the
torque a synchronous RPDO (transmission type 0-240) carries takes force at
the next SYNC, as CiA 301 has synchronous RPDOs actuated at the SYNC: so the
command latched and the feedback sampled belong to the same instant, however
late the simulator handles the RPDO before it. (A lock-step drive latches it
on receipt, which is the same for it: it moves only at the SYNC.)
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from servobench.drivers.cia402 import CiA402State
from servobench.sim_backend.device import DeviceSample
from servobench.sim_backend.faults.can import BUSOFF_FAULT
from servobench.sim_backend.servers.canopen import pdo as can_pdo

if TYPE_CHECKING:
    from servobench.sim_backend.servers.canopen.drive import ServedCiA402Drive

#: EMCY: PDO not processed due to length error.
EMCY_PDO_LENGTH = 0x8210
NMT_OPERATIONAL = "OPERATIONAL"
#: SYNC COB-ID when the drive has no 0x1005.
DEFAULT_SYNC_COB = 0x80


class SyncEngine:
    """The served drive's PDO side (see the module docstring)."""

    def __init__(self, drive: ServedCiA402Drive) -> None:
        self.drive = drive
        self.dirty = True  #: PDO parameters changed since the maps were compiled
        self.frozen: DeviceSample | None = None  #: the sample of the SYNC being answered
        self._sync_cob: int | None = None
        self._rpdo_handlers: dict[int, Callable[[int, bytearray, float], None]] = {}
        self._tpdos: list[can_pdo.PdoChannel] = []
        self._sync_count = 0
        self._acted = 0.0  # the command of the cycle that ended at this SYNC
        self._stepped = 0.0  # the command the last SYNC latched for its cycle
        #: True while a synchronous RPDO of a real-time drive is being written into the dictionary.
        self.receiving_sync_rpdo = False
        #: Torque [plant units] a synchronous RPDO carried, taking force at the next SYNC.
        self.pending_command: float | None = None

    def torque_actual(self) -> float:
        """0x6077 [plant units]: at a SYNC the command of the cycle before, else the present one."""
        return self._acted if self.frozen is not None else self.drive.device.command

    def rebuild(self) -> None:
        """Compile the PDO maps and (re)subscribe the RPDOs and the SYNC."""
        drive = self.drive
        if not self.dirty or drive.network is None:
            return
        self.dirty = False
        for cob, handler in self._rpdo_handlers.items():
            drive.network.unsubscribe(cob, handler)
        self._rpdo_handlers = {}
        for channel in can_pdo.read_channels(drive.node, can_pdo.RPDO_COMM, can_pdo.RPDO_MAP):
            handler = self._rpdo_handler(channel)
            self._rpdo_handlers[channel.cob_id] = handler
            drive.network.subscribe(channel.cob_id, handler)
        self._tpdos = can_pdo.read_channels(drive.node, can_pdo.TPDO_COMM, can_pdo.TPDO_MAP)
        sync_cob = DEFAULT_SYNC_COB
        if drive.has(0x1005):
            sync_cob = int.from_bytes(drive.node.get_data(0x1005, 0), "little") & 0x7FF
        if sync_cob != self._sync_cob:
            if self._sync_cob is not None:
                drive.network.unsubscribe(self._sync_cob, self.on_sync)
            self._sync_cob = sync_cob
            drive.network.subscribe(sync_cob, self.on_sync)

    def _rpdo_handler(self, channel: can_pdo.PdoChannel) -> Callable[[int, bytearray, float], None]:
        drive = self.drive

        def on_rpdo(can_id: int, data: bytearray, timestamp: float) -> None:
            with drive.lock:
                if drive.nmt != NMT_OPERATIONAL:
                    return
                if len(data) < channel.length:
                    drive.node.emcy.send(EMCY_PDO_LENGTH, drive.error_register())
                    return
                self.receiving_sync_rpdo = channel.synchronous and drive.device.realtime
                try:
                    for entry, chunk in channel.unpack(data):
                        drive.node.set_data(entry.index, entry.subindex, chunk)
                finally:
                    self.receiving_sync_rpdo = False

        return on_rpdo

    def _clock(self) -> None:
        """Run the drive's loop on this SYNC's feedback (in CSP), then clock the device."""
        drive = self.drive
        injector, device = drive.injector, drive.device
        torque = None
        if drive.mode_is_csp():
            sample = injector.sample()
            torque = drive.csp_torque(sample.position, sample.velocity)
        pending, self.pending_command = self.pending_command, None
        if torque is not None:
            device.set_command(torque)
        elif pending is not None and drive.state is CiA402State.OPERATION_ENABLED:
            device.set_command(pending)  # the synchronous RPDO's torque, from this SYNC on
        self._acted = self._stepped
        self._stepped = device.command  # what acts from this SYNC to the next
        self.frozen = injector.step()

    def on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        drive = self.drive
        with drive.lock, drive.device.instant():
            if drive.nmt != NMT_OPERATIONAL:
                return
            self.rebuild()
            self._sync_count += 1
            wire = drive.injector.next_cycle()  # drive faults (fault, freeze) applied here
            for spec in wire:
                if spec.kind == "busoff":
                    drive.hook.bus_off(spec)
                    if drive.consumer.abort_option == 1:  # abort connection: fault
                        drive.device.fault(BUSOFF_FAULT, f"CAN bus-off (--fault {spec})")
            drive.sync_device()
            self._clock()
            try:
                frames = [
                    (ch.cob_id, ch.pack(drive.node.get_data))
                    for ch in self._tpdos
                    if ch.due(self._sync_count)
                ]
            finally:
                self.frozen = None
            transmissions = drive.hook.transmissions(wire, frames, drive.node.id)
        for tx in transmissions:
            if tx.delay_s > 0:
                drive.hook.send_later(tx.delay_s, lambda f=tx.frames: self.send_frames(f))
            else:
                self.send_frames(tx.frames)

    def send_frames(self, frames) -> None:
        network = self.drive.network
        send_batch = getattr(network, "send_messages", None)
        if send_batch is not None:  # the hub: all TPDOs of this SYNC in one TCP write
            send_batch(list(frames))
            return
        for cob_id, payload in frames:
            network.send_message(cob_id, payload)
