"""The ``--fault`` grammar shared by every served transport.

One fault per item, items separated by ``;`` (``serve-sim --fault`` may also
be repeated)::

    KIND@N          e.g.  drop@120        N: the cycle, counted from 1
    KIND@N:ARG      e.g.  delay@120:30    ARG: an integer (decimal or 0x hex)
    KEY=VALUE       e.g.  reject_mode=10  set-up misbehaviour (no cycle)

A *cycle* is one clocking request of the lock-step drive: a SYNC (CANopen),
a read that covers the velocity register (Modbus), a feedback query
(serial). ``N`` counts them from 1 since the server started, so against a
fresh server the fault hits the ``N``-th logged sample of the first run.

Kinds (see :data:`KINDS` for the transports each applies to):

==============  ===============================================================
``fault@N[:C]`` the drive faults (code ``C``, default 0x1000) before sampling
                cycle ``N``: CiA 402 FAULT with its EMCY, the Modbus fault
                register, the serial error flags
``freeze@N``    from cycle ``N`` on, position and velocity repeat the sample of
                cycle ``N`` (the sensor stops updating; the drive clock runs on)
``drop@N``      the drive is clocked but its answer is lost (CAN: the TPDOs of
                SYNC ``N``; serial: the feedback reply)
``delay@N:MS``  the answer of cycle ``N`` leaves ``MS`` milliseconds late
``dup@N``       the answer of cycle ``N`` is sent twice
``busoff@N[:MS]`` CAN: the drive's controller goes bus-off at SYNC ``N`` for
                ``MS`` ms (default 200): nothing in or out; with 0x6007 = 1 the
                drive faults (0x8140) and sends that EMCY once it recovers
``emcy@N[:C]``  CAN: the drive sends EMCY ``C`` (default 0xFF00) with the TPDOs of
                SYNC ``N`` but stays enabled (a warning)
``exception@N[:C]`` Modbus: cycle ``N`` is answered with exception ``C`` (default
                4) and not executed
``timeout@N``   Modbus: cycle ``N`` is not answered and not executed
``crc@N``       Modbus RTU: the answer of cycle ``N`` arrives with a bad CRC
``garble@N``    serial: one byte of the feedback reply is corrupted
``truncate@N``  serial: only the first half of the reply (and the line end) is sent
``interleave@N`` serial: another line is interleaved into the reply
==============  ===============================================================

Old spellings still work: ``silence@N`` (``drop`` on CANopen and serial,
``timeout`` on Modbus), ``busy@N`` (``exception@N:6``), and CANopen's
``reject_mode=M`` (SDO abort when 0x6060 is set to ``M``) and
``ignore_mode=M`` (0x6060 = ``M`` accepted, 0x6061 does not follow), which
apply to EtherCAT's CoE too; EtherCAT's ``complete_access=0`` (the slave
neither announces nor accepts SDO complete access: abort 0x06010000).

Pure: text in, frozen dataclasses out.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

from servobench.errors import DriveConfigError

#: Transports of ``serve-sim --transport`` served on this host's own links (the fault
#: matrix, :mod:`servobench.bench.testing.fault_scenarios`, runs each of them).
TRANSPORTS = ("canopen", "modbus-tcp", "modbus-rtu", "serial")
#: Transports that need a link of their own (EtherCAT: a network interface, in tests a veth
#: pair in a namespace); their faults are tested there (tests/test_ethercat_drive.py).
LINK_TRANSPORTS = ("ethercat",)
_ALL = frozenset(TRANSPORTS + LINK_TRANSPORTS)
_CAN = frozenset({"canopen"})
_ECAT = frozenset({"ethercat"})
_MODBUS = frozenset({"modbus-tcp", "modbus-rtu"})
_SERIAL = frozenset({"serial"})
#: Largest delay or bus-off time accepted [ms].
MAX_MS = 60_000
#: Modbus exception codes a server may answer (1-8, 10, 11).
MODBUS_EXCEPTIONS = frozenset({1, 2, 3, 4, 5, 6, 7, 8, 10, 11})


@dataclass(frozen=True)
class Kind:
    """One fault kind of the grammar.

    Attributes
    ----------
    name : str
        The ``KIND`` of ``KIND@N``.
    transports : frozenset of str
        Where it applies.
    arg : str
        What ``:ARG`` means: ``""`` (takes none), ``"ms"`` or ``"code"``.
    default : int or None
        Value when ``:ARG`` is left out; ``None`` makes it required.
    device : bool
        True for faults of the drive itself (the injector applies them); False
        for faults on the wire (the transport's hook applies them).
    """

    name: str
    transports: frozenset[str]
    arg: str = ""
    default: int | None = None
    device: bool = False
    summary: str = ""

    def check_arg(self, value: int) -> str | None:
        """Why ``value`` is no valid argument, or ``None``."""
        if self.arg == "ms" and not 0 <= value <= MAX_MS:
            return f"{value} ms is outside 0..{MAX_MS}"
        if self.arg == "code":
            if self.name == "exception" and value not in MODBUS_EXCEPTIONS:
                return f"{value} is no Modbus exception code ({', '.join(map(str, sorted(MODBUS_EXCEPTIONS)))})"
            if not 1 <= value <= 0xFFFF:
                return f"code {value:#x} is outside 0x0001..0xFFFF"
        return None


#: Every fault kind, by name.
KINDS: dict[str, Kind] = {
    k.name: k
    for k in (
        Kind("fault", _ALL, "code", 0x1000, True, "drive fault before sampling cycle N"),
        Kind("freeze", _ALL, "", None, True, "position/velocity stop updating after cycle N"),
        Kind("drop", _CAN | _SERIAL, summary="answer of cycle N lost (drive clocked)"),
        Kind("delay", _ALL, "ms", None, summary="answer of cycle N sent MS ms late"),
        Kind("dup", _CAN | _SERIAL, summary="answer of cycle N sent twice"),
        Kind("busoff", _CAN, "ms", 200, summary="drive bus-off for MS ms from SYNC N"),
        Kind("emcy", _CAN, "code", 0xFF00, summary="EMCY C with the TPDOs, drive stays enabled"),
        Kind("exception", _MODBUS, "code", 4, summary="exception C answered, request not executed"),
        Kind("timeout", _MODBUS, summary="request N not answered, not executed"),
        Kind("crc", frozenset({"modbus-rtu"}), summary="answer of cycle N with a bad CRC"),
        Kind("garble", _SERIAL, summary="one byte of the reply corrupted"),
        Kind("truncate", _SERIAL, summary="first half of the reply only"),
        Kind("interleave", _SERIAL, summary="another line interleaved into the reply"),
    )
}
#: Old spellings: name -> {transport: (kind, argument)}.
ALIASES: dict[str, dict[str, tuple[str, int | None]]] = {
    "silence": {
        "canopen": ("drop", None),
        "serial": ("drop", None),
        "modbus-tcp": ("timeout", None),
        "modbus-rtu": ("timeout", None),
    },
    "busy": {"modbus-tcp": ("exception", 6), "modbus-rtu": ("exception", 6)},
}
#: ``KEY=VALUE`` set-up faults: key -> transports.
SETTINGS: dict[str, frozenset[str]] = {
    "reject_mode": _CAN | _ECAT,
    "ignore_mode": _CAN | _ECAT,
    "complete_access": _ECAT,
}


def kinds_for(transport: str) -> list[str]:
    """Names of the fault kinds that apply to ``transport``, sorted."""
    return sorted(name for name, k in KINDS.items() if transport in k.transports)


@dataclass(frozen=True)
class FaultSpec:
    """One ``KIND@N[:ARG]`` item.

    Attributes
    ----------
    kind : str
        A key of :data:`KINDS` (aliases are resolved).
    cycle : int
        Cycle it hits, from 1.
    arg : int or None
        Argument (the default filled in), ``None`` for kinds that take none.
    text : str
        The item as written.
    """

    kind: str
    cycle: int
    arg: int | None = None
    text: str = ""

    @property
    def device(self) -> bool:
        return KINDS[self.kind].device

    def __str__(self) -> str:
        return f"{self.kind}@{self.cycle}" + ("" if self.arg is None else f":{self.arg}")


@dataclass(frozen=True)
class FaultPlan:
    """The parsed ``--fault`` items of one served drive."""

    transport: str
    specs: tuple[FaultSpec, ...] = ()
    settings: tuple[tuple[str, int], ...] = ()
    _by_cycle: dict[int, tuple[FaultSpec, ...]] = field(
        default_factory=dict, compare=False, repr=False
    )

    def __post_init__(self) -> None:
        by_cycle: dict[int, list[FaultSpec]] = {}
        for spec in self.specs:
            by_cycle.setdefault(spec.cycle, []).append(spec)
        self._by_cycle.update({k: tuple(v) for k, v in by_cycle.items()})

    def at(self, cycle: int) -> tuple[FaultSpec, ...]:
        """The faults due at ``cycle`` (device faults first)."""
        return self._by_cycle.get(cycle, ())

    def setting(self, key: str) -> frozenset[int]:
        """Values given for a ``KEY=VALUE`` setting."""
        return frozenset(v for k, v in self.settings if k == key)

    def __bool__(self) -> bool:
        return bool(self.specs or self.settings)


def _error(item: str, why: str, transport: str) -> DriveConfigError:
    return DriveConfigError(
        f"{transport} serve-sim: bad --fault {item!r}: {why} (use KIND@N[:ARG] with N >= 1; "
        f"KIND@N for {transport}: {', '.join(kinds_for(transport))})"
    )


def _int(text: str) -> int | None:
    text = text.strip()
    try:
        return int(text, 0)
    except ValueError:
        return None


def parse_item(item: str, transport: str) -> FaultSpec | tuple[str, int]:
    """One item: a :class:`FaultSpec`, or ``(key, value)`` for a setting."""
    name, at, rest = item.partition("@")
    name = name.strip()
    if not at:
        key, eq, value = item.partition("=")
        key = key.strip()
        if eq and key in SETTINGS:
            number = _int(value)
            if transport not in SETTINGS[key]:
                raise _error(item, f"{key} does not apply to {transport}", transport)
            if number is None or number < 0:
                raise _error(item, f"{key} needs a non-negative integer", transport)
            return key, number
        raise _error(item, "no @N", transport)
    cycle_text, colon, arg_text = rest.partition(":")
    written = name
    alias_arg: int | None = None
    if name in ALIASES:
        if transport not in ALIASES[name]:
            raise _error(item, f"{name} does not apply to {transport}", transport)
        name, alias_arg = ALIASES[name][transport]
    kind = KINDS.get(name)
    if kind is None:
        raise _error(item, f"unknown kind {name!r}", transport)
    if transport not in kind.transports:
        raise _error(
            item, f"{name} applies to {', '.join(sorted(kind.transports))} only", transport
        )
    cycle = _int(cycle_text)
    if cycle is None or cycle < 1 or not cycle_text.strip().isdigit():
        raise _error(item, f"cycle {cycle_text!r} is not an integer >= 1", transport)
    arg: int | None = None
    if colon:
        if not kind.arg or alias_arg is not None:
            raise _error(item, f"{written} takes no argument", transport)
        arg = _int(arg_text)
        if arg is None:
            raise _error(item, f"argument {arg_text!r} is not an integer", transport)
    elif kind.arg:
        arg = alias_arg if alias_arg is not None else kind.default
        if arg is None:
            raise _error(item, f"{name} needs :{kind.arg.upper()}", transport)
    if arg is not None and (why := kind.check_arg(arg)):
        raise _error(item, why, transport)
    return FaultSpec(name, cycle, arg, item.strip())


def parse_plan(text: str | Iterable[str], transport: str) -> FaultPlan:
    """Parse ``;``-separated items (or several such strings) for ``transport``.

    Raises
    ------
    DriveConfigError
        One line naming the item, why it is wrong and the kinds that apply.
    """
    if transport not in _ALL:
        raise DriveConfigError(f"unknown transport {transport!r} for --fault")
    chunks = [text] if isinstance(text, str) else list(text)
    specs: list[FaultSpec] = []
    settings: list[tuple[str, int]] = []
    wire_at: dict[int, str] = {}
    for chunk in chunks:
        for item in filter(None, (s.strip() for s in chunk.split(";"))):
            parsed = parse_item(item, transport)
            if isinstance(parsed, tuple):
                settings.append(parsed)
                continue
            if not parsed.device:
                if parsed.cycle in wire_at:
                    raise _error(
                        item,
                        f"cycle {parsed.cycle} already has {wire_at[parsed.cycle]!r}",
                        transport,
                    )
                wire_at[parsed.cycle] = item
            specs.append(parsed)
    specs.sort(key=lambda s: (s.cycle, not s.device))
    return FaultPlan(transport, tuple(specs), tuple(settings))


def grammar_help() -> str:
    """A few lines for ``serve-sim --help``."""
    lines = [
        "fault items (--fault, repeatable; ';' separates items; N counts the drive's cycles",
        "from 1: SYNCs, clocking Modbus reads, serial feedback queries, EtherCAT process data):",
    ]
    for name, k in KINDS.items():
        arg = {"": "", "ms": ":MS", "code": ":CODE"}[k.arg]
        if k.arg and k.default is not None:
            arg = f"[{arg}]"
        where = "all" if k.transports == _ALL else ",".join(sorted(k.transports))
        lines.append(f"  {name + '@N' + arg:<19} {k.summary} ({where})")
    lines.append("  silence@N, busy@N, reject_mode=M, ignore_mode=M: older spellings")
    lines.append("  complete_access=0: EtherCAT slave without SDO complete access")
    return "\n".join(lines)
