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
``pos_scale`` (position units per 0x6064 increment, default 1),
``vel_scale`` (velocity units/s per 0x606C LSB, default 1), ``eds`` (the
drive's own EDS file; default the shipped generic ``drivers/data/cia402.eds``),
``sync_cob`` (the SYNC COB-ID written to the drive's 0x1005 and sent each
cycle, default 0x80).

Several hosts on one bus: each host's SYNC would clock every drive that
listens to 0x80, so give each drive its own SYNC with ``sync_cob`` (a free
11-bit id outside CiA 301's restricted ones, e.g. 0x90) and each host its own
heartbeat node with ``host_node`` (otherwise a drive's watchdog is fed by
the other host and would not notice its own host die).

Units: the command ``u`` is in rated torques (0x6076): the target torque
0x6071 and torque actual 0x6077 are per-mille of the rated torque, so
``0x6071 = round(1000 u)``, 1e-3 rated torque resolution, clamped to the
drive's max torque 0x6072 as the drive itself does. ``Feedback.t_s`` is the
drive clock: the high-resolution time stamp 0x1013 [µs] sampled at each SYNC.

Set-up runs over SDO in NMT PRE-OPERATIONAL (mode, PDO mapping, heartbeats),
the cycle in OPERATIONAL: :meth:`exchange` sends RPDO1 (controlword, target
torque) and a SYNC, and waits for the SYNC's TPDO1 (statusword, torque
actual, 0x1013) and TPDO2 (velocity 0x606C, position 0x6064). The CiA 402
state machine is walked with :func:`servobench.drivers.cia402.plan`, each step under a
deadline; failures raise, never log. :meth:`read` uses SDO and sends no
SYNC, so it does not clock a lock-step simulated drive. Position (0x6064)
and the time stamp (0x1013) are unwrapped across their 32-bit roll-over.
A TPDO pair whose time stamp was already consumed (a duplicate, or a late
answer to an earlier SYNC) is dropped, never taken for this SYNC's. An EMCY
with a non-zero error code ends the next cycle with
:class:`~servobench.errors.DriveFaultError` even if the drive stays enabled
(a warning): identification data taken while the drive signals an error is
not trusted.

Watchdog: the host produces heartbeats every ``watchdog / 4`` (node
``host_node``); the drive consumes them (0x1016, time ``watchdog``) and
faults (abort connection option 0x6007 = 1) when they stop, e.g. when the
host process dies. Opening leaves the drive disabled (a drive found enabled
is switched off); closing disarms the consumer.
"""

from __future__ import annotations

import logging
import math
import socket
import struct
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import can
import canopen

from servobench.drivers.base import Drive, DriveInfo, Feedback
from servobench.drivers.canopen_link import (
    CounterUnwrap,
    HeartbeatProducer,
    TappedNetwork,
    TrafficRecorder,
    load_eds,
)
from servobench.drivers.cia402 import (
    CW_DISABLE_VOLTAGE,
    CiA402State,
    Step,
    decode_statusword,
    interpolation_period,
    plan,
)
from servobench.errors import (
    DriveConfigError,
    DriveConnectionError,
    DriveError,
    DriveFaultError,
    DriveTimeoutError,
    StateTransitionError,
    UsageError,
)

# The library's own log lines would reach stderr through logging's last-resort
# handler; every failure is raised as a typed error here instead. An application
# that configures logging still sees them.
logging.getLogger("canopen").addHandler(logging.NullHandler())
logging.getLogger("can").addHandler(logging.NullHandler())

S = CiA402State

#: SDO response timeout unless the URL sets ``sdo_timeout`` [s].
SDO_TIMEOUT_S = 0.3
#: Wait for the TPDOs of one SYNC unless the URL sets ``pdo_timeout`` [s].
PDO_TIMEOUT_S = 0.1
#: Deadline for reaching a socketcand server over TCP [s] (python-can itself retries for 10 s).
CONNECT_TIMEOUT_S = 2.0
#: Deadline of each CiA 402 state transition [s].
STATE_TIMEOUT_S = 1.0
#: Deadline for 0x6061 to show the requested mode [s].
MODE_TIMEOUT_S = 0.5
#: Drive heartbeat period the host sets (0x1017), used to confirm NMT states [ms].
DRIVE_HEARTBEAT_MS = 100
#: Deadline for a heartbeat reporting a requested NMT state [s].
NMT_TIMEOUT_S = 3 * DRIVE_HEARTBEAT_MS / 1000 + 0.2
#: Host heartbeat period as a fraction of the drive's consumer time (watchdog).
HOST_HEARTBEAT_FRACTION = 0.25
#: Statusword polling period while waiting for a state [s].
STATE_POLL_S = 0.002
#: Modes of operation by URL name: (0x6060 value, description).
MODES = {"cst": (10, "cyclic synchronous torque"), "pt": (4, "profile torque")}
#: COB-ID of the SYNC the host produces (0x1005) unless the URL sets ``sync_cob``.
SYNC_COB_ID = 0x80
#: CiA 301 restricted 11-bit COB-IDs, which no SYNC may use (inclusive ranges).
RESTRICTED_COB_IDS = (
    (0x000, 0x07F), (0x101, 0x180), (0x581, 0x5FF), (0x601, 0x67F),
    (0x6E0, 0x6FF), (0x701, 0x77F), (0x780, 0x7FF),
)  # fmt: skip
#: COB-ID bit 31: PDO not valid.
COB_INVALID = 0x80000000
#: SDO aborts meaning "this drive has no such object".
ABORT_NO_OBJECT = (0x06020000, 0x06090011)
NMT_PRE_OPERATIONAL, NMT_OPERATIONAL = 0x80, 0x01
NMT_STATES = {0x80: 127, 0x01: 5}  # command -> heartbeat state


class CANopen402Drive(Drive):
    """A CiA 402 drive on CANopen, commanded in torque (see the module docstring for the URL)."""

    query_keys = frozenset(
        {"interface", "channel", "node", "bitrate", "host", "port", "mode", "host_node",
         "sdo_timeout", "pdo_timeout", "pos_scale", "vel_scale", "eds", "sync_cob"}
    )  # fmt: skip
    units = {"u": "rated torque (0x6076)", "v": "velocity units/s", "x": "position units"}
    drive_clock = True  # Feedback.t_s is the drive's 0x1013 time stamp

    def __init__(self, url) -> None:
        super().__init__(url)
        q = self.url
        self.interface = q.get_str("interface", "socketcan")
        self.channel = q.get_str("channel") or q.host
        if not self.channel:
            raise DriveConfigError("canopen:// needs a channel: canopen://CHANNEL?... or channel=")
        self.node_id = q.get_int("node")
        self.host_node = q.get_int("host_node", 127)
        if self.node_id is None or not 1 <= self.node_id <= 127:
            raise DriveConfigError("canopen:// needs node=1..127, the drive's node id")
        if not 1 <= self.host_node <= 127 or self.host_node == self.node_id:
            raise DriveConfigError(
                f"host_node must be 1..127 and not the drive's node {self.node_id}"
            )
        self.bitrate = q.get_int("bitrate", 1_000_000)
        self.server: tuple[str, int] | None = None
        if self.interface == "socketcand":
            if "host" not in q.query or "port" not in q.query:
                raise DriveConfigError(
                    "interface=socketcand needs host= and port= of the socketcand server"
                )
            self.server = (q.get_str("host"), q.get_int("port"))
        elif "host" in q.query or "port" in q.query:
            raise DriveConfigError("host= and port= apply to interface=socketcand only")
        mode = q.get_str("mode", "cst")
        if mode not in MODES:
            raise DriveConfigError(f"mode must be one of {', '.join(MODES)}, got {mode!r}")
        self.mode, self.mode_name = MODES[mode]
        self.sdo_timeout_s = q.get_float("sdo_timeout", SDO_TIMEOUT_S)
        self.pdo_timeout_s = q.get_float("pdo_timeout", PDO_TIMEOUT_S)
        self.pos_scale = q.get_float("pos_scale", 1.0)
        self.vel_scale = q.get_float("vel_scale", 1.0)
        if min(self.sdo_timeout_s, self.pdo_timeout_s, self.pos_scale, self.vel_scale) <= 0:
            raise DriveConfigError("sdo_timeout, pdo_timeout, pos_scale and vel_scale must be > 0")
        self.eds_path = q.get_str("eds")
        self.sync_cob = q.get_int("sync_cob", SYNC_COB_ID)
        if not 0 < self.sync_cob <= 0x7FF or any(
            lo <= self.sync_cob <= hi for lo, hi in RESTRICTED_COB_IDS
        ):
            raise DriveConfigError(
                f"sync_cob=0x{self.sync_cob:X} is not a usable 11-bit COB-ID "
                "(CiA 301 restricts 0x000-0x07F, 0x101-0x180, 0x581-0x5FF, 0x601-0x67F, 0x6E0-0x7FF)"
            )
        if self.sync_cob in (0x80 + self.node_id, 0x180 + self.node_id, 0x280 + self.node_id,
                             0x200 + self.node_id):  # fmt: skip
            raise DriveConfigError(
                f"sync_cob=0x{self.sync_cob:X} collides with node {self.node_id}'s own EMCY or PDOs"
            )
        self.network: TappedNetwork | None = None
        self.node: canopen.RemoteNode | None = None
        self.torque_actual = 0.0  #: last 0x6077 [rated torques]
        self._heartbeat: HeartbeatProducer | None = None
        self._consumer_armed = False
        self._controlword = 0
        self._torque = 0  # 0x6071 [per-mille]
        self._max_permille = 0x7FFF
        self._expected: CiA402State | None = None
        self._rx1: bytes | None = None
        self._rx2: bytes | None = None
        self._rx_event = threading.Event()
        self._last_stamp: int | None = None  # 0x1013 of the last TPDO pair consumed
        self._emcy: tuple[int, int] | None = None  # (error code, error register) pending
        self._nmt = threading.Condition()
        self._nmt_seen = (0, -1)  # (heartbeats received, last NMT state)
        self._position = CounterUnwrap(32)
        self._clock = CounterUnwrap(32)
        self._recorders: list[TrafficRecorder] = []

    # -------------------------------------------------------------- SDO layer
    @contextmanager
    def _translated(self, what: str, error: type[DriveError] = DriveConfigError) -> Iterator[None]:
        try:
            yield
        except canopen.SdoAbortedError as err:
            raise error(
                f"node {self.node_id}: {what} refused, SDO abort 0x{err.code:08X} ({err})"
            ) from err
        except canopen.SdoCommunicationError as err:
            raise DriveTimeoutError(
                f"node {self.node_id} did not answer SDO ({what}) within {self.sdo_timeout_s} s: {err}"
            ) from err
        except (can.CanError, OSError) as err:
            raise DriveConnectionError(f"CAN link failed during {what}: {err}") from err

    def _var(self, index: int, sub: int):
        var = self.node.sdo.get_variable(index, sub)
        if var is None:
            raise DriveConfigError(f"object 0x{index:04X}:{sub} is not in the drive's EDS")
        return var

    def _read(self, index: int, sub: int = 0):
        with self._translated(f"read 0x{index:04X}:{sub}"):
            return self._var(index, sub).raw

    def _write(
        self, index: int, sub: int, value, error: type[DriveError] = DriveConfigError
    ) -> None:
        with self._translated(f"write 0x{index:04X}:{sub} = {value!r}", error):
            self._var(index, sub).raw = value

    # -------------------------------------------------------------- lifecycle
    def _open(self) -> None:
        network = TappedNetwork()
        kwargs = {"interface": self.interface, "channel": self.channel, "bitrate": self.bitrate}
        if self.server is not None:
            self._probe_server()
            kwargs.update(host=self.server[0], port=self.server[1], tcp_tune=True)
        try:
            network.connect(**kwargs)
        except (can.CanError, OSError, ValueError, ImportError) as err:
            raise DriveConnectionError(
                f"cannot open CAN {self.interface} {self.channel}: {err}"
            ) from err
        self.network = network
        try:
            self._set_up()
        except BaseException:
            self._disconnect()
            raise

    def _probe_server(self) -> None:
        """Fail fast (not after python-can's 10 s of retries) when nothing listens."""
        host, port = self.server
        try:
            socket.create_connection((host, port), timeout=CONNECT_TIMEOUT_S).close()
        except OSError as err:
            raise DriveConnectionError(
                f"cannot reach the socketcand server {host}:{port}: {err.strerror or err}"
            ) from err

    def _set_up(self) -> None:
        node = canopen.RemoteNode(self.node_id, load_eds(self.node_id, self.eds_path))
        node.sdo.RESPONSE_TIMEOUT = self.sdo_timeout_s
        self.network.add_node(node)
        self.node = node
        node.nmt.add_heartbeat_callback(self._on_heartbeat)
        self.network.subscribe(0x180 + self.node_id, self._on_tpdo1)
        self.network.subscribe(0x280 + self.node_id, self._on_tpdo2)
        self.network.subscribe(0x80 + self.node_id, self._on_emcy)
        node.nmt.send_command(NMT_PRE_OPERATIONAL)
        profile = self._read(0x1000) & 0xFFFF
        if profile != 402:
            raise DriveConfigError(
                f"node {self.node_id} is no CiA 402 drive (0x1000 profile {profile})"
            )
        self._write(0x1017, 0, DRIVE_HEARTBEAT_MS)
        self._await_nmt(NMT_PRE_OPERATIONAL)
        if math.isfinite(self.limits.max_command):
            self._write(0x6072, 0, min(round(self.limits.max_command * 1000), 0xFFFF))
        self._max_permille = min(self._read(0x6072), 0x7FFF)
        self._write(0x6071, 0, 0)
        self._set_mode()
        self._map_pdos()
        self._write(0x1005, 0, self.sync_cob)
        node.nmt.send_command(NMT_OPERATIONAL)
        self._await_nmt(NMT_OPERATIONAL)
        state = self._state()
        if state in (S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE):  # left enabled by someone else
            self._goto(S.SWITCH_ON_DISABLED)
        self._expected = None

    def _set_mode(self) -> None:
        self._write(0x6060, 0, self.mode)
        deadline = time.monotonic() + MODE_TIMEOUT_S
        while (shown := self._read(0x6061)) != self.mode:
            if time.monotonic() > deadline:
                raise StateTransitionError(
                    f"node {self.node_id} did not switch to mode {self.mode} ({self.mode_name}): "
                    f"0x6061 still reads {shown} after {MODE_TIMEOUT_S} s"
                )
            time.sleep(STATE_POLL_S)

    def _map_pdos(self) -> None:
        """RPDO1: controlword, target torque. TPDO1/2 on every SYNC (type 1): statusword,
        torque actual, 0x1013 time stamp / velocity actual, position actual."""
        n = self.node_id
        self._map(0x1400, 0x200 + n, 1, [(0x6040, 16), (0x6071, 16)])
        self._map(0x1800, 0x180 + n, 1, [(0x6041, 16), (0x6077, 16), (0x1013, 32)])
        self._map(0x1801, 0x280 + n, 1, [(0x606C, 32), (0x6064, 32)])
        od = self.node.object_dictionary
        for comm in (0x1401, 0x1402, 0x1403, 0x1802, 0x1803):
            if comm in od:
                self._write(comm, 1, COB_INVALID | (od[comm][1].default or 0) & 0x7FF)

    def _map(
        self, comm: int, cob_id: int, transmission: int, objects: list[tuple[int, int]]
    ) -> None:
        mapping = comm + 0x200
        self._write(comm, 1, COB_INVALID | cob_id)
        self._write(comm, 2, transmission)
        self._write(mapping, 0, 0)
        for sub, (index, bits) in enumerate(objects, start=1):
            self._write(mapping, sub, index << 16 | bits)
        self._write(mapping, 0, len(objects))
        self._write(comm, 1, cob_id)

    def _on_heartbeat(self, state: int) -> None:
        with self._nmt:
            self._nmt_seen = (self._nmt_seen[0] + 1, state)
            self._nmt.notify_all()

    def _await_nmt(self, command: int) -> None:
        """Wait for a heartbeat reporting the state NMT ``command`` asks for."""
        want = NMT_STATES[command]
        deadline = time.monotonic() + NMT_TIMEOUT_S
        with self._nmt:
            while self._nmt_seen[1] != want:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise StateTransitionError(
                        f"node {self.node_id} did not report NMT state {want} within {NMT_TIMEOUT_S} s "
                        f"(last heartbeat state {self._nmt_seen[1]})"
                    )
                self._nmt.wait(left)

    def _configure_watchdog(self, timeout_s: float) -> None:
        """Host heartbeats every ``timeout_s / 4``; the drive consumes them (0x1016) and
        faults (0x6007 = 1) when they stop for ``timeout_s``."""
        time_ms = math.ceil(timeout_s * 1000)
        if time_ms > 0xFFFF:
            raise UsageError(f"watchdog {timeout_s} s exceeds the 65.535 s of 0x1016")
        if self._heartbeat is None:
            period_s = max(timeout_s * HOST_HEARTBEAT_FRACTION, 0.001)
            self._heartbeat = HeartbeatProducer(self.network, self.host_node, period_s)
            self._heartbeat.start()
        self._write(0x1016, 1, self.host_node << 16 | time_ms)
        self._consumer_armed = True
        self._write(0x6007, 0, 1)

    def _close(self) -> None:
        try:
            if self._consumer_armed and self.node is not None:
                self._consumer_armed = False
                self._write(0x1016, 1, 0)  # a clean exit is no heartbeat loss
            if self.node is not None:
                with self._translated("NMT pre-operational"):
                    self.node.nmt.send_command(NMT_PRE_OPERATIONAL)
        finally:
            self._disconnect()

    def _disconnect(self) -> None:
        if self._heartbeat is not None:
            self._heartbeat.stop()
            self._heartbeat = None
        try:
            if self.network is not None:
                network, self.network, self.node = self.network, None, None
                network.disconnect()
        finally:
            for recorder in self._recorders:
                recorder.stop()
            self._recorders = []

    def _record_traffic(self, path: str) -> None:
        recorder = TrafficRecorder(path)
        self._recorders.append(recorder)
        self.network.taps.append(recorder)
        self.network.notifier.add_listener(recorder)

    # ------------------------------------------------------------ 402 states
    def _state(self) -> CiA402State:
        return decode_statusword(self._read(0x6041))

    def _controlword_write(self, controlword: int) -> None:
        self._write(0x6040, 0, controlword, StateTransitionError)
        self._controlword = controlword

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
        code = self._read(0x603F)
        return DriveFaultError(f"node {self.node_id} in FAULT 0x{code:04X} {context}", code)

    def _enable(self) -> None:
        if self._state() in (S.FAULT, S.FAULT_REACTION_ACTIVE):
            raise self._fault_error("cannot enable; reset the fault first")
        self._emcy = None  # what the drive reported before this enable is not news
        self._torque = 0
        self._write(0x6071, 0, 0)
        self._goto(S.OPERATION_ENABLED)
        self._expected = S.OPERATION_ENABLED

    def _disable(self) -> None:
        if self.node is None:
            return
        self._expected = None
        if self._state() in (
            S.OPERATION_ENABLED,
            S.QUICK_STOP_ACTIVE,
            S.SWITCHED_ON,
            S.READY_TO_SWITCH_ON,
        ):
            self._goto(S.SWITCH_ON_DISABLED)

    def _quick_stop(self) -> None:
        self._torque = 0
        if self._state() is S.OPERATION_ENABLED:
            self._goto(S.QUICK_STOP_ACTIVE)
            self._expected = S.QUICK_STOP_ACTIVE
        else:
            self._write(0x6071, 0, 0)

    def _reset_fault(self) -> None:
        if self._state() not in (S.FAULT, S.FAULT_REACTION_ACTIVE):
            return
        self._controlword_write(CW_DISABLE_VOLTAGE)  # bit 7 low: the reset is a rising edge
        self._goto(S.SWITCH_ON_DISABLED)
        self._expected = None
        self._emcy = None

    def _fault_code(self) -> int:
        return self._read(0x603F)

    # ---------------------------------------------------------------- cycles
    def _permille(self, u: float) -> int:
        return max(-self._max_permille, min(self._max_permille, round(u * 1000.0)))

    def _send_rpdo(self) -> None:
        with self._translated("RPDO1"):
            self.network.send_message(
                0x200 + self.node_id, struct.pack("<Hh", self._controlword, self._torque)
            )

    def _write_command(self, u: float) -> None:
        self._torque = self._permille(u)
        self._send_rpdo()

    def _on_tpdo1(self, can_id: int, data: bytearray, timestamp: float) -> None:
        self._rx1 = bytes(data)

    def _on_tpdo2(self, can_id: int, data: bytearray, timestamp: float) -> None:
        rx1 = self._rx1
        if (
            rx1 is not None
            and len(rx1) >= 8
            and struct.unpack_from("<I", rx1, 4)[0] == self._last_stamp
        ):
            self._rx1 = None  # a duplicate or a late pair of a SYNC already answered
            return
        self._rx2 = bytes(data)
        self._rx_event.set()

    def _on_emcy(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if len(data) >= 3:
            code, register = struct.unpack_from("<HB", data)
            if code:  # 0x0000 is "error reset / no error"
                self._emcy = (code, register)

    def _exchange(self, u: float) -> Feedback:
        if self._heartbeat is not None:
            self._heartbeat.check()
        self._torque = self._permille(u)
        self._rx1 = self._rx2 = None
        self._rx_event.clear()
        rpdo = struct.pack("<Hh", self._controlword, self._torque)
        with self._translated("RPDO1 + SYNC"):
            self.network.send_messages([(0x200 + self.node_id, rpdo), (self.sync_cob, b"")])
        if not self._rx_event.wait(self.pdo_timeout_s):
            raise DriveTimeoutError(
                f"no TPDO from node {self.node_id} within {self.pdo_timeout_s * 1e3:.0f} ms of SYNC"
            )
        rx1, rx2 = self._rx1, self._rx2
        if rx1 is None or len(rx1) < 8 or rx2 is None or len(rx2) < 8:
            raise DriveTimeoutError(
                f"incomplete TPDOs from node {self.node_id} at this SYNC: {rx1!r}, {rx2!r}"
            )
        statusword, torque, t_us = struct.unpack_from("<HhI", rx1)
        velocity, position = struct.unpack_from("<ii", rx2)
        self._last_stamp = t_us
        self._check_state(statusword)
        if self._emcy is not None:
            code, register = self._emcy
            self._expected = None
            raise DriveFaultError(
                f"node {self.node_id} sent EMCY 0x{code:04X} (error register 0x{register:02X})",
                code,
            )
        self.torque_actual = torque / 1000.0
        return self._feedback(t_us, velocity, position)

    def _check_state(self, statusword: int) -> None:
        state = decode_statusword(statusword)
        if state in (S.FAULT, S.FAULT_REACTION_ACTIVE):
            self._expected = None
            raise self._fault_error(f"(statusword 0x{statusword:04X})")
        if self._expected is not None and state is not self._expected:
            raise StateTransitionError(
                f"node {self.node_id} left {self._expected.value}: statusword 0x{statusword:04X} ({state.value})"
            )

    def _feedback(self, t_us: int, velocity: int, position: int) -> Feedback:
        return Feedback(
            t_s=self._clock(t_us) * 1e-6,
            velocity=velocity * self.vel_scale,
            position=self._position(position) * self.pos_scale,
        )

    def _read_feedback(self) -> Feedback:
        """One sample over SDO, without a SYNC (the drive is not clocked)."""
        self._check_state(self._read(0x6041))
        return self._feedback(self._read(0x1013), self._read(0x606C), self._read(0x6064))

    def _set_cycle(self, period_s: float) -> None:
        period_us = period_s * 1e6
        if abs(period_us - round(period_us)) > 1e-6:
            raise UsageError(f"cycle period {period_s} s is not a whole number of µs (0x1006)")
        value, index = interpolation_period(period_s)
        self._write(0x1006, 0, round(period_us))
        self._write(0x60C2, 1, value)
        self._write(0x60C2, 2, index)

    # ---------------------------------------------------------------- status
    def _optional(self, index: int, sub: int = 0, default=""):
        try:
            return self._read(index, sub)
        except DriveConfigError as err:
            if (
                isinstance(err.__cause__, canopen.SdoAbortedError)
                and err.__cause__.code in ABORT_NO_OBJECT
            ):
                return default
            raise

    def _info(self) -> DriveInfo:
        state = self._state()
        vendor, product = self._optional(0x1018, 1, 0), self._optional(0x1018, 2, 0)
        return DriveInfo(
            transport="canopen",
            vendor=f"0x{vendor:08X}",
            product=f"{self._optional(0x1008)} (product code 0x{product:08X})",
            firmware=str(self._optional(0x100A)),
            serial_number=str(self._optional(0x1018, 4)),
            state=state.value,
            fault_code=self._read(0x603F) if state is S.FAULT else 0,
            units=dict(self.units),
            extra={
                "node": self.node_id,
                "interface": self.interface,
                "mode": self._read(0x6061),
                "rated_torque_Nm": self._read(0x6076) / 1000.0,
                "max_torque_permille": self._read(0x6072),
                "revision": self._optional(0x1018, 3, 0),
            },
        )
