"""Serving the simulated drive over real protocols: CANopen, Modbus, serial."""
