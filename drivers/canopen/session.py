"""One open ``canopen://`` link to a CiA 402 node: bring-up, cyclic frames, clock, watchdog.

:class:`CanopenSession` is the part of :class:`~servobench.drivers.canopen.drive.CANopen402Drive`
that talks CANopen: it connects the bus, finds out what the drive has,
brings it up (:mod:`servobench.drivers.canopen.bringup`), keeps the RPDO
contents, sends RPDOs + SYNC and decodes the TPDOs into scaled feedback,
keeps the drive clock, and produces the host heartbeat. The drive class keeps
the CiA 402 power states and the :class:`~servobench.drivers.base.Drive` semantics.
"""

from __future__ import annotations

import math
import os
import time

import can
import canopen

from servobench.drivers.base import Limits
from servobench.drivers.canopen.bringup import (
    DRIVE_HEARTBEAT_MS,
    NMT_OPERATIONAL,
    NMT_PRE_OPERATIONAL,
    MappingRefused,
    NmtTracker,
    install_layout,
    read_factors,
    set_mode,
    write_cycle,
)
from servobench.drivers.canopen.cycle import CycleIO
from servobench.drivers.canopen.link import (
    HeartbeatProducer,
    TappedNetwork,
    TrafficRecorder,
    load_eds,
    probe_socketcand,
)
from servobench.drivers.canopen.mapping import Layout, plan_layout
from servobench.drivers.canopen.options import SYNC_COB_ID, CanopenOptions
from servobench.drivers.canopen.sdo import ABSENT, DriveObjects, SdoAccess, aborted_with
from servobench.drivers.cia402 import MODE_CSP, supports_mode
from servobench.drivers.cia402_units import derive_scaling
from servobench.errors import (
    DriveConfigError,
    DriveConnectionError,
    UsageError,
)

#: Host heartbeat period as a fraction of the drive's consumer time (watchdog).
HOST_HEARTBEAT_FRACTION = 0.25
#: Objects the drive-side hold needs mapped: (index, into an RPDO, name).
HOLD_OBJECTS = ((0x60B2, True, "torque offset"), (0x607A, True, "target position"),
                (0x6077, False, "torque actual value"))  # fmt: skip
#: Objects a layout maps that a drive cannot refuse (0x6071 is not in a hold-only layout,
#: :attr:`CanopenSession.hold_only`).
REQUIRED = (0x6040, 0x6071, 0x6041, 0x606C, 0x6064)


class CanopenSession:
    """The CANopen side of one open drive (see the module docstring)."""

    def __init__(self, options: CanopenOptions, limits: Limits) -> None:
        self.options, self.limits = options, limits
        self.network: TappedNetwork | None = None
        self.node: canopen.RemoteNode | None = None
        self.sdo: SdoAccess | None = None
        self.objects: DriveObjects | None = None
        self.layout: Layout | None = None
        self.scaling = None
        self.factors = None
        self.io: CycleIO | None = None  #: the cyclic frames, once connected
        self.hold_reason: str | None = "not open"
        self.mode = options.mode  #: the mode of operation the drive is in (0x6060)
        self.notes = {"max_torque": "", "watchdog_action": ""}
        self._nmt = NmtTracker(options.node_id)
        self._heartbeat: HeartbeatProducer | None = None
        self._consumer_armed = False
        self._cycle_written: float | None = None
        self._recorders: list[TrafficRecorder] = []

    # ------------------------------------------------------------- the link
    def connect(self) -> None:
        o = self.options
        kwargs = {"interface": o.interface, "channel": o.channel, "bitrate": o.bitrate}
        if o.server is not None:
            probe_socketcand(o.server[0], o.server[1], o.channel)
            kwargs.update(host=o.server[0], port=o.server[1], tcp_tune=True)
        network = TappedNetwork()
        try:
            network.connect(**kwargs)
        except (can.CanError, OSError, ValueError, ImportError) as err:
            raise DriveConnectionError(f"cannot open CAN {o.interface} {o.channel}: {err}") from err
        self.network = network

    def disconnect(self) -> None:
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

    def record_traffic(self, path: str) -> None:
        recorder = TrafficRecorder(path)
        self._recorders.append(recorder)
        self.network.taps.append(recorder)
        self.network.notifier.add_listener(recorder)

    def nmt(self, command: int) -> None:
        """Send NMT ``command`` to the node and wait for its heartbeat to confirm."""
        with self.sdo.translated(f"NMT 0x{command:02X}"):
            self.node.nmt.send_command(command)
        if self.objects.has(0x1017):
            self._nmt.await_state(command)
        else:  # no heartbeat to confirm with: give the node a moment
            time.sleep(0.05)

    # ------------------------------------------------------------ bring-up
    def _object_dictionary(self) -> tuple[canopen.ObjectDictionary, bool]:
        path = self.options.eds_path
        try:
            return load_eds(self.options.node_id, path), bool(path)
        except (OSError, ValueError, KeyError) as err:
            raise DriveConfigError(f"cannot read the EDS {path}: {err}") from err

    def bring_up(self) -> None:
        """NMT pre-operational, identity, units, limits, mode, PDOs, SYNC; then operational."""
        o, n = self.options, self.options.node_id
        od, from_eds = self._object_dictionary()
        self.node = canopen.RemoteNode(n, od)
        self.network.add_node(self.node)
        self.sdo = SdoAccess(self.node, o.sdo_timeout_s)
        self.objects = DriveObjects(od, from_eds, self.sdo)
        self.io = io = CycleIO(o, self.network, self.sdo)
        self.node.nmt.add_heartbeat_callback(self._nmt.on_heartbeat)
        self.network.subscribe(0x180 + n, io.on_tpdo1)
        self.network.subscribe(0x280 + n, io.on_tpdo2)
        self.network.subscribe(0x80 + n, io.on_emcy)
        with self.sdo.translated("NMT pre-operational"):
            self.node.nmt.send_command(NMT_PRE_OPERATIONAL)
        profile = self.sdo.read(0x1000) & 0xFFFF
        if profile != 402:
            raise DriveConfigError(f"node {n} is no CiA 402 drive (0x1000 profile {profile})")
        if self.objects.has(0x1017):
            self.sdo.write(0x1017, 0, DRIVE_HEARTBEAT_MS)
        self.nmt(NMT_PRE_OPERATIONAL)
        self.factors = read_factors(self.objects)
        self.scaling = io.scaling = derive_scaling(self.factors, o.overrides)
        self._torque_limit()
        self._torque_mode()
        self._map()
        if self.objects.has(0x1005):
            self.sdo.write(0x1005, 0, o.sync_cob)
        elif o.sync_cob != SYNC_COB_ID:
            raise DriveConfigError(f"node {n} has no 0x1005 to take sync_cob=0x{o.sync_cob:X}")
        cycle_us = self.objects.value(0x1006, 0, 0)
        io.period_s = cycle_us * 1e-6 if cycle_us else None
        self.nmt(NMT_OPERATIONAL)

    def _torque_limit(self) -> None:
        """0x6072 (per mille of the rated torque) from ``max_u`` where the drive has it."""
        scale, unit = self.scaling.u.scale, self.scaling.u.unit
        if not self.objects.has(0x6072):
            self.notes["max_torque"] = "host-side clamping only (the drive has no 0x6072)"
            return
        if math.isfinite(self.limits.max_command):
            self.sdo.write(0x6072, 0, min(round(self.limits.max_command / scale), 0xFFFF))
        self.io.max_lsb = lsb = min(self.sdo.read(0x6072), 0x7FFF)
        self.notes["max_torque"] = f"0x6072 = {lsb} ({lsb * scale:.6g} {unit})"

    @property
    def hold_only(self) -> bool:
        """Commanded only by the torque offset 0x60B2 under the drive's own position hold
        (``mode=csp``, chosen or fallen back to): the target torque 0x6071 is neither mapped
        nor written, and the drive need not have it."""
        return self.options.mode_key == "csp"

    @property
    def has_target_torque(self) -> bool:
        """The drive has the target torque 0x6071 and can map it into an RPDO."""
        return self.objects.mappable(0x6071, receive=True)

    def zero_target_torque(self) -> None:
        """Target torque 0x6071 = 0 over SDO, where the command mode uses it."""
        if not self.hold_only:
            self.sdo.write(0x6071, 0, 0)

    def _torque_mode(self) -> None:
        o = self.options
        modes = self.objects.value(0x6502)
        if modes is not None and not supports_mode(modes, o.mode):
            raise DriveConfigError(
                f"node {o.node_id} does not offer mode {o.mode} ({o.mode_name}): "
                f"0x6502 = 0x{modes:08X}"
            )
        self.hold_reason = self._hold_capability(modes)
        if self.hold_only and self.hold_reason is not None and not self.has_target_torque:
            raise DriveConfigError(
                f"node {o.node_id} cannot be identified: no target torque 0x6071, and no torque "
                f"offset under its position hold: {self.hold_reason}"
            )
        if not self.hold_only and not self.has_target_torque:
            raise DriveConfigError(
                f"node {o.node_id} has no target torque 0x6071 (absent or not PDO-mappable) for "
                f"{o.mode_name}"
            )
        self.zero_target_torque()
        set_mode(self.sdo, o.mode, o.mode_name)
        self.mode = o.mode

    def _hold_capability(self, modes: int | None) -> str | None:
        """Why the drive-side hold is unavailable, ``None`` when it is available."""
        if modes is None:
            return "the drive has no 0x6502 (supported drive modes) to announce CSP"
        if not supports_mode(modes, MODE_CSP):
            return f"no cyclic synchronous position (0x6502 = 0x{modes:08X})"
        for index, receive, name in HOLD_OBJECTS:
            if not self.objects.mappable(index, receive=receive):
                return f"0x{index:04X} ({name}) absent or not PDO-mappable"
        if math.isfinite(self.limits.max_command) and not self.objects.has(0x6072):
            return "max_u cannot bound the drive's own loop without max torque 0x6072"
        return None

    def _map(self) -> None:
        """Plan and install the PDOs; in probing mode, re-plan around objects the drive
        refuses to map (its EDS would have said so)."""
        objects, n = self.objects, self.options.node_id
        for _ in range(len(HOLD_OBJECTS) + 2):
            try:
                hold = self.hold_reason is None
                self.layout = self.io.layout = plan_layout(
                    n, lambda i: objects.mappable(i, receive=True),
                    lambda i: objects.mappable(i, receive=False),
                    hold=hold, clock=True, torque=not (self.hold_only and hold),
                )  # fmt: skip
            except ValueError as err:
                raise DriveConfigError(f"node {n}: {err}") from None
            try:
                install_layout(self.sdo, objects, self.layout)
                return
            except MappingRefused as err:
                if objects.from_eds or err.index in REQUIRED:
                    raise
                objects.refuse_mapping(err.index)
                if self.hold_reason is None and any(err.index == h[0] for h in HOLD_OBJECTS):
                    self.hold_reason = f"the drive refused to map 0x{err.index:04X}"
        raise DriveConfigError(f"node {n} refused every PDO mapping servobench tried")

    # ------------------------------------------------------- cycle & watchdog
    def set_cycle(self, period_s: float) -> None:
        """The cycle for the SYNC-count clock, and 0x1006/0x60C2 written in PRE-OPERATIONAL."""
        self.io.period_s = period_s
        if self._cycle_written == period_s:
            return
        self.nmt(NMT_PRE_OPERATIONAL)
        try:
            write_cycle(self.sdo, self.objects, period_s)
        finally:
            self.nmt(NMT_OPERATIONAL)
        self._cycle_written = period_s

    def arm_watchdog(self, timeout_s: float) -> bool:
        """Heartbeat producer and the drive's consumer; True when 0x6007 makes it fault."""
        time_ms, n = math.ceil(timeout_s * 1000), self.options.node_id
        if time_ms > 0xFFFF:
            raise UsageError(f"watchdog {timeout_s} s exceeds the 65.535 s of 0x1016")
        if not self.objects.has(0x1016, 1):
            raise DriveConfigError(
                f"node {n} has no heartbeat consumer 0x1016: it cannot notice a silent host"
            )
        if self._heartbeat is None:
            period_s = max(timeout_s * HOST_HEARTBEAT_FRACTION, 0.001)
            self._heartbeat = HeartbeatProducer(self.network, self.options.host_node, period_s)
            self._heartbeat.start()
            self.io.heartbeat = self._heartbeat
        self.sdo.write(0x1016, 1, self.options.host_node << 16 | time_ms)
        self._consumer_armed = True
        consumer = f"heartbeat consumer 0x1016 ({time_ms} ms)"
        if self.objects.has(0x6007):
            self.sdo.write(0x6007, 0, 1)
            self.notes["watchdog_action"] = f"{consumer}, 0x6007 = 1: fault"
            return True
        self.notes["watchdog_action"] = f"{consumer}, no 0x6007: the drive's own reaction"
        return False

    def close(self, restore_mode: int | None) -> None:
        """Back to the torque mode if asked, disarm the consumer, PRE-OPERATIONAL, disconnect."""
        try:
            if restore_mode is not None and self.node is not None:
                set_mode(self.sdo, restore_mode, "torque mode")
                self.mode = restore_mode
            if self._consumer_armed and self.node is not None:
                self._consumer_armed = False
                self.sdo.write(0x1016, 1, 0)  # a clean exit is no heartbeat loss
            if self.node is not None:
                with self.sdo.translated("NMT pre-operational"):
                    self.node.nmt.send_command(NMT_PRE_OPERATIONAL)
        finally:
            self.disconnect()

    # ---------------------------------------------------------------- status
    def optional(self, index: int, sub: int, default):
        """An identity object the drive may lack."""
        try:
            return self.objects.value(index, sub, default)
        except DriveConfigError as err:
            if aborted_with(err, ABSENT):
                return default
            raise

    def metadata(self) -> dict[str, str]:
        """What a reader of the log must know about units, clock, limits and the hold."""
        s, layout = self.scaling, self.layout
        meta = {}
        for key in ("u", "v", "x"):
            factor = getattr(s, key)
            meta[f"scale_{key}"] = f"{factor.scale:.12g}"
            meta[f"scale_{key}_source"] = factor.source
        od = (f"EDS {os.path.basename(self.options.eds_path)}" if self.objects.from_eds
              else "SDO probing (types from the generic CiA 402 EDS)")  # fmt: skip
        meta.update(
            drive_clock="0x1013 time stamp at each SYNC" if layout.has_clock
            else "SYNC count x cycle period (no PDO-mappable 0x1013)",
            object_dictionary=od,
            drive_hold="cyclic synchronous position: target 0x607A, offset 0x60B2, 0x6077 read back"
            if self.hold_reason is None else f"unavailable: {self.hold_reason}",
            **self.notes,
        )  # fmt: skip
        return meta

    def info_extra(self) -> dict[str, object]:
        f = self.factors
        return {
            "rated_torque_Nm": None if f.rated_torque_mNm is None else f.rated_torque_mNm / 1000.0,
            "rated_current_A": None if f.rated_current_mA is None else f.rated_current_mA / 1000.0,
            "max_torque_permille": self.io.max_lsb if self.objects.has(0x6072) else None,
            **self.metadata(),
        }
