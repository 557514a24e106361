"""``canopen://`` -- a CiA 402 servo drive on CANopen, in a torque mode.

``canopen://can0?interface=socketcan&node=2&bitrate=1000000``
``canopen://vcan0?interface=socketcand&host=127.0.0.1&port=29536&node=2``

Query keys: ``interface`` (python-can interface, default ``socketcan``),
``channel`` (when the URL host cannot hold it, e.g. case or slashes),
``node`` (required, 1..127), ``bitrate`` [bit/s] (default 1000000),
``host`` and ``port`` (the socketcand server, required with
``interface=socketcand`` only), ``mode`` (``cst``: cyclic synchronous torque
0x6060 = 10, default; ``pt``: profile torque, 4), ``host_node`` (node id of
the host's heartbeat, default 127), ``sdo_timeout`` and ``pdo_timeout`` [s],
``eds`` (the drive's own EDS file; without it servobench asks the drive by
SDO which objects it has), ``sync_cob`` (the SYNC COB-ID written to the
drive's 0x1005 and sent each cycle, default 0x80), and the unit overrides
``pos_scale`` (rad, or m on a linear axis, per 0x6064 LSB), ``vel_scale``
(rad/s or m/s per 0x606C LSB) and ``torque_constant`` (N m/A, N/A on a linear
motor: turns a current-mode drive's amperes into torque).

Several hosts on one bus: each host's SYNC would clock every drive that
listens to 0x80, so give each drive its own SYNC with ``sync_cob`` (a free
11-bit id outside CiA 301's restricted ones, e.g. 0x90) and each host its own
heartbeat node with ``host_node`` (otherwise a drive's watchdog is fed by
the other host and would not notice its own host die).

The drive's own object dictionary decides the bring-up: its EDS when the URL
names one, else SDO probing (abort 0x06020000: the object does not exist).
Units come from its factor group (:mod:`servobench.drivers.cia402_units`):
``u`` in N m (N on a linear axis, A for a current-mode drive without a
torque constant), ``v`` in rad/s or m/s, ``x`` in rad or m, or the drive's
own units where they cannot be converted. The drive clock is the time stamp
0x1013 [µs] sampled at each SYNC when the drive can map it, else the SYNC
count times the cycle period. Without 0x6072 (max torque) ``max_u`` is
enforced by the host alone; without 0x6007 (abort connection option) what
the drive does when the host's heartbeat stops is its own setting, and a
one-line :class:`~servobench.errors.DriveWarning` says so.

Log metadata (:meth:`CANopen402Drive.log_metadata`), beside ``unit_u``,
``unit_v``, ``unit_x``: ``scale_u``, ``scale_v``, ``scale_x`` (SI per LSB of
0x6071, 0x606C, 0x6064) with ``scale_u_source``, ``scale_v_source``,
``scale_x_source`` (the objects or URL keys each factor came from),
``drive_clock``, ``object_dictionary`` (``EDS <file>`` or ``SDO probing``),
``max_torque`` (0x6072, or host-side clamping only), ``watchdog_action`` and
``drive_hold``.

Set-up runs over SDO in NMT PRE-OPERATIONAL (mode, PDO mapping, heartbeats;
the cycle period 0x1006 and interpolation period 0x60C2 too, in
:meth:`set_cycle`), the cycle in OPERATIONAL: :meth:`exchange` sends the
RPDOs and a SYNC, and waits for the SYNC's TPDOs (the layout is in
:mod:`servobench.drivers.canopen.mapping`). The CiA 402 state machine is walked with
:func:`servobench.drivers.cia402.plan`, each step under a deadline; failures
raise, never log. :meth:`read` uses SDO and sends no SYNC, so it does not
clock a lock-step simulated drive. Position and the time stamp are unwrapped
across their 32-bit roll-over. A TPDO pair that repeats the time stamp
before it and began to arrive before this cycle's SYNC (a duplicate, or a
late answer to an earlier SYNC) is dropped; one that answers this SYNC with
the stamp before is a repeated sample of a drive whose tick is slower than
the SYNC. Without 0x1013 a late pair cannot be told from the answer. An EMCY with a
non-zero error code ends the next cycle with :class:`~servobench.errors.DriveFaultError`.

Drive-side hold (:meth:`hold_position`): where the drive offers cyclic
synchronous position (0x6502 bit 7) and maps the torque offset 0x60B2, the
target position 0x607A and the torque actual value 0x6077, the drive's own
loop holds 0x607A = ``x_ref``, the host's command goes out as the torque
offset, and ``Feedback.applied`` is 0x6077 (read back on every SYNC in any
mode). With a finite ``max_u`` the drive must have 0x6072, which bounds its
loop's torque. :attr:`supports_drive_hold` is set at open.

Watchdog: the host produces heartbeats every ``watchdog / 4`` (node
``host_node``); the drive consumes them (0x1016, time ``watchdog``) and
faults (0x6007 = 1) when they stop, e.g. when the host process dies. Opening
leaves the drive disabled (a drive found enabled is switched off); closing
disarms the consumer and returns the drive to its torque mode.
"""

from __future__ import annotations

import logging
import math
import threading
import time
import warnings

import canopen

from servobench.drivers.base import Drive, DriveInfo, Feedback
from servobench.drivers.canopen.bringup import read_up, set_mode
from servobench.drivers.canopen.link import load_eds
from servobench.drivers.canopen.options import AUTO, QUERY_KEYS, CanopenOptions
from servobench.drivers.canopen.session import CanopenSession
from servobench.drivers.cia402 import (
    CW_DISABLE_VOLTAGE,
    MODE_CSP,
    MODE_CST,
    CiA402State,
    Step,
    decode_statusword,
    plan,
    quick_stop_end,
    stop_axis,
    supports_mode,
)
from servobench.drivers.link_budget import canopen_cycle_s
from servobench.errors import (
    DriveConfigError,
    DriveFaultError,
    DriveWarning,
    StateTransitionError,
    UsageError,
)

# The library's own log lines would reach stderr through logging's last-resort
# handler; every failure is raised as a typed error here instead.
logging.getLogger("canopen").addHandler(logging.NullHandler())
logging.getLogger("can").addHandler(logging.NullHandler())

S = CiA402State

__all__ = ["CANopen402Drive", "load_eds"]

#: Deadline of each CiA 402 state transition [s].
STATE_TIMEOUT_S = 1.0
#: Statusword polling period while waiting for a state [s].
STATE_POLL_S = 0.002


class CANopen402Drive(Drive):
    """A CiA 402 drive on CANopen, commanded in torque (see the module docstring for the URL)."""

    query_keys = QUERY_KEYS
    drive_clock = True  # 0x1013, or the SYNC count times the cycle period

    def __init__(self, url) -> None:
        super().__init__(url)
        self.options = CanopenOptions.from_url(self.url)
        o = self.options
        self.interface, self.channel, self.node_id = o.interface, o.channel, o.node_id
        self.bitrate, self.host_node, self.sync_cob = o.bitrate, o.host_node, o.sync_cob
        self.session: CanopenSession | None = None
        self.supports_drive_hold = False  # set at open, from the drive's objects
        self.torque_actual = 0.0  #: last 0x6077 [command units]
        self._expected: CiA402State | None = None
        self._quick_stop_option: int | None = None
        self._command = "not open"

    # --------------------------------------------------------------- plumbing
    @property
    def node(self) -> canopen.RemoteNode | None:
        """The driver's canopen node (for raw SDO access in tests and tools)."""
        return None if self.session is None else self.session.node

    @property
    def network(self):
        return None if self.session is None else self.session.network

    def _sdo(self):
        return self.session.sdo

    # -------------------------------------------------------------- lifecycle
    def _open(self) -> None:
        session = CanopenSession(self.options, self.limits)
        session.connect()
        try:
            if self.read_only:  # SDO uploads only: no download, no NMT command
                read_up(session)
            else:
                session = self._bring_up(session)
            self.session = session
            self.units = session.scaling.units
            self.supports_drive_hold = session.hold_reason is None
            self._quick_stop_option = session.optional(0x605A, 0, None)
            if not self.read_only and self._state() in (S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE):
                self._goto(S.SWITCH_ON_DISABLED)  # left enabled by someone else
        except BaseException:
            self.session = None
            session.disconnect()
            raise
        self._expected = None

    def _bring_up(self, session: CanopenSession) -> CanopenSession:
        """Bring the node up in the URL's mode; ``mode`` unset on a drive without cyclic
        synchronous torque: again, in cyclic synchronous position with the torque offset
        (:attr:`hold_only`). Returns the session brought up."""
        o = self.options
        try:
            session.bring_up()
        except DriveConfigError:
            modes = None if session.objects is None else session.optional(0x6502, 0, None)
            no_cst = modes is not None and not supports_mode(modes, MODE_CST)
            if o.mode_key != AUTO or modes is None or not (no_cst or not session.has_target_torque):
                raise
            session.disconnect()
            self.options = o.with_mode("csp")
            session = CanopenSession(self.options, self.limits)
            session.connect()
            try:
                self._bring_up_hold_only(session, f"no cyclic synchronous torque (0x6502 = 0x{modes:08X}, "
                                         "bit 9 clear)" if no_cst else "no target torque 0x6071")  # fmt: skip
            except BaseException:
                session.disconnect()
                raise
            return session
        if o.mode_key == "csp":
            self._bring_up_hold_only(session, "mode=csp", brought_up=True)
        else:
            self._command = f"{o.mode_name}: target torque 0x6071"
        return session

    def _bring_up_hold_only(self, session: CanopenSession, why: str, brought_up: bool = False) -> None:
        if not brought_up:
            session.bring_up()
        if session.hold_reason is not None:
            head = f"node {self.node_id}: mode=csp, but " if why == "mode=csp" else (
                f"node {self.node_id} cannot be identified: {why}, and ")
            raise DriveConfigError(f"{head}no torque offset under its position hold: {session.hold_reason}")
        self.hold_only = True
        self._command = ("torque offset 0x60B2 under the drive's own cyclic synchronous position hold, "
                         f"0x6077 read back ({why})")  # fmt: skip

    def _configure_watchdog(self, timeout_s: float) -> None:
        """Host heartbeats every ``timeout_s / 4``; the drive consumes them (0x1016) and
        faults (0x6007 = 1) when they stop for ``timeout_s``."""
        if not self.session.arm_watchdog(timeout_s):
            warnings.warn(
                f"node {self.node_id} has no abort connection option 0x6007: when the host's "
                "heartbeat stops, the drive reacts as its own settings say (check that it stops the axis)",
                DriveWarning,
                stacklevel=3,
            )

    def _close(self) -> None:
        session, self.session = self.session, None
        if session is not None and self.read_only:
            session.disconnect()
        elif session is not None:
            session.close(self.options.mode if session.mode != self.options.mode else None)

    def _record_traffic(self, path: str) -> None:
        self.session.record_traffic(path)

    # ------------------------------------------------------------ 402 states
    def _state(self) -> CiA402State:
        return decode_statusword(self._sdo().read(0x6041))

    def _controlword_write(self, controlword: int) -> None:
        self._sdo().write(0x6040, 0, controlword, StateTransitionError)
        self.session.io.values[0x6040] = controlword

    def _goto(self, target: CiA402State) -> None:
        state = self._state()
        for step in plan(state, target):
            if step.controlword is not None:
                self._controlword_write(step.controlword)
            state = self._await_state(step, state)

    def _await_state(self, step: Step, before: CiA402State) -> CiA402State:
        deadline = time.monotonic() + STATE_TIMEOUT_S
        while (state := self._state()) is not step.next_state:
            if state in (S.FAULT, S.FAULT_REACTION_ACTIVE) and before is not S.FAULT:
                raise self._fault_error(f"while going to {step.next_state.value}")
            if time.monotonic() > deadline:
                if before is S.FAULT:
                    raise self._fault_error("persists after fault reset")
                cw = "none (automatic)" if step.controlword is None else f"0x{step.controlword:04X}"
                raise StateTransitionError(
                    f"node {self.node_id} stayed in {state.value} after controlword {cw}; "
                    f"expected {step.next_state.value} within {STATE_TIMEOUT_S} s"
                )
            time.sleep(STATE_POLL_S)
        return state

    def _fault_error(self, context: str) -> DriveFaultError:
        code = self._sdo().read(0x603F)
        return DriveFaultError(f"node {self.node_id} in FAULT 0x{code:04X} {context}", code)

    def _enable(self) -> None:
        if self._state() in (S.FAULT, S.FAULT_REACTION_ACTIVE):
            raise self._fault_error("cannot enable; reset the fault first")
        self.session.io.emcy = None  # what the drive reported before this enable is not news
        if self.hold_only:  # the drive's own loop holds where the axis stands
            self.session.io.set_target(self.session.io.read_feedback().position)
        self.session.io.set_torque(0.0, holding=self._offset)
        self.session.zero_target_torque()
        self._goto(S.OPERATION_ENABLED)
        self._expected = S.OPERATION_ENABLED

    def _disable(self) -> None:
        if self.session is None:
            return
        self._expected = None
        try:
            if self._state() in (S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE, S.SWITCHED_ON,
                                 S.READY_TO_SWITCH_ON):  # fmt: skip
                self._goto(S.SWITCH_ON_DISABLED)
        finally:
            if self.session.mode != self.options.mode:  # leave a hold: back to the torque mode
                self._leave_hold()

    @property
    def _offset(self) -> bool:
        """The command goes out as the torque offset 0x60B2 (a hold, or a hold-only drive)."""
        return self.holding or self.hold_only

    def _quick_stop(self) -> None:
        """Quick stop as 0x605A says it ends; disable voltage where the drive stays enabled."""
        self.session.io.set_torque(0.0, holding=self._offset)
        if self._state() is not S.OPERATION_ENABLED:
            self.session.zero_target_torque()
            return
        self._expected = None
        self._expected, remark = stop_axis(self._await, self._quick_stop_option, f"node {self.node_id}",
                                           STATE_TIMEOUT_S)  # fmt: skip
        if remark and remark not in self.remarks:
            self.remarks.append(remark)

    def _await(self, controlword: int, target: CiA402State) -> CiA402State:
        """Send ``controlword`` and poll until ``target`` or the deadline; the state reached."""
        self._controlword_write(controlword)
        deadline = time.monotonic() + STATE_TIMEOUT_S
        while (state := self._state()) is not target:
            if state in (S.FAULT, S.FAULT_REACTION_ACTIVE):
                raise self._fault_error(f"while stopping (controlword 0x{controlword:04X})")
            if time.monotonic() > deadline:
                break
            time.sleep(STATE_POLL_S)
        return state

    def _reset_fault(self) -> None:
        if self._state() not in (S.FAULT, S.FAULT_REACTION_ACTIVE):
            return
        self._controlword_write(CW_DISABLE_VOLTAGE)  # bit 7 low: the reset is a rising edge
        self._goto(S.SWITCH_ON_DISABLED)
        self._expected = None
        self.session.io.emcy = None

    def _fault_code(self) -> int:
        return self._sdo().read(0x603F)

    # ---------------------------------------------------------------- cycles
    def _representable(self, u: float) -> float:
        return u if self.session is None else self.session.io.representable(u)

    def _set_command(self, u: float) -> None:
        if self.hold_only and not self.holding and u:
            raise UsageError(
                f"node {self.node_id} takes a command only as the torque offset of its own position "
                f"hold ({self._command.split('(')[-1].rstrip(')')}): excite it under hold_position, as "
                "sidbe does in closed loop"
            )
        self.session.io.set_torque(u, holding=self._offset)

    def _write_command(self, u: float) -> None:
        self._set_command(u)
        self.session.io.send_rpdos(holding=self._offset)

    def _exchange(self, u: float) -> Feedback:
        io = self.session.io
        self._set_command(u)
        cycle = io.cycle(holding=self._offset)
        self._check_state(cycle.statusword)
        if io.emcy is not None:
            code, register = io.emcy
            self._expected = None
            raise DriveFaultError(
                f"node {self.node_id} sent EMCY 0x{code:04X} (error register 0x{register:02X})",
                code,
            )
        if not math.isnan(cycle.feedback.applied):
            self.torque_actual = cycle.feedback.applied
        return cycle.feedback

    def _check_state(self, statusword: int) -> None:
        state = decode_statusword(statusword)
        if state in (S.FAULT, S.FAULT_REACTION_ACTIVE):
            self._expected = None
            raise self._fault_error(f"(statusword 0x{statusword:04X})")
        if self._expected is not None and state is not self._expected:
            raise StateTransitionError(
                f"node {self.node_id} left {self._expected.value}: statusword 0x{statusword:04X} ({state.value})"
            )

    def _read_feedback(self) -> Feedback:
        """One sample over SDO, without a SYNC (the drive is not clocked)."""
        self._check_state(self._sdo().read(0x6041))
        return self.session.io.read_feedback()

    def _set_cycle(self, period_s: float) -> None:
        """0x1006 and 0x60C2 are written in NMT PRE-OPERATIONAL, then the node goes back."""
        if self.enabled:
            raise UsageError(
                "set the cycle before enabling: 0x1006 and 0x60C2 are written in NMT PRE-OPERATIONAL"
            )
        self.session.set_cycle(period_s)

    # ------------------------------------------------------------- the hold
    def _hold_position(self, x_ref: float) -> None:
        if not self.limits.min_position <= x_ref <= self.limits.max_position:
            raise UsageError(
                f"x_ref {x_ref:.6g} is outside the allowed travel "
                f"[{self.limits.min_position:.6g}, {self.limits.max_position:.6g}]"
            )
        self.session.io.set_target(x_ref)
        self.session.io.set_torque(0.0, holding=True)
        if self.session.mode != MODE_CSP:  # a hold-only drive is in CSP since open
            set_mode(self._sdo(), MODE_CSP, "cyclic synchronous position")
            self.session.mode = MODE_CSP

    def _release_hold(self) -> None:
        self._leave_hold()

    def _leave_hold(self) -> None:
        self.session.io.set_torque(0.0, holding=self.hold_only)
        if self.session.mode != self.options.mode:  # a hold-only drive goes on holding its target
            set_mode(self._sdo(), self.options.mode, self.options.mode_name)
            self.session.mode = self.options.mode

    # ------------------------------------------------------------ real time
    def clock_source(self) -> str:
        """``drive`` with 0x1013 mapped; else ``kernel`` while the kernel sends the SYNC, else ``host``."""
        if self.session is not None and self.session.layout is not None and self.session.layout.has_clock:
            return "drive"
        return "kernel" if self.options.interface == "socketcan" else "host"

    def io_threads(self) -> tuple[int, ...]:
        """The CAN receive threads of python-can's notifier (the TPDOs arrive there)."""
        network = self.network
        notifier = None if network is None else network.notifier
        readers = [] if notifier is None else list(notifier._readers)
        return tuple(r.native_id for r in readers if isinstance(r, threading.Thread) and r.native_id)

    def start_cycle_clock(self, period_s: float) -> bool:
        """On SocketCAN (``interface=socketcan``) the SYNC from the kernel's broadcast manager."""
        if self.options.interface != "socketcan" or self.session is None:
            return False
        self.session.io.start_kernel_sync(period_s)
        return True

    def stop_cycle_clock(self) -> None:
        if self.session is not None:
            self.session.io.stop_kernel_sync()

    def cycle_counts(self) -> dict[str, int]:
        if self.session is None or self.options.interface != "socketcan":
            return {}
        return dict(self.session.io.counts)

    # ---------------------------------------------------------------- status
    def max_rate_hz(self) -> float:
        """From the wire time of the fullest cycle of the actual mapping at ``bitrate``
        (worst-case bit stuffing; with the hold's RPDO when the drive can hold)."""
        if self.session is None:
            return math.inf
        layout = self.session.layout
        return 1.0 / canopen_cycle_s(layout.cycle_frames(layout.can_hold), self.options.bitrate)[1]

    def log_metadata(self) -> dict[str, str]:
        meta = super().log_metadata()
        if self.session is not None:
            meta.update(self.session.metadata())
            option = self._quick_stop_option
            meta["command"] = self._command
            meta["quick_stop_option"] = "none (no 0x605A)" if option is None else (
                f"0x605A = {option}: ends in {quick_stop_end(option).value}")
        return meta

    def _info(self) -> DriveInfo:
        state, session = self._state(), self.session
        ident = [session.optional(0x1018, sub, 0) for sub in (1, 2, 3, 4)]
        return DriveInfo(
            transport="canopen",
            vendor=f"0x{ident[0]:08X}",
            product=f"{session.optional(0x1008, 0, '')} (product code 0x{ident[1]:08X})",
            firmware=str(session.optional(0x100A, 0, "")),
            serial_number=str(ident[3] or ""),
            state=state.value,
            fault_code=self._sdo().read(0x603F) if state is S.FAULT else 0,
            units=dict(self.units),
            extra={
                "node": self.node_id,
                "interface": self.interface,
                "mode": self._sdo().read(0x6061),
                "revision": ident[2],
                **session.info_extra(),
            },
        )
