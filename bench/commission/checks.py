"""Step 1: the link and the drive -- identity, firmware, state, faults, feedback.

The drive must answer, report its identity where the protocol has one, be
free of faults (one reset is attempted, or offered at the terminal) and
return finite feedback inside the allowed travel. Anything else refuses
commissioning with the reason.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

from servobench.bench.commission.errors import CommissionRefused
from servobench.bench.commission.ui import Console
from servobench.drivers.base import Drive, DriveInfo, Feedback
from servobench.errors import DriveError, LimitExceededError


@dataclass(frozen=True)
class DriveCheck:
    """Outcome of the link and drive check.

    Attributes
    ----------
    info : DriveInfo
        Identity and state as the drive reported them.
    fault_found : int
        Fault code found on connecting, 0 if none.
    fault_reset : bool
        True when a fault was found and a reset cleared it.
    feedback : Feedback
        One feedback sample read at rest [drive units].
    units : mapping
        The drive layer's units of ``u``, ``v``, ``x`` (``Drive.units``; "" where unknown).
    """

    info: DriveInfo
    fault_found: int
    fault_reset: bool
    feedback: Feedback
    units: Mapping[str, str] = field(default_factory=dict)

    def unit(self, signal: str) -> str:
        """`` <unit>`` of ``signal`` for a terminal line, or ``" (drive units)"`` when unknown."""
        return f" {self.units[signal]}" if self.units.get(signal) else " (drive units)"

    def as_dict(self) -> dict[str, object]:
        i = self.info
        return {
            "transport": i.transport,
            "vendor": i.vendor,
            "product": i.product,
            "firmware": i.firmware,
            "serial_number": i.serial_number,
            "state": i.state,
            "units": dict(i.units),
            "fault_found": self.fault_found,
            "fault_reset": self.fault_reset,
            "position_at_start": self.feedback.position,
        }


def describe_info(info: DriveInfo) -> str:
    """One line naming the drive."""
    who = " ".join(p for p in (info.vendor, info.product) if p) or "(no identity reported)"
    parts = [f"{info.transport}: {who}"]
    if info.firmware:
        parts.append(f"firmware {info.firmware}")
    if info.serial_number:
        parts.append(f"serial {info.serial_number}")
    if info.state:
        parts.append(f"state {info.state}")
    return ", ".join(parts)


def check_drive(
    drive: Drive,
    console: Console,
    *,
    dry_run: bool,
    allow_reset: Callable[[int], bool],
) -> DriveCheck:
    """Check an open drive; raise :class:`CommissionRefused` when it is not fit.

    Parameters
    ----------
    drive : Drive
        Open, not enabled.
    console : Console
        Where to report.
    dry_run : bool
        Only read: a fault is reported, not reset.
    allow_reset : callable(code) -> bool
        Asked before the one reset attempt (always True under ``--yes``).
    """
    try:
        info = drive.info()
        code = drive.fault_code()
    except DriveError as err:
        raise CommissionRefused(f"the drive does not answer the link check: {err}") from err
    console.ok(describe_info(info))
    reset = False
    if code:
        console.warn(f"drive reports fault 0x{code:04X}")
        if dry_run:
            console.say("dry run: would attempt one fault reset and refuse if the fault stays")
        elif not allow_reset(code):
            raise CommissionRefused(f"drive in fault 0x{code:04X} and the reset was declined")
        else:
            _reset_once(drive, code)
            reset = True
            console.ok(f"fault 0x{code:04X} reset")
    if dry_run and code:
        return DriveCheck(info, code, False, Feedback(math.nan, math.nan, math.nan, code), dict(drive.units))
    feedback = _read_at_rest(drive)
    check = DriveCheck(info, code, reset, feedback, dict(drive.units))
    console.ok(f"feedback: velocity {feedback.velocity:.4g}{check.unit('v')}, "
               f"position {feedback.position:.4g}{check.unit('x')}")  # fmt: skip
    return check


def _reset_once(drive: Drive, code: int) -> None:
    reason = ""
    try:
        drive.reset_fault()
        remaining = drive.fault_code()
    except DriveError as err:
        remaining, reason = getattr(err, "code", 0) or code, f" ({err})"
    if remaining:
        raise CommissionRefused(
            f"drive in fault 0x{remaining:04X} that will not reset{reason}; "
            "clear its cause (the drive's manual lists the code), power-cycle if needed, and run again"
        )


def _read_at_rest(drive: Drive) -> Feedback:
    try:
        fb = drive.read()
    except LimitExceededError as err:
        raise CommissionRefused(
            f"the axis is outside the confirmed envelope before moving: {err}; "
            "move it inside the allowed travel by hand, or correct xmin/xmax"
        ) from err
    except DriveError as err:
        raise CommissionRefused(f"cannot read feedback: {err}") from err
    if not (math.isfinite(fb.velocity) and math.isfinite(fb.position)):
        raise CommissionRefused(
            f"feedback is not finite (velocity {fb.velocity}, position {fb.position}); "
            "check the encoder wiring and the feedback configuration"
        )
    return fb
