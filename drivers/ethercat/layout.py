"""The process data the ``ethercat://`` drive maps, and its byte layout: pure, no I/O.

RxPDO (SM2, outputs) and TxPDO (SM3, inputs) of one PDO each (0x1600 and
0x1A00), entries in this order where the slave has the object::

    RxPDO  0x6040 controlword (16)   0x6071 target torque (16)
           0x607A target position (32)   0x60B2 torque offset (16)     [the hold]
    TxPDO  0x6041 statusword (16)    0x6064 position (32)   0x606C velocity (32)
           0x6077 torque actual (16)
           0x10F8 timestamp object [ns] (64), else 0x1013 time stamp [µs] (32)  [where mappable]

The time stamp is the slave's clock at the instant the inputs were sampled:
0x10F8 (ETG.1000.6, UNSIGNED64) its DC system time, 0x1013 (CiA 301,
UNSIGNED32, wrapping) a microsecond counter. One of them is mapped, 0x10F8
where the slave has it.

A mapping entry is ``index << 16 | subindex << 8 | bits`` (ETG.1000.6 / CiA 301).
"""

from __future__ import annotations

import struct
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

#: (index, bits, struct code); the first two of each direction are required.
RX_OBJECTS = ((0x6040, 16, "H"), (0x6071, 16, "h"), (0x607A, 32, "i"), (0x60B2, 16, "h"))
TX_OBJECTS = ((0x6041, 16, "H"), (0x6064, 32, "i"), (0x606C, 32, "i"), (0x6077, 16, "h"),
              (0x10F8, 64, "Q"), (0x1013, 32, "I"))  # fmt: skip
#: Time stamp objects, the preferred first.
TIMESTAMPS = (0x10F8, 0x1013)
REQUIRED_RX = (0x6040, 0x6071)
REQUIRED_TX = (0x6041, 0x6064, 0x606C)


def mapping_entry(index: int, bits: int, subindex: int = 0) -> int:
    return index << 16 | subindex << 8 | bits


@dataclass(frozen=True)
class PdoLayout:
    """The objects of one direction, in frame order."""

    objects: tuple[tuple[int, int, str], ...]

    @classmethod
    def choose(cls, table, present: Iterable[int]) -> PdoLayout:
        have = set(present)
        return cls(tuple(o for o in table if o[0] in have))

    @property
    def fmt(self) -> str:
        return "<" + "".join(code for _i, _b, code in self.objects)

    @property
    def size(self) -> int:
        return struct.calcsize(self.fmt)

    @property
    def indices(self) -> tuple[int, ...]:
        return tuple(i for i, _b, _c in self.objects)

    def entries(self) -> list[int]:
        return [mapping_entry(i, b) for i, b, _c in self.objects]

    def has(self, index: int) -> bool:
        return index in self.indices

    def pack(self, values: Mapping[int, int]) -> bytes:
        return struct.pack(self.fmt, *(values.get(i, 0) for i in self.indices))

    def unpack(self, data: bytes) -> dict[int, int]:
        return dict(zip(self.indices, struct.unpack_from(self.fmt, data), strict=True))
