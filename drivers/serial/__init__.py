"""The ``serial://`` drive: line-based ASCII drive protocols (pyserial).

:mod:`.drive` is the drive (``SerialAsciiDrive``); :mod:`.link` the port and its request/reply
lines; :mod:`.dialect` the TOML dialects it shares with the served serial drive, written with
:mod:`.line_template` templates and framed by :mod:`.ascii_line`.
Importing this package loads no transport library. Imports are absolute, so this package,
``servobench.drivers.serial``, never hides pyserial's top-level ``serial``.
"""
