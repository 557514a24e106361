"""Transport-agnostic servo drives, selected by URL (``sim://``, ``canopen://``, ...).

Importing this package loads no transport library; backends are imported on
demand by :func:`open_drive`.
"""

from servobench.drivers.base import Drive, DriveInfo, Feedback, Limits
from servobench.drivers.registry import available_schemes, open_drive
from servobench.errors import (
    DriveConfigError,
    DriveConnectionError,
    DriveError,
    DriveFaultError,
    DriveTimeoutError,
    DriveUnavailableError,
    ServobenchError,
    StateTransitionError,
)

__all__ = [
    "Drive",
    "DriveConfigError",
    "DriveConnectionError",
    "DriveError",
    "DriveFaultError",
    "DriveInfo",
    "DriveTimeoutError",
    "DriveUnavailableError",
    "Feedback",
    "Limits",
    "ServobenchError",
    "StateTransitionError",
    "available_schemes",
    "open_drive",
]
