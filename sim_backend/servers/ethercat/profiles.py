"""Drive profiles: quirks of real EtherCAT drives the served slave emulates (``serve-sim --profile``).

``--profile NAME[,NAME...]`` (repeatable) changes the slave's object
dictionary or behaviour as some real drives differ from the served
default; none given, the slave is the default one, byte for byte:

=====================  ===================================================================
``no-cst``             0x6502 announces no cyclic synchronous torque (bit 9 clear; CSP,
                       bit 7, stays): 0x6060 = 10 aborts 0x06090030 (value range
                       exceeded). The torque offset 0x60B2 stays mappable and the
                       position loop adds it in CSP; torque actual 0x6077 stays mappable
``cycle-time-ro``      0x1C32:02 and 0x1C33:02 (cycle time) read only: a download aborts
                       0x06010002 (attempt to write a read only object)
``no-complete-access`` SDO complete access neither announced (SII) nor accepted: abort
                       0x06010000 (unsupported access to an object), as ``--fault
                       complete_access=0``
``ca-stored-wrong``    a complete-access download of a PDO assignment or mapping (0x1C12,
                       0x1C13, 0x1600-0x1603, 0x1A00-0x1A03) is answered OK and its entries
                       stored, but sub-index 0 is taken from the padding byte after the
                       count (0 from a master that pads with zeros): the PDO reads back
                       empty; entry-by-entry writes work
``quick-stop=N``       0x605A (quick stop option code) = N (0..8), honoured: 0..4 end a
                       quick stop in SWITCH ON DISABLED (transitions 11 and 12 at once,
                       the served quick stop being torque off), 5..8 stay in QUICK STOP
                       ACTIVE. Without it the drive stays in QUICK STOP ACTIVE whatever
                       0x605A says
``no-quick-stop``      the quick stop command (controlword x01x) is ignored in every
                       state (an enabled axis stays in OPERATION ENABLED); disable voltage
                       (bit 1 clear) still leads to SWITCH ON DISABLED, and so does
                       leaving AL OP with the axis enabled
=====================  ===================================================================

Pure: text in, a frozen :class:`DriveProfile` out; :func:`apply_to_od` edits
an object dictionary before the slave is built on it.
"""

from __future__ import annotations

from dataclasses import dataclass

import canopen

from servobench.drivers.cia402 import MODE_CST, SUPPORTED_MODE_BITS
from servobench.errors import UsageError
from servobench.sim_backend.servers.ethercat import objects as O

#: Profile name -> one-line description (``quick-stop`` takes ``=N``).
PROFILES: dict[str, str] = {
    "no-cst": "0x6502 without CST, 0x6060 = 10 refused",
    "cycle-time-ro": "0x1C32:02 / 0x1C33:02 read only",
    "no-complete-access": "SDO complete access refused (0x06010000)",
    "ca-stored-wrong": "complete-access PDO downloads stored with sub 0 from the padding byte",
    "quick-stop": "=N: 0x605A quick stop option code N (0..8), honoured",
    "no-quick-stop": "the quick stop command is ignored",
}
#: 0x605A option codes that end a quick stop in SWITCH ON DISABLED (CiA 402 6.5.3).
QUICK_STOP_TO_DISABLED = range(0, 5)
#: 0x605A option codes the profile takes (the standard's; negative ones are the maker's).
QUICK_STOP_OPTIONS = range(0, 9)
QUICK_STOP_OPTION = 0x605A
SUPPORTED_DRIVE_MODES = 0x6502
#: Objects whose complete-access download ``ca-stored-wrong`` stores wrongly.
PDO_CONFIG_OBJECTS = frozenset(
    [O.RXPDO_ASSIGN, O.TXPDO_ASSIGN]
    + [O.RXPDO_MAP + n for n in range(O.PDOS_PER_DIRECTION)]
    + [O.TXPDO_MAP + n for n in range(O.PDOS_PER_DIRECTION)]
)


@dataclass(frozen=True)
class DriveProfile:
    """The quirks the served slave emulates (module docstring); the default has none."""

    names: tuple[str, ...] = ()
    no_cst: bool = False
    cycle_time_ro: bool = False
    complete_access: bool = True
    ca_stored_wrong: bool = False
    #: 0x605A value, honoured; ``None``: 0x605A as the EDS gives it, a quick stop stays.
    quick_stop_option: int | None = None
    ignore_quick_stop: bool = False

    @property
    def count_from_padding(self) -> frozenset[int]:
        """Objects whose complete-access download takes sub-index 0 from the padding byte."""
        return PDO_CONFIG_OBJECTS if self.ca_stored_wrong else frozenset()


def parse_profiles(text: str) -> DriveProfile:
    """The :class:`DriveProfile` of ``--profile`` values joined by commas (empty: none).

    Raises
    ------
    UsageError
        An unknown name, a bad ``quick-stop=N``, or names that contradict each other.
    """
    fields: dict[str, object] = {}
    names: list[str] = []
    for item in (part.strip() for part in text.split(",")):
        if not item:
            continue
        name, sep, arg = item.partition("=")
        if name not in PROFILES:
            raise UsageError(
                f"--profile: unknown profile {name!r}; choose from {', '.join(PROFILES)}"
            )
        if (name == "quick-stop") != bool(sep):
            raise UsageError(f"--profile: write quick-stop=N (N 0..8), got {item!r}")
        if name == "quick-stop":
            if not (arg.isdigit() and int(arg) in QUICK_STOP_OPTIONS):
                raise UsageError(f"--profile quick-stop=N: N must be 0..8, got {arg!r}")
            fields["quick_stop_option"] = int(arg)
        else:
            fields[_FIELD[name]] = name != "no-complete-access"
        names.append(item)
    if "quick_stop_option" in fields and fields.get("ignore_quick_stop"):
        raise UsageError("--profile: quick-stop=N and no-quick-stop contradict each other")
    if fields.get("complete_access") is False and fields.get("ca_stored_wrong"):
        raise UsageError("--profile: no-complete-access and ca-stored-wrong contradict each other")
    return DriveProfile(names=tuple(names), **fields)  # type: ignore[arg-type]


_FIELD = {
    "no-cst": "no_cst",
    "cycle-time-ro": "cycle_time_ro",
    "no-complete-access": "complete_access",
    "ca-stored-wrong": "ca_stored_wrong",
    "no-quick-stop": "ignore_quick_stop",
}


def apply_to_od(profile: DriveProfile, od: canopen.ObjectDictionary) -> None:
    """Edit ``od`` (the slave's, before it is served) for ``profile``'s objects."""
    if profile.no_cst and SUPPORTED_DRIVE_MODES in od:
        var = od[SUPPORTED_DRIVE_MODES]
        var.default = int(var.default or 0) & ~(1 << SUPPORTED_MODE_BITS[MODE_CST])
    if profile.cycle_time_ro:
        for index in (O.SM_OUTPUT_PARAMETER, O.SM_INPUT_PARAMETER):
            od[index][2].access_type = "ro"
    if profile.quick_stop_option is not None and QUICK_STOP_OPTION in od:
        od[QUICK_STOP_OPTION].default = profile.quick_stop_option
