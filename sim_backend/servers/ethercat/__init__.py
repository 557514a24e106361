"""The simulated drive as an EtherCAT CoE CiA 402 slave (``serve-sim --transport ethercat``).

Layers, each its own module, from the wire up:

* :mod:`.frame` -- EtherCAT frames and datagrams as bytes (pure codec);
* :mod:`.al` -- the AL state machine (INIT, PRE-OP, SAFE-OP, OP) as data;
* :mod:`.sii` -- the SII (EEPROM) image of the slave;
* :mod:`.esc` -- the slave controller: register space, datagram execution with
  working counters, SyncManagers, FMMUs, EEPROM interface, watchdog, DC;
* :mod:`.mailbox` -- the mailbox header and the CoE SDO server;
* :mod:`.coe_drive` -- the CiA 402 application behind the ESC;
* :mod:`.serve_ethercat` -- the AF_PACKET socket loop and ``serve()``.
"""
