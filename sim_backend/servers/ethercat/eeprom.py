"""The ESC's EEPROM interface (registers 0x0500-0x050F) over the SII image: pure, on bytes.

Registers (ESC datasheet section II, 0x0500 ff.)::

    0x0500  EEPROM configuration (PDI / ECAT access)      0x0501  PDI access state
    0x0502  control/status: bit 0 write enable, bit 6 eight-byte reads, bits 8..10
            command (1 read, 2 write, 4 reload), bit 13 acknowledge/command error,
            bit 14 write enable error, bit 15 busy
    0x0504  word address (32 bit)                          0x0508  data (8 bytes)

A command written by the master is executed at once (never busy): a read
puts 8 bytes of the image from the word address into the data register
(0xFF past the end), a write stores one word when write enable is set in
the same write, a reload takes the configured station alias again.
"""

from __future__ import annotations

import struct

from servobench.sim_backend.servers.ethercat import registers as R

CMD_READ, CMD_WRITE, CMD_RELOAD = 0x01, 0x02, 0x04
ERROR_COMMAND = 0x2000
ERROR_WRITE_ENABLE = 0x4000
WRITE_ENABLE = 0x0001


def execute_eeprom_command(mem: bytearray, sii: bytearray) -> None:
    """Run the command in ``mem``'s EEPROM control register on ``sii``; leave the status."""
    control = int.from_bytes(mem[R.EEPROM_CONTROL : R.EEPROM_CONTROL + 2], "little")
    command = control >> 8 & 0x07
    (address,) = struct.unpack_from("<I", mem, R.EEPROM_ADDRESS)
    status = R.EEPROM_READ_8_BYTES
    at = 2 * address
    if command == CMD_READ:
        if at >= len(sii):
            status |= ERROR_COMMAND
        else:
            chunk = bytes(sii[at : at + 8])
            mem[R.EEPROM_DATA : R.EEPROM_DATA + 8] = chunk + b"\xff" * (8 - len(chunk))
    elif command == CMD_WRITE:
        if not control & WRITE_ENABLE:
            status |= ERROR_WRITE_ENABLE
        elif at + 2 > len(sii):
            status |= ERROR_COMMAND
        else:
            sii[at : at + 2] = mem[R.EEPROM_DATA : R.EEPROM_DATA + 2]
    elif command == CMD_RELOAD:
        mem[R.STATION_ALIAS : R.STATION_ALIAS + 2] = sii[8:10]
    mem[R.EEPROM_CONTROL : R.EEPROM_CONTROL + 2] = status.to_bytes(2, "little")
