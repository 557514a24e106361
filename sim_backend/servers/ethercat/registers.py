"""The ESC register map as data (Beckhoff ESC datasheet section II, ETG.1000.4).

Each entry: address, size [bytes], whether EtherCAT may write it, and the
value after power-on. The slave controller (:mod:`.esc`) builds its write
mask and its reset image from :data:`REGISTERS`; everything in 0x0000..0x0FFF
not listed is reserved: it reads 0 and ignores writes, as on an ESC.
"""

from __future__ import annotations

from typing import NamedTuple


class Register(NamedTuple):
    address: int
    size: int
    writable: bool
    reset: int = 0


TYPE = 0x0000
REVISION = 0x0001
BUILD = 0x0002
FMMUS_SUPPORTED = 0x0004
SMS_SUPPORTED = 0x0005
RAM_SIZE = 0x0006
PORT_DESCRIPTOR = 0x0007
FEATURES = 0x0008
STATION_ADDRESS = 0x0010
STATION_ALIAS = 0x0012
DL_CONTROL = 0x0100
DL_STATUS = 0x0110
AL_CONTROL = 0x0120
AL_STATUS = 0x0130
AL_STATUS_CODE = 0x0134
PDI_CONTROL = 0x0140
ESC_CONFIG = 0x0141
ECAT_EVENT_MASK = 0x0200
ERROR_COUNTERS = 0x0300
WD_DIVIDER = 0x0400
WD_TIME_PDI = 0x0410
WD_TIME_PD = 0x0420
WD_STATUS_PD = 0x0440
WD_COUNTER_PD = 0x0442
WD_COUNTER_PDI = 0x0443
EEPROM_CONFIG = 0x0500
EEPROM_PDI_ACCESS = 0x0501
EEPROM_CONTROL = 0x0502
EEPROM_ADDRESS = 0x0504
EEPROM_DATA = 0x0508
FMMU0 = 0x0600
FMMU_BYTES = 16
FMMU_COUNT = 8
SM0 = 0x0800
SM_BYTES = 8
SM_COUNT = 8
DC_RECEIVE_TIME_PORT0 = 0x0900
DC_SYSTEM_TIME = 0x0910
DC_RECEIVE_TIME_PU = 0x0918
DC_SYSTEM_TIME_OFFSET = 0x0920
DC_SYSTEM_TIME_DELAY = 0x0928
DC_SYSTEM_TIME_DIFF = 0x092C
DC_SPEED_COUNTER_START = 0x0930
DC_FILTER_DEPTH = 0x0934
DC_CYCLIC_UNIT_CONTROL = 0x0980
DC_ACTIVATION = 0x0981
DC_SYNC0_STATUS = 0x098E
DC_START_TIME = 0x0990
DC_SYNC0_CYCLE = 0x09A0
DC_SYNC1_CYCLE = 0x09A4
#: Process RAM (8 KiB, as an ET1100).
RAM_START = 0x1000
RAM_END = 0x3000

#: ESC type (0x11: an ET1100-like controller).
ESC_TYPE = 0x11
#: 0x0008 features: bit 0 FMMU bytewise, bit 2 distributed clocks, bit 3 64-bit DC.
FEATURE_DC = 0x0004
FEATURE_DC64 = 0x0008
#: Watchdog divider after reset: (2498 + 2) x 40 ns = 100 µs per watchdog tick.
WD_DIVIDER_RESET = 2498
WD_TIME_RESET = 1000  # 1000 ticks = 100 ms
#: DL status: PDI operational, PDI watchdog reloaded, link on port 0, port 0
#: open with communication, ports 1..3 closed (an end of the line).
DL_STATUS_END_OF_LINE = 0x0001 | 0x0002 | 0x0010 | 0x0200 | 0x0400 | 0x1000 | 0x4000
#: EEPROM control/status bit 6: the interface reads 8 bytes at once.
EEPROM_READ_8_BYTES = 0x0040

REGISTERS: tuple[Register, ...] = (
    Register(TYPE, 1, False, ESC_TYPE),
    Register(REVISION, 1, False, 0x02),
    Register(BUILD, 2, False, 0x0001),
    Register(FMMUS_SUPPORTED, 1, False, FMMU_COUNT),
    Register(SMS_SUPPORTED, 1, False, SM_COUNT),
    Register(RAM_SIZE, 1, False, (RAM_END - RAM_START) // 1024),
    Register(PORT_DESCRIPTOR, 1, False, 0x0F),  # ports 0 and 1 MII
    Register(FEATURES, 2, False, 0x0001 | FEATURE_DC | FEATURE_DC64),
    Register(STATION_ADDRESS, 2, True),
    Register(STATION_ALIAS, 2, False),
    Register(DL_CONTROL, 4, True, 0x00000001),
    Register(0x0108, 2, True),  # physical read/write offset
    Register(DL_STATUS, 2, False, DL_STATUS_END_OF_LINE),
    Register(AL_CONTROL, 2, True, 0x0001),
    Register(AL_STATUS, 2, False, 0x0001),
    Register(AL_STATUS_CODE, 2, False),
    Register(PDI_CONTROL, 1, False),
    Register(ESC_CONFIG, 1, False),
    Register(ECAT_EVENT_MASK, 2, True),
    Register(0x0204, 4, True),  # AL event mask (PDI side, writable here too)
    Register(0x0210, 2, False),  # ECAT event request
    Register(ERROR_COUNTERS, 20, True),  # write clears
    Register(WD_DIVIDER, 2, True, WD_DIVIDER_RESET),
    Register(WD_TIME_PDI, 2, True, WD_TIME_RESET),
    Register(WD_TIME_PD, 2, True, WD_TIME_RESET),
    Register(WD_STATUS_PD, 2, False, 0x0001),
    Register(WD_COUNTER_PD, 1, True),
    Register(WD_COUNTER_PDI, 1, True),
    Register(EEPROM_CONFIG, 1, True),
    Register(EEPROM_PDI_ACCESS, 1, False),
    Register(EEPROM_CONTROL, 2, True, EEPROM_READ_8_BYTES),
    Register(EEPROM_ADDRESS, 4, True),
    Register(EEPROM_DATA, 8, True),
    Register(FMMU0, FMMU_BYTES * FMMU_COUNT, True),
    Register(DC_RECEIVE_TIME_PORT0, 16, True),  # a write latches the receive times
    Register(DC_SYSTEM_TIME, 8, True),  # a write is the reference clock's time (drift)
    Register(DC_RECEIVE_TIME_PU, 8, False),
    Register(DC_SYSTEM_TIME_OFFSET, 8, True),
    Register(DC_SYSTEM_TIME_DELAY, 4, True),
    Register(DC_SYSTEM_TIME_DIFF, 4, False),
    Register(DC_SPEED_COUNTER_START, 2, True, 0x1000),
    Register(0x0932, 2, False),
    Register(DC_FILTER_DEPTH, 2, True, 0x0C04),
    Register(DC_CYCLIC_UNIT_CONTROL, 1, True),
    Register(DC_ACTIVATION, 1, True),
    Register(0x0982, 2, False),  # SYNC pulse length
    Register(DC_SYNC0_STATUS, 1, False),
    Register(DC_START_TIME, 8, True),
    Register(DC_SYNC0_CYCLE, 4, True),
    Register(DC_SYNC1_CYCLE, 4, True),
)


def sm_register(n: int, offset: int = 0) -> int:
    """Address of byte ``offset`` of SyncManager ``n``'s registers."""
    return SM0 + n * SM_BYTES + offset


# SyncManager register bytes: start (0..1), length (2..3), control (4), status (5),
# activate (6), PDI control (7); only status and PDI control are read-only.
SM_CONTROL, SM_STATUS, SM_ACTIVATE, SM_PDI_CONTROL = 4, 5, 6, 7
SM_MODE_MAILBOX = 0x02  # control bits 1..0: 00 buffered, 10 mailbox
SM_DIR_WRITE = 0x04  # control bits 3..2: 00 ECAT reads, 01 ECAT writes
SM_WATCHDOG_ENABLE = 0x40  # control bit 6
SM_STATUS_MAILBOX_FULL = 0x08
SM_ACTIVATE_ENABLE = 0x01
SM_ACTIVATE_REPEAT = 0x02


def write_mask() -> bytearray:
    """One flag byte per register address: 1 where EtherCAT may write."""
    mask = bytearray(RAM_START)
    for reg in REGISTERS:
        if reg.writable:
            mask[reg.address : reg.address + reg.size] = b"\x01" * reg.size
    for n in range(SM_COUNT):
        for offset in (0, 1, 2, 3, SM_CONTROL, SM_ACTIVATE):
            mask[sm_register(n, offset)] = 1
    return mask


def reset_image() -> bytearray:
    """The register space after power-on (process RAM zero)."""
    mem = bytearray(RAM_END)
    for reg in REGISTERS:
        mem[reg.address : reg.address + reg.size] = reg.reset.to_bytes(reg.size, "little")
    return mem
