"""Bringing a CiA 402 drive up over SDO: NMT states, PDO mapping, mode, cycle, factor group.

Every step writes only objects the drive has (:class:`~servobench.drivers.canopen.sdo.DriveObjects`)
and raises a typed error when the drive refuses, never logs and carries on.
:func:`read_up` is the read-only open: SDO uploads only, no NMT command.
The PDO procedure is CiA 301's: invalidate the PDO (COB-ID bit 31), set the
transmission type, clear the map (sub-index 0), write the entries, set their
number, validate. COB-IDs are read, modified and written back: bit 30 (no RTR
on this PDO) and whatever else the drive keeps there stays as the drive has it.
"""

from __future__ import annotations

import threading
import time
from typing import TYPE_CHECKING

import canopen

from servobench.drivers.canopen.cycle import CycleIO
from servobench.drivers.canopen.mapping import SYNCHRONOUS, Layout, Pdo, plan_layout
from servobench.drivers.canopen.sdo import DriveObjects, SdoAccess, aborted_with
from servobench.drivers.cia402 import interpolation_period
from servobench.drivers.cia402_units import FactorObjects, derive_scaling
from servobench.errors import DriveConfigError, StateTransitionError, UsageError

if TYPE_CHECKING:
    from servobench.drivers.canopen.session import CanopenSession

#: COB-ID bit 31: PDO not valid. Bit 30: no RTR allowed on this PDO (kept as the drive has it).
COB_INVALID = 0x80000000
COB_NO_RTR = 0x40000000
#: NMT commands the host sends, and the heartbeat state each leads to.
NMT_PRE_OPERATIONAL, NMT_OPERATIONAL = 0x80, 0x01
NMT_STATES = {NMT_PRE_OPERATIONAL: 127, NMT_OPERATIONAL: 5}
#: Drive heartbeat period the host sets (0x1017), used to confirm NMT states [ms].
DRIVE_HEARTBEAT_MS = 100
#: Deadline for a heartbeat reporting a requested NMT state [s].
NMT_TIMEOUT_S = 3 * DRIVE_HEARTBEAT_MS / 1000 + 0.2
#: Deadline for 0x6061 to show the requested mode [s].
MODE_TIMEOUT_S = 0.5
#: Polling period while waiting for the drive [s].
POLL_S = 0.002
#: SDO aborts that mean "this object cannot be mapped (like that)" (CiA 301).
ABORT_NOT_MAPPABLE = (0x06040041, 0x06040043)
#: PDOs servobench looks at, beyond the ones it maps (disabled so they send nothing).
MAX_PDOS = 4


class NmtTracker:
    """Follows the drive's heartbeats to confirm the NMT states the host asks for."""

    def __init__(self, node_id: int) -> None:
        self.node_id = node_id
        self._cond = threading.Condition()
        self._state = -1

    def on_heartbeat(self, state: int) -> None:
        with self._cond:
            self._state = state
            self._cond.notify_all()

    def await_state(self, command: int) -> None:
        """Wait for a heartbeat reporting the state NMT ``command`` leads to."""
        want = NMT_STATES[command]
        deadline = time.monotonic() + NMT_TIMEOUT_S
        with self._cond:
            while self._state != want:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise StateTransitionError(
                        f"node {self.node_id} did not report NMT state {want} within "
                        f"{NMT_TIMEOUT_S} s (last heartbeat state {self._state})"
                    )
                self._cond.wait(left)


def set_mode(sdo: SdoAccess, mode: int, name: str) -> None:
    """Write 0x6060 = ``mode`` and wait until 0x6061 shows it."""
    sdo.write(0x6060, 0, mode)
    deadline = time.monotonic() + MODE_TIMEOUT_S
    while (shown := sdo.read(0x6061)) != mode:
        if time.monotonic() > deadline:
            raise StateTransitionError(
                f"node {sdo.node_id} did not switch to mode {mode} ({name}): "
                f"0x6061 still reads {shown} after {MODE_TIMEOUT_S} s"
            )
        time.sleep(POLL_S)


class MappingRefused(DriveConfigError):
    """The drive refused to map ``index`` into a PDO."""

    def __init__(self, message: str, index: int) -> None:
        super().__init__(message)
        self.index = index


def _cob_word(sdo: SdoAccess, comm: int) -> int:
    """The PDO's COB-ID entry as the drive has it."""
    return int(sdo.read(comm, 1))


def _map_one(sdo: SdoAccess, pdo: Pdo) -> None:
    kept = _cob_word(sdo, pdo.comm) & COB_NO_RTR  # bit 30 as the drive has it; 11-bit id
    sdo.write(pdo.comm, 1, COB_INVALID | kept | pdo.cob_id)
    sdo.write(pdo.comm, 2, SYNCHRONOUS)
    sdo.write(pdo.mapping, 0, 0)
    for sub, (index, entry) in enumerate(zip(pdo.objects, pdo.entries(), strict=True), start=1):
        try:
            sdo.write(pdo.mapping, sub, entry)
        except DriveConfigError as err:
            if aborted_with(err, ABORT_NOT_MAPPABLE):
                raise MappingRefused(str(err), index) from err
            raise
    sdo.write(pdo.mapping, 0, len(pdo.objects))
    sdo.write(pdo.comm, 1, kept | pdo.cob_id)


def install_layout(sdo: SdoAccess, objects: DriveObjects, layout: Layout) -> None:
    """Write ``layout`` into the drive's PDO parameters; disable the PDOs it does not use.

    Raises
    ------
    MappingRefused
        The drive refused one of the mapped objects.
    DriveConfigError
        The drive lacks a PDO the layout needs, or refused another write.
    """
    for pdo in (*layout.rpdos, *layout.tpdos):
        if not objects.has(pdo.comm, 1) or not objects.has(pdo.mapping, 0):
            raise DriveConfigError(
                f"node {sdo.node_id} has no PDO 0x{pdo.comm:04X}/0x{pdo.mapping:04X} "
                f"to carry {', '.join(f'0x{i:04X}' for i in pdo.objects)}"
            )
        _map_one(sdo, pdo)
    used = {pdo.comm for pdo in (*layout.rpdos, *layout.tpdos)}
    for base in (0x1400, 0x1800):
        for comm in range(base, base + MAX_PDOS):
            if comm in used or not objects.has(comm, 1):
                continue
            word = _cob_word(sdo, comm)
            if not word & COB_INVALID:
                sdo.write(comm, 1, word | COB_INVALID)


def read_factors(objects: DriveObjects) -> FactorObjects:
    """The factor-group objects the drive has (CiA 402-2)."""
    return FactorObjects(
        rated_torque_mNm=objects.value(0x6076),
        rated_current_mA=objects.value(0x6075),
        encoder=objects.pair(0x608F),
        gear=objects.pair(0x6091),
        feed=objects.pair(0x6092),
        position_unit=objects.value(0x60A8),
        velocity_unit=objects.value(0x60A9),
    )


def write_cycle(sdo: SdoAccess, objects: DriveObjects, period_s: float) -> None:
    """Communication cycle 0x1006 [µs] and interpolation period 0x60C2, where the drive has
    them. The caller puts the node in NMT PRE-OPERATIONAL first, as many drives demand."""
    period_us = period_s * 1e6
    if abs(period_us - round(period_us)) > 1e-6:
        raise UsageError(f"cycle period {period_s} s is not a whole number of µs (0x1006)")
    interpolation = objects.has(0x60C2, 1) and objects.has(0x60C2, 2)
    value, index = interpolation_period(period_s) if interpolation else (0, 0)
    if objects.has(0x1006):
        sdo.write(0x1006, 0, round(period_us))
    if interpolation:
        sdo.write(0x60C2, 1, value)
        sdo.write(0x60C2, 2, index)


def read_up(session: CanopenSession) -> None:
    """A read-only open of ``session`` (connected): what the bring-up learns, by SDO upload only.

    The object dictionary, identity profile, factor group and units, the
    modes, the PDO layout the bring-up would map (planned, not written) and
    max torque 0x6072; no SDO download, no NMT command, no heartbeat: the
    node stays in the NMT state it is in.
    """
    o, n = session.options, session.options.node_id
    od, from_eds = session._object_dictionary()
    session.node = canopen.RemoteNode(n, od)
    session.network.add_node(session.node)
    sdo = session.sdo = SdoAccess(session.node, o.sdo_timeout_s)
    objects = session.objects = DriveObjects(od, from_eds, sdo)
    io = session.io = CycleIO(o, session.network, sdo)
    profile = sdo.read(0x1000) & 0xFFFF
    if profile != 402:
        raise DriveConfigError(f"node {n} is no CiA 402 drive (0x1000 profile {profile})")
    session.factors = read_factors(objects)
    session.scaling = io.scaling = derive_scaling(session.factors, o.overrides)
    session.hold_reason = session._hold_capability(objects.value(0x6502))
    try:
        session.layout = io.layout = plan_layout(
            n, lambda i: objects.mappable(i, receive=True), lambda i: objects.mappable(i, receive=False),
            hold=session.hold_reason is None, clock=True,
        )  # fmt: skip
    except ValueError as err:
        raise DriveConfigError(f"node {n}: {err}") from None
    if objects.has(0x6072):
        io.max_lsb = lsb = min(sdo.read(0x6072), 0x7FFF)
        u = session.scaling.u
        session.notes["max_torque"] = f"0x6072 = {lsb} ({lsb * u.scale:.6g} {u.unit})"
    else:
        session.notes["max_torque"] = "host-side clamping only (the drive has no 0x6072)"
    session.notes["watchdog_action"] = "none armed (read-only)"
