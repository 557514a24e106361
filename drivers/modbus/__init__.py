"""The ``modbus+tcp://`` and ``modbus+rtu://`` drives (pymodbus).

:mod:`.drive` is the drive (``ModbusDrive``); :mod:`.link` the client connection;
:mod:`.regmap` the register maps it shares with the served Modbus drive.
Importing this package loads no transport library.
"""
