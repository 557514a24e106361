"""The simulated drive served as a serial ASCII drive on a pty (``serve-sim --transport serial``).

:mod:`.serve_serial` serves a dialect; :mod:`.odrive_firmware` is the ODrive firmware it imitates.
"""
