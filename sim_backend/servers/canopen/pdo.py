"""PDOs of the served drive: the maps the host wrote by SDO, checked and compiled.

canopen's :class:`~canopen.LocalNode` stores PDO parameters but neither sends
TPDOs nor applies received RPDOs. The served drive reads its communication
(0x1400/0x1800 + n) and mapping (0x1600/0x1A00 + n) parameters with
:func:`read_channels` and packs/unpacks frames with :class:`PdoChannel`.
Mapping writes are checked as CiA 301 demands (:func:`check_mapping_write`),
so a host that maps carelessly fails here as it would on a real drive.

Mapping entry (UNSIGNED32)::

    bits 31..16 index | bits 15..8 sub-index | bits 7..0 length [bits]
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from canopen import LocalNode
from canopen.objectdictionary import ObjectDictionary, ODVariable
from canopen.sdo import SdoAbortedError

RPDO_COMM, RPDO_MAP = 0x1400, 0x1600
TPDO_COMM, TPDO_MAP = 0x1800, 0x1A00
#: COB-ID bit 31: the PDO does not exist / is not valid.
COB_INVALID = 0x80000000
#: Largest number of PDOs of each direction the engine looks at.
MAX_PDOS = 4

ABORT_NO_OBJECT = 0x06020000
ABORT_NOT_MAPPABLE = 0x06040041
ABORT_PDO_TOO_LONG = 0x06040042
ABORT_INCOMPATIBLE = 0x06040043
ABORT_VALUE_RANGE = 0x06090030


@dataclass(frozen=True)
class MappedObject:
    """One entry of a PDO map: object ``index:subindex`` of ``bits`` bits."""

    index: int
    subindex: int
    bits: int

    @classmethod
    def from_entry(cls, entry: int) -> MappedObject:
        return cls(entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF)


@dataclass(frozen=True)
class PdoChannel:
    """A valid (enabled) PDO as configured.

    Attributes
    ----------
    number : int
        PDO number, 1-based.
    cob_id : int
        11-bit CAN identifier.
    transmission_type : int
        0..240 synchronous (every ``n``-th SYNC; 0 is treated as 1),
        254/255 event-driven.
    entries : tuple of MappedObject
        The mapped objects, in frame order.
    """

    number: int
    cob_id: int
    transmission_type: int
    entries: tuple[MappedObject, ...]

    @property
    def length(self) -> int:
        """Frame payload [bytes]."""
        return sum(e.bits for e in self.entries) // 8

    @property
    def synchronous(self) -> bool:
        return self.transmission_type <= 240

    def due(self, sync_count: int) -> bool:
        """True when this TPDO goes out on the ``sync_count``-th SYNC (1-based)."""
        return self.synchronous and sync_count % max(self.transmission_type, 1) == 0

    def pack(self, get: Callable[[int, int], bytes]) -> bytes:
        """The frame payload, reading each mapped object with ``get(index, subindex)``."""
        return b"".join(get(e.index, e.subindex)[: e.bits // 8] for e in self.entries)

    def unpack(self, data: bytes) -> list[tuple[MappedObject, bytes]]:
        """Split a received payload into its mapped objects."""
        out, pos = [], 0
        for e in self.entries:
            n = e.bits // 8
            out.append((e, bytes(data[pos : pos + n])))
            pos += n
        return out


def _u32(node: LocalNode, index: int, subindex: int) -> int:
    return int.from_bytes(node.get_data(index, subindex), "little")


def read_channels(node: LocalNode, comm_base: int, map_base: int) -> list[PdoChannel]:
    """The valid PDOs of one direction (``RPDO_COMM, RPDO_MAP`` or ``TPDO_COMM, TPDO_MAP``)."""
    channels = []
    for n in range(MAX_PDOS):
        if comm_base + n not in node.object_dictionary:
            continue
        cob = _u32(node, comm_base + n, 1)
        if cob & COB_INVALID:
            continue
        count = node.get_data(map_base + n, 0)[0]
        entries = tuple(
            MappedObject.from_entry(_u32(node, map_base + n, sub)) for sub in range(1, count + 1)
        )
        ttype = node.get_data(comm_base + n, 2)[0]
        channels.append(PdoChannel(n + 1, cob & 0x7FF, ttype, entries))
    return channels


def is_pdo_parameter(index: int) -> bool:
    """A PDO communication or mapping parameter."""
    return any(
        base <= index < base + MAX_PDOS for base in (RPDO_COMM, RPDO_MAP, TPDO_COMM, TPDO_MAP)
    )


def is_mapping_parameter(index: int) -> bool:
    return any(base <= index < base + MAX_PDOS for base in (RPDO_MAP, TPDO_MAP))


def _object(od: ObjectDictionary, index: int, subindex: int) -> ODVariable:
    if index not in od:
        raise SdoAbortedError(ABORT_NO_OBJECT)
    obj = od[index]
    if not isinstance(obj, ODVariable):
        if subindex not in obj:
            raise SdoAbortedError(ABORT_NO_OBJECT)
        obj = obj[subindex]
    return obj


def check_mapping_write(node: LocalNode, index: int, subindex: int, value: int) -> None:
    """Raise :class:`SdoAbortedError` unless writing ``value`` to a mapping parameter is valid.

    CiA 301 procedure: invalidate the PDO (COB-ID bit 31), set sub-index 0
    to 0, write the entries, set sub-index 0 to their number, validate.
    """
    receive = RPDO_MAP <= index < RPDO_MAP + MAX_PDOS
    comm = (RPDO_COMM if receive else TPDO_COMM) + (index & 0xFF)
    if not _u32(node, comm, 1) & COB_INVALID:
        raise SdoAbortedError(ABORT_INCOMPATIBLE)  # mapping of a valid PDO must not change
    od = node.object_dictionary
    if subindex == 0:
        if value > 8:
            raise SdoAbortedError(ABORT_VALUE_RANGE)
        entries = [MappedObject.from_entry(_u32(node, index, s)) for s in range(1, value + 1)]
        for e in entries:
            _check_entry(od, e, receive)
        if sum(e.bits for e in entries) > 64:
            raise SdoAbortedError(ABORT_PDO_TOO_LONG)
        return
    if node.get_data(index, 0)[0] != 0:
        raise SdoAbortedError(ABORT_INCOMPATIBLE)  # sub-index 0 must be 0 while mapping
    if value:
        _check_entry(od, MappedObject.from_entry(value), receive)


def _check_entry(od: ObjectDictionary, entry: MappedObject, receive: bool) -> None:
    obj = _object(od, entry.index, entry.subindex)
    readable_ok = obj.writable if receive else obj.readable
    if not obj.pdo_mappable or not readable_ok:
        raise SdoAbortedError(ABORT_NOT_MAPPABLE)
    if entry.bits != len(obj) or entry.bits % 8:
        raise SdoAbortedError(ABORT_INCOMPATIBLE)
