"""The ``canopen://`` drive: CiA 402 over CANopen (python-can and canopen).

:mod:`.drive` is the drive (``CANopen402Drive``); :mod:`.options` its URL keys; :mod:`.link` the
bus, node and EDS; :mod:`.sdo`, :mod:`.bringup`, :mod:`.mapping`, :mod:`.session` and :mod:`.cycle`
its bring-up and cyclic exchange. The CiA 402 state machine and units it shares with
``ethercat://`` are :mod:`servobench.drivers.cia402` and :mod:`servobench.drivers.cia402_units`.
Importing this package loads no transport library.
"""
