"""The PDO mapping of ``canopen://``, planned from the objects the drive has.

Pure: no I/O. :func:`plan_layout` chooses what each PDO carries; the drive
writes it over SDO (:mod:`servobench.drivers.canopen.bringup`) and packs and
unpacks the cyclic frames with :meth:`Pdo.pack` / :meth:`Pdo.unpack`::

    RPDO1  0x200+n  controlword 0x6040 [, target torque 0x6071] [, torque offset 0x60B2]
    RPDO2  0x300+n  target position 0x607A                      (drive-side hold only)
    TPDO1  0x180+n  statusword 0x6041 [, torque actual 0x6077] [, time stamp 0x1013]
    TPDO2  0x280+n  velocity actual 0x606C, position actual 0x6064

Every TPDO is synchronous (transmission type 1: on each SYNC), so one cycle
on the wire is the RPDOs, a SYNC and the TPDOs (:meth:`Layout.cycle_frames`).
The bracketed objects are mapped when the drive has them and can map them:
the time stamp gives the drive clock, the torque actual value ``Feedback.applied``,
and the torque offset with the target position the drive-side hold. A drive
commanded only under its own hold (``Drive.hold_only``) gets no target
torque: its command is the torque offset alone.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass

#: struct format of each object servobench maps (CiA 301/402 types).
FORMATS: dict[int, str] = {
    0x6040: "H",  # controlword, UNSIGNED16
    0x6071: "h",  # target torque, INTEGER16
    0x60B2: "h",  # torque offset, INTEGER16
    0x607A: "i",  # target position, INTEGER32
    0x6041: "H",  # statusword, UNSIGNED16
    0x6077: "h",  # torque actual value, INTEGER16
    0x1013: "I",  # high-resolution time stamp, UNSIGNED32
    0x606C: "i",  # velocity actual value, INTEGER32
    0x6064: "i",  # position actual value, INTEGER32
}
#: Communication parameter of the first RPDO / TPDO (mapping parameter: + 0x200).
RPDO_COMM, TPDO_COMM = 0x1400, 0x1800
#: Transmission type of every PDO servobench maps: synchronous, every SYNC.
SYNCHRONOUS = 1

#: ``has(index) -> bool``: whether the drive can map ``index`` in this direction.
Mappable = Callable[[int], bool]


@dataclass(frozen=True)
class Pdo:
    """One PDO: its communication parameter index, COB-ID and mapped objects in frame order."""

    comm: int
    cob_id: int
    objects: tuple[int, ...]

    @property
    def mapping(self) -> int:
        """Index of the mapping parameter (0x1600 + n or 0x1A00 + n)."""
        return self.comm + 0x200

    @property
    def format(self) -> str:
        return "<" + "".join(FORMATS[i] for i in self.objects)

    @property
    def length(self) -> int:
        """Frame payload [bytes]."""
        return struct.calcsize(self.format)

    def entries(self) -> list[int]:
        """Mapping entries (index << 16 | sub-index << 8 | bits), CiA 301."""
        return [i << 16 | 8 * struct.calcsize(FORMATS[i]) for i in self.objects]

    def pack(self, values: dict[int, int]) -> bytes:
        return struct.pack(self.format, *(values[i] for i in self.objects))

    def unpack(self, data: bytes) -> dict[int, int] | None:
        """The mapped values by index, ``None`` when ``data`` is too short."""
        if len(data) < self.length:
            return None
        return dict(zip(self.objects, struct.unpack_from(self.format, data), strict=True))


@dataclass(frozen=True)
class Layout:
    """What the host maps: the command PDOs, the feedback PDOs, and what they carry."""

    rpdo_command: Pdo
    rpdo_hold: Pdo | None
    tpdo_state: Pdo
    tpdo_motion: Pdo

    @property
    def has_clock(self) -> bool:
        """The drive's time stamp 0x1013 comes with every SYNC."""
        return 0x1013 in self.tpdo_state.objects

    @property
    def has_torque_actual(self) -> bool:
        return 0x6077 in self.tpdo_state.objects

    @property
    def can_hold(self) -> bool:
        """The torque offset and the target position are mapped (drive-side hold)."""
        return self.rpdo_hold is not None

    @property
    def rpdos(self) -> tuple[Pdo, ...]:
        return (self.rpdo_command,) + ((self.rpdo_hold,) if self.rpdo_hold else ())

    @property
    def tpdos(self) -> tuple[Pdo, ...]:
        return (self.tpdo_state, self.tpdo_motion)

    def cycle_frames(self, holding: bool) -> list[int]:
        """Data lengths [bytes] of the frames of one cycle: RPDOs, SYNC, TPDOs."""
        rpdos = self.rpdos if holding else (self.rpdo_command,)
        return [p.length for p in rpdos] + [0] + [p.length for p in self.tpdos]


def plan_layout(
    node_id: int, receive: Mappable, transmit: Mappable, *, hold: bool, clock: bool,
    torque: bool | None = None,
) -> Layout:  # fmt: skip
    """The PDOs for node ``node_id`` given what it can map.

    Parameters
    ----------
    receive, transmit : callable
        Whether the drive can map an object into an RPDO / a TPDO.
    hold : bool
        Map the torque offset 0x60B2 and the target position 0x607A (the
        caller checked the drive offers cyclic synchronous position).
    clock : bool
        Map the time stamp 0x1013 when the drive can.
    torque : bool or None
        Map the target torque 0x6071: True always (a torque mode), False never
        (a drive commanded by the torque offset under its own hold alone, which
        needs ``hold``), None (default) where the drive can, or where nothing
        else would carry the command (the plan of a read-only open).

    Raises
    ------
    ValueError
        An object the layout needs cannot be mapped, or nothing would carry the command.
    """
    if torque is False and not hold:
        raise ValueError(
            "without the target torque 0x6071 only the torque offset 0x60B2 can carry the command"
        )
    with_torque = (receive(0x6071) or not hold) if torque is None else torque
    command = (0x6040,) + ((0x6071,) if with_torque else ()) + ((0x60B2,) if hold else ())
    state = (0x6041,) + tuple(
        i for i, wanted in ((0x6077, True), (0x1013, clock)) if wanted and transmit(i)
    )
    for index in command + ((0x607A,) if hold else ()):
        if not receive(index):
            raise ValueError(f"0x{index:04X} cannot be mapped into an RPDO")
    for index in (0x6041, 0x606C, 0x6064):
        if not transmit(index):
            raise ValueError(f"0x{index:04X} cannot be mapped into a TPDO")
    return Layout(
        rpdo_command=Pdo(RPDO_COMM, 0x200 + node_id, command),
        rpdo_hold=Pdo(RPDO_COMM + 1, 0x300 + node_id, (0x607A,)) if hold else None,
        tpdo_state=Pdo(TPDO_COMM, 0x180 + node_id, state),
        tpdo_motion=Pdo(TPDO_COMM + 1, 0x280 + node_id, (0x606C, 0x6064)),
    )
