"""The slave's SII (EEPROM) image (ETG.2010), built from its description: pure, no I/O.

Word addresses of the fixed part (16-bit words, little-endian)::

    0x0000..0x0006  ESC configuration (PDI control, PDI config, SYNC pulse, alias)
    0x0007          checksum: CRC-8 (x^8 + x^2 + x + 1, initial 0xFF) of bytes 0..13
    0x0008  vendor id (32)     0x000A  product code (32)
    0x000C  revision (32)      0x000E  serial number (32)
    0x0014  bootstrap receive mailbox offset, size; 0x0016 send offset, size
    0x0018  standard receive mailbox offset (master -> slave), 0x0019 its size
    0x001A  standard send mailbox offset (slave -> master), 0x001B its size
    0x001C  mailbox protocols (bit 2 CoE)
    0x003E  EEPROM size [kbit] - 1       0x003F  version (1)

From word 0x0040 on, categories, each ``type (16), size [words] (16), data``,
ended by type 0xFFFF:

* Strings (10): count, then length-prefixed strings (index 1 is the first);
* General (30): group, image, order and name string indices, CoE details
  (byte 5: bit 0 SDO, 1 SDO info, 2 PDO assign, 3 PDO config, 4 upload at
  startup, 5 SDO complete access), FoE, EoE, SoE, 402 channels, flags;
* FMMU (40): one byte per FMMU (1 outputs, 2 inputs, 3 SM status);
* SyncM (41): per SM start (16), length (16), control (8), status (8),
  enable (8), type (8: 1 mailbox out, 2 mailbox in, 3 outputs, 4 inputs);
* TxPDO (50) / RxPDO (51): per PDO index (16), entry count (8), SM (8),
  DC sync (8), name (8), flags (16), then per entry index (16), subindex (8),
  name (8), data type (8), bit length (8), flags (16).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

CAT_STRINGS = 10
CAT_GENERAL = 30
CAT_FMMU = 40
CAT_SYNCM = 41
CAT_TXPDO = 50
CAT_RXPDO = 51
CAT_END = 0xFFFF

MBX_PROTO_COE = 0x0004
# CoE details bits of the General category.
COE_SDO = 0x01
COE_SDO_INFO = 0x02
COE_PDO_ASSIGN = 0x04
COE_PDO_CONFIG = 0x08
COE_COMPLETE_ACCESS = 0x20

FMMU_OUTPUTS, FMMU_INPUTS = 1, 2
SM_MBX_OUT, SM_MBX_IN, SM_OUTPUTS, SM_INPUTS = 1, 2, 3, 4
#: EEPROM size [bytes] (16 kbit).
EEPROM_BYTES = 2048


def crc8(data: bytes) -> int:
    """The SII checksum: CRC-8, polynomial 0x07, initial value 0xFF, no reflection."""
    crc = 0xFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc << 1 ^ 0x07) & 0xFF if crc & 0x80 else crc << 1 & 0xFF
    return crc


@dataclass(frozen=True)
class SyncManagerSpec:
    start: int
    length: int
    control: int
    kind: int  # SM_MBX_OUT .. SM_INPUTS
    enable: int = 0x01


@dataclass(frozen=True)
class PdoEntrySpec:
    index: int
    subindex: int
    bits: int
    data_type: int = 0
    name: str = ""


@dataclass(frozen=True)
class PdoSpec:
    index: int
    sync_manager: int
    entries: tuple[PdoEntrySpec, ...]
    name: str = ""


@dataclass(frozen=True)
class SlaveDescription:
    """What the SII tells of the slave."""

    vendor_id: int
    product_code: int
    revision: int
    serial: int
    name: str
    group: str
    order: str
    sync_managers: tuple[SyncManagerSpec, ...]
    fmmus: tuple[int, ...]
    txpdos: tuple[PdoSpec, ...]
    rxpdos: tuple[PdoSpec, ...]
    coe_details: int = COE_SDO | COE_SDO_INFO | COE_PDO_ASSIGN | COE_PDO_CONFIG
    pdi_control: int = 0x0005  # SPI slave (no process data from the PDI's side), as ESCs with µC
    channels_402: int = 1

    def mailbox(self, kind: int) -> SyncManagerSpec:
        return next(sm for sm in self.sync_managers if sm.kind == kind)


def _category(kind: int, data: bytes) -> bytes:
    if len(data) % 2:
        data += b"\x00"
    return struct.pack("<HH", kind, len(data) // 2) + data


class _Strings:
    def __init__(self) -> None:
        self.items: list[bytes] = []

    def index(self, text: str) -> int:
        if not text:
            return 0
        raw = text.encode("ascii")[:255]
        if raw not in self.items:
            self.items.append(raw)
        return self.items.index(raw) + 1

    def encode(self) -> bytes:
        return bytes([len(self.items)]) + b"".join(bytes([len(s)]) + s for s in self.items)


def _pdos(specs: tuple[PdoSpec, ...], strings: _Strings) -> bytes:
    out = b""
    for pdo in specs:
        out += struct.pack(
            "<HBBBBH", pdo.index, len(pdo.entries), pdo.sync_manager, 0, strings.index(pdo.name), 0
        )
        for e in pdo.entries:
            out += struct.pack(
                "<HBBBBH", e.index, e.subindex, strings.index(e.name), e.data_type, e.bits, 0
            )
    return out


def build_image(desc: SlaveDescription) -> bytes:
    """The EEPROM content of ``desc`` [bytes], padded with 0xFF to :data:`EEPROM_BYTES`."""
    rx, tx = desc.mailbox(SM_MBX_OUT), desc.mailbox(SM_MBX_IN)
    config = struct.pack("<7H", desc.pdi_control, 0, 0, 0, 0, 0, 0)
    head = config + struct.pack("<H", crc8(config))
    head += struct.pack("<IIII", desc.vendor_id, desc.product_code, desc.revision, desc.serial)
    head += bytes(8)  # 0x0010..0x0013
    head += struct.pack("<HHHH", 0, 0, 0, 0)  # bootstrap mailboxes: none
    head += struct.pack("<HHHHH", rx.start, rx.length, tx.start, tx.length, MBX_PROTO_COE)
    head += bytes(2 * (0x3E - 0x1D))
    head += struct.pack("<HH", EEPROM_BYTES * 8 // 1024 - 1, 1)
    strings = _Strings()
    # the device name first: masters name the slave after string 1 (SOEM does)
    name, group, image, order = (strings.index(s) for s in (desc.name, desc.group, "", desc.order))
    general = struct.pack(
        "<BBBBBBBBBBBBhH",
        group, image, order, name, 0, desc.coe_details, 0, 0, 0, desc.channels_402, 0, 0, 0, 0,
    ) + bytes(16)  # fmt: skip
    syncm = b"".join(
        struct.pack("<HHBBBB", sm.start, sm.length, sm.control, 0, sm.enable, sm.kind)
        for sm in desc.sync_managers
    )
    txpdo, rxpdo = _pdos(desc.txpdos, strings), _pdos(desc.rxpdos, strings)
    body = (
        _category(CAT_STRINGS, strings.encode())
        + _category(CAT_GENERAL, general)
        + _category(CAT_FMMU, bytes(desc.fmmus))
        + _category(CAT_SYNCM, syncm)
        + _category(CAT_TXPDO, txpdo)
        + _category(CAT_RXPDO, rxpdo)
        + struct.pack("<H", CAT_END)
    )
    image_bytes = head + body
    if len(image_bytes) > EEPROM_BYTES:
        raise ValueError(f"SII image of {len(image_bytes)} bytes exceeds the EEPROM")
    return image_bytes + b"\xff" * (EEPROM_BYTES - len(image_bytes))
