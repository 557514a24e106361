"""The simulated drive as a CANopen CiA 402 slave.

:class:`ServedCiA402Drive` puts a :class:`~servobench.sim_backend.device.SimulatedDevice`
behind a :class:`canopen.LocalNode` loaded from the shipped EDS. canopen's
LocalNode answers SDOs; this module adds what it lacks:

* the CiA 402 power state machine, stepped by every controlword (SDO or
  RPDO) with :func:`servobench.drivers.cia402.next_state`, the same tables the host plans
  with, and mirrored onto the device (``enable``, ``disable``,
  ``quick_stop``, ``reset_fault``);
* PDOs: RPDO payloads are written into the object dictionary (controlword,
  target torque -> ``device.set_command``); on each SYNC the device is
  clocked once (``device.step()``: feedback sampled at the SYNC, then the
  latched torque held for one cycle) and the synchronous TPDOs are sent;
* NMT: PDOs and SYNC only in OPERATIONAL; leaving OPERATIONAL while the
  axis is enabled quick-stops it; a heartbeat goes out at once on a change;
* the heartbeat consumer 0x1016: host heartbeats feed the device watchdog,
  set to the consumer time when 0x6007 (abort connection option) is 1,
  so host silence faults the axis with 0x8130 (the sim_backend watchdog
  thread does the tripping); an EMCY goes out on every fault.

Units served: 0x6071/0x6072/0x6077 per-mille of the rated torque, the
device's command unit being one rated torque; 0x6064 in :data:`POS_SCALE`
position units per increment, 0x606C in :data:`VEL_SCALE` velocity units per
LSB; 0x1013 the device clock in µs. The quick stop (0x605A) keeps QUICK STOP
ACTIVE; profile torque ignores torque slopes (the torque steps).

Simplifications: synchronous RPDOs act on receipt (the device latches the
torque for the next SYNC anyway, but a controlword changes the state at
once); event-driven TPDOs (types 254/255) are not produced; SDO is also
answered in NMT STOPPED; 0x6007 takes 0 (no action) or 1 (fault) only.
"""

from __future__ import annotations

import struct
import threading
from collections.abc import Callable

import canopen
from canopen.objectdictionary import ODVariable
from canopen.sdo import SdoAbortedError

from servobench.drivers.cia402 import CiA402State, encode_statusword, next_state
from servobench.sim_backend.device import DeviceSample, PowerState, SimulatedDevice
from servobench.sim_backend.faults.can import BUSOFF_FAULT, CanFaultHook
from servobench.sim_backend.faults.injector import FaultInjector
from servobench.sim_backend.faults.spec import FaultPlan
from servobench.sim_backend.servers import can_pdo

S = CiA402State

#: Position units per increment of 0x6064, and velocity units/s per LSB of 0x606C.
POS_SCALE = 1e-6
VEL_SCALE = 1e-6
#: Modes of operation the simulated drive runs (0x6060 values).
SUPPORTED_MODES = {4: "profile torque", 10: "cyclic synchronous torque"}
#: 0x6007 values the simulated drive implements: 0 no action, 1 fault.
ABORT_OPTIONS = (0, 1)
#: SDO abort: attempt to write a read only object.
ABORT_READ_ONLY = 0x06010002
#: EMCY: PDO not processed due to length error.
EMCY_PDO_LENGTH = 0x8210

NMT_OPERATIONAL = "OPERATIONAL"
NMT_STATE_CODES = {"INITIALISING": 0, "STOPPED": 4, "OPERATIONAL": 5, "PRE-OPERATIONAL": 127}

_I16 = (-(2**15), 2**15 - 1)
_I32 = (-(2**31), 2**31 - 1)


def _clamp(value: float, bounds: tuple[int, int]) -> int:
    return min(max(round(value), bounds[0]), bounds[1])


def _wrap_i32(value: float) -> int:
    return (round(value) + 2**31) % 2**32 - 2**31


class ServedCiA402Drive:
    """A :class:`SimulatedDevice` served as CiA 402 node ``node_id``.

    Parameters
    ----------
    device : SimulatedDevice
        The simulated drive.
    node : canopen.LocalNode
        The node, with the shipped EDS; this class registers its callbacks.
    injector : FaultInjector, optional
        Faults to inject (:mod:`servobench.sim_backend.faults`); SYNCs are its cycles.
    """

    def __init__(
        self,
        device: SimulatedDevice,
        node: canopen.LocalNode,
        injector: FaultInjector | None = None,
    ) -> None:
        self.device = device
        self.node = node
        self.injector = injector or FaultInjector(device, FaultPlan("canopen"))
        self.hook = CanFaultHook(self.injector)
        self._reject_modes = self.injector.plan.setting("reject_mode")
        self._ignore_modes = self.injector.plan.setting("ignore_mode")
        self.network: canopen.Network | None = None
        self._lock = threading.RLock()
        self._state = S.NOT_READY_TO_SWITCH_ON
        self._controlword = 0
        self._mode = 0
        self._nmt = "INITIALISING"
        self._sync_cob: int | None = None
        self._rpdo_handlers: dict[int, Callable[[int, bytearray, float], None]] = {}
        self._tpdos: list[can_pdo.PdoChannel] = []
        self._pdo_dirty = True
        self._sync_count = 0
        self._frozen: DeviceSample | None = None
        self._consumer_cob: int | None = None
        self._consumer_s: float | None = None
        self._abort_option = 1
        self._initial_max_command = device.max_command
        node.add_read_callback(self._on_read)
        node.add_write_callback(self._on_write)

    # --------------------------------------------------------------- lifecycle
    def attach(self, network: canopen.Network) -> None:
        """Join ``network`` (NMT, SYNC, RPDO and heartbeat subscriptions)."""
        self.network = network
        network.add_node(self.node)
        network.subscribe(0, self._on_nmt)  # after the NmtSlave's own handler
        self._load_settings()

    def boot(self) -> None:
        """Power-on: boot-up message, PRE-OPERATIONAL, then SWITCH ON DISABLED (transition 1)."""
        with self._lock:
            if self.device.state is PowerState.FAULT:
                self._enter_fault()
            else:
                self._state = S.SWITCH_ON_DISABLED
            self.node.nmt.send_command(0x81)  # INITIALISING: sends the boot-up message
            self.node.nmt.send_command(0x80)  # PRE-OPERATIONAL, starts the 0x1017 heartbeat
            self._nmt = self.node.nmt.state

    def poll(self) -> None:
        """Periodic housekeeping: notice device faults (watchdog) and send their EMCY."""
        with self._lock:
            self._sync_device()
            if self.hook.recovered() and self._state is S.FAULT:
                self._send_emcy(self.device.fault_code, self._error_register())  # lost in bus-off

    def close(self) -> None:
        self.hook.close()
        self.node.nmt.stop_heartbeat()

    # ------------------------------------------------------------- 402 states
    def _sync_device(self) -> None:
        """Follow what the device did by itself (fault, watchdog, external disable)."""
        dev = self.device.state
        if dev is PowerState.FAULT and self._state is not S.FAULT:
            self._enter_fault()  # transitions 13 and 14 at once
        elif dev is PowerState.DISABLED and self._state in (
            S.OPERATION_ENABLED,
            S.QUICK_STOP_ACTIVE,
        ):
            self._state = S.SWITCH_ON_DISABLED

    def _enter_fault(self) -> None:
        self._state = S.FAULT
        code = self.device.fault_code
        self._send_emcy(code, self._error_register())

    def _error_register(self) -> int:
        if self._state is not S.FAULT:
            return 0
        comm = 0x10 if (self.device.fault_code & 0xFF00) == 0x8100 else 0
        return 0x01 | comm

    def _send_emcy(self, code: int, register: int) -> None:
        if self.network is not None:
            self.node.emcy.send(code, register)

    def _apply_controlword(self, controlword: int) -> None:
        previous, self._controlword = self._controlword, controlword
        self._sync_device()
        target = next_state(self._state, controlword, previous)
        if target is self._state:
            return
        if target is S.OPERATION_ENABLED:
            self.device.enable()
            self.device.set_command(self._torque_command())
        elif target is S.QUICK_STOP_ACTIVE:
            self.device.quick_stop()
        elif self._state is S.FAULT:
            self.device.reset_fault()  # transition 15
            self._send_emcy(0, 0)  # error reset
        else:
            self.device.disable()
        self._state = target

    def _torque_command(self) -> float:
        """Latched target torque [rated torques], 0 outside the torque modes."""
        if self._mode not in SUPPORTED_MODES:
            return 0.0
        permille = struct.unpack("<h", self.node.get_data(0x6071, 0))[0]
        return permille / 1000.0

    # ---------------------------------------------------------- OD callbacks
    def _on_read(self, index: int, subindex: int, od: ODVariable) -> int | None:
        with self._lock:
            if index == 0x6041:
                self._sync_device()
                return encode_statusword(self._state)
            if index == 0x603F:
                self._sync_device()
                return self.device.fault_code if self._state is S.FAULT else 0
            if index == 0x6077:
                return _clamp(self.device.command * 1000.0, _I16)
            if index == 0x6061:
                return self._mode
            if index == 0x1001:
                return self._error_register()
            if index not in (0x6064, 0x606C, 0x1013):
                return None
            # at a SYNC the sample it took, otherwise the present one (no clocking)
            sample = self._frozen or self.injector.sample()
            if index == 0x6064:
                return _wrap_i32(sample.position / POS_SCALE)
            if index == 0x606C:
                return _clamp(sample.velocity / VEL_SCALE, _I32)
            return round(sample.t_s * 1e6) & 0xFFFFFFFF

    def _on_write(self, index: int, subindex: int, od: ODVariable, data: bytes) -> None:
        value = od.decode_raw(data)
        with self._lock:
            if index == 0x6040:
                self._apply_controlword(value)
            elif index == 0x6071:
                if self._state is S.OPERATION_ENABLED and self._mode in SUPPORTED_MODES:
                    self.device.set_command(value / 1000.0)
            elif index == 0x6060:
                self._set_mode(value)
            elif index == 0x6072:
                self.device.max_command = value / 1000.0
            elif index == 0x1006:
                if value > 0:
                    self.device.set_cycle(value * 1e-6)
            elif index == 0x1013:
                raise SdoAbortedError(ABORT_READ_ONLY)  # the clock is the plant's
            elif index == 0x1016:
                self._set_consumer(value)
            elif index == 0x6007:
                if value not in ABORT_OPTIONS:
                    raise SdoAbortedError(can_pdo.ABORT_VALUE_RANGE)
                self._abort_option = value
                self._apply_watchdog()
            elif can_pdo.is_mapping_parameter(index):
                can_pdo.check_mapping_write(self.node, index, subindex, value)
            if can_pdo.is_pdo_parameter(index) or index == 0x1005:
                self._pdo_dirty = True

    def _set_mode(self, mode: int) -> None:
        if mode in self._reject_modes or (mode not in SUPPORTED_MODES and mode != 0):
            raise SdoAbortedError(can_pdo.ABORT_VALUE_RANGE)
        if mode in self._ignore_modes:
            return
        self._mode = mode
        if self._state is S.OPERATION_ENABLED:
            self.device.set_command(self._torque_command())

    def _set_consumer(self, value: int) -> None:
        node_id, time_ms = (value >> 16) & 0x7F, value & 0xFFFF
        if self.network is not None and self._consumer_cob is not None:
            self.network.unsubscribe(self._consumer_cob, self._on_host_heartbeat)
            self._consumer_cob = None
        if node_id and time_ms:
            self._consumer_cob = 0x700 + node_id
            self._consumer_s = time_ms / 1000.0
            if self.network is not None:
                self.network.subscribe(self._consumer_cob, self._on_host_heartbeat)
        else:
            self._consumer_s = None
        self._apply_watchdog()

    def _apply_watchdog(self) -> None:
        self.device.set_watchdog(self._consumer_s if self._abort_option == 1 else None)

    def _load_settings(self) -> None:
        """Apply the object dictionary's settings to the device (at start and after a reset)."""
        with self._lock:
            if self._initial_max_command < float("inf"):
                permille = min(round(self._initial_max_command * 1000.0), 0xFFFF)
                self.node.data_store.setdefault(0x6072, {})[0] = struct.pack("<H", permille)
            self.device.max_command = struct.unpack("<H", self.node.get_data(0x6072, 0))[0] / 1000.0
            cycle_us = round(self.device.cycle_s * 1e6)  # 0x1006 tells the device's cycle
            self.node.data_store.setdefault(0x1006, {})[0] = struct.pack("<I", cycle_us)
            self._abort_option = struct.unpack("<h", self.node.get_data(0x6007, 0))[0]
            self._set_consumer(int.from_bytes(self.node.get_data(0x1016, 1), "little"))
            self._mode = struct.unpack("<b", self.node.get_data(0x6060, 0))[0]
            self._pdo_dirty = True

    # ------------------------------------------------------------------ NMT
    def _on_nmt(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if len(data) < 2 or data[1] not in (0, self.node.id):
            return
        with self._lock:
            old, new = self._nmt, self.node.nmt.state
            if new == "INITIALISING":  # reset node (0x81) or reset communication (0x82)
                self._reset(application=data[0] == 0x81)
                return
            self._nmt = new
            if new == old:
                return
            if old == NMT_OPERATIONAL and self._state is S.OPERATION_ENABLED:
                self._apply_controlword(0x0002)  # leaving OPERATIONAL stops the axis
            if new == NMT_OPERATIONAL:
                self._pdo_dirty = True
                self._rebuild_pdos()
            if self.node.get_data(0x1017, 0) != b"\x00\x00":
                self.network.send_message(0x700 + self.node.id, [NMT_STATE_CODES.get(new, 0)])

    def _reset(self, application: bool) -> None:
        """NMT reset node (application and communication parameters) or reset communication."""
        for index in list(self.node.data_store):
            if application or 0x1000 <= index <= 0x1FFF:
                del self.node.data_store[index]
        if application and self._state is not S.FAULT:
            self.device.disable()
            self._state = S.SWITCH_ON_DISABLED
        self._load_settings()
        self.node.nmt.send_command(0x81)  # boot-up message
        self.node.nmt.send_command(0x80)
        self._nmt = self.node.nmt.state

    def _on_host_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        self.device.feed()

    # ------------------------------------------------------------------ PDOs
    def _rebuild_pdos(self) -> None:
        if not self._pdo_dirty or self.network is None:
            return
        self._pdo_dirty = False
        for cob, handler in self._rpdo_handlers.items():
            self.network.unsubscribe(cob, handler)
        self._rpdo_handlers = {}
        for channel in can_pdo.read_channels(self.node, can_pdo.RPDO_COMM, can_pdo.RPDO_MAP):
            handler = self._rpdo_handler(channel)
            self._rpdo_handlers[channel.cob_id] = handler
            self.network.subscribe(channel.cob_id, handler)
        self._tpdos = can_pdo.read_channels(self.node, can_pdo.TPDO_COMM, can_pdo.TPDO_MAP)
        sync_cob = int.from_bytes(self.node.get_data(0x1005, 0), "little") & 0x7FF
        if sync_cob != self._sync_cob:
            if self._sync_cob is not None:
                self.network.unsubscribe(self._sync_cob, self._on_sync)
            self._sync_cob = sync_cob
            self.network.subscribe(sync_cob, self._on_sync)

    def _rpdo_handler(self, channel: can_pdo.PdoChannel) -> Callable[[int, bytearray, float], None]:
        def on_rpdo(can_id: int, data: bytearray, timestamp: float) -> None:
            with self._lock:
                if self._nmt != NMT_OPERATIONAL:
                    return
                if len(data) < channel.length:
                    self._send_emcy(EMCY_PDO_LENGTH, self._error_register())
                    return
                for entry, chunk in channel.unpack(data):
                    self.node.set_data(entry.index, entry.subindex, chunk)

        return on_rpdo

    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        with self._lock:
            if self._nmt != NMT_OPERATIONAL:
                return
            self._rebuild_pdos()
            self._sync_count += 1
            wire = self.injector.next_cycle()  # drive faults (fault, freeze) applied here
            for spec in wire:
                if spec.kind == "busoff":
                    self.hook.bus_off(spec)
                    if self._abort_option == 1:  # abort connection: fault
                        self.device.fault(BUSOFF_FAULT, f"CAN bus-off (--fault {spec})")
            self._sync_device()
            self._frozen = self.injector.step()
            try:
                frames = [
                    (ch.cob_id, ch.pack(self.node.get_data))
                    for ch in self._tpdos
                    if ch.due(self._sync_count)
                ]
            finally:
                self._frozen = None
            transmissions = self.hook.transmissions(wire, frames, self.node.id)
        for tx in transmissions:
            if tx.delay_s > 0:
                self.hook.send_later(tx.delay_s, lambda f=tx.frames: self._send_frames(f))
            else:
                self._send_frames(tx.frames)

    def _send_frames(self, frames) -> None:
        send_batch = getattr(self.network, "send_messages", None)
        if send_batch is not None:  # the hub: all TPDOs of this SYNC in one TCP write
            send_batch(list(frames))
            return
        for cob_id, payload in frames:
            self.network.send_message(cob_id, payload)
