"""ODrive firmware 0.5.x as the served simulator answers its ASCII protocol.

The behaviour follows ODrive's firmware source at the tags fw-v0.5.1 to
fw-v0.5.6 (github.com/odriverobotics/ODrive), read, not copied:

* ``Firmware/communication/ascii_protocol.cpp``: a line is dispatched on its
  first character (``c``, ``f``, ``u``, ``r``, ``w``, ``i``, ``s`` ...);
  arguments are scanned as ``sscanf`` does (``"c %u %f"``), and too few of
  them answer ``invalid command format``; an axis number beyond the axes
  answers ``invalid motor N``; a property the object tree lacks answers
  ``invalid property``, one that cannot be written (read-only, or a value
  that does not scan) ``not implemented``; any other first character
  answers ``unknown command``. An empty line is ignored by fw-v0.5.1
  (``cmd[0] != 0``) and answered ``unknown command`` from fw-v0.5.2 on (the
  ``switch`` default). ``sc`` (clear errors) exists from fw-v0.5.2; before
  it, ``s`` followed by anything but ``s``, ``e``, ``r`` does nothing.
* ``Firmware/fibre-cpp/protocol.hpp`` (fw-v0.5.6; fibre ``to_string`` in
  fw-v0.5.1): a read answers floats as ``%f``, integers as ``%u``/``%d``,
  booleans as ``0``/``1``, in a 10-byte buffer (at most 9 characters).
* ``Firmware/MotorControl/axis.cpp`` (``watchdog_check``): with
  ``config.enable_watchdog`` set, the watchdog is checked on every control
  loop in every axis state, idle included, and sets the latching error
  ``WATCHDOG_TIMER_EXPIRED`` (0x800); ``watchdog_feed`` is called by
  ``c``/``v``/``p``/``q``/``t``/``u`` and on entering closed-loop control,
  never by ``r`` or ``w``.

Simplifications: one axis (``f 1`` answers ``invalid motor 1``); torque
control only (``p``, ``q``, ``v``, ``t``, ``e``, ``h`` answer ``not implemented``);
an injected drive fault sets ``axis0.error`` MOTOR_FAILED (0x40) and
``axis0.motor.error`` DRV_FAULT (0x8); the drive leaves its fault once every
error property reads 0. Arming the watchdog restarts its timer (the
firmware's counter resumes where it stood; the host feeds before arming
either way).
"""

from __future__ import annotations

import contextlib
import math
import re
from collections.abc import Callable
from dataclasses import dataclass

from servobench.errors import DriveFaultError
from servobench.sim_backend.device import WATCHDOG_FAULT, PowerState, SimulatedDevice

#: Firmware releases this model covers.
VERSIONS = ((0, 5, 1), (0, 5, 2), (0, 5, 3), (0, 5, 4), (0, 5, 5), (0, 5, 6))
DEFAULT_VERSION = (0, 5, 6)
#: First release with ``sc`` and with ``unknown command`` for an empty line.
CLEAR_ERRORS_SINCE = (0, 5, 2)
#: Axes of the simulated drive.
AXIS_COUNT = 1
#: Longest answer to ``r``: the firmware's ``char response[10]``.
READ_CHARS = 9
AXIS_STATE_UNDEFINED, AXIS_STATE_IDLE, AXIS_STATE_CLOSED_LOOP = 0, 1, 8
AXIS_ERROR_MOTOR_FAILED = 0x40
AXIS_ERROR_WATCHDOG_TIMER_EXPIRED = 0x800
MOTOR_ERROR_DRV_FAULT = 0x8
#: What the simulated board reports (hardware 3.6, 24 V variant) and its serial number.
HW_VERSION = (3, 6, 24)
SERIAL_NUMBER = "SIM000000001"

_UINT = r"\s*(\d+)"
_FLOAT = r"\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)"
#: Marks the answer to ``f``: the server clocks the drive and formats the reply itself.
FEEDBACK = object()


@dataclass
class Property:
    """A property of the object tree: how it reads, how it is written (None: read-only)."""

    kind: type
    read: Callable[[], float | int | bool]
    write: Callable[[float | int | bool], None] | None = None


def to_string(kind: type, value: float | int | bool) -> str:
    """What ``r`` answers for ``value``: ``%f`` / ``%d`` / ``0``-``1``, cut to 9 characters."""
    if kind is bool:
        text = "1" if value else "0"
    elif kind is float:
        text = f"{float(value):f}"
    else:
        text = str(int(value))
    return text[:READ_CHARS]


def from_string(kind: type, text: str) -> float | int | bool | None:
    """What ``w`` stores for ``text`` (``sscanf`` ``%f`` / ``%u`` / ``%d``), None if it does not scan."""
    m = re.match(_FLOAT if kind is float else r"\s*([-+]?\d+)", text)
    if m is None:
        return None
    value = float(m.group(1)) if kind is float else int(m.group(1))
    if kind is float and not math.isfinite(value):
        return None
    return bool(value) if kind is bool else value


class OdriveFirmware:
    """The line handling of one firmware release (see the module doc).

    Parameters
    ----------
    device : SimulatedDevice
        The simulated axis; its watchdog is checked in every state from now on.
    version : tuple of int
        Firmware release, one of :data:`VERSIONS`.
    cycle_extension : bool
        Serve servobench's ``axis0.config.servobench_cycle`` property (the
        lock-step cycle; not part of the firmware).
    """

    def __init__(
        self, device: SimulatedDevice, version: tuple[int, ...] = DEFAULT_VERSION,
        cycle_extension: bool = True,
    ) -> None:  # fmt: skip
        if version not in VERSIONS:
            known = ", ".join(".".join(map(str, v)) for v in VERSIONS)
            raise ValueError(f"firmware {'.'.join(map(str, version))} is not modelled ({known})")
        self.device = device
        self.version = version
        device.watchdog_in_every_state = True
        self.errors = {"axis": 0, "motor": 0, "encoder": 0, "controller": 0}
        self.watchdog_timeout_s = 0.0
        self.watchdog_enabled = False
        device.listeners.append(self._on_state)
        self.properties = self._properties(cycle_extension)

    # -------------------------------------------------------------- the tree
    def _properties(self, cycle_extension: bool) -> dict[str, Property]:
        d = self.device
        props = {
            "vbus_voltage": Property(float, lambda: 24.0),
            "axis0.current_state": Property(int, self._current_state),
            "axis0.requested_state": Property(int, lambda: AXIS_STATE_UNDEFINED, self._request),
            "axis0.config.watchdog_timeout": Property(
                float, lambda: self.watchdog_timeout_s, self._set_timeout
            ),
            "axis0.config.enable_watchdog": Property(
                bool, lambda: self.watchdog_enabled, self._set_enabled
            ),
            "axis0.encoder.pos_estimate": Property(float, lambda: d.sample().position),
            "axis0.encoder.vel_estimate": Property(float, lambda: d.sample().velocity),
        }
        for i, name in enumerate(("major", "minor", "revision")):
            props[f"fw_version_{name}"] = Property(int, lambda i=i: self.version[i])
        props["fw_version_unreleased"] = Property(int, lambda: 0)
        for i, name in enumerate(("major", "minor", "variant")):
            props[f"hw_version_{name}"] = Property(int, lambda i=i: HW_VERSION[i])
        for part in self.errors:
            name = "axis0.error" if part == "axis" else f"axis0.{part}.error"
            props[name] = Property(
                int, lambda p=part: self.errors[p], lambda v, p=part: self._set_error(p, v)
            )
        if cycle_extension:
            props["axis0.config.servobench_cycle"] = Property(
                float, lambda: d.cycle_s, lambda v: d.set_cycle(float(v))
            )
        return props

    def _current_state(self) -> int:
        return AXIS_STATE_CLOSED_LOOP if self.device.state is PowerState.ENABLED else AXIS_STATE_IDLE

    def _request(self, state: float | int | bool) -> None:
        if state == AXIS_STATE_CLOSED_LOOP:
            if not any(self.errors.values()):  # with an error set, the axis falls back to idle
                with contextlib.suppress(DriveFaultError):
                    self.device.enable()  # feeds the watchdog, as entering closed loop does
        elif state == AXIS_STATE_IDLE:
            self.device.disable()

    def _arm(self) -> None:
        on = self.watchdog_enabled and self.watchdog_timeout_s > 0
        self.device.set_watchdog(self.watchdog_timeout_s if on else None)

    def _set_timeout(self, value: float | int | bool) -> None:
        self.watchdog_timeout_s = max(0.0, float(value))
        self._arm()

    def _set_enabled(self, value: float | int | bool) -> None:
        self.watchdog_enabled = bool(value)
        self._arm()

    def _set_error(self, part: str, value: float | int | bool) -> None:
        self.errors[part] = int(value) & 0xFFFFFFFF
        if self.device.state is PowerState.FAULT and not any(self.errors.values()):
            self.device.reset_fault()

    def _on_state(self, state: PowerState, fault_code: int) -> None:
        if state is PowerState.FAULT:
            if fault_code == WATCHDOG_FAULT:
                self.errors["axis"] |= AXIS_ERROR_WATCHDOG_TIMER_EXPIRED
            else:
                self.errors["axis"] |= AXIS_ERROR_MOTOR_FAILED
                self.errors["motor"] |= MOTOR_ERROR_DRV_FAULT

    def clear_errors(self) -> None:
        """``sc`` (fw-v0.5.2 on): every error cleared, the drive out of its fault."""
        for part in self.errors:
            self.errors[part] = 0
        self.device.reset_fault()

    # -------------------------------------------------------------- the lines
    def handle(self, body: str) -> list[str] | object:
        """Reply bodies to one request line (checksum and comment removed), or :data:`FEEDBACK`."""
        if not body:
            return [] if self.version < CLEAR_ERRORS_SINCE else ["unknown command"]
        first = body[0]
        if first in "cfu":
            return self._axis_command(first, body)
        if first in "pqvth" or (first == "e" and self.version >= CLEAR_ERRORS_SINCE):
            return ["not implemented"]
        if first == "i":
            hw, fw = HW_VERSION, self.version
            return [
                f"Hardware version: {hw[0]}.{hw[1]}-{hw[2]}V",
                f"Firmware version: {fw[0]}.{fw[1]}.{fw[2]}",
                f"Serial number: {SERIAL_NUMBER}",
            ]
        if first == "s":
            if body[1:2] == "c" and self.version >= CLEAR_ERRORS_SINCE:
                self.clear_errors()
            return []
        if first == "r":
            return self._read(body)
        if first == "w":
            return self._write(body)
        return ["unknown command"]

    def _axis_command(self, letter: str, body: str) -> list[str] | object:
        pattern = letter + _UINT + (_FLOAT if letter == "c" else "")
        m = re.match(pattern, body)
        if m is None:
            return ["invalid command format"]
        axis = int(m.group(1))
        if axis >= AXIS_COUNT:
            return [f"invalid motor {axis}"]
        if letter == "f":
            return FEEDBACK
        if letter == "c":
            self.device.set_command(float(m.group(2)))  # feeds the watchdog
        else:
            self.device.feed()
        return []

    def _read(self, body: str) -> list[str]:
        m = re.match(r"r\s*(\S+)", body)
        if m is None:
            return ["invalid command format"]
        prop = self.properties.get(m.group(1))
        if prop is None:
            return ["invalid property"]
        return [to_string(prop.kind, prop.read())]

    def _write(self, body: str) -> list[str]:
        m = re.match(r"w\s*(\S+)(?:\s+(\S+))?", body)
        if m is None:
            return ["invalid command format"]
        prop = self.properties.get(m.group(1))
        if prop is None:
            return ["invalid property"]
        value = None if m.group(2) is None else from_string(prop.kind, m.group(2))
        if prop.write is None or value is None:
            return ["not implemented"]
        try:
            prop.write(value)
        except ValueError:  # only servobench's cycle extension refuses a value
            return ["invalid command format"]
        return []
