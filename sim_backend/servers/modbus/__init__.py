"""The simulated drive served over Modbus TCP and RTU (``serve-sim --transport modbus-tcp|modbus-rtu``).

:mod:`.serve_modbus` serves it; :mod:`.framing` is the MBAP header and RTU CRC, :mod:`.pdu` the
register bridge to the drive.
"""
