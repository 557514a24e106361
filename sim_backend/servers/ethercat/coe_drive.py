"""The CiA 402 application behind the served ESC: AL states, mailbox, process data.

:class:`CoeSlave` is the :class:`~.esc.Application` of the slave. It keeps the
CANopen served drive's object logic
(:class:`~servobench.sim_backend.servers.canopen.drive.ServedCiA402Drive`: the
CiA 402 power state machine stepped with :mod:`servobench.drivers.cia402`'s
tables, CST and CSP with torque offset, the factor group) and adds what
EtherCAT changes:

* AL transitions (:mod:`.al`): INIT -> PRE-OP checks the mailbox
  SyncManagers against the SII (0x0016); PRE-OP -> SAFE-OP compiles the
  assigned PDOs (0x1C12/0x1C13) and checks SM2/SM3 against them (0x001D,
  0x001E) and the SYNC0 cycle, when active, against 0x1C32 (0x0030); the
  PDO assignment and mapping and 0x1C32 are written in PRE-OP only (abort
  0x08000022 later); leaving OP (or SAFE-OP) while the axis is enabled
  quick-stops it, as leaving NMT OPERATIONAL does on CANopen;
* SAFE-OP -> OP completes when the first outputs arrived (SM2), as the
  slave stack of real drives waits for valid outputs;
* the process data cycle: each completed SM2 buffer in OP writes the
  RxPDO objects, clocks the device once (the position loop first in CSP)
  and leaves the TxPDO of the sample taken there in SM3 (:class:`PdoCycle`).
  A ``clock="real"`` device is not clocked but looked at: the frame is
  handled at the one instant it arrived
  (:mod:`~servobench.sim_backend.servers.ethercat.serve_ethercat`), so the
  outputs it carries take force, and the inputs are sampled, at that
  instant, the axis having moved in wall-clock time meanwhile with the last
  outputs received; a lock-step device makes one cycle of each frame;
* DC-synchronous (``real`` only, SYNC0 active and 0x1C32:01 = 2, which the
  master writes in PRE-OP where 0x1C32:04 announces it): the process data
  cycle runs at each SYNC0 event of the slave's own DC clock instead of at
  the frame, as a DC-synchronous drive does: the outputs last received take
  force and the inputs are sampled at the event's instant (the serve loop
  handles each event at that instant of the plant, however late it gets to
  it, and before any frame that arrived after it; until then nothing else,
  the state report's thread included, integrates the plant past its
  instant: ``SimulatedDevice.hold_before_s``), and the frames only
  deliver outputs and read the inputs of the last event. The host's timing
  then never reaches the sample instants, which fall on the SYNC0 grid.
  Events the loop got to late together are merged: the outputs last
  received take force at the first of them, as a drive's SYNC0 interrupt
  puts them in force, and the inputs are sampled at the last (merged into
  the last alone, a command that arrived before the first acted only from
  the last: a cycle after the instant the master's log, ``t_act``, says);
* the timestamp object 0x10F8 (where served) is the DC system time of the
  sample: in ``real`` the ESC's system time at the frame's arrival or at
  the SYNC0 event (the instant the inputs were sampled; with a drive tick,
  ``serve-sim --tick``, the tick they were sampled at); in lock-step the
  drive clock (cycles times the cycle) on the DC time base (plus the offset
  0x0920 the master wrote);
* the SM watchdog: when it expires the slave goes to SAFE-OP with the
  error flag and 0x001B, and the axis faults (0x8130, the device
  watchdog's code) with a CoE emergency;
* EMCYs become CoE emergency mailbox messages;
* a :class:`~.profiles.DriveProfile` (``serve-sim --profile``) emulates a
  real drive's quirks (:mod:`.profiles`): its objects are edited before the
  slave is built, the SDO server stores or refuses complete access as it
  says, and the drive honours 0x605A or ignores the quick stop command.
"""

from __future__ import annotations

import struct
import threading
import time
from collections.abc import Callable

import canopen
from canopen.sdo import SdoAbortedError

from servobench.drivers.cia402 import (
    CW_DISABLE_VOLTAGE,
    CW_QUICK_STOP,
    CiA402State,
    decode_controlword,
)
from servobench.sim_backend.device import (
    WATCHDOG_FAULT,
    DeviceSample,
    PowerState,
    SimulatedDevice,
)
from servobench.sim_backend.faults.injector import FaultInjector
from servobench.sim_backend.servers.canopen import pdo as can_pdo
from servobench.sim_backend.servers.canopen.drive import ServedCiA402Drive
from servobench.sim_backend.servers.canopen.sync import SyncEngine
from servobench.sim_backend.servers.ethercat import al, profiles
from servobench.sim_backend.servers.ethercat import objects as O
from servobench.sim_backend.servers.ethercat.coe_sdo import SdoServer
from servobench.sim_backend.servers.ethercat.esc import Application, Esc
from servobench.sim_backend.servers.ethercat.mailbox import (
    MBXERR_UNSUPPORTED_PROTOCOL,
    TYPE_COE,
    decode_mailbox,
    emergency,
    mailbox_error,
)
from servobench.sim_backend.servers.ethercat.sii import build_image

A = al.AlState
ABORT_DEVICE_STATE = 0x08000022
#: Objects written in PRE-OP only: the PDO assignment and mapping, the SM parameters.
PRE_OP_ONLY = (O.RXPDO_ASSIGN, O.TXPDO_ASSIGN, O.SM_OUTPUT_PARAMETER, O.SM_INPUT_PARAMETER)
_NMT = {A.INIT: "INITIALISING", A.PRE_OP: "PRE-OPERATIONAL", A.SAFE_OP: "OPERATIONAL",
        A.OP: "OPERATIONAL", A.BOOT: "INITIALISING"}  # fmt: skip


class _CoeNetwork(canopen.Network):
    """The canopen network the drive object logic talks to: EMCYs go to the mailbox."""

    def __init__(self, on_emcy) -> None:
        super().__init__()
        self._on_emcy = on_emcy

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        if 0x80 < can_id < 0x100 and len(data) >= 3:
            code, register = struct.unpack_from("<HB", bytes(data))
            self._on_emcy(code, register)


class CoeCiA402Drive(ServedCiA402Drive):
    """The CANopen served drive's object logic with CoE's PDO rules.

    The PDO assignment, mapping and SM parameters are written in PRE-OP only
    (abort 0x08000022 later); a mapping is written with sub-index 0 at 0 and
    checked entry by entry (mappable, direction, size), without CANopen's
    COB-ID procedure and 8-byte limit; 0x1C32:02 sets the device's cycle.
    """

    #: The slave's AL state (set by :class:`CoeSlave`).
    al_state: Callable[[], al.AlState] = staticmethod(lambda: A.INIT)
    #: The DC system time [ns] of a sample (set by :class:`CoeSlave`).
    dc_time_of: Callable[[DeviceSample], int] = staticmethod(lambda sample: 0)
    #: The real drive's quirks it emulates (set by :class:`CoeSlave`).
    profile: profiles.DriveProfile = profiles.DriveProfile()

    def _apply_controlword(self, controlword: int) -> None:
        """The CiA 402 step, with the profile's quick stop (:mod:`.profiles`)."""
        quirks = self.profile
        if quirks.ignore_quick_stop and decode_controlword(controlword, self._controlword) == (
            CW_QUICK_STOP
        ):
            self._controlword = controlword
            self.sync_device()
            return
        super()._apply_controlword(controlword)
        if (
            quirks.quick_stop_option is not None
            and self.state is CiA402State.QUICK_STOP_ACTIVE
            and self._int(profiles.QUICK_STOP_OPTION, "h") in profiles.QUICK_STOP_TO_DISABLED
        ):
            self.device.disable()  # the quick stop is torque off: done at once (transition 12)
            self.state = CiA402State.SWITCH_ON_DISABLED

    def _on_read(self, index: int, subindex: int, od) -> int | None:
        if index == O.TIMESTAMP:
            with self.lock:  # at a process data cycle the sample it took, else the present one
                return self.dc_time_of(self.sync.frozen or self.injector.sample())
        return super()._on_read(index, subindex, od)

    def _on_write(self, index: int, subindex: int, od, data: bytes) -> None:
        state = self.al_state()
        mapping = can_pdo.is_mapping_parameter(index)
        if state > A.PRE_OP and (index in PRE_OP_ONLY or mapping):
            raise SdoAbortedError(ABORT_DEVICE_STATE)
        if index in (O.RXPDO_ASSIGN, O.TXPDO_ASSIGN):
            self._check_assignment(index, subindex, od.decode_raw(data))
        elif mapping:
            self._check_mapping(index, subindex, od.decode_raw(data))
            return
        elif index == O.SM_OUTPUT_PARAMETER and subindex == 1:
            kind = od.decode_raw(data)
            (supported,) = struct.unpack("<H", self.node.get_data(O.SM_OUTPUT_PARAMETER, 4))
            if kind not in (O.SYNC_FREE_RUN, O.SYNC_SM, O.SYNC_DC0) or not supported >> kind & 1:
                raise SdoAbortedError(can_pdo.ABORT_VALUE_RANGE)
            return
        elif (
            index == profiles.QUICK_STOP_OPTION
            and self.profile.quick_stop_option is not None
            and od.decode_raw(data) not in profiles.QUICK_STOP_OPTIONS
        ):
            raise SdoAbortedError(can_pdo.ABORT_VALUE_RANGE)  # honoured: the standard's codes
        elif index == O.SM_OUTPUT_PARAMETER and subindex == 2:
            cycle_ns = od.decode_raw(data)
            if cycle_ns and cycle_ns < O.MIN_CYCLE_NS:
                raise SdoAbortedError(can_pdo.ABORT_VALUE_RANGE)
            if cycle_ns:
                self.device.set_cycle(cycle_ns * 1e-9)
            return
        super()._on_write(index, subindex, od, data)

    def _check_assignment(self, index: int, subindex: int, value: int) -> None:
        base = O.RXPDO_MAP if index == O.RXPDO_ASSIGN else O.TXPDO_MAP
        if subindex == 0:
            if value > O.PDOS_PER_DIRECTION:
                raise SdoAbortedError(can_pdo.ABORT_VALUE_RANGE)
            return
        if self.node.get_data(index, 0)[0] != 0:
            raise SdoAbortedError(can_pdo.ABORT_INCOMPATIBLE)  # sub 0 must be 0 meanwhile
        if value and not base <= value < base + O.PDOS_PER_DIRECTION:
            raise SdoAbortedError(can_pdo.ABORT_VALUE_RANGE)

    def _check_mapping(self, index: int, subindex: int, value: int) -> None:
        receive = O.RXPDO_MAP <= index < O.RXPDO_MAP + O.PDOS_PER_DIRECTION
        if subindex == 0:
            if value > 8:
                raise SdoAbortedError(can_pdo.ABORT_VALUE_RANGE)
            for s in range(1, value + 1):
                (entry,) = struct.unpack("<I", self.node.get_data(index, s))
                self._check_entry(can_pdo.MappedObject.from_entry(entry), receive)
            return
        if self.node.get_data(index, 0)[0] != 0:
            raise SdoAbortedError(can_pdo.ABORT_INCOMPATIBLE)
        if value:
            self._check_entry(can_pdo.MappedObject.from_entry(value), receive)

    def _check_entry(self, entry: can_pdo.MappedObject, receive: bool) -> None:
        if not self.has(entry.index, entry.subindex):
            raise SdoAbortedError(can_pdo.ABORT_NO_OBJECT)
        obj = self.od[entry.index]
        var = obj if not hasattr(obj, "subindices") else obj[entry.subindex]
        if not var.pdo_mappable or not (var.writable if receive else var.readable):
            raise SdoAbortedError(can_pdo.ABORT_NOT_MAPPABLE)
        if entry.bits != len(var) or entry.bits % 8:
            raise SdoAbortedError(can_pdo.ABORT_INCOMPATIBLE)


class PdoCycle(SyncEngine):
    """The process data side of the drive: one call of :meth:`cycle` per SM2 buffer."""

    def __init__(self, drive: ServedCiA402Drive) -> None:
        super().__init__(drive)
        self.rx: list[can_pdo.MappedObject] = []
        self.tx: list[can_pdo.MappedObject] = []
        #: How late the next answer goes out (``--fault delay@N:MS``) [s]; pending until the
        #: serve loop sends that answer, however many SYNC0 cycles run before it.
        self.delay_s = 0.0

    def rebuild(self) -> None:
        """CANopen's PDO channels do not exist here (see :meth:`compile`)."""

    def compile(self) -> tuple[int, int]:
        """Read the PDO assignment; the output and input sizes [bytes]."""
        self.rx = self._entries(O.RXPDO_ASSIGN)
        self.tx = self._entries(O.TXPDO_ASSIGN)
        return sum(e.bits for e in self.rx) // 8, sum(e.bits for e in self.tx) // 8

    def _entries(self, assign: int) -> list[can_pdo.MappedObject]:
        node, out = self.drive.node, []
        for n in range(1, node.get_data(assign, 0)[0] + 1):
            (pdo,) = struct.unpack("<H", node.get_data(assign, n))
            for sub in range(1, node.get_data(pdo, 0)[0] + 1):
                (entry,) = struct.unpack("<I", node.get_data(pdo, sub))
                out.append(can_pdo.MappedObject.from_entry(entry))
        return out

    def pack(self) -> bytes:
        """The TxPDO image of the present (frozen) sample."""
        data = b""
        for e in self.tx:
            raw = self.drive.node.get_data(e.index, e.subindex) if e.index else b""
            data += raw[: e.bits // 8].ljust(e.bits // 8, b"\x00")
        return data

    def cycle(self, outputs: bytes) -> bytes:
        """Apply ``outputs`` (the RxPDO image), clock the device once, return the TxPDO image."""
        drive = self.drive
        with drive.lock:
            pos = 0
            for e in self.rx:
                n = e.bits // 8
                if e.index:
                    drive.node.set_data(e.index, e.subindex, outputs[pos : pos + n])
                pos += n
            wire = drive.injector.next_cycle()  # drive faults (fault, freeze) due at this cycle
            delay_s = sum(spec.arg for spec in wire if spec.kind == "delay") / 1000.0
            if delay_s:  # kept when later cycles run before the next frame comes (a late host)
                self.delay_s = delay_s
            drive.sync_device()
            self._clock()
            try:
                return self.pack()
            finally:
                self.frozen = None


class CoeSlave(Application):
    """The served slave: the ESC, the SDO server and the CiA 402 drive."""

    def __init__(
        self,
        device: SimulatedDevice,
        injector: FaultInjector,
        keys: dict[str, str] | None = None,
        serial: int = 1,
        timestamp: bool = True,
        clock_ns: Callable[[], int] = time.monotonic_ns,
        profile: profiles.DriveProfile | None = None,
    ) -> None:
        self.device = device
        profile = profile or profiles.DriveProfile()
        od = O.ethercat_od(device.cycle_s, timestamp, dc_synchronous=device.realtime)
        profiles.apply_to_od(profile, od)
        complete_access = profile.complete_access and (
            0 not in injector.plan.setting("complete_access")
        )
        self.description = O.description(od, serial, complete_access)
        self.node = canopen.LocalNode(1, od)
        self.drive = CoeCiA402Drive(device, self.node, injector, keys)
        self.drive.profile = profile
        self.drive.al_state = lambda: self.esc.al_state
        self.drive.dc_time_of = self._dc_time_of
        self.pdo = self.drive.sync = PdoCycle(self.drive)
        self.lock = threading.RLock()
        self.esc = Esc(build_image(self.description), self, clock_ns)  # the device's clock, in ns
        self.sdo = SdoServer(
            self.node, O.MAILBOX_BYTES, complete_access, profile.count_from_padding
        )
        self.drive.attach(_CoeNetwork(self._emergency))
        # power-on: transition 1 (CANopen's boot() also sends NMT messages CoE has not)
        self.drive.sync_device()
        if self.drive.state is not CiA402State.FAULT:
            self.drive.state = CiA402State.SWITCH_ON_DISABLED
        self.drive.nmt = _NMT[A.INIT]
        self._outputs_seen = False
        self._pending_op = False
        self.sizes = (0, 0)
        self._outputs: bytes | None = None  # DC-synchronous: the outputs last received
        self._next_sync0: int | None = None  # DC-synchronous: system time of the next event [ns]

    def _dc_time_of(self, sample: DeviceSample) -> int:
        """0x10F8: the DC system time [ns] at which ``sample`` was taken (module docstring)."""
        if self.device.tick is not None:  # the drive's tick the sample was taken at
            return self.esc.system_time_at(round(self.device.wall_instant_of(sample.t_s) * 1e9))
        if self.device.realtime:
            return self.esc.system_time_ns()  # the frame's arrival while a frame passes
        return self.esc.system_time_of(round(sample.t_s * 1e9))

    # --------------------------------------------------------------- AL
    def al_transition(self, current: al.AlState, target: al.AlState) -> int:
        if target > current and target is not A.BOOT:
            code = self._check_up(current, target)
            if code:
                return code
        if target < current or target is A.INIT:
            self._leave(current, target)
        if current is A.INIT and target is not A.INIT:
            self.drive.device.begin_session()  # a master starts over: a new host session
        self.drive.nmt = _NMT[target]
        if target is A.OP and not self._outputs_seen and self.sizes[0]:
            self._pending_op = True  # done when the first outputs arrive
            self.drive.nmt = _NMT[A.SAFE_OP]
            return al.PENDING
        return al.NO_ERROR

    def _check_up(self, current: al.AlState, target: al.AlState) -> int:
        if current is A.INIT:
            for n in (0, 1):
                spec = self.description.sync_managers[n]
                start, length, control, enabled = self.esc.sm(n)
                if not enabled or (start, length, control & 0x0F) != (
                    spec.start,
                    spec.length,
                    spec.control & 0x0F,
                ):
                    return al.INVALID_MAILBOX_CONFIG
        if current <= A.PRE_OP and target >= A.SAFE_OP:
            try:
                self.sizes = self.pdo.compile()
            except (SdoAbortedError, struct.error):
                return al.INVALID_OUTPUT_CONFIG
            for n, size, code in ((2, self.sizes[0], al.INVALID_OUTPUT_CONFIG),
                                  (3, self.sizes[1], al.INVALID_INPUT_CONFIG)):  # fmt: skip
                _start, length, _control, enabled = self.esc.sm(n)
                if size and (not enabled or length != size):
                    return code
            sync0 = self.esc.sync0()
            if sync0 is not None and not sync0[1] >= O.MIN_CYCLE_NS:
                return al.INVALID_DC_SYNC_CONFIG
            if sync0 is not None:
                self.device.set_cycle(sync0[1] * 1e-9)
            self._outputs_seen = False
        return al.NO_ERROR

    def _leave(self, current: al.AlState, target: al.AlState) -> None:
        if self.drive.state is CiA402State.OPERATION_ENABLED and target < A.OP:
            stop = CW_DISABLE_VOLTAGE if self.drive.profile.ignore_quick_stop else CW_QUICK_STOP
            self.node.set_data(0x6040, 0, stop.to_bytes(2, "little"))  # as leaving NMT OP
        if target is A.INIT:
            self.esc.reset_mailboxes()
        self._pending_op = False
        self._outputs = self._next_sync0 = None

    # ------------------------------------------------------------ mailbox
    def mailbox_written(self, data: bytes) -> None:
        try:
            message = decode_mailbox(data)
        except ValueError:
            return
        if message.kind != TYPE_COE:
            self.esc.post_mailbox(mailbox_error(MBXERR_UNSUPPORTED_PROTOCOL, message.counter))
            return
        reply = self.sdo.handle(message)
        if reply is not None:
            self.esc.post_mailbox(reply)

    def _emergency(self, code: int, register: int) -> None:
        if self.esc.al_state >= A.PRE_OP:
            self.esc.post_mailbox(emergency(code, register))

    # ------------------------------------------------------- process data
    def outputs_written(self, data: bytes) -> None:
        state = self.esc.al_state
        if state is A.SAFE_OP and self._pending_op:
            self._pending_op = False
            self._outputs_seen = True
            self.drive.nmt = _NMT[A.OP]
            self.esc.set_al(A.OP)
            state = A.OP
        if state is A.SAFE_OP:
            self._outputs_seen = True
            self.refresh_inputs()
            return
        if state is not A.OP:
            return
        if self.dc_synchronous:
            self._outputs = data  # they take force at the next SYNC0 event
            return
        self._cycle(data)

    def _cycle(self, data: bytes) -> None:
        try:
            inputs = self.pdo.cycle(data)
        except SdoAbortedError:
            inputs = self.pdo.pack()
        self.esc.set_inputs(3, inputs)

    @property
    def dc_synchronous(self) -> bool:
        """The process data cycle runs at SYNC0 (module docstring)."""
        if not self.device.realtime or self.esc.sync0() is None:
            return False
        (kind,) = struct.unpack("<H", self.node.get_data(O.SM_OUTPUT_PARAMETER, 1))
        return kind == O.SYNC_DC0

    def sync0_due(self, clock_ns: int) -> None:
        """Run the SYNC0 events due up to ``clock_ns`` (the ESC's clock), each at its own instant."""
        sync0 = self.esc.sync0()
        if sync0 is None or not self.dc_synchronous:
            self._next_sync0 = self.device.hold_before_s = None
            return
        start, cycle = sync0
        if self._next_sync0 is None:
            self._next_sync0 = start
        now = self.esc.system_time_at(clock_ns)
        if now >= self._next_sync0:
            first = self._next_sync0  # the outputs last received take force here
            event = first + (now - first) // cycle * cycle  # the latest due: its sample is read
            self._next_sync0 = event + cycle
            for due in (first, event) if event > first else (event,):
                at_ns = self.esc.clock_of_system(due)
                with self.device.instant(at_ns * 1e-9), self.esc.frame_at(at_ns):
                    if self.esc.al_state is A.OP and self._outputs is not None:
                        self._cycle(self._outputs)
                    else:
                        self.refresh_inputs()
        # the next event samples the plant as it stands at its instant: nothing integrates past it
        self.device.hold_before_s = self.esc.clock_of_system(self._next_sync0) * 1e-9

    def refresh_inputs(self) -> None:
        """Keep the inputs current while no outputs arrive (SAFE-OP)."""
        if self.esc.al_state in (A.SAFE_OP, A.OP) and self.pdo.tx:
            with self.drive.lock:
                self.esc.set_inputs(3, self.pdo.pack())

    def watchdog_expired(self) -> None:
        if self.esc.al_state is not A.OP:
            return
        with self.drive.lock:
            if self.device.state in (PowerState.ENABLED, PowerState.QUICK_STOP):
                wd = self.esc.watchdog_s() or 0.0
                self.device.fault(WATCHDOG_FAULT, f"SM watchdog: no outputs for {wd:.3f} s")
            self.drive.sync_device()
        self.drive.nmt = _NMT[A.SAFE_OP]
        self.esc.set_al(A.SAFE_OP, al.SM_WATCHDOG)
