"""``ethercat://`` -- a CiA 402 servo drive over EtherCAT (CoE), servobench as the master.

``ethercat://eth1?slave=1`` (query keys: :mod:`servobench.drivers.ethercat.options`).

Needs pysoem (``pip install 'servobench[ethercat]'``) and CAP_NET_RAW. At open
(:class:`~servobench.drivers.ethercat.master.EthercatMaster`): scan, the
slave's identity, the CiA 402 check (0x1000 profile 402), the command mode
from 0x6502 and ``mode`` (below), the factor group read as on CANopen
(:mod:`servobench.drivers.cia402_units`), the quick stop option code 0x605A,
max torque 0x6072 from ``max_u`` where the slave has it, mode 0x6060, the PDO
mapping (:mod:`.layout`), then SAFE-OP and OP with DC SYNC0 at the cycle
period where the slave has distributed clocks, DC-synchronous (0x1C32:01 = 2)
where the slave announces it in 0x1C32:04. :meth:`set_cycle` (before
enabling) takes the slave back to PRE-OP, sets 0x1C32:02 [ns] and 0x60C2
where it has them, and comes back to OP with SYNC0 at the new period.

Required are only what the run cannot work without: the PDO mapping, the
mode of operation 0x6060 and the DC settings. The optional objects (0x6072,
0x1C32:01, 0x1C32:02, 0x60C2) are read first and written only where they
differ; one the slave refuses (read-only 0x1C32:02, abort 0x06010002, as on
many drives) is a remark (``Drive.remarks``, the log's ``remarks``), not an
error. ``open(read_only=True)`` (``commission --dry-run``) only reads: the
identity, the objects, state and feedback over SDO, in PRE-OP; no SDO
download, no state beyond PRE-OP, no watchdog.

Command mode (``mode``): cyclic synchronous torque, the target torque 0x6071
(``cst``; ``auto``, the default, where 0x6502 announces it); else, or with
``mode=csp``, the torque offset 0x60B2 under the drive's own cyclic
synchronous position loop (``Drive.hold_only``): enabling holds the position
the axis stands at (0x607A), :meth:`hold_position` moves the hold, and
0x6077 reads back the total torque applied. Neither: one line naming what
is missing.

Quick stop (:meth:`stop`) follows 0x605A: SWITCH ON DISABLED (codes 0-4) and
QUICK STOP ACTIVE (5-8) both count as stopped; a drive still OPERATION
ENABLED (or elsewhere) after :data:`STATE_TIMEOUT_S` gets "disable voltage"
(transition 9/12) and is checked disabled, and the remark says so; only if
that fails too does the stop raise.

Each :meth:`exchange` is one frame (two with a DC-synchronous slave, whose
outputs take force and inputs are sampled at its SYNC0 events: the outputs,
then, once its DC clock passed the next event, the inputs sampled there,
:meth:`_sample_at_sync0`): the controlword and target torque (or,
in the hold, the torque offset and target position) out; statusword,
position, velocity, torque actual and the time stamp in. The drive clock
(``Feedback.t_s``, from 0 at the first sample of the session) is the DC
system time at which the slave sampled its inputs, the timestamp object
0x10F8 [ns], where it maps one; else its time stamp 0x1013 [µs]; else from
the DC system time of the frame (the reference clock's 0x0910 read in the
same frame by an FRMW): the SYNC0 event before it for a DC-synchronous
slave, else the instant the frame passed the slave (when a slave
synchronous to the SM2 event samples); else the host's clock. A
DC-synchronous slave's feedback also says where its command took force
(``Feedback.t_act_s``, :meth:`reports_action_instant`): a reading frame
that passed the slave after the next SYNC0 event (the host woke a cycle or
more late) returns that event's sample, while the command acted since the
event before; the runner logs it as ``t_act``. Such a slave paces a real-time
run itself (:meth:`start_cycle_clock`): the host sends each cycle's outputs
right after reading the last ones, one exchange per SYNC0 event.
``drive_clock`` is True in all but the last case; the log's ``drive_clock``
says which. Position and 0x1013 are unwrapped across their 32-bit roll-over.

The CiA 402 state machine is walked through the process data with
:func:`servobench.drivers.cia402.plan`, each step under a deadline. Drive-side
hold (:meth:`hold_position`): where 0x6502 offers cyclic synchronous position
and the slave maps 0x607A, 0x60B2 and 0x6077, the drive's loop holds 0x607A and
the host's command is the torque offset. Safety: the SM watchdog is armed at
open (``watchdog``), disarmed at close; a statusword in FAULT raises
:class:`~servobench.errors.DriveFaultError` (0x603F), a lost link
:class:`~servobench.errors.DriveConnectionError`; the Drive base stops the axis
on any error.

Log metadata beside the units: ``scale_u``/``scale_v``/``scale_x`` and their
``_source``, ``drive_clock``, ``distributed_clocks``, ``complete_access``,
``drive_hold``, ``command``, ``quick_stop_option``, ``remarks``; the trailer
counts ``link_wkc_errors``.
"""

from __future__ import annotations

import math
import struct
import time
from collections.abc import Mapping
from dataclasses import replace

from servobench.drivers.base import Drive, DriveInfo, Feedback
from servobench.drivers.canopen.link import CounterUnwrap
from servobench.drivers.cia402 import (
    CW_DISABLE_VOLTAGE,
    MODE_CSP,
    MODE_CST,
    CiA402State,
    decode_statusword,
    interpolation_period,
    plan,
    quick_stop_end,
    stop_axis,
    supports_mode,
)
from servobench.drivers.cia402_units import FactorObjects, Scaling, derive_scaling
from servobench.drivers.ethercat.layout import REQUIRED_RX, TIMESTAMPS
from servobench.drivers.ethercat.master import OP, EthercatMaster
from servobench.drivers.ethercat.options import QUERY_KEYS, EthercatOptions
from servobench.errors import (
    DriveConfigError,
    DriveConnectionError,
    DriveFaultError,
    StateTransitionError,
    UsageError,
)

S = CiA402State
#: Deadline of each CiA 402 state transition, and of the quick stop [s].
STATE_TIMEOUT_S = 1.0
#: How long each step of the CiA 402 walk towards a state may take [s]: a failure to answer, not
#: a stop, so as long as the master's AL transitions (a loaded host sends frames late).
WALK_TIMEOUT_S = 3.0
#: The RxPDO objects a drive commanded under its own hold (``hold_only``) needs.
HOLD_RX = (0x6040, 0x607A, 0x60B2)
#: A DC-synchronous exchange: margin after the SYNC0 event before the inputs are read [s],
#: and how many cycles (beyond 1 s) it waits for the slave's DC clock to pass the event.
SYNC0_MARGIN_S = 50e-6
SYNC0_WAIT_CYCLES = 100
DEFAULT_CYCLE_S = 1e-3
_I16 = 32767


class EthercatDrive(Drive):
    """A CiA 402 drive on EtherCAT, commanded in torque (see the module docstring)."""

    query_keys = QUERY_KEYS
    drive_clock = True  # the slave's time stamp, or DC system time (False: host clock only)

    def __init__(self, url) -> None:
        super().__init__(url)
        self.options = EthercatOptions.from_url(self.url)
        self.bus: EthercatMaster | None = None
        self.scaling: Scaling | None = None
        self.supports_drive_hold = False
        self._clock_description = ""
        self._cycle_s = DEFAULT_CYCLE_S
        self._values: dict[int, int] = {}
        self._x_unwrap = CounterUnwrap(32)
        self._t_unwrap = CounterUnwrap(32)
        self._dc0: int | None = None
        self._expected: CiA402State | None = None
        self._hold_reason = "not checked"
        self._command = "not open"
        self._identity: dict[str, object] = {}
        self._quick_stop_option: int | None = None

    # -------------------------------------------------------------- lifecycle
    def _open(self) -> None:
        bus = self.bus = EthercatMaster(self.options)
        try:
            bus.open()
            if self.read_only:
                self._read_up(bus)
            else:
                self._bring_up(bus)
        except BaseException:
            self.bus = None
            bus.close(read_only=self.read_only)
            raise

    def _remark(self, text: str | None) -> None:
        if text and text not in self.remarks:
            self.remarks.append(text)

    def _objects(self, bus: EthercatMaster) -> tuple[int, list[int], list[int]]:
        """The checks and reads of any open: 0x1000, 0x6502, identity, factor group, 0x605A, the
        command mode; the supported modes and the RxPDO/TxPDO objects the slave has."""
        device_type = bus.sdo_read(0x1000, 0, "I")
        if device_type & 0xFFFF != 402:
            raise DriveConfigError(
                f"{bus.name} is no CiA 402 drive: device type 0x{device_type:08X} (0x1000)"
            )
        modes = bus.sdo_read(0x6502, 0, "I")
        self._identity = {**bus.identity(), "device_type": device_type, "modes": modes}
        self.scaling = derive_scaling(self._factors(bus), self.options.overrides)
        self.units = self.scaling.units
        self._quick_stop_option = bus.sdo_optional(0x605A, 0, "h")
        rx = [
            i for i in (0x6040, 0x6071, 0x607A, 0x60B2) if bus.sdo_optional(i, 0, "h") is not None
        ]
        tx = [i for i in (0x6041, 0x6064, 0x606C, 0x6077)
              if bus.sdo_optional(i, 0, "H") is not None]  # fmt: skip
        stamp = next((i for i in TIMESTAMPS if bus.sdo_optional(i, 0, "H") is not None), None)
        tx += [stamp] if stamp is not None else []
        self.hold_only = self._command_mode(bus.name, modes, rx, tx)
        return modes, rx, tx

    def _command_mode(self, name: str, modes: int, rx: list[int], tx: list[int]) -> bool:
        """True: commanded as torque offset under the drive's own CSP hold; False: CST. Raises
        the one line naming what is missing where neither is there."""
        want = self.options.mode
        cst = supports_mode(modes, MODE_CST) and 0x6071 in rx
        lacking = [f"0x{i:04X}" for i, have in ((0x607A, rx), (0x60B2, rx), (0x6077, tx))
                   if i not in have]  # fmt: skip
        csp = supports_mode(modes, MODE_CSP) and not lacking
        no_cst = (f"no cyclic synchronous torque (0x6502 = 0x{modes:08X}, bit 9 clear)"
                  if not supports_mode(modes, MODE_CST) else "no target torque 0x6071")  # fmt: skip
        if want == "cst" and not cst:
            raise DriveConfigError(f"{name}: mode=cst, but it has {no_cst}")
        if want == "cst" or (want == "auto" and cst):
            self._command = "cyclic synchronous torque: target torque 0x6071"
            return False
        if not csp:
            missing = ("no cyclic synchronous position (0x6502 bit 7 clear)"
                       if not supports_mode(modes, MODE_CSP)
                       else f"lacks {', '.join(lacking)} for a torque offset under its position hold")  # fmt: skip
            head = (f"{name}: mode=csp, but it has " if want == "csp"
                    else f"{name} cannot be identified: {no_cst}, and ")  # fmt: skip
            raise DriveConfigError(head + missing)
        why = "mode=csp" if want == "csp" else no_cst
        self._command = (f"torque offset 0x60B2 under the drive's own cyclic synchronous position "
                         f"hold, 0x6077 read back ({why})")  # fmt: skip
        return True

    def _read_up(self, bus: EthercatMaster) -> None:
        """A read-only open: identity and objects over SDO in PRE-OP, nothing written."""
        modes, rx, tx = self._objects(bus)
        bus.plan_pdos(rx, tx, HOLD_RX if self.hold_only else REQUIRED_RX)
        self._hold_reason = None if self.hold_only else self._hold_check(bus, modes)
        self.supports_drive_hold = self._hold_reason is None
        self._clock_description = "read-only: feedback over SDO (no process data)"
        self.drive_clock = False

    def _bring_up(self, bus: EthercatMaster) -> None:
        modes, rx, tx = self._objects(bus)
        if math.isfinite(self.limits.max_command) and bus.sdo_optional(0x6072, 0, "H") is not None:
            lsb = min(0xFFFF, int(self.limits.max_command / abs(self.scaling.u.scale)))
            refused = bus.sdo_write_optional(0x6072, 0, "H", lsb)
            self._remark(refused and f"max torque {refused}: max_u is enforced by the host alone")
        mode = MODE_CSP if self.hold_only else MODE_CST
        bus.sdo_write(0x6060, 0, struct.pack("<b", mode))  # required: refused, the run cannot work
        self._write_cycle(bus, self._cycle_s)
        self._remark(bus.choose_dc_synchronous())  # in PRE-OP: map_pdos ends in SAFE-OP
        bus.map_pdos(rx, tx, HOLD_RX if self.hold_only else REQUIRED_RX)  # config_map: SAFE-OP
        self._hold_reason = None if self.hold_only else self._hold_check(bus, modes)
        self.supports_drive_hold = self._hold_reason is None
        bus.go_op(self._cycle_s)
        self._clock_description = (
            "0x10F8 DC system time of each sample [ns]" if bus.tx.has(0x10F8)
            else "0x1013 time stamp of each sample [µs]" if bus.tx.has(0x1013)
            else "DC system time of each sample (the SYNC0 event before each frame)"
            if bus.dc_synchronous
            else "DC system time of each frame (SYNC0 on)" if bus.has_dc
            else "host clock (no time stamp, no DC)"
        )  # fmt: skip
        self.drive_clock = bus.tx.has(0x10F8) or bus.tx.has(0x1013) or bus.has_dc
        self._dc0 = None  # the drive clock starts at 0 with the session
        bus.keep_alive = True
        bus.start_keepalive()
        state = self._state()
        if state in (S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE):  # left enabled by someone else
            self._goto(S.SWITCH_ON_DISABLED)

    @staticmethod
    def _factors(bus: EthercatMaster) -> FactorObjects:
        def pair(index: int):
            a, b = bus.sdo_optional(index, 1, "I"), bus.sdo_optional(index, 2, "I")
            return None if a is None or b is None else (a, b)

        return FactorObjects(
            rated_torque_mNm=bus.sdo_optional(0x6076, 0, "I"),
            rated_current_mA=bus.sdo_optional(0x6075, 0, "I"),
            encoder=pair(0x608F), gear=pair(0x6091), feed=pair(0x6092),
            position_unit=bus.sdo_optional(0x60A8, 0, "I"),
            velocity_unit=bus.sdo_optional(0x60A9, 0, "I"),
        )  # fmt: skip

    @staticmethod
    def _hold_check(bus: EthercatMaster, modes: int) -> str | None:
        if not supports_mode(modes, MODE_CSP):
            return "0x6502 announces no cyclic synchronous position"
        lacking = [f"0x{i:04X}" for i, layout in ((0x607A, bus.rx), (0x60B2, bus.rx),
                                                  (0x6077, bus.tx)) if not layout.has(i)]  # fmt: skip
        return f"the slave lacks {', '.join(lacking)}" if lacking else None

    def _write_cycle(self, bus: EthercatMaster, period_s: float) -> None:
        """0x1C32:02 [ns] and 0x60C2 where the slave has them, writable and different; a
        refusal is a remark (the slave runs its cycle as it is set, SYNC0 paces it)."""
        refused = bus.sdo_write_optional(0x1C32, 2, "I", round(period_s * 1e9))
        self._remark(refused and f"SM2 cycle time {refused}")
        if bus.sdo_optional(0x60C2, 1, "B") is not None:
            value, index = interpolation_period(period_s)
            refused = (bus.sdo_write_optional(0x60C2, 1, "B", value)
                       or bus.sdo_write_optional(0x60C2, 2, "b", index))  # fmt: skip
            self._remark(refused and f"interpolation period {refused}")

    def _configure_watchdog(self, timeout_s: float) -> None:
        self.bus.set_watchdog(timeout_s)

    def _close(self) -> None:
        bus, self.bus = self.bus, None
        if bus is not None:
            bus.close(read_only=self.read_only)

    def _set_cycle(self, period_s: float) -> None:
        if self.enabled:
            raise UsageError("set the cycle before enabling: 0x1C32 and SYNC0 are set in PRE-OP")
        if self.bus is None or period_s == self._cycle_s:
            self._cycle_s = period_s
            return
        self.bus.keep_alive = False
        self.bus.back_to_pre_op()
        self._write_cycle(self.bus, period_s)
        self._cycle_s = period_s
        self.bus.go_op(period_s)
        self.bus.keep_alive = True

    # ---------------------------------------------------------------- cycles
    def _frame(self) -> dict[int, int]:
        bus = self.bus
        if bus.keepalive_error is not None:
            raise bus.keepalive_error
        inputs, dc_ns = bus.cycle(bus.rx.pack(self._values))
        values = bus.tx.unpack(inputs)
        values["dc"] = dc_ns
        return values

    def _state(self) -> CiA402State:
        return decode_statusword(self._frame()[0x6041])

    def _goto(self, target: CiA402State) -> None:
        state = self._state()
        from_fault = state in (S.FAULT, S.FAULT_REACTION_ACTIVE)
        for step in plan(state, target):
            if step.controlword is not None:
                self._values[0x6040] = step.controlword
            deadline = time.monotonic() + WALK_TIMEOUT_S
            while (state := self._state()) is not step.next_state:
                if state in (S.FAULT, S.FAULT_REACTION_ACTIVE) and not from_fault:
                    raise self._fault_error(f"while going to {step.next_state.value}")
                if time.monotonic() > deadline:
                    if from_fault:
                        raise self._fault_error("persists after fault reset")
                    al_state, code = self.bus.read_state()
                    where = "" if al_state == OP else (
                        f" (AL state 0x{al_state:02X}, AL status code 0x{code:04X}: "
                        "the slave takes no outputs outside OP)")  # fmt: skip
                    raise StateTransitionError(
                        f"{self.bus.name} stayed in {state.value}, expected "
                        f"{step.next_state.value} within {WALK_TIMEOUT_S} s{where}"
                    )

    def _fault_error(self, context: str) -> DriveFaultError:
        code = self.bus.sdo_read(0x603F, 0, "H")
        self._expected = None
        return DriveFaultError(f"{self.bus.name} in FAULT 0x{code:04X} {context}", code)

    def _enable(self) -> None:
        if self.bus.back_to_op() is not None:
            self._remark(f"the SM watchdog had taken {self.bus.name} to SAFE-OP while the axis "
                         "was not enabled (the host was silent longer than the watchdog); "
                         "back in OP")  # fmt: skip
        values = self._frame()
        if decode_statusword(values[0x6041]) in (S.FAULT, S.FAULT_REACTION_ACTIVE):
            raise self._fault_error("cannot enable; reset the fault first")
        if self.hold_only:  # the drive's own loop holds where the axis stands
            self._values[0x607A] = values[0x6064]
        self._values.update({0x6071: 0, 0x60B2: 0})
        self._goto(S.OPERATION_ENABLED)
        self._expected = S.OPERATION_ENABLED
        self.bus.keep_alive = False  # from now on only the host's cycles feed the SM watchdog

    def _disable(self) -> None:
        if self.bus is None:
            return
        self._expected = None
        self._values.update({0x6071: 0, 0x60B2: 0})
        try:
            if self._state() in (S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE, S.SWITCHED_ON,
                                 S.READY_TO_SWITCH_ON):  # fmt: skip
                self._goto(S.SWITCH_ON_DISABLED)
        finally:
            if self._holding:
                self._leave_hold()
            self.bus.keep_alive = True

    def _quick_stop(self) -> None:
        """Quick stop as 0x605A says it ends; disable voltage where the drive stays enabled."""
        self._values.update({0x6071: 0, 0x60B2: 0})
        if self._state() is not S.OPERATION_ENABLED:
            return
        self._expected = None
        self._expected, remark = stop_axis(self._await, self._quick_stop_option, self.bus.name,
                                           STATE_TIMEOUT_S)  # fmt: skip
        if remark:
            self._remark(remark)

    def _await(self, controlword: int, target: CiA402State) -> CiA402State:
        """Send ``controlword`` and cycle until ``target`` or the deadline; the state reached
        (a quick stop's target, else any of :data:`QUICK_STOPPED` at the deadline)."""
        self._values[0x6040] = controlword
        deadline = time.monotonic() + STATE_TIMEOUT_S
        while (state := self._state()) is not target:
            if state in (S.FAULT, S.FAULT_REACTION_ACTIVE):
                raise self._fault_error(f"while stopping (controlword 0x{controlword:04X})")
            if time.monotonic() > deadline:
                break
        return state

    def _reset_fault(self) -> None:
        if self._state() not in (S.FAULT, S.FAULT_REACTION_ACTIVE):
            return
        self._values[0x6040] = CW_DISABLE_VOLTAGE  # bit 7 low first: the reset is an edge
        self._frame()
        self._goto(S.SWITCH_ON_DISABLED)
        self._expected = None

    def _fault_code(self) -> int:
        return self.bus.sdo_read(0x603F, 0, "H")

    def _representable(self, u: float) -> float:
        if self.scaling is None:
            return u
        scale = self.scaling.u.scale
        return max(-_I16, min(_I16, round(u / scale))) * scale

    def _set_command(self, u: float) -> None:
        """``u`` into the target torque, or under a hold the torque offset."""
        raw = round(u / self.scaling.u.scale)
        offset = self._holding or self.hold_only
        if self.hold_only and not self._holding and raw:
            raise UsageError(
                f"{self.bus.name} takes a command only as the torque offset of its own position "
                f"hold ({self._command.split('(')[-1].rstrip(')')}): excite it under hold_position, as "
                "sidbe does in closed loop"
            )
        self._values[0x60B2 if offset else 0x6071] = raw
        if offset:
            self._values[0x6071] = 0

    def _write_command(self, u: float) -> None:
        self._set_command(u)
        self._frame()

    def _exchange(self, u: float) -> Feedback:
        self._set_command(u)
        values = self._frame()
        if not self.bus.dc_synchronous:
            return self._feedback(values)
        values, due = self._sample_at_sync0(values["dc"])
        fb = self._feedback(values)
        # the sample is the last SYNC0 event's before the reading frame: where that is after
        # ``due`` (the host woke a cycle or more late), the command acted that much earlier
        late_ns = self.bus.last_sync0(values["dc"]) - due
        return replace(fb, t_act_s=fb.t_s - max(0, late_ns) * 1e-9)

    def reports_action_instant(self) -> bool:
        return self.bus is not None and self.bus.dc_synchronous

    def start_cycle_clock(self, period_s: float) -> bool:
        """A DC-synchronous slave paces the cycle itself: each exchange waits for its next SYNC0
        event (:meth:`_sample_at_sync0`), so the host sends the next outputs as soon as it has
        read the last inputs, one exchange per event, and keeps no schedule of its own (a host
        schedule beats against the slave's clock: an exchange sent just past an event waits a
        whole cycle, and one late by more than a cycle never catches up)."""
        return self.bus is not None and self.bus.dc_synchronous

    def _sample_at_sync0(self, sent_dc_ns: int) -> tuple[dict[int, int], int]:
        """A DC-synchronous slave: the inputs sampled once the outputs sent took force, and the
        SYNC0 event [DC ns] at which they did.

        The outputs of the frame that passed the slave at ``sent_dc_ns`` take
        force at the next SYNC0 event, where the inputs are sampled; this
        waits for the slave's DC clock to pass that event (it runs at the
        host's rate) and reads them, so ``u_k`` is held from the instant of the
        sample returned, as the exchange contract says. A frame that comes too
        early (its DC time before the event) is sent again. One that comes a
        cycle or more late (the host woke late) returns a later event's sample:
        :meth:`_exchange` then says where the command acted (``Feedback.t_act_s``).
        """
        bus = self.bus
        due, sent_at = bus.next_sync0(sent_dc_ns), time.monotonic_ns()
        deadline = time.monotonic() + SYNC0_WAIT_CYCLES * bus.sync0[1] * 1e-9 + 1.0
        while True:
            wait_ns = due - sent_dc_ns - (time.monotonic_ns() - sent_at)
            if wait_ns > 0:
                time.sleep(wait_ns * 1e-9 + SYNC0_MARGIN_S)
            values = self._frame()
            if values["dc"] >= due:
                return values, due
            if time.monotonic() > deadline:
                raise DriveConnectionError(
                    f"{bus.name}: its DC clock did not reach the next SYNC0 event "
                    f"({(due - values['dc']) * 1e-6:.3f} ms short)"
                )

    def _feedback(self, values: Mapping[int, int]) -> Feedback:
        state = decode_statusword(values[0x6041])
        if state in (S.FAULT, S.FAULT_REACTION_ACTIVE):
            raise self._fault_error(f"(statusword 0x{values[0x6041]:04X})")
        if self._expected is not None and state is not self._expected:
            raise StateTransitionError(
                f"{self.bus.name} left {self._expected.value}: statusword 0x{values[0x6041]:04X}"
            )
        s = self.scaling
        if 0x10F8 in values:
            self._dc0 = values[0x10F8] if self._dc0 is None else self._dc0
            t_s = (values[0x10F8] - self._dc0) * 1e-9
        elif 0x1013 in values:
            t_s = self._t_unwrap(values[0x1013]) * 1e-6
        elif self.bus.has_dc:  # the frame's DC time; DC-synchronous: the SYNC0 event before it
            dc = self.bus.last_sync0(values["dc"]) if self.bus.dc_synchronous else values["dc"]
            self._dc0 = dc if self._dc0 is None else self._dc0
            t_s = (dc - self._dc0) * 1e-9
        else:
            t_s = time.monotonic()
        applied = values[0x6077] * s.u.scale if 0x6077 in values else math.nan
        return Feedback(
            t_s=t_s,
            velocity=values[0x606C] * s.v.scale,
            position=self._x_unwrap(values[0x6064]) * s.x.scale,
            applied=applied,
        )

    def _read_feedback(self) -> Feedback:
        """Over SDO (mailbox): no process data, the slave is not clocked."""
        bus = self.bus
        values = {0x6041: bus.sdo_read(0x6041, 0, "H"), 0x6064: bus.sdo_read(0x6064, 0, "i"),
                  0x606C: bus.sdo_read(0x606C, 0, "i"), "dc": 0}  # fmt: skip
        if bus.tx.has(0x10F8):
            values[0x10F8] = bus.sdo_read(0x10F8, 0, "Q")
        if bus.tx.has(0x1013):
            values[0x1013] = bus.sdo_read(0x1013, 0, "I")
        if bus.tx.has(0x6077):
            values[0x6077] = bus.sdo_read(0x6077, 0, "h")
        return self._feedback(values)

    # ------------------------------------------------------------- the hold
    def _hold_position(self, x_ref: float) -> None:
        if not self.limits.min_position <= x_ref <= self.limits.max_position:
            raise UsageError(
                f"x_ref {x_ref:.6g} is outside the allowed travel "
                f"[{self.limits.min_position:.6g}, {self.limits.max_position:.6g}]"
            )
        target = round(x_ref / self.scaling.x.scale)
        self._values.update({0x607A: (target + 2**31) % 2**32 - 2**31, 0x60B2: 0, 0x6071: 0})
        if not self.hold_only:  # hold-only: in CSP since open
            self.bus.sdo_write(0x6060, 0, struct.pack("<b", MODE_CSP))

    def _release_hold(self) -> None:
        self._leave_hold()

    def _leave_hold(self) -> None:
        self._values.update({0x60B2: 0, 0x6071: 0})
        if not self.hold_only:  # hold-only: the drive goes on holding the last target
            self.bus.sdo_write(0x6060, 0, struct.pack("<b", MODE_CST))

    # ---------------------------------------------------------------- status
    def link_recoveries(self) -> Mapping[str, int]:
        return {"wkc_errors": self.bus.wkc_errors} if self.bus is not None else {}

    def log_metadata(self) -> dict[str, str]:
        meta = super().log_metadata()
        if self.scaling is None or self.bus is None:
            return meta
        for key in ("u", "v", "x"):
            factor = getattr(self.scaling, key)
            meta[f"scale_{key}"] = f"{factor.scale:.12g}"
            meta[f"scale_{key}_source"] = factor.source
        option = self._quick_stop_option
        meta.update(
            command=self._command,
            quick_stop_option="none (no 0x605A)" if option is None else (
                f"0x605A = {option}: ends in {quick_stop_end(option).value}"),
            drive_clock=self._clock_description,
            distributed_clocks=(f"SYNC0 every {self._cycle_s * 1e6:.0f} µs"
                                + (", DC-synchronous (0x1C32:01 = 2)" if self.bus.dc_synchronous
                                   else "")) if self.bus.has_dc else "none",
            complete_access="not mapped (read-only)" if self.read_only else "yes"
            if self.bus.complete_access else self.bus.complete_access_note or "refused: mapped entry by entry",
            drive_hold="cyclic synchronous position: target 0x607A, offset 0x60B2, 0x6077 read back"
            if self._hold_reason is None else f"unavailable: {self._hold_reason}",
        )  # fmt: skip
        return meta

    def _info(self) -> DriveInfo:
        ident, bus = self._identity, self.bus
        state = decode_statusword(bus.sdo_read(0x6041, 0, "H"))
        al_state, al_code = bus.read_state()
        return DriveInfo(
            transport="ethercat",
            vendor=f"0x{ident['vendor']:08X}",
            product=f"{ident['name']} (product code 0x{ident['product']:08X})",
            firmware=f"revision 0x{ident['revision']:08X}",
            state=state.value,
            fault_code=self._fault_code() if state is S.FAULT else 0,
            units=dict(self.units),
            extra={"slave": self.options.slave, "iface": self.options.iface,
                   "al_state": f"0x{al_state:02X}", "al_status_code": f"0x{al_code:04X}",
                   "emergency": None if bus.emergency is None else f"0x{bus.emergency[0]:04X}",
                   "wkc_errors": bus.wkc_errors, **self.log_metadata()},
        )  # fmt: skip
