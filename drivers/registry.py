"""Find drive backends by URL scheme.

Like python-can's ``can.interfaces.BACKENDS``: a lazy table of
``scheme -> (module, class)`` strings, merged with the entry-point group
``servobench.drives`` so third-party packages can add transports. Modules are
imported on demand; an import failure becomes :class:`DriveUnavailableError`.
"""

from __future__ import annotations

import importlib
from importlib.metadata import entry_points
from typing import TYPE_CHECKING

from servobench.drivers.url import parse_drive_url
from servobench.errors import DriveUnavailableError

if TYPE_CHECKING:
    from servobench.drivers.base import Drive

#: Built-in backends: URL scheme -> (module, class name).
BACKENDS: dict[str, tuple[str, str]] = {
    "sim": ("servobench.drivers.sim", "SimDrive"),
    "canopen": ("servobench.drivers.canopen.drive", "CANopen402Drive"),
    "modbus+tcp": ("servobench.drivers.modbus.drive", "ModbusDrive"),
    "modbus+rtu": ("servobench.drivers.modbus.drive", "ModbusDrive"),
    "serial": ("servobench.drivers.serial.drive", "SerialAsciiDrive"),
    "ethercat": ("servobench.drivers.ethercat.drive", "EthercatDrive"),
}

ENTRY_POINT_GROUP = "servobench.drives"


def _entry_point_backends() -> dict[str, tuple[str, str]]:
    found: dict[str, tuple[str, str]] = {}
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        module, _, attr = ep.value.partition(":")
        found[ep.name.lower()] = (module, attr)
    return found


def available_schemes() -> list[str]:
    """All registered URL schemes, built-in and from entry points, sorted."""
    return sorted(set(BACKENDS) | set(_entry_point_backends()))


def resolve(scheme: str) -> type[Drive]:
    """Return the :class:`~servobench.drivers.base.Drive` subclass registered for ``scheme``."""
    scheme = scheme.lower()
    table = {**_entry_point_backends(), **BACKENDS}
    if scheme not in table:
        raise DriveUnavailableError(
            f"unknown drive scheme {scheme!r}; known: {', '.join(available_schemes())}"
        )
    module_name, class_name = table[scheme]
    try:
        module = importlib.import_module(module_name)
    except ImportError as err:
        raise DriveUnavailableError(
            f"drive backend {scheme!r} cannot be loaded ({module_name}): {err}"
        ) from None
    try:
        return getattr(module, class_name)
    except AttributeError:
        raise DriveUnavailableError(f"{module_name} has no drive class {class_name!r}") from None


def open_drive(url: str) -> Drive:
    """Create (not yet opened) the drive that ``url`` names.

    Examples
    --------
    >>> with open_drive("sim://?M=0.1&B=1") as drive:   # doctest: +SKIP
    ...     drive.enable()
    """
    parsed = parse_drive_url(url)
    cls = resolve(parsed.scheme)
    return cls(parsed)
