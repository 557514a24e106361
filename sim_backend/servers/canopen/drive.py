"""The simulated drive as a CANopen CiA 402 slave.

:class:`ServedCiA402Drive` puts a :class:`~servobench.sim_backend.device.SimulatedDevice`
behind a :class:`canopen.LocalNode` loaded from an EDS: the shipped generic one,
or any other (``serve-sim --eds FILE``), whose object set it then has and no
more: SDO access to an object the EDS lacks aborts with 0x06020000, and the
drive leaves out whatever needs an object it lacks. canopen's LocalNode
answers SDOs; this module adds what it lacks:

* the CiA 402 power state machine, stepped by every controlword (SDO or
  RPDO) with :func:`servobench.drivers.cia402.next_state`, the same tables the host plans
  with, and mirrored onto the device (``enable``, ``disable``,
  ``quick_stop``, ``reset_fault``);
* the modes of operation it implements and its 0x6502 announces: profile
  torque (4), cyclic synchronous torque (10) (target torque 0x6071 plus the
  torque offset 0x60B2), and cyclic synchronous position (8), where its own
  position loop (:mod:`servobench.sim_backend.servers.canopen.position_loop`)
  holds the target position 0x607A at every SYNC;
* PDOs and the SYNC (:mod:`servobench.sim_backend.servers.canopen.sync`);
* units: the plant is in SI, the objects speak the drive's factor group
  (:mod:`servobench.sim_backend.servers.canopen.factor`); 0x1013 is the device
  clock (UNSIGNED32 µs, wrapping; in ``clock=real`` the drive's free-running
  clock at the instant the SYNC's sample was taken, in lockstep the cycle
  count times the cycle); 0x6077 reports the torque applied over the cycle before the
  SYNC, as a drive samples its actual value;
* NMT: PDOs and SYNC only in OPERATIONAL; no SDO in STOPPED (CiA 301: there
  only NMT and error control); leaving OPERATIONAL while the
  axis is enabled quick-stops it; a heartbeat goes out at once on a change;
  0x1006 and 0x60C2 (both set the device's cycle) are written in
  PRE-OPERATIONAL only (abort 0x08000022 in OPERATIONAL, as many drives do);
* the heartbeat consumer 0x1016: host heartbeats feed the device watchdog,
  set to the consumer time when 0x6007 (abort connection option) is 1,
  or always when the drive has no 0x6007, so host silence faults the axis
  with 0x8130 (the sim_backend watchdog thread does the tripping); an EMCY
  goes out on every fault;
* host sessions: an NMT command while no host is present (none consumed in
  0x1016, or its heartbeats stopped) begins a new session: the drive clock
  restarts at 0 and the command is dropped, as on every served transport.

Simplifications: synchronous RPDOs act on receipt (the device latches the
torque for the next SYNC anyway -- a real-time device takes it at the next
SYNC, :mod:`~servobench.sim_backend.servers.canopen.sync` -- but a controlword
changes the state at once); event-driven TPDOs (types 254/255) are not produced;
0x6007 takes 0 (no action) or 1 (fault) only; the quick stop (0x605A) keeps
QUICK STOP ACTIVE; profile torque ignores torque slopes (the torque steps).
"""

from __future__ import annotations

import math
import struct
import threading
from collections.abc import Mapping

import canopen
from canopen.objectdictionary import ODVariable
from canopen.sdo import SdoAbortedError

from servobench.drivers.cia402 import (
    MODE_CSP,
    MODE_CST,
    MODE_PROFILE_TORQUE,
    CiA402State,
    encode_statusword,
    next_state,
    supports_mode,
)
from servobench.sim_backend.device import PowerState, SimulatedDevice, clock_counts
from servobench.sim_backend.faults.can import CanFaultHook
from servobench.sim_backend.faults.injector import FaultInjector
from servobench.sim_backend.faults.spec import FaultPlan
from servobench.sim_backend.servers.canopen import pdo as can_pdo
from servobench.sim_backend.servers.canopen.factor import ServedFactors
from servobench.sim_backend.servers.canopen.heartbeat import HeartbeatConsumer
from servobench.sim_backend.servers.canopen.position_loop import PositionLoop, gains_from_keys
from servobench.sim_backend.servers.canopen.sync import SyncEngine

S = CiA402State

#: Modes of operation the simulated drive implements (0x6060 values).
IMPLEMENTED_MODES = {
    MODE_PROFILE_TORQUE: "profile torque",
    MODE_CSP: "cyclic synchronous position",
    MODE_CST: "cyclic synchronous torque",
}
#: 0x6007 values the simulated drive implements: 0 no action, 1 fault.
ABORT_OPTIONS = (0, 1)
#: SDO aborts: attempt to write a read only object; not in the present device state.
ABORT_READ_ONLY = 0x06010002
ABORT_DEVICE_STATE = 0x08000022
#: Objects written only in NMT PRE-OPERATIONAL (they change the drive's cycle).
PRE_OPERATIONAL_ONLY = (0x1006, 0x60C2)

NMT_OPERATIONAL = "OPERATIONAL"
NMT_STATE_CODES = {"INITIALISING": 0, "STOPPED": 4, "OPERATIONAL": 5, "PRE-OPERATIONAL": 127}

_I16 = (-(2**15), 2**15 - 1)
_I32 = (-(2**31), 2**31 - 1)


def clamp(value: float, bounds: tuple[int, int]) -> int:
    return min(max(round(value), bounds[0]), bounds[1])


def wrap_i32(value: float) -> int:
    return (round(value) + 2**31) % 2**32 - 2**31


class ServedCiA402Drive:
    """A :class:`SimulatedDevice` served as CiA 402 node ``node_id``.

    Parameters
    ----------
    device : SimulatedDevice
        The simulated drive, its plant in SI units.
    node : canopen.LocalNode
        The node, with its EDS; this class registers its callbacks.
    injector : FaultInjector, optional
        Faults to inject (:mod:`servobench.sim_backend.faults`); SYNCs are its cycles.
    keys : mapping, optional
        The served drive's ``sim://`` keys (:data:`~servobench.sim_backend.servers.canopen.factor.SIM_KEYS`).
    """

    def __init__(
        self,
        device: SimulatedDevice,
        node: canopen.LocalNode,
        injector: FaultInjector | None = None,
        keys: Mapping[str, str] | None = None,
    ) -> None:
        keys = dict(keys or {})
        self.device = device
        self.node = node
        self.od = node.object_dictionary
        self.factors = ServedFactors.from_config(keys, self.od)
        self.lsb = self.factors.command_per_lsb()  # plant command per LSB of 0x6071/0x6077
        gains = {k: float(v) for k, v in keys.items() if k.startswith("pos_k")}
        self.loop = PositionLoop(gains_from_keys(gains, device.params.M, device.params.B))
        self.injector = injector or FaultInjector(device, FaultPlan("canopen"))
        self.hook = CanFaultHook(self.injector)
        self._reject_modes = self.injector.plan.setting("reject_mode")
        self._ignore_modes = self.injector.plan.setting("ignore_mode")
        announced = self._default(0x6502)
        self.modes = {
            m for m in IMPLEMENTED_MODES if announced is None or supports_mode(announced, m)
        }
        self.network: canopen.Network | None = None
        self.lock = threading.RLock()
        self.state = S.NOT_READY_TO_SWITCH_ON
        self.mode = 0
        self.nmt = "INITIALISING"
        self.sync = SyncEngine(self)
        self._controlword = 0
        self.consumer = HeartbeatConsumer(device)
        self._initial_max_command = device.max_command
        node.add_read_callback(self._on_read)
        node.add_write_callback(self._on_write)

    def has(self, index: int, sub: int = 0) -> bool:
        """True when the served object dictionary has ``index:sub``."""
        if index not in self.od:
            return False
        obj = self.od[index]
        return sub == 0 if isinstance(obj, ODVariable) else sub in obj

    def _default(self, index: int, sub: int = 0) -> int | None:
        if not self.has(index, sub):
            return None
        try:
            return int.from_bytes(self.node.get_data(index, sub), "little", signed=False)
        except SdoAbortedError:  # no value in the EDS
            return None

    def _store(self, index: int, sub: int, value: int) -> None:
        obj = self.od[index]
        var = obj if isinstance(obj, ODVariable) else obj[sub]
        self.node.data_store.setdefault(index, {})[sub] = var.encode_raw(value)

    def _int(self, index: int, fmt: str, sub: int = 0, default: int = 0) -> int:
        """The stored value of ``index:sub``; ``default`` when the EDS gives none and none was written."""
        try:
            return struct.unpack("<" + fmt, self.node.get_data(index, sub))[0]
        except SdoAbortedError:
            return default

    # --------------------------------------------------------------- lifecycle
    def attach(self, network: canopen.Network) -> None:
        """Join ``network`` (NMT, SYNC, RPDO and heartbeat subscriptions)."""
        self.network = self.consumer.network = network
        network.add_node(self.node)
        network.unsubscribe(self.node.sdo.rx_cobid, self.node.sdo.on_request)
        network.subscribe(self.node.sdo.rx_cobid, self._on_sdo)
        network.subscribe(0, self._on_nmt)  # after the NmtSlave's own handler
        self._load_settings()

    def boot(self) -> None:
        """Power-on: boot-up message, PRE-OPERATIONAL, then SWITCH ON DISABLED (transition 1)."""
        with self.lock:
            if self.device.state is PowerState.FAULT:
                self._enter_fault()
            else:
                self.state = S.SWITCH_ON_DISABLED
            self.node.nmt.send_command(0x81)  # INITIALISING: sends the boot-up message
            self.node.nmt.send_command(0x80)  # PRE-OPERATIONAL, starts the 0x1017 heartbeat
            self.nmt = self.node.nmt.state

    def poll(self) -> None:
        """Periodic housekeeping: notice device faults (watchdog) and send their EMCY."""
        with self.lock:
            self.sync_device()
            if self.hook.recovered() and self.state is S.FAULT:
                self._send_emcy(self.device.fault_code, self.error_register())  # lost in bus-off

    def close(self) -> None:
        self.hook.close()
        self.node.nmt.stop_heartbeat()

    # ------------------------------------------------------------- 402 states
    def sync_device(self) -> None:
        """Follow what the device did by itself (fault, watchdog, external disable)."""
        dev = self.device.state
        if dev is PowerState.FAULT and self.state is not S.FAULT:
            self._enter_fault()  # transitions 13 and 14 at once
        elif dev is PowerState.DISABLED and self.state in (
            S.OPERATION_ENABLED,
            S.QUICK_STOP_ACTIVE,
        ):
            self.state = S.SWITCH_ON_DISABLED

    def _enter_fault(self) -> None:
        self.state = S.FAULT
        self._send_emcy(self.device.fault_code, self.error_register())

    def error_register(self) -> int:
        if self.state is not S.FAULT:
            return 0
        comm = 0x10 if (self.device.fault_code & 0xFF00) == 0x8100 else 0
        return 0x01 | comm

    def _send_emcy(self, code: int, register: int) -> None:
        if self.network is not None:
            self.node.emcy.send(code, register)

    def _apply_controlword(self, controlword: int) -> None:
        previous, self._controlword = self._controlword, controlword
        self.sync_device()
        target = next_state(self.state, controlword, previous)
        if target is self.state:
            return
        if target is S.OPERATION_ENABLED:
            self.device.enable()
            self.loop.reset()
            self.device.set_command(self._torque_command())
        elif target is S.QUICK_STOP_ACTIVE:
            self.device.quick_stop()
        elif self.state is S.FAULT:
            self.device.reset_fault()  # transition 15
            self._send_emcy(0, 0)  # error reset
        else:
            self.device.disable()
        self.state = target

    def _torque_command(self) -> float:
        """Latched command [plant units] in the torque modes: target torque + torque offset."""
        if self.mode not in (MODE_CST, MODE_PROFILE_TORQUE):
            return 0.0 if self.mode != MODE_CSP else self.device.command
        offset = self._int(0x60B2, "h") if self.has(0x60B2) else 0
        return (self._int(0x6071, "h") + offset) * self.lsb

    def mode_is_csp(self) -> bool:
        """True while the drive's own position loop runs (CSP, operation enabled)."""
        return self.mode == MODE_CSP and self.state is S.OPERATION_ENABLED

    def csp_torque(self, position: float, velocity: float) -> float | None:
        """The position loop's torque for this SYNC [plant units], ``None`` outside CSP."""
        if not self.mode_is_csp():
            return None
        per_unit = self.factors.position_raw(1.0)
        error_raw = wrap_i32(self._int(0x607A, "i") - wrap_i32(self.factors.position_raw(position)))
        offset = (self._int(0x60B2, "h") if self.has(0x60B2) else 0) * self.lsb
        limit = min(self.device.max_command, _I16[1] * self.lsb)
        return self.loop.torque(error_raw / per_unit, velocity, offset, limit, self.device.cycle_s)

    # ---------------------------------------------------------- OD callbacks
    def _on_read(self, index: int, subindex: int, od: ODVariable) -> int | None:
        with self.lock:
            if index == 0x6041:
                self.sync_device()
                return encode_statusword(self.state)
            if index == 0x603F:
                self.sync_device()
                return self.device.fault_code if self.state is S.FAULT else 0
            if index == 0x6077:
                return clamp(self.sync.torque_actual() / self.lsb, _I16)
            if index == 0x6061:
                return self.mode
            if index == 0x1001:
                return self.error_register()
            if index not in (0x6064, 0x606C, 0x1013):
                return None
            # at a SYNC the sample it took, otherwise the present one (no clocking)
            sample = self.sync.frozen or self.injector.sample()
            if index == 0x6064:
                return wrap_i32(self.factors.position_raw(sample.position))
            if index == 0x606C:
                return clamp(self.factors.velocity_raw(sample.velocity), _I32)
            return clock_counts(sample.t_s, 1e-6) & 0xFFFFFFFF  # UNSIGNED32 µs (CiA 301), wrapping

    def _on_write(self, index: int, subindex: int, od: ODVariable, data: bytes) -> None:
        value = od.decode_raw(data)
        with self.lock:
            if index in PRE_OPERATIONAL_ONLY and self.nmt == NMT_OPERATIONAL:
                raise SdoAbortedError(ABORT_DEVICE_STATE)
            if index == 0x6040:
                self._apply_controlword(value)
            elif index in (0x6071, 0x60B2):
                self._set_torque(index, value)
            elif index == 0x6060:
                self._set_mode(value)
            elif index == 0x6072:
                self.device.max_command = value * self.lsb
            elif index == 0x1006:
                if value > 0:
                    self.device.set_cycle(value * 1e-6)
            elif index == 0x60C2:
                self._set_interpolation_period(subindex, value)
            elif index == 0x1013:
                raise SdoAbortedError(ABORT_READ_ONLY)  # the clock is the plant's
            elif index == 0x1016:
                self.consumer.configure(value)
            elif index == 0x6007:
                if value not in ABORT_OPTIONS:
                    raise SdoAbortedError(can_pdo.ABORT_VALUE_RANGE)
                self.consumer.set_abort_option(value)
            elif can_pdo.is_mapping_parameter(index):
                can_pdo.check_mapping_write(self.node, index, subindex, value)
            if can_pdo.is_pdo_parameter(index) or index == 0x1005:
                self.sync.dirty = True

    def _set_torque(self, index: int, value: int) -> None:
        if self.state is not S.OPERATION_ENABLED or self.mode not in (
            MODE_CST,
            MODE_PROFILE_TORQUE,
        ):
            return  # in CSP the offset acts at the next SYNC
        other = 0x60B2 if index == 0x6071 else 0x6071
        rest = self._int(other, "h") if self.has(other) else 0
        if self.sync.receiving_sync_rpdo:  # real time: takes force at the next SYNC (sync.py)
            self.sync.pending_command = (value + rest) * self.lsb
            return
        self.device.set_command((value + rest) * self.lsb)

    def _set_interpolation_period(self, subindex: int, value: int) -> None:
        """0x60C2 = value x 10^index s sets the cycle, as on drives without 0x1006."""
        units = value if subindex == 1 else self._int(0x60C2, "B", 1)
        exponent = value if subindex == 2 else self._int(0x60C2, "b", 2, -3)
        if subindex in (1, 2) and units > 0 and -7 <= exponent <= 0:
            self.device.set_cycle(units * 10.0**exponent)

    def _set_mode(self, mode: int) -> None:
        if mode in self._reject_modes or (mode not in self.modes and mode != 0):
            raise SdoAbortedError(can_pdo.ABORT_VALUE_RANGE)
        if mode in self._ignore_modes:
            return
        self.mode = mode
        self.loop.reset()
        if self.state is S.OPERATION_ENABLED and mode != MODE_CSP:
            self.device.set_command(self._torque_command())

    def _load_settings(self) -> None:
        """Apply the object dictionary's settings to the device (at start and after a reset)."""
        with self.lock:
            for (index, sub), value in self.factors.od_values().items():
                if self.has(index, sub):
                    self._store(index, sub, value)
            if self.has(0x6072):
                if self._initial_max_command < math.inf:
                    self._store(0x6072, 0, min(round(self._initial_max_command / self.lsb), 0xFFFF))
                self.device.max_command = self._int(0x6072, "H") * self.lsb
            if self.has(0x1006):  # 0x1006 tells the device's cycle
                self._store(0x1006, 0, round(self.device.cycle_s * 1e6))
            self.consumer.abort_option = self._int(0x6007, "h", 0, 1) if self.has(0x6007) else 1
            self.consumer.configure(self._int(0x1016, "I", 1) if self.has(0x1016, 1) else 0)
            self.mode = self._int(0x6060, "b")
            self.sync.dirty = True

    # ------------------------------------------------------------------ NMT
    def _on_sdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if self.node.nmt.state != "STOPPED":  # CiA 301: no SDO in STOPPED
            self.node.sdo.on_request(can_id, data, timestamp)

    def _on_nmt(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if len(data) < 2 or data[1] not in (0, self.node.id):
            return
        with self.lock:
            if not self.consumer.host_present():
                self._begin_session()
            old, new = self.nmt, self.node.nmt.state
            if new == "INITIALISING":  # reset node (0x81) or reset communication (0x82)
                self._reset(application=data[0] == 0x81)
                return
            self.nmt = new
            if new == old:
                return
            if old == NMT_OPERATIONAL and self.state is S.OPERATION_ENABLED:
                self._apply_controlword(0x0002)  # leaving OPERATIONAL stops the axis
            if new == NMT_OPERATIONAL:
                self.sync.dirty = True
                self.sync.rebuild()
            if self.has(0x1017) and self.node.get_data(0x1017, 0) != b"\x00\x00":
                self.network.send_message(0x700 + self.node.id, [NMT_STATE_CODES.get(new, 0)])

    def _begin_session(self) -> None:
        """An NMT command from a host while none is present: a new host session.

        The axis a vanished host left enabled (0x6007 = 0: no reaction) is
        quick-stopped first, so the CiA 402 state and the device agree; then
        the device starts clean (:meth:`SimulatedDevice.begin_session`: drive
        clock at 0, command dropped).
        """
        if self.state is S.OPERATION_ENABLED:
            self._apply_controlword(0x0002)
        self.device.begin_session()

    def _reset(self, application: bool) -> None:
        """NMT reset node (application and communication parameters) or reset communication."""
        for index in list(self.node.data_store):
            if application or 0x1000 <= index <= 0x1FFF:
                del self.node.data_store[index]
        if application and self.state is not S.FAULT:
            self.device.disable()
            self.state = S.SWITCH_ON_DISABLED
        self._load_settings()
        self.node.nmt.send_command(0x81)  # boot-up message
        self.node.nmt.send_command(0x80)
        self.nmt = self.node.nmt.state
