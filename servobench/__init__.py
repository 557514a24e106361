"""servobench: SIDBE identification of servo drives with friction, on a real bus."""

__version__ = "0.1.0"
