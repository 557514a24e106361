"""The simulated drive as an EtherCAT CoE CiA 402 slave (``serve-sim --transport ethercat``).

Layers, each its own module, from the wire up:

* :mod:`.frame` -- EtherCAT frames and datagrams as bytes (pure codec);
* :mod:`.registers` -- the ESC register map as data (address, size, writable, reset value);
* :mod:`.al` -- the AL state machine (INIT, PRE-OP, SAFE-OP, OP) as data;
* :mod:`.sii` -- the SII (EEPROM) image of the slave;
* :mod:`.esc` -- the slave controller: datagram execution with working
  counters, SyncManagers and mailboxes, FMMUs, SM watchdog, DC registers;
* :mod:`.eeprom` -- its EEPROM interface over the SII image;
* :mod:`.mailbox` -- the mailbox and CoE headers (pure codec);
* :mod:`.coe_sdo` -- the CoE SDO server (expedited, normal, segmented, complete access);
* :mod:`.objects` -- the object dictionary (the CANopen served drive's, plus CoE's
  0x1C00/0x1C12/0x1C13/0x1C32/0x1C33) and the SII description made from it;
* :mod:`.coe_drive` -- the CiA 402 application behind the ESC;
* :mod:`.profiles` -- real drives' quirks it can emulate (``--profile``);
* :mod:`.serve_ethercat` -- the AF_PACKET socket loop and ``serve()``.
"""
